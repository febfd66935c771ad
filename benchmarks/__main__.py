"""Run the benchmarks: ``python -m benchmarks [--quick] [--out FILE.json] [--markdown FILE.md]``.

Prints Markdown tables (runs against both baselines, per-evaluation profile,
scaling rows, sweep throughput, LMI design, targets) and writes every number
to a JSON file; ``--markdown`` writes the tables, with the machine and its
load, into a file as well (``benchmarks/RESULTS.md`` includes that part).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks import suite
from benchmarks.cases import with_duration
from benchmarks.evaluation import evaluation_profile
from benchmarks.report import format_report, targets
from benchmarks.scaling import ScalingSettings, scaling_rows
from benchmarks.sweep import sweep_throughput
from benchmarks.timing import machine_info, speed_probe

DIAGRAMS = Path(__file__).resolve().parents[1] / "diagrams"
PAPER = DIAGRAMS / "two_state_paper.yaml"
MIMO = DIAGRAMS / "coupled_two_state.yaml"
MULTIBODY = (DIAGRAMS / "pendulum_upright.yaml", DIAGRAMS / "cart_pole.yaml")

SECTIONS = (
    "paper",
    "overhead",
    "profile",
    "bellman",
    "points",
    "basis",
    "state_dimension",
    "scaling",
    "blocks",
    "integrators",
    "sweep",
    "compile",
    "lmi",
)

QUICK = suite.Settings(
    repeats=2,
    overhead_batches=3,
    overhead_calls=200,
    point_grids=((10, 10), (25, 40)),
    integrator_cases=(("runge_kutta3", 1e-3, 0.1), ("radau3", 1e-3, 0.1)),
    lmi_cases=(("drake", "clarabel"), ("cvxpy", "clarabel")),
    bellman_batches=3,
    bellman_calls=200,
    scaling=ScalingSettings(point_counts=(100, 1000), duration=0.1, basis_duration=0.02, repeats=1),
    sweep_counts=(1, 2),
    sweep_repeats=1,
)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="Time the Drake closed loop against a fused numpy baseline.",
    )
    p.add_argument(
        "--quick", action="store_true", help="fewer repeats, cases and points (a smoke run)"
    )
    p.add_argument("--out", type=Path, help="write the results to this JSON file")
    p.add_argument(
        "--markdown", type=Path, help="write the Markdown tables (and the machine) to this file"
    )
    p.add_argument("--repeats", type=int, help="timed runs per case (default 5, quick 2)")
    p.add_argument(
        "--duration",
        type=float,
        help="simulated seconds of the paper, coupled and multibody runs and of the sweep "
        "(default: each scenario's horizon; the scaling rows have their own)",
    )
    p.add_argument(
        "--only",
        nargs="+",
        choices=SECTIONS,
        metavar="SECTION",
        help=f"run only these sections: {', '.join(SECTIONS)}",
    )
    return p


def run(
    settings: suite.Settings, sections: Sequence[str], duration: float | None
) -> dict[str, Any]:
    """Run ``sections`` and return the results, with the targets checked."""
    from ofrl_drake import load_scenario

    paper = with_duration(load_scenario(PAPER), duration)
    mimo = with_duration(load_scenario(MIMO), duration)
    multibody = [with_duration(load_scenario(path), duration) for path in MULTIBODY]
    results: dict[str, Any] = {
        "machine": machine_info(),
        "settings": {
            "repeats": settings.repeats,
            "duration": paper.simulation.duration,
            "baseline": {
                "method": suite.BASELINE_METHOD,
                "rtol": suite.BASELINE_TOLERANCES[0],
                "atol": suite.BASELINE_TOLERANCES[1],
                "kinds": list(suite.BASELINES),
            },
            "paper_simulation": {
                "integrator": paper.simulation.integrator,
                "accuracy": paper.simulation.accuracy,
                "max_step": paper.simulation.max_step,
                "log_period": paper.simulation.log_period,
            },
        },
        "section_seconds": {},
        "speed_probe": {"start": speed_probe()},
    }
    jobs = {
        "paper": lambda: suite.paper_end_to_end(paper, settings),
        "overhead": lambda: suite.evaluation_overhead(paper, settings),
        "profile": lambda: evaluation_profile(
            paper, settings.overhead_calls, settings.overhead_batches
        ),
        "bellman": lambda: suite.bellman_math(paper, settings),
        "points": lambda: suite.points_scaling(paper, settings),
        "basis": lambda: suite.basis_scaling(paper, settings),
        "state_dimension": lambda: suite.state_dimension([paper, mimo], settings),
        "scaling": lambda: scaling_rows(settings.scaling),
        "blocks": lambda: suite.block_kinds([paper, mimo, *multibody], settings),
        "integrators": lambda: suite.integrators(paper, settings),
        "sweep": lambda: sweep_throughput(
            paper, settings.sweep_counts, settings.sweep_repeats, duration=duration
        ),
        "compile": lambda: suite.compile_cost(str(PAPER)),
        "lmi": lambda: suite.lmi_design([paper, mimo], settings),
    }
    for name in SECTIONS:
        if name not in sections:
            continue
        print(f"running {name} ...", file=sys.stderr, flush=True)
        seconds, value = suite.timed(jobs[name])
        results["lmi_design" if name == "lmi" else name] = value
        results["section_seconds"][name] = seconds
    results["speed_probe"]["end"] = speed_probe()
    results["targets"] = targets(results)
    return results


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = _parser().parse_args(argv)
    settings = QUICK if args.quick else suite.Settings()
    if args.repeats is not None:
        if args.repeats < 1:
            _parser().error("--repeats must be >= 1")
        settings = dataclasses.replace(settings, repeats=args.repeats)
    if args.duration is not None and not args.duration > 0:
        _parser().error("--duration must be > 0")
    results = run(settings, args.only or SECTIONS, args.duration)
    text = format_report(results)
    print(text)
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(text + "\n")
        print(f"\nwrote {args.markdown}", file=sys.stderr)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2) + "\n")
        print(f"\nwrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
