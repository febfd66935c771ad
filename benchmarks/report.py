"""The benchmark targets, checked on the results, and the Markdown tables."""

from __future__ import annotations

from typing import Any

__all__ = ["LIMITS", "format_report", "targets"]

#: Target -> limit: the paper ratio (ours / baseline, whole runs), the W error
#: of ours over every logged time, the per-evaluation overhead and the Bellman
#: math per call (microseconds), the N-scaling ratio, the n = 4 ratio and the
#: Drake/cvxpy design-time ratio.
LIMITS = {
    "paper_ratio": 2.0,
    "paper_W_max_error": 1e-6,
    "overhead_us": 40.0,
    "bellman_us_N100": 10.0,
    "points_ratio": 10.0,
    "coupled_ratio": 2.0,
    "lmi_drake_over_cvxpy": 1.0,
}


def _target(value: float | None, limit: float) -> dict[str, Any]:
    return {"value": value, "limit": limit, "met": value is not None and value <= limit}


def targets(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``{name: {"value", "limit", "met"}}`` for each target the results cover."""
    out: dict[str, dict[str, Any]] = {}
    if "paper" in results:
        out["paper_ratio"] = _target(results["paper"]["ratio"], LIMITS["paper_ratio"])
        out["paper_W_max_error"] = _target(
            results["paper"]["ours"]["W_max_error"], LIMITS["paper_W_max_error"]
        )
    if "overhead" in results:
        out["overhead_us"] = _target(results["overhead"]["overhead_us"], LIMITS["overhead_us"])
    for row in results.get("bellman", []):
        if row["N"] == 100:
            out["bellman_us_N100"] = _target(row["us_per_call"], LIMITS["bellman_us_N100"])
    rows = results.get("points", [])
    if len(rows) > 1:
        ratio = rows[-1]["ours"]["median"] / rows[0]["ours"]["median"]
        out["points_ratio"] = _target(ratio, LIMITS["points_ratio"])
    for row in results.get("state_dimension", []):
        if row["n"] == 4 and "ratio" in row:
            out["coupled_ratio"] = _target(row["ratio"], LIMITS["coupled_ratio"])
    lmi = [r for r in results.get("lmi_design", []) if "median" in r]
    for scenario in dict.fromkeys(r["scenario"] for r in lmi):
        for solver in dict.fromkeys(r["solver"] for r in lmi):
            times = {
                r["backend"]: r["median"]
                for r in lmi
                if r["scenario"] == scenario and r["solver"] == solver
            }
            if {"drake", "cvxpy"} <= set(times):
                out[f"lmi_drake_over_cvxpy[{scenario}, {solver}]"] = _target(
                    times["drake"] / times["cvxpy"], LIMITS["lmi_drake_over_cvxpy"]
                )
    return out


def _seconds(x: float) -> str:
    return f"{x:.3f}" if x >= 0.1 else f"{x:.4f}"


def _err(x: float) -> str:
    return f"{x:.1e}"


_HEADER = (
    "| case | runner | median s | min s | max s | evals | steps | us/eval "
    "| W(T) err | max W err | ratio |"
)
_RULE = "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|"


def _run_row(case: str, runner: str, r: dict[str, Any], ratio: float | None) -> str:
    return (
        f"| {case} | {runner} | {_seconds(r['median'])} | {_seconds(r['min'])} "
        f"| {_seconds(r['max'])} | {r['num_derivative_evaluations']} | {r['num_steps']} "
        f"| {r['us_per_evaluation']:.0f} | {_err(r['W_final_error'])} "
        f"| {_err(r['W_max_error'])} | {'' if ratio is None else f'{ratio:.2f}x'} |"
    )


def _pair(case: str, row: dict[str, Any]) -> list[str]:
    ours = row["ours"]
    lines = [_run_row(case, f"drake {ours['integrator']} {ours['accuracy']:g}", ours, None)]
    if "baseline" in row:
        lines.append(_run_row(case, "numpy + LSODA", row["baseline"], row["ratio"]))
    return lines


def format_report(results: dict[str, Any]) -> str:
    """Markdown: the runs table, the per-evaluation overhead, the LMI table, the targets."""
    lines = [_HEADER, _RULE]
    if "paper" in results:
        lines += _pair("paper (N=100, L=3, n=2)", results["paper"])
    for row in results.get("points", []):
        lines += _pair(f"N = {row['N']}", row)
    for row in results.get("basis", []):
        lines += _pair(f"degrees {row['degrees']} (L = {row['L']})", row)
    for row in results.get("state_dimension", []):
        lines += _pair(f"n = {row['n']} ({row['scenario']})", row)
    for row in results.get("integrators", []):
        case = f"{row['integrator']} @ {row['accuracy']:g} (log every {row['log_period']:g} s)"
        lines.append(_run_row(case, "drake", row, None))
    out = ["\n".join(lines)]

    if "paper" in results:
        p = results["paper"]
        out.append(
            f"Paper scenario: ours {_seconds(p['ours']['median'])} s whole "
            f"(simulation alone {_seconds(p['ours']['advance']['median'])} s, observer "
            f"design {_seconds(p['design']['median'])} s), baseline "
            f"{_seconds(p['baseline']['median'])} s: {p['ratio']:.2f}x whole "
            f"(median of the per-repeat ratios {p['ratio_of_pairs']:.2f}x), "
            f"{p['ratio_simulation_only']:.2f}x simulation alone."
        )
    if "overhead" in results:
        o = results["overhead"]
        out.append(
            f"One derivative evaluation (median of {o['batches']} batches of {o['calls']}): "
            f"diagram {o['diagram_us']:.1f} us, fused numpy {o['fused_us']:.1f} us, overhead "
            f"{o['overhead_us']:.1f} us; fastest batches {o['diagram_min_us']:.1f} us and "
            f"{o['fused_min_us']:.1f} us, overhead {o['overhead_min_us']:.1f} us "
            f"(max |difference| {o['max_derivative_difference']:.1e})."
        )

    blocks = results.get("blocks", [])
    if blocks:
        table = [
            "| scenario | n | blocks | median s | min s | max s | simulation s | evals | steps "
            "| us/eval | python / symbolic |",
            "|---|--:|---|--:|--:|--:|--:|--:|--:|--:|--:|",
        ]
        for r in blocks:
            for kind in ("symbolic", "python"):
                k = r[kind]
                speedup = f"{r['python_over_symbolic']:.2f}x" if kind == "python" else ""
                table.append(
                    f"| {r['scenario']} | {r['n']} | {kind} | {_seconds(k['median'])} "
                    f"| {_seconds(k['min'])} | {_seconds(k['max'])} "
                    f"| {_seconds(k['advance']['median'])} | {k['num_derivative_evaluations']} "
                    f"| {k['num_steps']} | {k['us_per_evaluation']:.0f} | {speedup} |"
                )
        designs = ", ".join(f"{r['scenario']} {_seconds(r['design_seconds'])} s" for r in blocks)
        out.append(
            "\n".join(table)
            + "\n\nWhole `simulate()` with the observer design given (designed once: "
            + designs
            + ")."
        )

    bellman = results.get("bellman", [])
    if bellman:
        parts = ", ".join(
            f"N = {r['N']}: {r['us_per_call']:.1f} us (fastest batch {r['us_per_call_min']:.1f})"
            for r in bellman
        )
        out.append(f"Bellman math per call (both sums, median of batches): {parts}.")
    if "compile" in results:
        c = results["compile"]
        mb = {k: v / 2**20 for k, v in c["install_bytes"].items()}
        out.append(
            f"numba {c['versions']['numba']} (llvmlite {c['versions']['llvmlite']}), installed "
            f"{mb['numba']:.0f} MB + {mb['llvmlite']:.0f} MB. Fresh process: `import numba` "
            f"{c['warm']['import_numba']:.2f} s; first `simulate()` (0.1 s of the paper "
            f"scenario) {c['cold']['first_simulate']:.2f} s with an empty kernel cache, "
            f"{c['warm']['first_simulate']:.2f} s with the cache filled, "
            f"{c['warm']['second_simulate']:.2f} s the second time: first-call compile "
            f"{c['compile_s']:.1f} s, once per machine (kernels cached on disk)."
        )

    lmi = results.get("lmi_design", [])
    if lmi:
        table = [
            "| scenario | backend | solver | median s | min s | max s | solve s "
            "| certified | max eig | norm L |",
            "|---|---|---|--:|--:|--:|--:|---|--:|--:|",
        ]
        for r in lmi:
            if "failed" in r:
                table.append(
                    f"| {r['scenario']} | {r['backend']} | {r['solver']} "
                    f"| failed: {r['failed']} |||||||"
                )
                continue
            table.append(
                f"| {r['scenario']} | {r['backend']} | {r['solver']} | {_seconds(r['median'])} "
                f"| {_seconds(r['min'])} | {_seconds(r['max'])} | {_seconds(r['solve_time'])} "
                f"| {r['certified']} | {r['max_eigenvalue']:.2e} | {r['gain_norm']:.1f} |"
            )
        out.append("\n".join(table))

    probe = results.get("speed_probe", {})
    if {"start", "end"} <= set(probe):
        a, b = probe["start"], probe["end"]
        out.append(
            "Machine speed probe (start / end of the run): 3x3 numpy product "
            f"{a['numpy_matmul_3x3_us']:.2f} / {b['numpy_matmul_3x3_us']:.2f} us, empty Python "
            f"call {a['python_call_us']:.3f} / {b['python_call_us']:.3f} us."
        )

    checks = results.get("targets", {})
    if checks:
        table = ["| target | value | limit | met |", "|---|--:|--:|---|"]
        for name, t in checks.items():
            value = "n/a" if t["value"] is None else f"{t['value']:.3g}"
            table.append(f"| {name} | {value} | {t['limit']:g} | {'yes' if t['met'] else 'NO'} |")
        out.append("\n".join(table))
    return "\n\n".join(out)
