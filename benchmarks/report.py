"""The benchmark targets, checked on the results, and the Markdown tables.

Every target that compares with a baseline is checked against the stronger
one (:mod:`benchmarks.precomputed_numpy`, key ``precomputed``); the same
ratio against the fused baseline (:mod:`benchmarks.fused_numpy`) is reported
beside it, in the ``fused`` column.
"""

from __future__ import annotations

from typing import Any

__all__ = ["LIMITS", "format_report", "targets"]

#: Target -> limit: the paper ratio (ours / the stronger baseline, whole
#: runs), the W error of ours over every logged time, the per-evaluation
#: overhead and the Bellman math per call (microseconds), the N-scaling ratio,
#: the n = 4 ratio, the cost of an extra initial state in a sweep over one
#: run's simulation (J* cached), and the Drake/cvxpy design-time ratio.
LIMITS = {
    "paper_ratio": 2.0,
    "paper_W_max_error": 1e-6,
    "overhead_us": 40.0,
    "bellman_us_N100": 10.0,
    "points_ratio": 10.0,
    "coupled_ratio": 2.0,
    "sweep_extra_state_over_simulation": 1.5,
    "lmi_drake_over_cvxpy": 1.0,
}


def _target(value: float | None, limit: float, fused: float | None = None) -> dict[str, Any]:
    out = {"value": value, "limit": limit, "met": value is not None and value <= limit}
    if fused is not None:
        out["fused"] = fused
    return out


def targets(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``{name: {"value", "limit", "met"[, "fused"]}}`` for each target the results cover."""
    out: dict[str, dict[str, Any]] = {}
    if "paper" in results:
        p = results["paper"]
        out["paper_ratio"] = _target(p["ratio"], LIMITS["paper_ratio"], p["ratio_fused"])
        out["paper_W_max_error"] = _target(p["ours"]["W_max_error"], LIMITS["paper_W_max_error"])
    if "overhead" in results:
        o = results["overhead"]
        out["overhead_us"] = _target(
            o["overhead_us"], LIMITS["overhead_us"], o["overhead_us_fused"]
        )
    for row in results.get("bellman", []):
        if row["N"] == 100:
            out["bellman_us_N100"] = _target(row["us_per_call"], LIMITS["bellman_us_N100"])
    rows = results.get("points", [])
    if len(rows) > 1:
        ratio = rows[-1]["ours"]["median"] / rows[0]["ours"]["median"]
        out["points_ratio"] = _target(ratio, LIMITS["points_ratio"])
    for row in results.get("state_dimension", []):
        if row["n"] == 4 and "ratio" in row:
            out["coupled_ratio"] = _target(
                row["ratio"], LIMITS["coupled_ratio"], row.get("ratio_fused")
            )
    if "sweep" in results:
        out["sweep_extra_state_over_simulation"] = _target(
            results["sweep"]["cached"]["extra_state_over_simulation"],
            LIMITS["sweep_extra_state_over_simulation"],
        )
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


def _load(values: Any) -> str:
    return "n/a" if not values else " / ".join(f"{v:.2f}" for v in values)


_HEADER = (
    "| case | runner | median s | min s | max s | evals | steps | us/eval "
    "| W(T) err | max W err | ours / this |"
)
_RULE = "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|"

#: Result key -> runner label of the baselines, in table order.
_RUNNERS = {"precomputed": "precomputed numpy + LSODA", "fused": "fused numpy + LSODA"}


def _run_row(case: str, runner: str, r: dict[str, Any], ratio: float | None) -> str:
    return (
        f"| {case} | {runner} | {_seconds(r['median'])} | {_seconds(r['min'])} "
        f"| {_seconds(r['max'])} | {r['num_derivative_evaluations']} | {r['num_steps']} "
        f"| {r['us_per_evaluation']:.0f} | {_err(r['W_final_error'])} "
        f"| {_err(r['W_max_error'])} | {'' if ratio is None else f'{ratio:.2f}x'} |"
    )


def _rows(case: str, row: dict[str, Any]) -> list[str]:
    ours = row["ours"]
    lines = [_run_row(case, f"drake {ours['integrator']} {ours['accuracy']:g}", ours, None)]
    for kind, label in _RUNNERS.items():
        if kind in row:
            suffix = "" if kind == "precomputed" else f"_{kind}"
            lines.append(_run_row(case, label, row[kind], row[f"ratio{suffix}"]))
    return lines


def _runs_table(results: dict[str, Any]) -> str:
    lines = [_HEADER, _RULE]
    if "paper" in results:
        lines += _rows("paper (N=100, L=3, n=2)", results["paper"])
    for row in results.get("points", []):
        lines += _rows(f"N = {row['N']}", row)
    for row in results.get("basis", []):
        lines += _rows(f"degrees {row['degrees']} (L = {row['L']})", row)
    for row in results.get("state_dimension", []):
        lines += _rows(f"n = {row['n']} ({row['scenario']})", row)
    for row in results.get("integrators", []):
        case = f"{row['integrator']} @ {row['accuracy']:g} (log every {row['log_period']:g} s)"
        lines.append(_run_row(case, "drake", row, None))
    return "\n".join(lines)


def _paper_text(p: dict[str, Any]) -> str:
    ours = p["ours"]
    return (
        f"Paper scenario: ours {_seconds(ours['median'])} s whole (simulation alone "
        f"{_seconds(ours['advance']['median'])} s, observer design "
        f"{_seconds(p['design']['median'])} s), {ours['num_derivative_evaluations']} "
        f"evaluations. Stronger baseline {_seconds(p['precomputed']['median'])} s "
        f"({p['precomputed']['num_derivative_evaluations']} evaluations): "
        f"**{p['ratio']:.2f}x** whole (median of the per-repeat ratios "
        f"{p['ratio_of_pairs']:.2f}x), {p['ratio_simulation_only']:.2f}x simulation alone. "
        f"Fused baseline {_seconds(p['fused']['median'])} s: {p['ratio_fused']:.2f}x whole "
        f"(per-repeat {p['ratio_of_pairs_fused']:.2f}x), "
        f"{p['ratio_simulation_only_fused']:.2f}x simulation alone."
    ) + _floor_text(p)


def _floor_text(p: dict[str, Any]) -> str:
    floor = p.get("floor")
    if floor is None:
        return ""
    return (
        f" Floor of the overhead levers (the same loop logged only at 0 and at the horizon, "
        f"with no run guard, in the same alternation): `AdvanceTo` "
        f"{_seconds(floor['advance']['median'])} s ({floor['num_derivative_evaluations']} "
        f"evaluations), so `simulate()` would take {_seconds(floor['whole']['median'])} s "
        f"whole: {p['ratio_floor']:.2f}x the stronger baseline."
    )


def _overhead_text(o: dict[str, Any]) -> str:
    return (
        f"One derivative evaluation (median of {o['batches']} interleaved batches of "
        f"{o['calls']}): diagram {o['diagram_us']:.1f} us, stronger baseline's right-hand "
        f"side {o['precomputed_us']:.1f} us, fused {o['fused_us']:.1f} us; overhead "
        f"{o['overhead_us']:.1f} us over the stronger, {o['overhead_us_fused']:.1f} us over "
        f"the fused; fastest batches {o['diagram_min_us']:.1f}, {o['precomputed_min_us']:.1f} "
        f"and {o['fused_min_us']:.1f} us (max |difference| "
        f"{o['max_derivative_difference']:.1e})."
    )


def _profile_table(p: dict[str, Any]) -> str:
    lines = [
        "| block | class | states | work us | work us, median batch | with invalidation us "
        "| invalidation alone us |",
        "|---|---|--:|--:|--:|--:|--:|",
    ]
    for b in sorted(p["blocks"], key=lambda b: -b["work_us"]):
        lines.append(
            f"| {b['slot']} | {b['block']} | {b['num_states']} | {b['work_us']:.1f} "
            f"| {b['work_median_us']:.1f} | {b['total_us']:.1f} | {b['invalidation_us']:.1f} |"
        )
    return (
        "\n".join(lines)
        + f"\n\nFastest of {p['batches']} interleaved batches of {p['calls']} (median batch "
        "beside). The whole diagram: "
        f"{p['diagram_us']:.1f} us per evaluation (median batch {p['diagram_median_us']:.1f}; "
        f"{p['num_states']} states; setting the state alone {p['set_state_us']:.1f} us); the "
        f"blocks' work adds up to {p['blocks_work_us']:.1f} us. A whole run: "
        f"{p['advance_us_per_evaluation']:.1f} us of `AdvanceTo` per evaluation over "
        f"{p['num_derivative_evaluations']} evaluations, so "
        f"{p['outside_evaluation_us']:.1f} us per evaluation (over the median batch) go to the "
        "integrator, the loggers and the run guard."
    )


def _scaling_tables(s: dict[str, list[dict[str, Any]]]) -> str:
    groups = (
        ("points", "N", lambda r: f"{r['N']}"),
        ("basis", "degrees (L)", lambda r: f"{r['degrees']} ({r['L']})"),
        (
            "state_dimension",
            "n (scenario, L, N)",
            lambda r: f"{r['n']} ({r['scenario']}, L = {r['L']}, N = {r['N']})",
        ),
    )
    out = []
    for key, head, label in groups:
        rows = s.get(key, [])
        if not rows:
            continue
        lines = [
            f"| {head} | horizon s | median s | simulation s | s per simulated s "
            "| evals per simulated s | us/eval | growth: s per simulated s | growth: evals "
            "| growth: us/eval |",
            "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
        ]
        for r in rows:
            lines.append(
                f"| {label(r)} | {r['duration']:g} | {_seconds(r['median'])} "
                f"| {_seconds(r['advance']['median'])} "
                f"| {r['seconds_per_simulated_second']:.3f} "
                f"| {r['evaluations_per_simulated_second']:.0f} | {r['us_per_evaluation']:.0f} "
                f"| {r['seconds_per_simulated_second_growth']:.2f}x "
                f"| {r['evaluations_growth']:.2f}x | {r['us_per_evaluation_growth']:.2f}x |"
            )
        out.append("\n".join(lines))
    return "\n\n".join(out)


def _sweep_table(s: dict[str, Any]) -> str:
    lines = [
        "| J* | initial states | median s | min s | max s | runs / s per worker "
        "| median run wall s |",
        "|---|--:|--:|--:|--:|--:|--:|",
    ]
    for mode in ("solved", "cached"):
        for k, c in s[mode]["cases"].items():
            lines.append(
                f"| {mode} | {k} | {_seconds(c['median'])} | {_seconds(c['min'])} "
                f"| {_seconds(c['max'])} | {c['runs_per_second']:.2f} "
                f"| {_seconds(c['run_wall_time_median'])} |"
            )
    first, last = s["counts"][0], s["counts"][-1]
    solved, cached = s["solved"], s["cached"]
    return (
        "\n".join(lines)
        + f"\n\n`ablate` of the {s['scenario']} scenario's own loop over {s['duration']:g} s, "
        f"serial (one worker), {first} against {last} initial states. One extra initial "
        f"state costs {_seconds(solved['extra_state_seconds'])} s with J* solved and "
        f"{_seconds(cached['extra_state_seconds'])} s with J* cached: "
        f"{cached['extra_state_over_simulation']:.2f}x one run's simulation alone "
        f"({_seconds(s['simulation']['median'])} s), "
        f"{cached['extra_state_over_simulate']:.2f}x one whole `simulate()` "
        f"({_seconds(s['simulate']['median'])} s)."
    )


def _blocks_table(blocks: list[dict[str, Any]]) -> str:
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
    return (
        "\n".join(table)
        + "\n\nWhole `simulate()` with the observer design given (designed once: "
        + designs
        + ")."
    )


def _compile_text(c: dict[str, Any]) -> str:
    mb = {k: v / 2**20 for k, v in c["install_bytes"].items()}
    return (
        f"numba {c['versions']['numba']} (llvmlite {c['versions']['llvmlite']}), installed "
        f"{mb['numba']:.0f} MB + {mb['llvmlite']:.0f} MB. Fresh process: `import numba` "
        f"{c['warm']['import_numba']:.2f} s; first `simulate()` (0.1 s of the paper "
        f"scenario) {c['cold']['first_simulate']:.2f} s with an empty kernel cache, "
        f"{c['warm']['first_simulate']:.2f} s with the cache filled, "
        f"{c['warm']['second_simulate']:.2f} s the second time: first-call compile "
        f"{c['compile_s']:.1f} s, once per machine (kernels cached on disk)."
    )


def _lmi_table(lmi: list[dict[str, Any]]) -> str:
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
    return "\n".join(table)


def _machine_text(results: dict[str, Any]) -> str:
    m = results.get("machine", {})
    probe = results.get("speed_probe", {})
    text = (
        f"Machine: {m.get('cpu', '?')}, {m.get('cpu_count', '?')} CPUs; Python "
        f"{m.get('python', '?')}, numpy {m.get('numpy', '?')}, scipy {m.get('scipy', '?')}, "
        f"Drake {m.get('drake', '?')}; {m.get('platform', '?')}. Commit "
        f"{m.get('commit') or '?'}"
        + (
            ""
            if m.get("tree_clean") is None
            else (" (tree clean)" if m["tree_clean"] else " (tree with uncommitted changes)")
        )
        + "."
    )
    if {"start", "end"} <= set(probe):
        a, b = probe["start"], probe["end"]
        text += (
            " Load average (1, 5, 15 min) at the start "
            f"{_load(a.get('load_average'))}, at the end {_load(b.get('load_average'))}. "
            "Speed probe (start / end): 3x3 numpy product "
            f"{a['numpy_matmul_3x3_us']:.2f} / {b['numpy_matmul_3x3_us']:.2f} us, empty Python "
            f"call {a['python_call_us']:.3f} / {b['python_call_us']:.3f} us."
        )
    return text


def _targets_table(checks: dict[str, dict[str, Any]]) -> str:
    table = [
        "| target | value (stronger baseline) | fused baseline | limit | met |",
        "|---|--:|--:|--:|---|",
    ]
    for name, t in checks.items():
        value = "n/a" if t["value"] is None else f"{t['value']:.3g}"
        fused = f"{t['fused']:.3g}" if "fused" in t else ""
        table.append(
            f"| {name} | {value} | {fused} | {t['limit']:g} | {'yes' if t['met'] else 'NO'} |"
        )
    return "\n".join(table)


def format_report(results: dict[str, Any]) -> str:
    """Markdown, one ``###`` section per part the results hold: the machine and its
    load, the runs, where an evaluation goes, the scaling rows, the sweep, the
    blocks, the Bellman math, numba, the LMI and the targets."""
    sections = [("Machine and load", _machine_text(results))]
    runs = [_runs_table(results)]
    if "paper" in results:
        runs.append(_paper_text(results["paper"]))
    if "overhead" in results:
        runs.append(_overhead_text(results["overhead"]))
    sections.append(("Runs", "\n\n".join(runs)))
    if "profile" in results:
        sections.append(("Where an evaluation goes", _profile_table(results["profile"])))
    if results.get("scaling"):
        sections.append(("Scaling rows", _scaling_tables(results["scaling"])))
    if "sweep" in results:
        sections.append(("Sweep throughput", _sweep_table(results["sweep"])))
    if results.get("blocks"):
        sections.append(
            ("The blocks: C++ symbolic against Python", _blocks_table(results["blocks"]))
        )
    bellman = results.get("bellman", [])
    if bellman:
        parts = ", ".join(
            f"N = {r['N']}: {r['us_per_call']:.1f} us (fastest batch {r['us_per_call_min']:.1f})"
            for r in bellman
        )
        sections.append(("Bellman math", f"Per call (both sums, median of batches): {parts}."))
    if "compile" in results:
        sections.append(("numba: cost of the dependency", _compile_text(results["compile"])))
    if results.get("lmi_design"):
        sections.append(("LMI design: Drake against cvxpy", _lmi_table(results["lmi_design"])))
    if results.get("targets"):
        sections.append(("Targets", _targets_table(results["targets"])))
    return "\n\n".join(f"### {title}\n\n{body}" for title, body in sections)
