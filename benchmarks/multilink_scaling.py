"""The multi-link scaling table: certified bounds and both sound certificates against n.

``python -m benchmarks.multilink_scaling [--rows NAME ...] [--poly-timeout S] [--out FILE]``

One row per plant, from the pendulum (n = 2) to n = 12, each on its own
observer box, input bound and decay rate:

* ``pendulum_upright``, ``cart_pole``, ``acrobot``, ``cart_double_pendulum``,
  ``quadrotor``: the shipped diagrams/*.yaml, loaded with
  :func:`ofrl_drake.load_scenario` and :func:`ofrl_drake.plants.resolve_system`
  as ``ofrl-drake design-observer`` loads them (with the scenario's
  ``observer.jacobian_tol`` and ``jacobian_rtol`` when it gives them);
* ``synthetic_n8_k24``, ``synthetic_n12_k36``: **synthetic** plants,
  :func:`benchmarks.structured_certificate.synthetic_system` (coupled copies
  of a two-state plant with ``k`` sine terms) on its box, at its input bound
  and rate. They stand in for a multi-link robot of n >= 8: a cart with three
  pendulums (diagrams/models/cart_triple_pendulum.urdf) gets finite
  certified bounds only when its budget stops the refinement, wider than
  its tolerance (docs/multilink.md).

For each: the time of the one ``jacobian_bounds(..., "certified")`` call
(on a freshly built model, so it includes building the symbolic Jacobians),
whether its refinement converged, the uncertain Jacobian entries ``k`` (of
the summed box ``M_f + M_g u`` at each input vertex, the largest), then, for
the ``polytopic``, ``structured`` and ``structured_row`` formulations of
:func:`ofrl_drake.design.design_observer` with those bounds: the LMI blocks
and their size (polytopic: ``3^m 2^k`` corners of size ``n``; structured: one
LMI of size ``n + k`` per distinct input vertex; structured_row: ``n + r``,
``r`` the uncertain rows), the wall time of the design
(building and solving the LMI, and checking the answer), ``||L||``,
``cond(P)`` and whether the decay claim is certified.

The polytopic design runs in a child process killed after ``--poly-timeout``
seconds, and not at all past :data:`ofrl_drake.lmi.MAX_CORNERS`; either way
the row says "not run" with its corner count. The run also records the
machine and its load average before and after. Nothing here is a timed
assertion; tests/test_benchmarks.py runs :func:`row` on the pendulum.
docs/multilink.md quotes the table of ``benchmarks/multilink_scaling.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DIAGRAMS = ROOT / "diagrams"

__all__ = [
    "FORMULATIONS",
    "ROWS",
    "SYNTHETIC",
    "Plant",
    "build",
    "format_table",
    "machine",
    "main",
    "row",
]

FORMULATIONS = ("polytopic", "structured", "structured_row")


#: Synthetic row name -> ``(n, k)`` of the synthetic plant family.
SYNTHETIC: dict[str, tuple[int, int]] = {"synthetic_n8_k24": (8, 24), "synthetic_n12_k36": (12, 36)}

#: Row name -> the scenario file it comes from (None: a :data:`SYNTHETIC` plant).
ROWS: dict[str, Path | None] = {
    "pendulum_upright": DIAGRAMS / "pendulum_upright.yaml",
    "cart_pole": DIAGRAMS / "cart_pole.yaml",
    "acrobot": DIAGRAMS / "acrobot.yaml",
    "cart_double_pendulum": DIAGRAMS / "cart_double_pendulum.yaml",
    "quadrotor": DIAGRAMS / "quadrotor.yaml",
    **dict.fromkeys(SYNTHETIC),
}


@dataclass(frozen=True)
class Plant:
    """What a row designs for: the model, its observer box, input bound and rate.

    ``tolerances``: the ``tol``/``rtol`` of its certified bounds, when the
    scenario gives them.
    """

    name: str
    system: Any
    box: tuple[np.ndarray, np.ndarray]
    input_bound: float
    alpha: float
    jacobian_method: str
    solver: str
    tolerances: tuple[tuple[str, float], ...] = ()


def build(name: str) -> Plant:
    """The plant of row ``name`` (a key of :data:`ROWS`), built with the library's loaders."""
    from ofrl_drake import load_scenario
    from ofrl_drake.plants import resolve_system

    if name not in ROWS:
        raise KeyError(f"unknown row {name!r}; choose from {sorted(ROWS)}.")
    path = ROWS[name]
    if path is None:
        from benchmarks.structured_certificate import (
            SYNTHETIC_ALPHA,
            SYNTHETIC_INPUT_BOUND,
            synthetic_system,
        )

        system, box = synthetic_system(*SYNTHETIC[name])
        return Plant(
            name, system, box, SYNTHETIC_INPUT_BOUND, SYNTHETIC_ALPHA, "certified", "clarabel"
        )
    scenario = load_scenario(path)
    o = scenario.observer
    box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
    tolerances = tuple(
        (key, float(value))
        for key, value in (("tol", o.jacobian_tol), ("rtol", o.jacobian_rtol))
        if value is not None
    )
    return Plant(
        name,
        resolve_system(scenario),
        box,
        float(scenario.input_bound),
        float(o.alpha),
        o.jacobian_method,
        o.solver,
        tolerances,
    )


def _blocks(plant: Plant, bounds: Any) -> dict[str, dict[str, Any]]:
    """LMI blocks of each formulation: polytopic corners, structured LMIs and sizes."""
    from ofrl_drake.design.sdp import DEFAULT_MARGIN
    from ofrl_drake.lmi import corner_count
    from ofrl_drake.sector import input_vertices
    from ofrl_drake.structured_lmi import structured_lmi

    vertices = input_vertices(plant.input_bound, bounds.m)
    corners = sum(corner_count(bounds, u) for u in vertices)
    C = plant.system.output_matrix
    entry, by_row = (
        structured_lmi(
            C, bounds, plant.input_bound, plant.alpha, margin=DEFAULT_MARGIN, grouping=grouping
        )
        for grouping in ("entry", "row")
    )
    return {
        "k": max(m.k for m in entry.models),
        "input_vertices": len(vertices),
        "polytopic": {"blocks": corners, "block_size": plant.system.n},
        "structured": {"blocks": len(entry.models), "block_size": max(entry.sizes)},
        "structured_row": {"blocks": len(by_row.models), "block_size": max(by_row.sizes)},
    }


def _design(plant: Plant, bounds: Any, formulation: str) -> dict[str, Any]:
    """Design with ``formulation`` in this process: wall time and the design's numbers."""
    from ofrl_drake.design import ObserverDesignInfeasible, design_observer

    start = time.perf_counter()
    try:
        d = design_observer(
            plant.system,
            plant.box,
            plant.input_bound,
            plant.alpha,
            bounds=bounds,
            solver=plant.solver,
            formulation=formulation,
        )
    except ObserverDesignInfeasible as err:
        return {
            "lmi_seconds": time.perf_counter() - start,
            "feasible": False,
            "status": str(err.status),
        }
    seconds = time.perf_counter() - start
    return {
        "lmi_seconds": seconds,
        "feasible": True,
        "status": d.status,
        "solve_time": d.solve_time,
        "gain_norm": d.gain_norm,
        "condition_number": d.condition_number,
        "decay_certified": bool(d.is_decay_certified),
    }


def _design_in_child(plant: Plant, bounds: Any, formulation: str, timeout: float) -> dict:
    """:func:`_design` in a fresh process (same bounds), killed by its pid after ``timeout`` s."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bounds.json"
        path.write_text(json.dumps(bounds.to_dict()))
        cmd = [sys.executable, "-m", "benchmarks.multilink_scaling"]
        cmd += ["--child", plant.name, formulation, str(path)]
        env = {
            **os.environ,
            "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
        }
        proc = subprocess.Popen(
            cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            return {"timeout": timeout}
    if proc.returncode != 0:
        return {"error": err.decode().strip().splitlines()[-1]}
    return json.loads(out.decode().strip().splitlines()[-1])


def _child(name: str, formulation: str, bounds_file: str) -> int:
    """The child of :func:`_design_in_child`: print :func:`_design`'s result as JSON."""
    from ofrl_drake.jacobian_bounds import JacobianBounds

    plant = build(name)
    data = json.loads(Path(bounds_file).read_text())
    bounds = JacobianBounds.from_dict(data, plant.box, plant.jacobian_method)
    print(json.dumps(_design(plant, bounds, formulation)))
    return 0


def row(name: str, *, poly_timeout: float | None = None) -> dict[str, Any]:
    """One row of the table: the plant ``name`` (a key of :data:`ROWS`).

    Parameters
    ----------
    name : str
        The row.
    poly_timeout : float, optional
        Run the polytopic design in a child process killed after this many
        seconds; None runs it in this process, without a limit.

    Returns
    -------
    dict
        ``name, source, n, m, q, k, input_vertices, input_bound, alpha, box,
        build_seconds`` (loading the model), ``bounds`` (``method, seconds,
        converged, tolerances``) and, per formulation, ``blocks,
        block_size`` and either ``not_run`` (why) or ``lmi_seconds, feasible,
        status`` (and when feasible ``solve_time, gain_norm,
        condition_number, decay_certified``).
    """
    from ofrl_drake.jacobian_bounds import jacobian_bounds
    from ofrl_drake.lmi import MAX_CORNERS

    start = time.perf_counter()
    plant = build(name)
    build_seconds = time.perf_counter() - start
    start = time.perf_counter()
    bounds = jacobian_bounds(
        plant.system, plant.box, plant.jacobian_method, **dict(plant.tolerances)
    )
    bounds_seconds = time.perf_counter() - start
    blocks = _blocks(plant, bounds)
    system = plant.system
    out: dict[str, Any] = {
        "name": name,
        "source": "synthetic" if ROWS[name] is None else ROWS[name].relative_to(ROOT).as_posix(),
        "n": system.n,
        "m": system.m,
        "q": system.q,
        "k": blocks["k"],
        "input_vertices": blocks["input_vertices"],
        "input_bound": plant.input_bound,
        "alpha": plant.alpha,
        "box": {"lower": plant.box[0].tolist(), "upper": plant.box[1].tolist()},
        "build_seconds": build_seconds,
        "bounds": {
            "method": bounds.method,
            "seconds": bounds_seconds,
            "converged": None if bounds.excess is None else bool(bounds.excess.converged),
            "tolerances": dict(plant.tolerances),
        },
    }
    for formulation in FORMULATIONS:
        entry = dict(blocks[formulation])
        if formulation == "polytopic" and entry["blocks"] > MAX_CORNERS:
            entry["not_run"] = f"not run: {entry['blocks']} corners (> MAX_CORNERS = {MAX_CORNERS})"
        elif formulation == "polytopic" and poly_timeout is not None:
            result = _design_in_child(plant, bounds, formulation, poly_timeout)
            if "timeout" in result:
                entry["not_run"] = (
                    f"not run: {entry['blocks']} corners (did not finish in {poly_timeout:g} s)"
                )
            elif "error" in result:
                entry["not_run"] = f"not run: {entry['blocks']} corners ({result['error']})"
            else:
                entry.update(result)
        else:
            entry.update(_design(plant, bounds, formulation))
        out[formulation] = entry
        print(f"  {name}: {formulation} done", file=sys.stderr, flush=True)
    return out


def machine() -> dict[str, Any]:
    """The machine the table was measured on."""
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
    }


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _status(status: str) -> str:
    """The solver's own word: ``"kSolutionFound (AlmostSolved)"`` -> ``"AlmostSolved"``."""
    inner = status.rpartition("(")[2].rstrip(")")
    return inner or status


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """The Markdown table of :func:`row` results, one line per plant and formulation."""
    out = [
        "| plant | n | k | bounds (s) | converged | formulation | LMI blocks x size "
        "| LMI (s) | solver | alpha | \\|\\|L\\|\\| | cond(P) | decay-certified |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        b = r["bounds"]
        for formulation in FORMULATIONS:
            e = r[formulation]
            blocks = f"{e['blocks']} x {e['block_size']}"
            head = (
                f"| {r['name']} | {r['n']} | {r['k']} | {b['seconds']:.3g} | {b['converged']} "
                f"| {formulation} | {blocks} "
            )
            if "not_run" in e:
                out.append(head + f"| {e['not_run']} | - | {r['alpha']:g} | - | - | - |")
            elif not e["feasible"]:
                out.append(
                    head + f"| {e['lmi_seconds']:.3g} | {_status(e['status'])} | {r['alpha']:g} "
                    "| infeasible | - | False |"
                )
            else:
                out.append(
                    head + f"| {e['lmi_seconds']:.3g} | {_status(e['status'])} | {r['alpha']:g} "
                    f"| {_fmt(e['gain_norm'], '.4g')} | {_fmt(e['condition_number'], '.3g')} "
                    f"| {e['decay_certified']} |"
                )
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the rows, print the table, write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", nargs="+", choices=list(ROWS), default=list(ROWS))
    parser.add_argument(
        "--poly-timeout",
        type=float,
        default=180.0,
        help="kill the polytopic design after this many seconds (default 180)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=ROOT / "benchmarks" / "multilink_scaling.json",
        help="the JSON file (default benchmarks/multilink_scaling.json)",
    )
    parser.add_argument(
        "--child", nargs=3, metavar=("ROW", "FORMULATION", "BOUNDS"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.child:
        return _child(*args.child)
    load_start = os.getloadavg()
    start = time.perf_counter()
    rows = [row(name, poly_timeout=args.poly_timeout) for name in args.rows]
    results = {
        "machine": machine(),
        "load_average": {"start": list(load_start), "end": list(os.getloadavg())},
        "poly_timeout": args.poly_timeout,
        "wall_time": time.perf_counter() - start,
        "rows": rows,
    }
    table = format_table(rows)
    print(table)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
