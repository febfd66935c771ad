"""Monte Carlo: one scenario under many noise seeds and sampled truths.

Run ``k`` of ``montecarlo(scenario, runs, seed)`` uses the measurement seed
``seed + k`` and, with ``mass_spread = s > 0``, a truth whose every body mass
is scaled by a factor drawn uniformly in ``[1 - s, 1 + s]`` (times the
scenario's own ``truth.body_mass_scale``), drawn from
``numpy.random.default_rng([seed, k])``. Everything else is the scenario.

Each run is scored like an ablation row: ``status``, ``regulated``
(:func:`~ofrl_drake.ablation_metrics.regulation`, with the scenario's
``simulation.regulation_tolerance``), ``|x(T) - x*|``, the rms
estimation error, ``J(T)`` and its ratio to ``J*`` of the nominal problem (the
model, noise-free, from ``x0``; solved once); a run the guard cut short keeps
NaN for the four numbers, whose values at the stop are not comparable (as in
``ablate``). The runs are tasks of the sweep
engine (:mod:`ofrl_drake.sweep`), serial or on Dask, up to
:data:`RUNS_PER_TASK` consecutive seeds per task (:func:`run_seeds`): a task
designs the observer once, and without a mass spread builds the closed loop
once and re-runs it by writing each seed into the context. With ``out``, rows are
appended to ``montecarlo.csv`` and fsynced as tasks finish, ``montecarlo.json``
records what defines the sweep so that ``resume`` refuses another one by name,
and ``runs/`` keeps each run's trajectories for the envelope figure
(:func:`write_montecarlo_report`), written with the run's row (none for a run
that failed before it had logs); the folder is a
:class:`~ofrl_drake.sweep_store.SweepStore`, as an ablation's is.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ofrl_drake.ablation_metrics import (
    optimality_ratio,
    regulation_shortfall,
    rms_estimation_error,
)
from ofrl_drake.atomic import atomic_write_text
from ofrl_drake.checks import (
    MAX_DRAKE_SEED,
    count_at_most,
    drake_seed,
    integer_at_least,
    is_real_number,
    number_to_json,
)
from ofrl_drake.errors import ModelError, OfrlError, OutputError, one_line, status_line
from ofrl_drake.limits import MAX_RUNS, RUNS_FIX
from ofrl_drake.plants import check_dynamics, dynamics_fingerprints
from ofrl_drake.scenario import MeasurementConfig, Scenario, TruthConfig, check_scenario
from ofrl_drake.sweep import execute, split_consecutive, worker_threads
from ofrl_drake.sweep_store import (
    DYNAMICS_KEY,
    OPTIMAL_KEY,
    SweepFiles,
    SweepStore,
    describe_difference,
    load_arrays,
)

__all__ = [
    "CSV_COLUMNS",
    "FILES",
    "RUNS_PER_TASK",
    "IdenticalRunsWarning",
    "MonteCarloError",
    "OptimalCostWarning",
    "envelope_samples",
    "identical_runs",
    "montecarlo",
    "montecarlo_table",
    "read_montecarlo_rows",
    "run_for",
    "run_seeds",
    "write_montecarlo_report",
]

#: The columns of ``montecarlo.csv``, in order.
CSV_COLUMNS = (
    "seed",
    "perturbation",
    "status",
    "regulated",
    "final_state_norm",
    "rms_estimation_error",
    "cost",
    "optimal_cost",
    "optimality_ratio",
    "wall_time",
)


class MonteCarloError(OfrlError):
    """A Monte Carlo sweep asked for with bad input (runs, spread, output, resume)."""


#: What a Monte Carlo sweep keeps in its ``--out`` folder (a :mod:`~ofrl_drake.sweep_store`).
FILES = SweepFiles(
    table="montecarlo.csv",
    plan="montecarlo.json",
    columns=CSV_COLUMNS,
    text=("seed", "perturbation", "status", "regulated"),
    command="montecarlo",
    kind="Monte Carlo table",
    error=MonteCarloError,
)


def _bodies(scenario: Scenario) -> list[str]:
    from ofrl_drake.plants import multibody_body_names, resolve_truth

    truth = resolve_truth(dataclasses.replace(scenario, truth=scenario.truth or TruthConfig()))
    names = multibody_body_names(truth)
    if names is None:
        raise MonteCarloError(
            "mass_spread (--mass-spread) perturbs the body masses of a multibody truth; the "
            "scenario's truth is not one (give plant.multibody or truth.plant.multibody)."
        )
    return [name for name in names if name != "world"]


def run_for(scenario: Scenario, seed: int, k: int, mass_spread: float) -> tuple[Scenario, dict]:
    """The scenario of run ``k``: its measurement seed and its perturbed truth, if any."""
    measurement = scenario.measurement or MeasurementConfig()
    changed = dataclasses.replace(
        scenario, measurement=dataclasses.replace(measurement, seed=int(seed) + int(k))
    )
    perturbation: dict[str, float] = {}
    if mass_spread > 0:
        truth = scenario.truth or TruthConfig()
        rng = np.random.default_rng([int(seed), int(k)])
        for body in _bodies(scenario):
            base = truth.body_mass_scale.get(body, 1.0)
            perturbation[body] = float(base * rng.uniform(1 - mass_spread, 1 + mass_spread))
        changed = dataclasses.replace(
            changed, truth=dataclasses.replace(truth, body_mass_scale=perturbation)
        )
    return changed, perturbation


#: At most this many runs per task: one task builds the loop (or designs the
#: observer) once for its runs; its rows are recorded when it ends.
RUNS_PER_TASK = 8


def run_seeds(
    scenario: Scenario,
    seed: int,
    ks: Sequence[int],
    mass_spread: float,
    dynamics: Mapping[str, str | None] | None = None,
) -> list[dict[str, Any]]:
    """Simulate runs ``ks`` (:func:`run_for`), designing the observer once; never raises.

    Without a mass spread the runs differ only in their noise seed, which a
    run writes into the context: one closed loop is built (Jacobian bounds,
    LMI, diagram) and re-run for every ``k``
    (``simulate(run, loop=loop)``). With one, each run's truth differs, so
    each run builds its own diagram, with the observer design of the first
    (the design is the model's, not the truth's). With ``dynamics`` (the
    client's :func:`~ofrl_drake.plants.dynamics_fingerprints`), a worker whose
    plant's code differs runs nothing (:func:`~ofrl_drake.plants.check_dynamics`).

    Returns
    -------
    list of dict
        ``{"row": ..., "logs": ...}`` per run, in the order of ``ks``; an error
        becomes the status of its run (of every run, if the build fails or the
        plant differs from the client's).
    """
    from ofrl_drake.diagram import build_closed_loop

    out: list[dict[str, Any]] = []
    try:
        check_dynamics(scenario, dynamics)
    except Exception as err:
        return [_failed(seed + k, {}, err, time.perf_counter()) for k in ks]
    loop: Any = None
    for k in ks:
        start = time.perf_counter()
        perturbation: dict[str, float] = {}  # unknown if drawing the truth fails
        try:
            run, perturbation = run_for(scenario, seed, k, mass_spread)
            if loop is None or mass_spread > 0:
                design = None if loop is None else loop.design
                loop = build_closed_loop(run, design=design)
            out.append(_one_run(run, loop, seed + k, perturbation, start))
        except Exception as err:  # the build failed: the status of this run
            out.append(_failed(seed + k, perturbation, err, start))
    return out


def _row(seed: int, perturbation: dict[str, float]) -> dict[str, Any]:
    return {
        "seed": str(int(seed)),
        "perturbation": json.dumps(perturbation, sort_keys=True),
        "regulated": "false",
        "final_state_norm": math.nan,
        "rms_estimation_error": math.nan,
        "cost": math.nan,
    }


def _failed(
    seed: int, perturbation: dict[str, float], err: BaseException, start: float
) -> dict[str, Any]:
    row = _row(seed, perturbation)
    row["status"] = status_line(err)
    row["wall_time"] = time.perf_counter() - start
    return {"row": row, "logs": {}}


def _one_run(
    run: Scenario, loop: Any, seed: int, perturbation: dict[str, float], start: float
) -> dict[str, Any]:
    """Simulate ``run`` on the built ``loop``; never raises (an error becomes its status)."""
    from ofrl_drake.simulation import simulate

    try:
        result = simulate(run, loop=loop, progress=False)
    except Exception as err:
        return _failed(seed, perturbation, err, start)
    row = _row(seed, perturbation)
    row["status"] = result.stopped or "ok"
    row["regulated"] = "true" if result.regulated else "false"
    if result.stopped is None:  # a run cut short keeps NaN: J(t_stop) is not J(T)
        row["final_state_norm"] = float(np.linalg.norm(result.x[-1]))
        row["rms_estimation_error"] = rms_estimation_error(result.t, result.x, result.xhat)
        row["cost"] = float(result.cost[-1])
    row["wall_time"] = time.perf_counter() - start
    logs = {"t": result.t, "x": result.original("x")}
    regulation = result.reports.get("regulation")
    if regulation is not None:  # why an ok run did not regulate, for montecarlo.md
        logs["final_error"] = np.asarray(regulation["final_error"], dtype=float)
        logs["regulation_tolerance"] = np.asarray(regulation["tolerance"], dtype=float)
        logs["inside_observer_box"] = np.asarray(regulation["inside_observer_box"])
    if result.state_units is not None:  # for the envelope's axes
        logs["state_units"] = np.asarray(result.state_units, dtype=str)
    return {"row": row, "logs": logs}


def read_montecarlo_rows(path: str | os.PathLike[str], *, repair: bool = False) -> list[dict]:
    """The rows of a ``montecarlo.csv`` (``seed``, ``perturbation``, ``status``,
    ``regulated`` as text, the rest as floats)."""
    return FILES.read(path, repair=repair)


def _plan(
    scenario: Scenario,
    runs: int,
    seed: int,
    mass_spread: float,
    dynamics: dict[str, str | None],
    optimal: dict[str, Any],
) -> dict[str, Any]:
    """The contents of ``montecarlo.json``: what defines the sweep, and how J* is had."""
    return {
        "scenario": scenario.name,
        "runs": int(runs),
        "seed": int(seed),
        "mass_spread": float(mass_spread),
        "scenario_values": dataclasses.asdict(scenario),
        DYNAMICS_KEY: dynamics,
        OPTIMAL_KEY: optimal,
    }


def _optimal_plan(optimal_cost: float | None, solver: str | None) -> dict[str, Any]:
    """How the sweep's J* is had: given, or solved (:func:`~ofrl_drake.optimal.solving`).

    Raises
    ------
    OfrlError
        If ``solver`` is not an available solver.
    """
    from ofrl_drake.optimal import solving

    if optimal_cost is None:
        return solving(None, solver)
    if solver is not None:
        raise MonteCarloError(
            f"solver: J* is given as optimal_cost = {optimal_cost!r}, so no solver {solver!r} "
            "runs; pass one or the other."
        )
    return {"optimal_cost": number_to_json(optimal_cost)}


def _resume_mismatch(old: Mapping[str, Any], new: Mapping[str, Any]) -> str | None:
    """Why a ``--resume`` with plan ``new`` cannot continue the sweep of plan ``old``."""
    where = describe_difference(old, new)
    return None if where is None else f"the folder's sweep differs in {where}"


def _check_seeds(seed: int, runs: int) -> None:
    """Refuse a sweep whose last measurement seed, ``seed + runs - 1``, Drake cannot keep.

    Drake keeps 32 bits of a seed (:func:`~ofrl_drake.checks.drake_seed`): a
    larger one fails inside pybind11 or repeats a smaller seed's noise.
    """
    try:
        drake_seed(
            f"the last run's measurement seed, seed + runs - 1 = {seed} + {runs} - 1 "
            "(--seed, --runs),",
            int(seed) + int(runs) - 1,
            error=MonteCarloError,
        )
    except MonteCarloError as err:
        largest = MAX_DRAKE_SEED - int(runs) + 1
        fix = (
            f"With runs = {runs}, give a seed of at most {largest}."
            if largest >= 0
            else f"Drake has {MAX_DRAKE_SEED + 1} seeds; give runs of at most that."
        )
        raise MonteCarloError(f"{err} {fix}") from None


def montecarlo(
    scenario: Scenario,
    runs: int,
    seed: int = 0,
    *,
    mass_spread: float = 0.0,
    client: Any = None,
    out: str | os.PathLike[str] | None = None,
    resume: bool = False,
    progress: bool | None = None,
    optimal_cost: float | None = None,
    solver: str | None = None,
) -> list[dict[str, Any]]:
    """Run ``scenario`` under ``runs`` noise seeds (and sampled truths) and score each run.

    Parameters
    ----------
    scenario : Scenario
        Validated; its ``measurement``, ``actuation`` and ``truth`` apply to
        every run, with the seed and masses of the run.
    runs : int
        ``N >= 1``.
    seed : int
        Run ``k`` uses measurement seed ``seed + k``; Drake keeps 32 bits of a
        seed, so ``seed + runs - 1`` must be at most ``2**32 - 1``.
    mass_spread : float
        ``0 <= s < 1``: each body mass of a multibody truth is scaled by
        ``U[1 - s, 1 + s]`` per run (0: no perturbation).
    client : distributed.Client, optional
        Run on this Dask cluster; without one, serially in this process.
    out : str or Path, optional
        Folder for ``montecarlo.csv`` (streamed), ``montecarlo.json`` and
        ``runs/``. A sweep that stops before its first row (an error, an
        interrupt) removes what it created there, so nothing half-written stays.
    resume : bool
        Keep the rows already in ``out`` and run only the missing seeds.
    progress : bool, optional
        A bar of finished runs on stderr (default: only on a terminal).
    optimal_cost : float, optional
        ``J*`` of the nominal problem (a number >= 0, or NaN if unknown);
        solved here when omitted.
    solver : {"snopt", "ipopt"}, optional
        The solver of that ``J*`` (default: SNOPT if available).

    Returns
    -------
    list of dict
        One row per run (:data:`CSV_COLUMNS`), in seed order, each also with
        ``optimal_status``: why ``J*`` is not available (NaN), the same for
        every row and not a column of the table; empty when it is.

    Raises
    ------
    MonteCarloError
        Before any run: for bad arguments (``runs`` not an integer from 1 to
        :data:`~ofrl_drake.limits.MAX_RUNS`, ``seed``, a last
        measurement seed ``seed + runs - 1`` above ``2**32 - 1``, which Drake
        cannot keep, a ``mass_spread`` that is not a number in ``[0, 1)``, an
        ``optimal_cost`` that is not a number >= 0 or NaN, an unknown or
        unavailable ``solver``), an existing table
        without ``resume``, or a ``resume`` of a different sweep (the first
        differing key named, with the folder's value and this call's);
        during the sweep, for a task that failed outside its own guard (a
        worker lost).
    OutputError
        If ``out`` cannot be written, or a file of ``out/runs/`` that belongs
        to no row of the table cannot be removed.
    """
    check_scenario(scenario, "montecarlo")
    count_at_most(
        "runs (--runs)",
        runs,
        1,
        MAX_RUNS,
        RUNS_FIX,
        error=MonteCarloError,
    )
    integer_at_least("seed (--seed)", seed, 0, error=MonteCarloError)
    _check_seeds(seed, runs)
    if not (is_real_number(mass_spread) and math.isfinite(mass_spread) and 0 <= mass_spread < 1):
        raise MonteCarloError(
            f"mass_spread (--mass-spread) must be in [0, 1); got {mass_spread!r}."
        )
    if optimal_cost is not None and not (
        is_real_number(optimal_cost) and (math.isnan(optimal_cost) or 0 <= optimal_cost < math.inf)
    ):
        raise MonteCarloError(
            "optimal_cost: must be J* of the nominal problem, a number >= 0 (NaN if unknown), "
            f"or None to solve it here; got {optimal_cost!r}."
        )
    how = _optimal_plan(optimal_cost, solver)  # refuses an unknown solver before any run
    if mass_spread > 0:
        _bodies(scenario)  # refuse a truth without bodies before any run
    dynamics = dynamics_fingerprints(scenario)  # in the plan, and checked by every task
    store = None if out is None else SweepStore(FILES, Path(out))
    # A sweep that stops before its first row removes what it wrote (SweepStore.recording).
    recording: contextlib.AbstractContextManager[list[dict[str, Any]]] = (
        contextlib.nullcontext([])
        if store is None
        else store.recording(
            _plan(scenario, runs, seed, mass_spread, dynamics, how),
            resume=resume,
            mismatch=_resume_mismatch,
        )
    )
    why: str | None = None
    if optimal_cost is not None and math.isnan(optimal_cost):
        why = "optimal_cost was given as NaN (unknown)"
    with recording as done:
        if optimal_cost is None:
            from ofrl_drake.optimal import optimal_control

            try:
                solved = optimal_control(scenario, solver=solver)
                why = None if solved.converged else solved.status
            except ModelError as err:  # a plant Drake cannot trace: the runs need no J*
                why = one_line(err)
            optimal_cost = solved.cost if why is None else math.nan
            if why is not None:
                warnings.warn(
                    OptimalCostWarning(
                        f"montecarlo {scenario.name}: J* of the nominal problem is not "
                        f"available, so the rows have no J/J*: {why}"
                    ),
                    stacklevel=2,
                )
        finished = {r["seed"]: r for r in done}
        todo = [k for k in range(runs) if str(seed + k) not in finished]

        parts = max(worker_threads(client), -(-len(todo) // RUNS_PER_TASK))

        def submit(engine: Any) -> dict[Any, tuple[int, ...]]:
            return {
                engine.submit(run_seeds, scenario, seed, tuple(ks), mass_spread, dynamics): tuple(
                    ks
                )
                for ks in split_consecutive(todo, parts)
            }

        def record(value: dict[str, Any]) -> dict:
            row = value["row"]
            row["optimal_cost"] = float(optimal_cost)
            row["optimality_ratio"] = optimality_ratio(row["cost"], optimal_cost)
            if store is not None:
                # The row's run, written with it; a run without logs leaves no earlier one.
                name = f"seed_{row['seed']}.npz"
                if value["logs"]:
                    store.save_run(name, value["logs"])
                else:
                    store.remove_run(name)
                store.write(row)
            finished[row["seed"]] = row
            return row

        def finish(ks: tuple[int, ...], value: Any, err: BaseException | None) -> list[dict]:
            if err is not None:  # the task guards itself; a worker lost is recorded too
                raise MonteCarloError(f"a Monte Carlo task failed (runs {list(ks)}): {err}")
            return [record(run) for run in value]

        execute(submit, finish, client=client, total=runs, done=runs - len(todo), progress=progress)
    return [{**finished[str(seed + k)], "optimal_status": why or ""} for k in range(runs)]


def _stats(values: Sequence[float]) -> str:
    """``mean ± std`` of the finite ``values``; ``(n = K)`` when K of them are not all."""
    arr = np.asarray(values, dtype=float)
    arr = arr[np.isfinite(arr)]
    if arr.size == 0:
        return "n/a"
    text = f"{arr.mean():.4g} ± {arr.std(ddof=1) if arr.size > 1 else 0.0:.2g}"
    return text if arr.size == len(values) else f"{text} (n = {arr.size})"


def montecarlo_table(rows: Sequence[dict]) -> str:
    """``montecarlo.md``'s statistics: success rate and mean ± standard deviation."""
    n = len(rows)
    ok = sum(r["status"] == "ok" for r in rows)
    good = sum(r["status"] == "ok" and r["regulated"] == "true" for r in rows)
    lines = [
        "| runs | ok | ok and regulated | success rate | \\|x(T) - x*\\| | rms \\|x - xhat\\| "
        "| J | J/J* |",
        "| --: | --: | --: | --: | --: | --: | --: | --: |",
        f"| {n} | {ok} | {good} | {good / n:.0%} | "
        f"{_stats([r['final_state_norm'] for r in rows])} | "
        f"{_stats([r['rms_estimation_error'] for r in rows])} | "
        f"{_stats([r['cost'] for r in rows])} | {_stats([r['optimality_ratio'] for r in rows])} |",
    ]
    return "\n".join(lines) + "\n"


def envelope_samples(
    logs: Sequence[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """Every run's state on one time grid, NaN after the run ended.

    ``logs`` holds ``(t, x)`` per run (``x`` of shape ``(T_k, n)``). The grid
    spans the longest run, as finely as its most finely logged run; a run the
    guard stopped early counts only up to its last sample (interpolating past
    it would hold its last state flat to the horizon). Returns ``(grid, stack)``
    with ``stack`` of shape ``(runs, grid size, n)``.
    """
    end = max(float(t[-1]) for t, _ in logs)
    size = max(t.size for t, _ in logs)
    grid = np.linspace(0.0, end, size)
    stack = np.full((len(logs), size, logs[0][1].shape[1]), np.nan)
    for k, (t, x) in enumerate(logs):
        inside = grid <= t[-1] * (1 + 1e-12)
        for i in range(x.shape[1]):
            stack[k, inside, i] = np.interp(grid[inside], t, x[:, i])
    return grid, stack


class OptimalCostWarning(UserWarning):
    """J* of a Monte Carlo sweep's nominal problem is not available (why is in the message)."""


class IdenticalRunsWarning(UserWarning):
    """Every run of a Monte Carlo sweep gave the same trajectory (nothing varied)."""


def identical_runs(logs: Sequence[tuple[np.ndarray, np.ndarray]]) -> bool:
    """Whether two or more runs' ``(t, x)`` logs are all equal, bit for bit.

    Without a mass spread the runs differ only in their measurement seed, which
    changes nothing when the scenario has no measurement noise: the envelope
    is then a band of width 0, and the report says so instead.
    """
    if len(logs) < 2:
        return False
    t0, x0 = logs[0]
    return all(np.array_equal(t, t0) and np.array_equal(x, x0) for t, x in logs[1:])


def _identical_note(rows: Sequence[dict], count: int) -> str:
    """One line: the ``count`` runs logged in ``runs/`` are identical, why, and the fix."""
    spread = any(json.loads(r["perturbation"]) for r in rows)
    why = (
        ""
        if spread
        else " (no --mass-spread, and the scenario has no measurement noise: the runs' "
        "noise seeds change nothing)"
    )
    return (
        f"the {count} runs are identical, bit for bit{why}; the envelope is their one curve. "
        "For runs that differ, give measurement.noise_std (with measurement.period > 0) "
        "or --mass-spread."
    )


def _state_units(runs: Sequence[Mapping[str, Any]]) -> list[str] | None:
    """The model's state units saved with the runs (``state_units``), or None if unknown."""
    for arrays in runs:
        if "state_units" in arrays:
            return [str(u) for u in arrays["state_units"]]
    return None


def _unit(units: Sequence[str] | None, i: int) -> str:
    """`` [m]`` for state entry ``i``, as the run's figures write it; empty if unknown.

    (:mod:`ofrl_drake.plotting` reads the units off a ``SimulationResult``; a
    sweep keeps only its runs' arrays.)
    """
    return f" [{units[i]}]" if units and units[i] else ""


def _not_regulated(row: Mapping[str, Any], arrays: Mapping[str, Any] | None) -> str:
    """Why a run that ended ``ok`` did not regulate, from the numbers saved with its logs."""
    if arrays is None or "final_error" not in arrays:  # not logged, or an earlier sweep's run
        return f"ok but not regulated (|x(T) - x*| = {row['final_state_norm']:.3g})"
    why = regulation_shortfall(
        arrays["final_error"], arrays["regulation_tolerance"], bool(arrays["inside_observer_box"])
    )
    return f"ok but not regulated: {why}"


def write_montecarlo_report(out: str | os.PathLike[str], rows: Sequence[dict], name: str) -> None:
    """``montecarlo.md`` and ``figures/envelope.png`` (the state envelope across runs).

    The envelope has one panel per state component (in the plant's own
    coordinates, with the model's units when it knows them), the legend below
    the panels. When the logged runs are all identical (:func:`identical_runs`),
    it draws their one curve instead of a band of width 0, and ``montecarlo.md``
    and an :class:`IdenticalRunsWarning` say so in one line. It draws the runs
    of ``rows`` saved in ``runs/``; when no run of ``rows`` was logged there is
    no envelope, and an ``envelope.png`` of an earlier sweep is removed.

    Warns
    -----
    IdenticalRunsWarning
        If two or more runs were logged and they are all identical.

    Raises
    ------
    OutputError
        If no run was logged and an earlier ``figures/envelope.png`` cannot be removed.
    """
    import matplotlib.pyplot as plt

    from ofrl_drake.plotting import save_png  # matplotlib only when a report is written

    out = Path(out)
    by_seed = {
        r["seed"]: arrays
        for r in rows
        if (arrays := load_arrays(out / "runs" / f"seed_{r['seed']}.npz")) is not None
    }
    saved = list(by_seed.values())
    logs = [(arrays["t"], arrays["x"]) for arrays in saved]
    same = identical_runs(logs)
    failed = [r for r in rows if not (r["status"] == "ok" and r["regulated"] == "true")]
    text = [
        f"# Monte Carlo: {name}",
        "",
        "A run succeeds when it ends `ok` and `regulated` (every |x_i(T) - x*_i| within "
        "`simulation.regulation_tolerance` of the observer box's half-width, 5% by default, "
        "and x, xhat inside the box).",
        "",
        montecarlo_table(rows),
    ]
    if rows and not any(math.isfinite(r["optimal_cost"]) for r in rows):
        why = next((r["optimal_status"] for r in rows if r.get("optimal_status")), None)
        text += [
            "J/J* is n/a: J* of the nominal problem is not available"
            + (f": {why}" if why else " (the command that ran the sweep said why).")
            + ("" if not why or why.endswith(".") else "."),
            "",
        ]
    if same:
        note = _identical_note(rows, len(logs))
        text += [note[0].upper() + note[1:], ""]
        warnings.warn(IdenticalRunsWarning(f"montecarlo {name}: {note}"), stacklevel=2)
    text += ["Runs that did not succeed:" if failed else "Every run succeeded.", ""]
    text += [
        f"- seed {r['seed']} ({r['perturbation']}): "
        + (_not_regulated(r, by_seed.get(r["seed"])) if r["status"] == "ok" else r["status"])
        for r in failed
    ]
    atomic_write_text(out / "montecarlo.md", "\n".join(text) + "\n")
    envelope = out / "figures" / "envelope.png"
    if not logs:  # an earlier sweep's envelope would pass for this one's
        try:
            envelope.unlink(missing_ok=True)
        except OSError as err:
            raise OutputError(
                f"--out: cannot remove {envelope} ({(err.strerror or 'error').lower()}): no "
                "run of this sweep was logged, and it draws runs that are not in "
                f"{FILES.table}; remove it yourself."
            ) from None
        return
    n = logs[0][1].shape[1]
    units = _state_units(saved)
    fig, axes = plt.subplots(n, 1, figsize=(6.5, 1.8 * n + 0.4), sharex=True, layout="constrained")
    axes = np.atleast_1d(axes)
    grid, stack = envelope_samples(logs)
    for i, ax in enumerate(axes):
        if same:
            ax.plot(grid, stack[0, :, i], lw=1.2, label=f"all {len(logs)} runs (identical)")
        else:
            lower, upper = np.nanmin(stack[:, :, i], axis=0), np.nanmax(stack[:, :, i], axis=0)
            ax.fill_between(grid, lower, upper, alpha=0.3, label="min-max")
            ax.plot(grid, np.nanmedian(stack[:, :, i], axis=0), lw=1.2, label="median")
        ax.set_ylabel(f"$x_{{{i + 1}}}${_unit(units, i)}")
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel(r"time $t$ [s]")
    what = f"{len(logs)} identical runs" if same else f"state envelope over {len(logs)} runs"
    fig.suptitle(f"{name}: {what}")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=len(handles), frameon=False)
    (out / "figures").mkdir(exist_ok=True)
    save_png(fig, envelope, 150)
