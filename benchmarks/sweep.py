"""Sweep throughput: ``ablate`` from 1 initial state against many, one worker.

:func:`sweep_throughput` times ``ofrl_drake.ablate`` (serial engine: one
worker) of the scenario's own loop (the variant ``baseline``) from the first
``k`` of ``max(counts)`` initial states drawn by
``ablation.sample_initial_states``, for each ``k`` in ``counts``, in two modes,
interleaved with a plain ``simulate()`` of the scenario:

* ``solved``: a fresh ``--out`` folder, so every initial state solves its
  ``J*`` (direct collocation), as a first sweep does;
* ``cached``: a fresh folder holding only the sweep's ``ablation.json`` and
  the ``optimal/`` cache of an untimed sweep over every state, so ``J*`` is
  read from disk and each initial state costs its run (build, simulate,
  metrics, the two policy evaluations, the row and trajectory files).

The cost per extra initial state is ``(t(k_max) - t(k_min)) / (k_max -
k_min)``; the target compares the ``cached`` one with one run's simulation
alone (``simulate()``'s ``AdvanceTo``).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.cases import with_duration
from benchmarks.timing import Timing, interleaved
from ofrl_drake.scenario import Scenario

__all__ = ["sweep_throughput"]


def sweep_throughput(
    scenario: Scenario,
    counts: Sequence[int],
    repeats: int,
    *,
    duration: float | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Seconds and runs per second of ``ablate`` for each number of initial states.

    Parameters
    ----------
    scenario : Scenario
    counts : sequence of int
        Numbers of initial states, e.g. ``(1, 8)``.
    repeats : int
        Interleaved timed runs of each case (after one warm-up round).
    duration : float, optional
        Horizon of the runs and of ``J*`` (default the scenario's).
    seed : int
        Seed of the initial states.
    """
    from ofrl_drake import ablate
    from ofrl_drake.ablation_grid import Variant, sample_initial_states
    from ofrl_drake.simulation import simulate

    counts = sorted(set(int(k) for k in counts))
    states = sample_initial_states(scenario, counts[-1], seed)
    variants = [Variant("baseline")]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        filled = root / "filled"
        ablate(scenario, variants, states, out=filled, duration=duration, progress=False)
        made = iter(range(10**9))

        def fresh(cached: bool) -> Path:
            out = root / f"run{next(made)}"
            if cached:
                shutil.copytree(filled / "optimal", out / "optimal")
                shutil.copy(filled / "ablation.json", out / "ablation.json")
            return out

        rows: dict[str, list[dict[str, Any]]] = {}

        def sweep(k: int, cached: bool) -> Callable[[], Any]:
            def run() -> Any:
                out = fresh(cached)
                found = ablate(
                    scenario, variants, states[:k], out=out, duration=duration, progress=False
                )
                rows[f"{'cached' if cached else 'solved'}_{k}"] = found
                shutil.rmtree(out)
                return found

            return run

        one = with_duration(scenario, duration)
        advance: list[float] = []

        def simulate_once() -> Any:
            result = simulate(one, progress=False)
            advance.append(result.wall_time)
            return result

        fns: dict[str, Callable[[], Any]] = {"simulate": simulate_once}
        for mode in ("solved", "cached"):
            for k in counts:
                fns[f"{mode}_{k}"] = sweep(k, mode == "cached")
        timings, _ = interleaved(fns, repeats)

    simulation = Timing(tuple(advance[-repeats:]))
    out: dict[str, Any] = {
        "scenario": scenario.name,
        "variants": [v.name for v in variants],
        "counts": counts,
        "workers": 1,
        "duration": scenario.simulation.duration if duration is None else duration,
        "simulate": timings["simulate"].to_dict(),
        "simulation": simulation.to_dict(),
    }
    first, last = counts[0], counts[-1]
    for mode in ("solved", "cached"):
        cases = {}
        for k in counts:
            timing = timings[f"{mode}_{k}"]
            cases[str(k)] = {
                **timing.to_dict(),
                "runs_per_second": k / timing.median,
                "run_wall_time_median": float(
                    np.median([r["wall_time"] for r in rows[f"{mode}_{k}"]])
                ),
                "statuses": sorted({r["status"] for r in rows[f"{mode}_{k}"]}),
            }
        extra = (timings[f"{mode}_{last}"].median - timings[f"{mode}_{first}"].median) / max(
            last - first, 1
        )
        out[mode] = {
            "cases": cases,
            "extra_state_seconds": extra,
            "extra_state_over_simulation": extra / simulation.median,
            "extra_state_over_simulate": extra / timings["simulate"].median,
        }
    return out
