"""Certified Jacobian bounds of multibody plants: the structure method against the others.

``python -m benchmarks.multibody_bounds [--timeout S] [--out FILE.json]``

For three upright plants (Drake's acrobot, Drake's cart-pole and
``diagrams/models/cart_double_pendulum.urdf``) on the boxes of
docs/multibody_bounds.md, three ways to bound the Jacobians of f and g:

* ``sampled``: min and max over a grid plus random points (not guaranteed);
* ``certified``: today's default for a multibody model, from its
  ``M(q), tau(q, v), B`` structure (:mod:`ofrl_drake.multibody_bounds`);
* ``expression``: the certified method on the symbolic ``f`` and ``g``
  themselves, what multibody models used before (the same ``f`` and ``g``
  wrapped in a plain :class:`~ofrl_drake.model.ControlAffineSystem`, which has
  no structure to offer).

Each runs in a fresh Python process (so its peak memory is its own), killed
after ``--timeout`` seconds. Reported: wall time of the ``jacobian_bounds``
call, the process's peak resident memory and the part the call added, whether
the refinement converged, and the widths against the sampled ones (the ratio
of certified to sampled width over the entries whose sampled width is not 0,
and the largest certified width among the entries whose sampled width is 0).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: name -> (model, upright equilibrium x*, box around it, in z = x - x*)
PLANTS: dict[str, tuple[str, list[float], tuple[list[float], list[float]]]] = {
    "acrobot": (
        "package://drake/examples/acrobot/Acrobot.urdf",
        [np.pi, 0.0, 0.0, 0.0],
        ([-0.3, -0.3, -2.0, -2.0], [0.3, 0.3, 2.0, 2.0]),
    ),
    "cart_pole": (
        "package://drake/examples/multibody/cart_pole/cart_pole.sdf",
        [0.0, np.pi, 0.0, 0.0],
        ([-2.0, -0.4, -1.5, -1.5], [2.0, 0.4, 1.5, 1.5]),
    ),
    "cart_double_pendulum": (
        str(ROOT / "diagrams" / "models" / "cart_double_pendulum.urdf"),
        [0.0, np.pi, 0.0, 0.0, 0.0, 0.0],
        ([-0.5, -0.2, -0.2, -1.0, -1.0, -1.0], [0.5, 0.2, 0.2, 1.0, 1.0, 1.0]),
    ),
}
METHODS = ("sampled", "certified", "expression")


def _peak_rss_mb() -> float:
    """This process's peak resident memory, MB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure_one(plant: str, method: str) -> dict[str, Any]:
    """Bounds of ``plant`` by ``method`` in this process: time, memory, the bounds."""
    from ofrl_drake.errors import OfrlError
    from ofrl_drake.jacobian_bounds import jacobian_bounds
    from ofrl_drake.model import ControlAffineSystem

    model, x_eq, box = PLANTS[plant]
    system = ControlAffineSystem.from_multibody(model).shifted(x_eq)
    if method == "expression":  # the same f and g, no structure: the expression method
        system = ControlAffineSystem(system.f, system.g, system.C, name=system.name)
    jacobian_bounds(system, box, "sampled")  # warm: imports, symbolic Jacobians
    before = _peak_rss_mb()
    start = time.perf_counter()
    try:
        bounds = jacobian_bounds(system, box, "sampled" if method == "sampled" else "certified")
    except OfrlError as err:  # reported, with its time and memory
        return {
            "seconds": time.perf_counter() - start,
            "peak_rss_mb": _peak_rss_mb(),
            "rss_before_mb": before,
            "raised": f"{type(err).__name__}: {err}",
        }
    seconds = time.perf_counter() - start
    return {
        "seconds": seconds,
        "peak_rss_mb": _peak_rss_mb(),
        "rss_before_mb": before,
        "converged": None if bounds.excess is None else bool(bounds.excess.converged),
        "bounds": bounds.to_dict(),
    }


def _run_child(plant: str, method: str, timeout: float) -> dict[str, Any]:
    """:func:`measure_one` in a fresh process, killed (by its pid) after ``timeout`` s."""
    cmd = [sys.executable, "-m", "benchmarks.multibody_bounds", "--one", plant, method]
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    peak = 0.0
    while proc.poll() is None:
        peak = max(peak, _vm_hwm_mb(proc.pid))
        if time.perf_counter() - start > timeout:
            proc.kill()
            proc.wait()
            return {"timeout": timeout, "peak_rss_mb": peak}
        time.sleep(0.2)
    out, err = proc.communicate()
    if proc.returncode != 0:
        return {"error": err.decode().strip().splitlines()[-1], "peak_rss_mb": peak}
    return json.loads(out.decode().strip().splitlines()[-1])


def _vm_hwm_mb(pid: int) -> float:
    """The peak resident memory of a running process, from /proc (0 if unreadable)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _widths(bounds: dict[str, Any]) -> np.ndarray:
    return np.concatenate(
        [
            (np.array(bounds["Mf2"]) - np.array(bounds["Mf1"])).ravel(),
            (np.array(bounds["Mg2"]) - np.array(bounds["Mg1"])).ravel(),
        ]
    )


def summarize(rows: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Width ratios against the sampled bounds of the same plant."""
    sampled = _widths(rows["sampled"]["bounds"])
    out = {}
    for method, row in rows.items():
        info = {k: v for k, v in row.items() if k != "bounds"}
        if "bounds" in row:
            w = _widths(row["bounds"])
            wide = sampled > 0
            ratio = w[wide] / sampled[wide]
            info.update(
                max_ratio=float(ratio.max()),
                median_ratio=float(np.median(ratio)),
                max_width=float(w.max()),
                max_width_where_sampled_is_0=float(w[~wide].max()) if (~wide).any() else 0.0,
            )
        out[method] = info
    return out


def _cell(info: dict[str, Any], key: str, fmt: str) -> str:
    if "timeout" in info:
        return f"> {info['timeout']:g} s, killed" if key == "seconds" else "-"
    if "error" in info:
        return info["error"][:40] if key == "seconds" else "-"
    if "raised" in info and key == "converged":
        return "raised " + info["raised"].split(":")[0]
    value = info.get(key)
    return "-" if value is None else format(value, fmt)


def table(results: dict[str, dict[str, Any]]) -> str:
    """The Markdown table of docs/multibody_bounds.md."""
    lines = [
        "| plant | method | time | peak memory (MB) | added (MB) | converged | "
        "max width ratio | median ratio | max width | width where sampled is 0 |",
        "|---|---|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for plant, methods in results.items():
        for method, info in methods.items():
            added = (
                "-"
                if "rss_before_mb" not in info
                else f"{info['peak_rss_mb'] - info['rss_before_mb']:.0f}"
            )
            seconds = _cell(info, "seconds", ".3g")
            seconds = seconds if not seconds[0].isdigit() else seconds + " s"
            lines.append(
                f"| {plant} | {method} | {seconds} | {info.get('peak_rss_mb', 0):.0f} | {added} | "
                f"{_cell(info, 'converged', '')} | {_cell(info, 'max_ratio', '.3g')} | "
                f"{_cell(info, 'median_ratio', '.3g')} | {_cell(info, 'max_width', '.4g')} | "
                f"{_cell(info, 'max_width_where_sampled_is_0', '.3g')} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run every plant and method; print the table; write the JSON."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.multibody_bounds", description=__doc__)
    p.add_argument("--timeout", type=float, default=300.0, help="seconds per run (default 300)")
    p.add_argument("--plants", nargs="+", choices=list(PLANTS), default=list(PLANTS))
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    p.add_argument("--out", type=Path, help="write the results to this JSON file")
    p.add_argument("--one", nargs=2, metavar=("PLANT", "METHOD"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.one:
        print(json.dumps(measure_one(*args.one)))
        return 0
    results = {}
    for plant in args.plants:
        rows = {"sampled": _run_child(plant, "sampled", args.timeout)}
        for method in args.methods:
            if method != "sampled":
                rows[method] = _run_child(plant, method, args.timeout)
        results[plant] = summarize(rows)
        print(f"{plant}: done", file=sys.stderr)
    print(table(results))
    if args.out:
        args.out.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
