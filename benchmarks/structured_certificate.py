"""Structured against polytopic observer certificate: cost and conservatism against k.

Run ``python -m benchmarks.structured_certificate [--quick] [--out FILE.json]``;
it prints Markdown tables (docs/structured_certificate.md quotes them) and can
write every number to JSON. Four sections:

* ``scenarios``: the shipped diagrams/*.yaml: uncertain entries, LMI blocks,
  the largest certified decay rate of each formulation (bisection), and design
  time, ``||L||`` and ``cond(P)`` at a common rate;
* ``scaling``: the synthetic plants of :func:`synthetic_system`, n = 2 ... 12,
  k uncertain entries up to 36: design time (wall, and the backend's build and
  solve), peak memory, LMI blocks and sizes, ``||L||``, ``cond(P)`` at a fixed
  rate, the largest certified rate, and the soundness re-checks. The
  polytopic formulation runs only while its corners stay within a budget;
* ``robustness``: the largest scale of the synthetic plants' uncertain terms
  each formulation certifies at a fixed rate (conservatism, measured);
* ``scheduling``: how many state variables the uncertain Jacobian entries
  depend on, against ``k``, and how many vertices the convex hull of the
  sampled Jacobian image has (what vertices over scheduling variables would
  cost).

Nothing here is a timed assertion; tests/test_structured_lmi.py checks the
numbers' meaning on small cases.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ofrl_drake.design import (
    ObserverDesignInaccurate,
    ObserverDesignInfeasible,
    design_observer,
)
from ofrl_drake.jacobian_bounds import JacobianBounds, jacobian_bounds, symbolic_jacobians
from ofrl_drake.lmi import corner_count, decay_certificate
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.plants import resolve_system
from ofrl_drake.scenario import load_scenario
from ofrl_drake.sector import input_vertices
from ofrl_drake.structured_lmi import structured_lmi

__all__ = [
    "FORMULATIONS",
    "max_rate",
    "peak_memory",
    "robustness",
    "scaling",
    "scenarios",
    "scheduling",
    "synthetic_system",
    "uncertain_entries",
]

DIAGRAMS = Path(__file__).resolve().parents[1] / "diagrams"
SCENARIOS = ("two_state_paper", "pendulum_upright", "cart_pole", "coupled_two_state")
#: ``(n, k)`` of the synthetic scaling runs.
SCALING = {
    2: (1, 2),
    4: (1, 2, 4, 6, 8),
    6: (2, 4, 6, 8, 10, 12, 14, 16, 18),
    8: (2, 4, 6, 8, 10, 12, 16, 20, 24),
    12: (12, 24, 36),
}
QUICK_SCALING = {2: (2,), 4: (4, 8), 6: (6,), 8: (16, 24)}
FORMULATIONS = ("polytopic", "entry", "row")
SECTIONS = ("scenarios", "scaling", "robustness", "scheduling")
#: The synthetic plants' input bound and the rate every formulation is timed at.
SYNTHETIC_INPUT_BOUND = 1.0
SYNTHETIC_ALPHA = 0.5


# ------------------------------------------------------------- the plants
def synthetic_system(
    n: int, k: int, seed: int = 0, *, scale: float = 1.0, half_width: float = 2.0
) -> tuple[ControlAffineSystem, tuple[np.ndarray, np.ndarray]]:
    """A plant with ``k`` uncertain Jacobian entries: ``n / 2`` coupled copies of a two-state plant.

    State ``x = [a; b]`` with ``p = n / 2`` unmeasured ``a_i`` and measured
    ``b_i`` (``C = [0 I]``):

        a_i' = -a_i + b_i + (sine terms),
        b_i' = -a_i - b_i + 0.5 (b_{i-1} - 2 b_i + b_{i+1}) + (sine terms) + g_i(x) u,

    with ``c_ij sin(x_j)`` added to row ``i`` for ``k`` entries ``(i, j)`` drawn
    with ``seed`` among all ``n**2`` (``|c_ij|`` in ``[0.5, 1.5] * scale``,
    random sign), and ``g_i = 1`` on the ``b`` rows, plus ``0.2 sin(x_j)`` at
    the first drawn entry. On the box ``|x_j| <= half_width`` each drawn
    Jacobian entry is ``A_ij + c_ij cos(x_j)``, an interval (of both signs of
    ``cos`` when ``half_width > pi / 2``); every other entry is constant. As in
    the paper's two-state plant, unmeasured states enter the measured rows
    through uncertain entries, and uncertain entries of the unmeasured rows
    are out of reach of output injection, so the certifiable rate is bounded
    and the formulations' conservatism shows. The entries are a prefix of one
    permutation, so a larger ``k`` adds entries to a smaller one's.

    Parameters
    ----------
    n : int
        Even state dimension, at least 2.
    k : int
        Uncertain entries, at most ``n**2``.
    seed : int
        Chooses the entries and the signs and sizes of ``c_ij``.
    scale : float
        Multiplies every ``c_ij``.
    half_width : float
        Half-width of the box.

    Returns
    -------
    system : ControlAffineSystem
    box : (lower, upper)
    """
    if n < 2 or n % 2:
        raise ValueError(f"n must be even and >= 2; got {n}.")
    p = n // 2
    candidates = [(i, j) for i in range(n) for j in range(n)]
    if not 0 <= k <= len(candidates):
        raise ValueError(f"k must be in [0, {n * n}] for n = {n}; got {k}.")
    rng = np.random.default_rng(seed)
    chain = np.zeros((p, p))
    for i in range(p - 1):
        chain[i : i + 2, i : i + 2] += 0.5 * np.array([[-1.0, 1.0], [1.0, -1.0]])
    eye = np.eye(p)
    A = np.block([[-eye, eye], [-eye, -eye + chain]])
    order = rng.permutation(len(candidates))
    coef = rng.choice([-1.0, 1.0], len(candidates)) * rng.uniform(0.5, 1.5, len(candidates))
    pairs = [candidates[o] for o in order[:k]]
    c = [scale * coef[o] for o in order[:k]]

    def f(x: Any) -> np.ndarray:
        rows = [sum(A[i, j] * x[j] for j in range(n) if A[i, j] != 0) + 0 * x[0] for i in range(n)]
        for (i, j), cij in zip(pairs, c, strict=True):
            rows[i] = rows[i] + cij * np.sin(x[j])
        return np.array(rows)

    def g(x: Any) -> np.ndarray:
        col = [float(i >= p) + 0 * x[0] for i in range(n)]
        if pairs:
            i, j = pairs[0]
            col[i] = col[i] + 0.2 * np.sin(x[j])
        return np.array(col)[:, None]

    C = np.hstack([np.zeros((p, p)), eye])
    system = ControlAffineSystem(f, g, C, name=f"synthetic_n{n}_k{k}")
    return system, (-half_width * np.ones(n), half_width * np.ones(n))


def uncertain_entries(bounds: JacobianBounds, input_bound: float) -> list[int]:
    """``k`` of the summed box at each input vertex (thin entries not counted)."""
    C = np.eye(bounds.n)[:1]
    problem = structured_lmi(C, bounds, input_bound, 0.0, margin=0.0)
    return [m.k for m in problem.models]


# ----------------------------------------------------------------- helpers
def peak_memory(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """``(seconds, MB, fn())``: the peak resident memory the call added.

    Linux: resets the peak (``/proc/self/clear_refs``) before the call and
    returns ``VmHWM`` after it minus ``VmRSS`` before it; NaN where that is not
    possible.
    """
    try:
        Path("/proc/self/clear_refs").write_text("5")
        before = _status_mb("VmRSS:")
    except OSError:
        before = float("nan")
    start = time.perf_counter()
    value = fn()
    seconds = time.perf_counter() - start
    return seconds, _status_mb("VmHWM:") - before, value


def _status_mb(key: str) -> float:
    """A ``/proc/self/status`` memory line in MB (NaN if absent)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _designer(
    formulation: str,
    system: ControlAffineSystem,
    box: Any,
    bounds: JacobianBounds,
    input_bound: float,
) -> Callable[[float], Any]:
    if formulation == "polytopic":
        return lambda alpha: design_observer(system, box, input_bound, alpha, bounds=bounds)
    name = "structured" if formulation == "entry" else "structured_row"
    return lambda alpha: design_observer(
        system, box, input_bound, alpha, bounds=bounds, formulation=name
    )


def max_rate(
    design: Callable[[float], Any], alpha_max: float, tol: float
) -> tuple[float | None, float | None, Any, int]:
    """Bisect the rate: ``(certified, not certified, design, attempts)``.

    ``certified`` is ``alpha_max`` and ``not certified`` None when
    ``alpha_max`` certifies; ``certified`` and the design are None when not
    even ``alpha = 0`` does.
    """
    attempts = 1
    try:
        return alpha_max, None, design(alpha_max), attempts
    except ObserverDesignInfeasible:
        pass
    lo, hi = 0.0, alpha_max
    attempts += 1
    try:
        best = design(0.0)
    except ObserverDesignInfeasible:
        return None, 0.0, None, attempts
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        attempts += 1
        try:
            best, lo = design(mid), mid
        except ObserverDesignInfeasible:
            hi = mid
    return lo, hi, best, attempts


def _numbers(design: Any) -> dict[str, Any]:
    if design is None:
        return {}
    return {
        "gain_norm": design.gain_norm,
        "condition_number": design.condition_number,
        "solve_time": design.solve_time,
        "max_eigenvalue": design.max_eigenvalue,
    }


def _timed_design(design: Callable[[float], Any], alpha: float) -> dict[str, Any]:
    try:
        seconds, mb, d = peak_memory(lambda: design(alpha))
    except ObserverDesignInfeasible as err:
        return {"feasible": False, "status": err.status}
    return {"feasible": True, "wall_time": seconds, "peak_mb": mb, **_numbers(d), "design": d}


def _blocks(formulation: str, bounds: JacobianBounds, C: np.ndarray, b: float) -> dict[str, Any]:
    """How many LMI blocks of which sizes each formulation hands the solver."""
    n = bounds.n
    if formulation == "polytopic":
        corners = sum(corner_count(bounds, u) for u in input_vertices(b, bounds.m))
        return {"blocks": corners, "block_size": n}
    problem = structured_lmi(C, bounds, b, 0.0, margin=0.0, grouping=formulation)
    return {"blocks": len(problem.models), "block_size": max(problem.sizes)}


# ---------------------------------------------------------------- sections
def scenarios(quick: bool = False) -> list[dict[str, Any]]:
    """The shipped scenarios: k, blocks, largest rate and numbers at a common rate."""
    rows = []
    names = SCENARIOS[:3] if quick else SCENARIOS
    for name in names:
        scenario = load_scenario(DIAGRAMS / f"{name}.yaml")
        system = resolve_system(scenario)
        o = scenario.observer
        box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
        bounds = jacobian_bounds(system, box, o.jacobian_method)
        b = scenario.input_bound
        rates = {}
        for formulation in FORMULATIONS:
            design = _designer(formulation, system, box, bounds, b)
            lo, hi, best, attempts = max_rate(design, 100.0, 1e-3)
            rates[formulation] = (lo, hi, best, attempts)
        common = min(o.alpha, 0.5 * min(r[0] or 0.0 for r in rates.values()))
        for formulation in FORMULATIONS:
            lo, hi, best, attempts = rates[formulation]
            at = _timed_design(_designer(formulation, system, box, bounds, b), common)
            at.pop("design", None)
            rows.append(
                {
                    "scenario": name,
                    "n": system.n,
                    "m": system.m,
                    "formulation": formulation,
                    "k": uncertain_entries(bounds, b),
                    **_blocks(formulation, bounds, system.output_matrix, b),
                    "max_rate": lo,
                    "not_certified": hi,
                    "attempts": attempts,
                    "at_max_rate": _numbers(best),
                    "common_alpha": common,
                    "at_common_alpha": at,
                }
            )
            print(f"  scenarios: {name} {formulation} done", file=sys.stderr, flush=True)
    return rows


def _recheck(d: Any, formulation: str, bounds: JacobianBounds, b: float, k: int) -> dict:
    """The soundness evidence of a structured design: exhaustive when k <= 12."""
    if formulation == "polytopic":
        return {}
    checks = d.delta_check(samples=2000, seed=0)
    out = {
        "delta_worst": max(c.worst for c in checks),
        "delta_exhaustive": all(c.exhaustive for c in checks),
    }
    if k <= 12:
        cert = decay_certificate(d.P, d.L, d.H, d.K, d.C, bounds, b, d.alpha)
        out["polytopic_recheck"] = max(v for _, v in cert)
    return out


def scaling(
    quick: bool = False,
    max_poly_k: int = 10,
    rate_corner_budget: int = 768,
    cases: dict[int, tuple[int, ...]] | None = None,
) -> list[dict[str, Any]]:
    """Synthetic plants: cost and numbers of each formulation against ``(n, k)``.

    ``cases`` (``{n: (k, ...)}``) replaces the default :data:`SCALING` (or
    :data:`QUICK_SCALING` with ``quick``).
    """
    rows = []
    if cases is None:
        cases = QUICK_SCALING if quick else SCALING
    b, alpha = SYNTHETIC_INPUT_BOUND, SYNTHETIC_ALPHA
    for n, ks in cases.items():
        for k in ks:
            system, box = synthetic_system(n, k)
            bounds = jacobian_bounds(system, box, "certified")
            ks_found = uncertain_entries(bounds, b)
            for formulation in FORMULATIONS:
                blocks = _blocks(formulation, bounds, system.output_matrix, b)
                row: dict[str, Any] = {
                    "n": n,
                    "k": max(ks_found),
                    "formulation": formulation,
                    **blocks,
                }
                if formulation == "polytopic" and k > max_poly_k:
                    row["skipped"] = f"k > {max_poly_k}: {blocks['blocks']} corners"
                    rows.append(row)
                    continue
                design = _designer(formulation, system, box, bounds, b)
                at = _timed_design(design, alpha)
                d = at.pop("design", None)
                row["alpha"] = alpha
                row.update(at)
                if d is not None:
                    row.update(_recheck(d, formulation, bounds, b, row["k"]))
                if formulation != "polytopic" or blocks["blocks"] <= rate_corner_budget:
                    lo, hi, _, attempts = max_rate(design, 8.0, 1e-2)
                    row.update({"max_rate": lo, "not_certified": hi, "attempts": attempts})
                rows.append(row)
                print(f"  scaling: n={n} k={k} {formulation} done", file=sys.stderr, flush=True)
    return rows


ROBUSTNESS = ((2, 2), (2, 3), (2, 4), (4, 12))
QUICK_ROBUSTNESS = ((2, 4),)


def robustness(quick: bool = False, scale_max: float = 2.0, tol: float = 0.05) -> list[dict]:
    """The largest ``scale`` of the uncertain terms each formulation certifies at alpha = 0.5.

    Bisection on ``scale`` of :func:`synthetic_system` (certified Jacobian
    bounds recomputed at each step): a direct measure of conservatism, since
    on these plants the rate is either capped near 1 by the plant's structure
    or unbounded (high gain), whatever the formulation. The cases are ones
    where the uncertainty, not the structure, limits the design (most
    synthetic cases with k <= 10 certify every scale up to 8 in all three).
    """
    rows = []
    for n, k in QUICK_ROBUSTNESS if quick else ROBUSTNESS:
        for formulation in FORMULATIONS:

            def failure(
                scale: float, formulation: str = formulation, n: int = n, k: int = k
            ) -> str:
                """The empty string if certified, else "inaccurate" or "infeasible"."""
                system, box = synthetic_system(n, k, scale=scale)
                bounds = jacobian_bounds(system, box, "certified")
                design = _designer(formulation, system, box, bounds, SYNTHETIC_INPUT_BOUND)
                try:
                    design(SYNTHETIC_ALPHA)
                except ObserverDesignInaccurate:
                    return "inaccurate"
                except ObserverDesignInfeasible:
                    return "infeasible"
                return ""

            start = time.perf_counter()
            lo, hi = 0.0, scale_max
            above = failure(hi)
            if not above:
                lo = hi
            while hi - lo > tol:
                mid = 0.5 * (lo + hi)
                why = failure(mid)
                if why:
                    hi, above = mid, why
                else:
                    lo = mid
            rows.append(
                {
                    "n": n,
                    "k": k,
                    "formulation": formulation,
                    "max_scale": lo,
                    "not_certified": hi if above else None,
                    "why": above,
                    "tol": tol,
                    "wall_time": time.perf_counter() - start,
                }
            )
            print(f"  robustness: n={n} k={k} {formulation} done", file=sys.stderr, flush=True)
    return rows


def _variables(expr: Any) -> set[str]:
    return {v.get_name() for v in expr.GetVariables()}


def _sorted(names: set[str]) -> list[str]:
    """``x(i)`` names in the order of ``i``."""
    return sorted(names, key=lambda s: int(s[2:-1]))


def scheduling(points_budget: int = 20_000) -> list[dict[str, Any]]:
    """What vertices over scheduling variables would cost, per plant.

    For each plant: ``k`` (uncertain entries of the summed box at ``u = +b``),
    the state variables those entries depend on (``s``), and the number of
    vertices of the convex hull of the uncertain entries' values sampled on a
    grid over those variables (at most ``points_budget`` points; the other
    variables at the box centre, where they do not matter), when ``k <= 6``. The hull of samples is
    an inner estimate: a sound polytope must enclose the whole image.
    """
    from scipy.spatial import ConvexHull, QhullError

    plants: list[tuple[str, ControlAffineSystem, Any, float]] = []
    for name in SCENARIOS:
        scenario = load_scenario(DIAGRAMS / f"{name}.yaml")
        o = scenario.observer
        box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
        plants.append((name, resolve_system(scenario), box, scenario.input_bound))
    for n, k in ((8, 24), (12, 36)):
        system, box = synthetic_system(n, k)
        plants.append((system.name, system, box, SYNTHETIC_INPUT_BOUND))
    rows = []
    for name, system, box, b in plants:
        bounds = jacobian_bounds(system, box, "certified")
        u = np.full(system.m, b)
        x, Jf, Jg = symbolic_jacobians(system)
        J = Jf + np.einsum("ijk,k->ij", Jg, u)
        lo = bounds.Mf1 + np.minimum(bounds.Mg1 * u, bounds.Mg2 * u).sum(-1)
        hi = bounds.Mf2 + np.maximum(bounds.Mg1 * u, bounds.Mg2 * u).sum(-1)
        free = np.argwhere(hi - lo > 1e-9 * np.maximum(1.0, np.abs(hi)))
        names = _sorted(set().union(*(_variables(J[i, j]) for i, j in free)))
        rows_vars = {
            int(i): _sorted(set().union(*(_variables(J[i, j]) for i2, j in free if i2 == i)))
            for i in np.unique(free[:, 0])
        }
        row: dict[str, Any] = {
            "plant": name,
            "n": system.n,
            "k": len(free),
            "scheduling_variables": names,
            "s": len(names),
            "rows": {str(i): v for i, v in rows_vars.items()},
            "box_corners": 2 ** len(free),
            "structured_size": system.n + len(free),
        }
        if 2 <= len(free) <= 6 and names:
            index = [int(v.get_name()[2:-1]) for v in x]
            used = [index.index(int(s[2:-1])) for s in names]
            lower, upper = np.asarray(box[0], float), np.asarray(box[1], float)
            samples = max(3, int(points_budget ** (1.0 / len(used))))
            grids = np.meshgrid(*(np.linspace(lower[j], upper[j], samples) for j in used))
            points = np.tile(0.5 * (lower + upper)[:, None], (1, grids[0].size))
            for j, grid in zip(used, grids, strict=True):
                points[j] = grid.ravel()
            from pydrake.symbolic import Evaluate

            values = np.array(
                [
                    [
                        Evaluate(np.array([[J[i, j]]]), dict(zip(x, p, strict=True)))[0, 0]
                        for i, j in free
                    ]
                    for p in points.T
                ]
            )
            try:
                row["hull_vertices"] = len(ConvexHull(values).vertices)
            except QhullError:
                row["hull_vertices"] = None  # the image is flat (lower-dimensional)
        rows.append(row)
    return rows


# ------------------------------------------------------------------ report
def _fmt(value: Any, spec: str = ".3g") -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return format(value, spec)
    return str(value)


def _rate(row: dict[str, Any]) -> str:
    """The bisected rate: ``>= alpha_max`` when the top of the search certified."""
    if "max_rate" not in row:
        return "-"
    if row["max_rate"] is None:
        return "none (not even 0)"
    if row["not_certified"] is None:
        return f">= {row['max_rate']:.4g}"
    return f"{row['max_rate']:.4g}"


def format_report(results: dict[str, Any]) -> str:
    """Markdown tables of :func:`scenarios`, :func:`scaling` and :func:`scheduling`."""
    out = []
    if results.get("scenarios"):
        out += [
            "### Shipped scenarios",
            "",
            "| scenario | formulation | k per distinct input vertex | LMI blocks x size | max rate "
            "| ‖L‖ / cond(P) at max rate | common alpha | time (s) | ‖L‖ | cond(P) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in results["scenarios"]:
            at, top = r["at_common_alpha"], r["at_max_rate"]
            out.append(
                f"| {r['scenario']} | {r['formulation']} | {r['k']} | {r['blocks']} x "
                f"{r['block_size']} | {_rate(r)} | {_fmt(top.get('gain_norm'))} / "
                f"{_fmt(top.get('condition_number'))} | {r['common_alpha']:.3g} | "
                f"{_fmt(at.get('wall_time'), '.2f')} | {_fmt(at.get('gain_norm'))} | "
                f"{_fmt(at.get('condition_number'))} |"
            )
        out.append("")
    if results.get("scaling"):
        out += [
            f"### Synthetic plants (alpha = {SYNTHETIC_ALPHA}, |u| <= {SYNTHETIC_INPUT_BOUND})",
            "",
            "| n | k | formulation | LMI blocks x size | design time (s) | solve (s) | added MB "
            "| ‖L‖ | cond(P) | max rate | re-check |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in results["scaling"]:
            if "skipped" in r:
                out.append(
                    f"| {r['n']} | {r['k']} | {r['formulation']} | {r['blocks']} x "
                    f"{r['block_size']} | skipped ({r['skipped']}) | | | | | | |"
                )
                continue
            if not r.get("feasible"):
                time_cells = "infeasible | | | | "
            else:
                time_cells = (
                    f"{r['wall_time']:.2f} | {r['solve_time']:.2f} | {r['peak_mb']:.0f} | "
                    f"{r['gain_norm']:.3g} | {r['condition_number']:.3g} "
                )
            check = ""
            if "polytopic_recheck" in r:
                check = f"all 2^k corners: {r['polytopic_recheck']:.2g}"
            elif "delta_worst" in r:
                check = f"sampled delta: {r['delta_worst']:.2g}"
            out.append(
                f"| {r['n']} | {r['k']} | {r['formulation']} | {r['blocks']} x "
                f"{r['block_size']} | {time_cells}| {_rate(r)} | {check} |"
            )
        out.append("")
    if results.get("robustness"):
        out += [
            f"### Largest uncertainty scale certified at alpha = {SYNTHETIC_ALPHA}",
            "",
            "| n | k | polytopic | entry | row |",
            "|---|---|---|---|---|",
        ]
        table: dict[tuple[int, int], dict[str, str]] = {}
        for r in results["robustness"]:
            why = f", {r['why']} at {r['not_certified']:.4g}" if r.get("why") else ""
            cell = f"{r['max_scale']:.4g} ({r['wall_time']:.0f} s{why})"
            table.setdefault((r["n"], r["k"]), {})[r["formulation"]] = cell
        for (n, k), cells in table.items():
            values = " | ".join(cells.get(f, "-") for f in FORMULATIONS)
            out.append(f"| {n} | {k} | {values} |")
        out.append("")
    if results.get("scheduling"):
        out += [
            "### Scheduling variables",
            "",
            "| plant | n | k | scheduling variables (s) | 2^k | hull vertices of the sampled "
            "image | structured size n + k |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in results["scheduling"]:
            out.append(
                f"| {r['plant']} | {r['n']} | {r['k']} | {', '.join(r['scheduling_variables'])} "
                f"({r['s']}) | {r['box_corners']} | {_fmt(r.get('hull_vertices'))} | "
                f"{r['structured_size']} |"
            )
        out.append("")
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the sections, print the tables, optionally write JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few small cases only")
    parser.add_argument("--out", type=Path, help="write every number to this JSON file")
    parser.add_argument(
        "--sections",
        nargs="+",
        default=list(SECTIONS),
        choices=SECTIONS,
    )
    parser.add_argument(
        "--only",
        nargs="+",
        metavar="N:K",
        help="scaling: run these (n, k) cases instead of the default list",
    )
    parser.add_argument(
        "--max-poly-k",
        type=int,
        default=10,
        help="run the polytopic formulation on synthetic plants up to this k (default 10)",
    )
    args = parser.parse_args(argv)
    results: dict[str, Any] = {}
    start = time.perf_counter()
    if "scenarios" in args.sections:
        results["scenarios"] = scenarios(args.quick)
    if "scaling" in args.sections:
        cases: dict[int, tuple[int, ...]] | None = None
        if args.only:
            cases = {}
            for item in args.only:
                n, k = (int(v) for v in item.split(":"))
                cases[n] = (*cases.get(n, ()), k)
        results["scaling"] = scaling(args.quick, args.max_poly_k, cases=cases)
    if "robustness" in args.sections:
        results["robustness"] = robustness(args.quick)
    if "scheduling" in args.sections:
        results["scheduling"] = scheduling()
    results["wall_time"] = time.perf_counter() - start
    print(format_report(results))
    if args.out:
        args.out.write_text(json.dumps(results, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
