"""Ablation sweeps: every variant from every initial state, against the optimum.

A sweep runs each :class:`~ofrl_drake.ablation_grid.Variant` (one choice per
slot, see :mod:`ofrl_drake.slots`) from each initial state
(:mod:`ofrl_drake.ablation_grid`), measures the run
(:mod:`ofrl_drake.ablation_metrics`) and divides its cost by the optimal cost
``J*`` from the same initial state (:mod:`ofrl_drake.optimal`). This module
holds the sweep itself: which tasks (:mod:`ofrl_drake.ablation_tasks`) it
submits, the rows it makes of them, and what its folder holds.

Engine
------
With a Dask ``distributed.Client`` the runs are Dask tasks; without one the
same tasks run one after another in this process (:mod:`ofrl_drake.sweep`).
A run task is one variant from its initial states still to do
(:func:`~ofrl_drake.ablation_tasks.run_variant_states`): the variant's loop,
its observer design (Jacobian bounds and LMI) included, is built once and
re-run from each state by writing the context only. On a cluster a variant's
states are split into as many tasks as it takes to keep every worker busy
(one task per variant when there are at least as many variants as workers).
``J*`` is one task per initial state, warm-started from the run from that
state of the first variant with the learned controller; those variants' tasks
go first, so in a serial sweep the rows come variant by variant, in the order
:func:`ablate` returns them when the first variant has the learned controller. Workers import
``ofrl_drake`` themselves, so a choice added with
:func:`~ofrl_drake.slots.register_variant` must be registered in the workers
too (e.g. in a module they import), not only in the driver.

Streaming and resume
--------------------
With ``out`` given, each row is appended to ``out/ablation.csv`` as soon as
its task and its ``J*`` are done, then flushed and fsynced, so a killed sweep
loses no row of a finished task (:mod:`ofrl_drake.sweep_store`). ``resume=True`` reads
the rows already there (dropping a torn last line) and runs only the missing
(variant, initial state) pairs; ``out/ablation.json`` records what defines the
sweep, so that a ``resume`` of another one is refused by name. Converged ``J*``
values are cached in ``out/optimal/``, one JSON file per scenario-problem hash
and initial state, and each run's trajectories are kept in ``out/runs/`` for
the figures (:mod:`ofrl_drake.ablation_report`), written with the run's row: a
run done again that fails before it has logs removes the file of its earlier
attempt, and a sweep in a folder without a table removes the files it finds
there with its first row (:class:`~ofrl_drake.sweep_store.SweepStore`).

A run that raises is recorded with its error on one line (``status``); the
sweep goes on. If the run is fine but ``J*`` did not converge, ``status`` is
``optimal_cost unavailable: <solver status>`` and ``optimal_cost`` and
``optimality_ratio`` are NaN. Numbers are written with ``repr`` (``nan``,
``inf`` for a run that never settled), so they read back exactly.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ofrl_drake.ablation_grid import (
    AblationError,
    Variant,
    initial_states_by_label,
    variant_list,
)
from ofrl_drake.ablation_metrics import optimality_ratio
from ofrl_drake.ablation_tasks import (
    METRICS,
    RunOutcome,
    _scenario_for,
    failed_optimum,
    run_variant_states,
    solve_optimal_task,
)
from ofrl_drake.checks import positive_number
from ofrl_drake.errors import OfrlError, one_line, status_line
from ofrl_drake.optimal import (
    Mesh,
    OptimalControlResult,
    OptimalCostCache,
    Trajectory,
    checked_mesh,
    solver_name,
    solving,
)
from ofrl_drake.plants import dynamics_fingerprints
from ofrl_drake.scenario import Scenario, check_scenario, validate_scenario
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
    "MAX_RUN_SLUG",
    "ablate",
    "load_run",
    "read_rows",
    "scenario_key",
]

#: The columns of ``ablation.csv``, in order.
CSV_COLUMNS = (
    "variant",
    "initial_state",
    "cost",
    "optimal_cost",
    "optimality_ratio",
    "final_state_norm",
    "settling_time",
    "rms_estimation_error",
    "min_learning_condition",
    "time_outside_box",
    "initial_policy_cost",
    "final_policy_cost",
    "initial_policy_ratio",
    "final_policy_ratio",
    "regulated",
    "wall_time",
    "status",
)

#: What an ablation keeps in its ``--out`` folder (a :mod:`~ofrl_drake.sweep_store`).
FILES = SweepFiles(
    table="ablation.csv",
    plan="ablation.json",
    columns=CSV_COLUMNS,
    text=("variant", "initial_state", "regulated", "status"),
    command="ablate",
    kind="ablation table",
    error=AblationError,
    folders=("runs", "optimal"),
)


# ------------------------------------------------------------------- rows
def _row(outcome: RunOutcome, optimum: OptimalControlResult) -> dict[str, Any]:
    m = outcome.metrics
    status = outcome.status
    if status == "ok" and not optimum.converged:
        status = f"optimal_cost unavailable: {optimum.status}"
    return {
        "variant": outcome.variant,
        "initial_state": outcome.initial_state,
        "cost": m["cost"],
        "optimal_cost": optimum.cost,
        "optimality_ratio": optimality_ratio(m["cost"], optimum.cost),
        "final_state_norm": m["final_state_norm"],
        "settling_time": m["settling_time"],
        "rms_estimation_error": m["rms_estimation_error"],
        "min_learning_condition": m["min_learning_condition"],
        "time_outside_box": m["time_outside_box"],
        "initial_policy_cost": m["initial_policy_cost"],
        "final_policy_cost": m["final_policy_cost"],
        "initial_policy_ratio": optimality_ratio(m["initial_policy_cost"], optimum.cost),
        "final_policy_ratio": optimality_ratio(m["final_policy_cost"], optimum.cost),
        "regulated": "true" if outcome.regulated else "false",
        "wall_time": outcome.wall_time,
        "status": one_line(status),
    }


def read_rows(path: str | os.PathLike[str], *, repair: bool = False) -> list[dict[str, Any]]:
    """The rows of an ``ablation.csv``, numbers as floats.

    Parameters
    ----------
    path : str or Path
    repair : bool
        Truncate the file after its last complete line (a sweep killed while
        writing can leave a torn one).

    Raises
    ------
    AblationError
        If the header is not :data:`CSV_COLUMNS` or a row is malformed.
    """
    return FILES.read(path, repair=repair)


def _run_slug(variant: str) -> str:
    """The part of a run's file name that names its variant (a file name's characters)."""
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", variant)


def _run_name(variant: str, label: str) -> str:
    """The file of one run in ``runs/``: ``<variant's slug>__<hash of the label>.npz``."""
    digest = hashlib.sha256(label.encode()).hexdigest()[:12]
    return f"{_run_slug(variant)}__{digest}.npz"


#: The longest slug of a variant's name (:func:`_run_slug`): a run's file is
#: written through a temporary ``.<file name>.XXXXXXXX``, and a file name has at
#: most 255 bytes on common file systems.
MAX_RUN_SLUG = 255 - len(".__0123456789ab.npz.XXXXXXXX")


def _check_run_names(variants: Sequence[Variant]) -> None:
    """Refuse variants whose runs' files in ``runs/`` would clash or not fit a file name.

    Two names that differ only in characters :func:`_run_slug` replaces
    (``a/b`` and ``a_b``), or only in case (``LQR`` and ``lqr``, one file on
    the case-insensitive file systems of macOS and Windows), would share one
    file per initial state: the figures would plot one variant's run under
    both names, and ``J*`` be warm-started from the wrong one.
    """
    seen: dict[str, str] = {}
    for variant in variants:
        slug = _run_slug(variant.name)
        if len(slug) > MAX_RUN_SLUG:
            raise AblationError(
                f"variants: the name {variant.name[:40]!r}... has {len(slug)} characters as a "
                f"file name in runs/; shorten it to at most {MAX_RUN_SLUG}."
            )
        other = seen.get(slug.casefold())
        if other is not None:
            why = (
                "characters other than letters, digits and _ . = - become _ in a file name"
                if _run_slug(other) == slug
                else "the file systems of macOS and Windows do not tell upper from lower case"
            )
            raise AblationError(
                f"variants: {other!r} and {variant.name!r} would share the files "
                f"runs/{slug}__<initial state>.npz ({why}); rename one of them."
            )
        seen[slug.casefold()] = variant.name


def _save_run(store: SweepStore, outcome: RunOutcome) -> None:
    """Make ``runs/`` hold this run's file, just before its row is written.

    A run without logs (it failed before it had any) removes the file an
    earlier attempt of its row left (a ``retry_failed``, a row the table lost):
    the figures would draw that attempt as this row's.
    """
    name = _run_name(outcome.variant, outcome.initial_state)
    if not outcome.logs:
        store.remove_run(name)
        return
    store.save_run(
        name,
        {
            "variant": outcome.variant,
            "initial_state": outcome.initial_state,
            "learned": outcome.learned,
            "status": outcome.status,
            **outcome.logs,
        },
    )


def load_run(runs_dir: str | os.PathLike[str], variant: str, label: str) -> dict[str, Any] | None:
    """The saved trajectories of one run (``t, x, xhat, u, cost``), or None."""
    return load_arrays(Path(runs_dir) / _run_name(variant, label))


def scenario_key(scenario: Scenario) -> str:
    """A hash of every field of ``scenario``."""
    text = json.dumps(dataclasses.asdict(scenario), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


# ------------------------------------------------------------------- plan
def _plan(
    scenario: Scenario,
    duration: float | None,
    labels: Sequence[str],
    variants: Sequence[Variant],
    seed: int | None,
    dynamics: dict[str, str | None],
    mesh: Mesh | None,
    solver: str | None,
) -> dict[str, Any]:
    """The contents of ``ablation.json``: what defines the sweep.

    With how ``J*`` is solved (:func:`~ofrl_drake.optimal.problem_key` has the
    same): rows of one initial state share one ``J*`` only if it is.
    """
    return {
        "scenario": scenario.name,
        "scenario_key": scenario_key(scenario),
        "duration": scenario.simulation.duration if duration is None else float(duration),
        "seed": seed,
        "initial_states": list(labels),
        "variants": {v.name: dict(v.choices) for v in variants},
        "scenario_values": dataclasses.asdict(scenario),
        DYNAMICS_KEY: dynamics,
        OPTIMAL_KEY: solving(mesh, solver),
    }


def _resume_mismatch(old: Mapping[str, Any], new: Mapping[str, Any]) -> str | None:
    """Why a ``--resume`` with plan ``new`` cannot continue the sweep of plan ``old``."""

    if "seed" in old and old["seed"] != new["seed"]:
        return f"the folder's sweep used --seed {old['seed']}, this one --seed {new['seed']}"
    if "initial_states" in old and old["initial_states"] != new["initial_states"]:
        return (
            f"the folder's sweep runs {len(old['initial_states'])} initial states "
            f"{', '.join(old['initial_states'])}, this one {len(new['initial_states'])}: "
            f"{', '.join(new['initial_states'])}"
        )
    if "variants" in old and old["variants"] != new["variants"]:
        gone = sorted(set(old["variants"]) - set(new["variants"]))
        added = sorted(set(new["variants"]) - set(old["variants"]))
        changed = sorted(
            k
            for k in set(old["variants"]) & set(new["variants"])
            if old["variants"][k] != new["variants"][k]
        )
        parts = [
            f"{what} {names}"
            for what, names in (("missing", gone), ("new", added), ("changed", changed))
            if names
        ]
        return f"the variants differ ({'; '.join(parts)})"
    if old.get("duration") != new["duration"]:
        return (
            f"the folder's sweep has a horizon of {old.get('duration')} s, "
            f"this one {new['duration']} s"
        )
    if "scenario_values" in old:
        where = describe_difference(old["scenario_values"], new["scenario_values"])
        if where is not None:
            return f"the scenario differs in {where}"
    if old.get("scenario_key") != new["scenario_key"]:
        return f"the folder holds a sweep of another scenario ({old.get('scenario')!r})"
    return None


# ------------------------------------------------------------------ sweep
@dataclass
class _Sweep:
    """The state of one sweep while its tasks finish: rows, optima, pending runs."""

    scenario: Scenario
    variants: dict[str, Variant]
    states: dict[str, np.ndarray]
    duration: float | None
    mesh: Mesh | None
    solver: str | None
    store: SweepStore | None
    dynamics: dict[str, str | None]  # the client's fingerprints: in the plan, checked by tasks
    seed: int | None = None
    workers: int = 1
    done: dict[tuple[str, str], dict[str, Any]] = field(default_factory=dict)
    optimum: dict[str, OptimalControlResult] = field(default_factory=dict)
    pending: dict[str, list[RunOutcome]] = field(default_factory=dict)
    cache: OptimalCostCache | None = None

    @property
    def horizon_scenario(self) -> Scenario:
        """The scenario with the sweep's horizon (the key of cached optima)."""
        if self.duration is None:
            return self.scenario
        simulation = dataclasses.replace(self.scenario.simulation, duration=self.duration)
        return dataclasses.replace(self.scenario, simulation=simulation)

    @contextlib.contextmanager
    def recording(self, resume: bool, retry_failed: bool = False) -> Iterator[None]:
        """Read the rows and optima already on disk and append to the table, for the block.

        With ``retry_failed``, rows whose status is not ``ok`` are dropped from
        the table (rewritten whole) so that their runs are done again. A sweep
        that stops before its first row removes what it created in the folder
        (:meth:`~ofrl_drake.sweep_store.SweepStore.recording`).
        """
        if self.store is None:
            yield
            return
        plan = _plan(
            self.scenario,
            self.duration,
            list(self.states),
            list(self.variants.values()),
            self.seed,
            self.dynamics,
            self.mesh,
            self.solver,
        )
        with self.store.recording(
            plan, resume=resume, mismatch=_resume_mismatch, retry_failed=retry_failed
        ) as rows:
            for row in rows:
                self.done[(row["variant"], row["initial_state"])] = row
            self.cache = OptimalCostCache(self.store.root / "optimal", self.mesh, self.solver)
            yield

    def submit(self, engine: Any, todo: Sequence[tuple[str, str]]) -> dict[Any, tuple]:
        """Submit the runs of ``todo`` and the missing optima; return handle -> task.

        One run task per variant, from its initial states of ``todo`` in order
        (split into consecutive parts when a cluster has more workers than
        there are variants to run). ``J*`` from a state is warm-started from
        the run of the first variant (in order) with the learned controller
        that runs from it, and submitted right after that task; without one,
        from a saved run, right after the first task from that state.
        """
        labels = {name: [lab for n, lab in todo if n == name] for name in self.variants}
        needed = [lab for lab in self.states if any(lab == b for _, b in todo)]
        for label in needed:
            if self.cache is not None and label not in self.optimum:
                cached = self.cache.get(self.horizon_scenario, self.states[label])
                if cached is not None:
                    self.optimum[label] = cached
        warm_from: dict[str, str] = {}  # label -> the variant whose run warm-starts J*
        for name, variant in self.variants.items():
            if variant.full_choices(self.scenario)["controller"] == "learned":
                for label in labels[name]:
                    if label not in self.optimum:
                        warm_from.setdefault(label, name)
        first = [n for n in self.variants if n in warm_from.values()]
        order = first + [n for n in self.variants if n not in first and labels[n]]
        parts = -(-self.workers // max(1, len(order)))  # tasks per variant, ceil
        tasks: dict[Any, tuple] = {}
        solving: set[str] = set()
        for name, mine in (
            (n, part) for n in order for part in split_consecutive(labels[n], parts)
        ):
            states = tuple(tuple(self.states[label]) for label in mine)
            args = (self.scenario, self.variants[name], states, self.duration, self.dynamics)
            handle = engine.submit(run_variant_states, *args)
            tasks[handle] = ("runs", (name, tuple(mine)))
            for label in mine:
                if label in self.optimum or label in solving:
                    continue
                if warm_from.get(label, name) != name:
                    continue  # warm-started by another variant's runs
                solving.add(label)
                warm = engine.ref(handle) if label in warm_from else self._saved_warm_start(label)
                x0 = tuple(self.states[label])
                solve = (
                    self.scenario,
                    x0,
                    warm,
                    self.duration,
                    self.mesh,
                    self.solver,
                    self.dynamics,
                )
                tasks[engine.submit(solve_optimal_task, *solve)] = ("optimal", label)
        return tasks

    def _saved_warm_start(self, label: str) -> Trajectory | None:
        if self.store is None:
            return None
        for v in self.variants.values():
            if v.full_choices(self.scenario)["controller"] != "learned":
                continue
            if (v.name, label) not in self.done:
                continue  # a file of no row in the table: not this sweep's run
            logs = load_run(self.store.runs, v.name, label)
            if logs is not None and str(logs.get("status", "ok")) == "ok":
                return Trajectory(t=logs["t"], x=logs["x"], u=logs["u"], cost=logs["cost"])
        return None

    def finished(self, task: tuple, value: Any, err: BaseException | None) -> list[dict]:
        """Record a finished task; return the rows it completes."""
        kind, key = task
        reason = status_line(err) if err is not None else "no result"
        if kind == "optimal":
            if err is not None or value is None:
                horizon = self.horizon_scenario.simulation.duration
                value = failed_optimum(self.states[key], horizon, reason)
            self.optimum[key] = value
            if self.cache is not None:
                self.cache.put(self.horizon_scenario, value)
            ready = self.pending.pop(key, [])
        else:
            name, labels = key
            if err is not None or value is None:
                nan = dict.fromkeys(METRICS, math.nan)
                value = [RunOutcome(name, label, nan, reason, 0.0, False) for label in labels]
            ready = []
            for outcome in value:
                if outcome.initial_state in self.optimum:
                    ready.append(outcome)
                else:
                    self.pending.setdefault(outcome.initial_state, []).append(outcome)
        rows = []
        for outcome in ready:
            row = _row(outcome, self.optimum[outcome.initial_state])
            self.done[(row["variant"], row["initial_state"])] = row
            if self.store is not None:
                _save_run(self.store, outcome)  # the row's run, written with it
                self.store.write(row)
            rows.append(row)
        return rows


def _check_sweep(
    scenario: Scenario,
    variants: Sequence[Variant],
    x0: Sequence[float],
    duration: float | None,
    mesh: Mesh | None,
    solver: str | None,
) -> float | None:
    """Refuse, before any run, what would fail every run or every ``J*``; return the horizon.

    ``duration`` must be a number > 0, ``mesh`` a :class:`~ofrl_drake.optimal.Mesh`,
    ``solver`` one of :data:`~ofrl_drake.optimal.SOLVERS`, and the scenario of
    every variant (its choices, from ``x0``, over the horizon) valid
    (:func:`~ofrl_drake.scenario.validate_scenario`: e.g. ``controller:
    constant`` needs ``variant.constant_input``).
    """
    try:
        if duration is not None:
            duration = positive_number("duration", duration)
        checked_mesh(mesh)
        if solver is not None:
            solver_name(solver)
    except OfrlError as err:
        raise AblationError(str(err)) from None
    try:  # the scenario and the horizon themselves, before any variant is blamed
        validate_scenario(_scenario_for(scenario, Variant("scenario"), x0, duration))
    except OfrlError as err:
        where = "scenario" if duration is None else f"scenario over duration = {duration:g} s"
        raise AblationError(f"{where}: {err}") from None
    for variant in variants:
        try:
            validate_scenario(_scenario_for(scenario, variant, x0, duration))
        except OfrlError as err:
            raise AblationError(f"variants.{variant.name}: {err}") from None
    return duration


def ablate(
    scenario: Scenario,
    variants: Sequence[Variant] | Mapping[str, Mapping[str, str]] | None = None,
    initial_states: Sequence[Sequence[float]] | np.ndarray | None = None,
    client: Any = None,
    *,
    out: str | os.PathLike[str] | None = None,
    resume: bool = False,
    duration: float | None = None,
    mesh: Mesh | None = None,
    solver: str | None = None,
    progress: bool | None = None,
    seed: int | None = None,
    retry_failed: bool = False,
) -> list[dict[str, Any]]:
    """Run every variant from every initial state and compare with ``J*``.

    Parameters
    ----------
    scenario : Scenario
        The validated base scenario.
    variants : sequence of Variant or mapping, optional
        Default :func:`~ofrl_drake.ablation_grid.default_variants`. A mapping
        ``name -> {slot: choice}`` is accepted too.
    initial_states : array_like, shape (K, n), optional
        True initial states ``x0`` (the estimate starts at ``x0 + scenario.xhat0
        - scenario.x0``). Default: the scenario's ``x0`` only.
    client : distributed.Client, optional
        Run on this Dask cluster; without one, run serially in this process.
    out : str or Path, optional
        Directory for ``ablation.csv`` (streamed), ``optimal/`` (cached ``J*``)
        and ``runs/`` (trajectories). Without it nothing is written. A sweep
        that stops before its first row (an error, an interrupt) removes what
        it created there, so nothing half-written stays; a folder that existed
        is left as it was found.
    resume : bool
        Keep the rows already in ``out/ablation.csv`` and run only the rest.
    duration : float, optional
        Horizon for both J and J*, instead of ``scenario.simulation.duration``.
    mesh : Mesh, optional
        Collocation grid of ``J*``.
    solver : {"snopt", "ipopt"}, optional
        Solver of ``J*`` (default SNOPT).
    progress : bool, optional
        Progress bar of finished runs on stderr; default only on a terminal.
    seed : int, optional
        The seed the initial states were drawn with
        (:func:`~ofrl_drake.ablation_grid.sample_initial_states`); recorded in
        ``ablation.json`` so a ``resume`` with another seed is refused by name.
    retry_failed : bool
        With ``resume``, run again the rows whose status is not ``ok``.

    Returns
    -------
    list of dict
        One record per (variant, initial state) with the keys
        :data:`CSV_COLUMNS`, variants in order and, within each, initial states
        in order. Numbers are floats (NaN where unavailable).

    Raises
    ------
    AblationError
        Before any run: for bad variants (not :class:`Variant` objects or a
        mapping, an unknown slot or choice, the message listing the valid
        ones, two names that make the same file name in ``runs/`` (``a/b``
        and ``a_b``: characters other than letters, digits and ``_ . = -``
        become ``_``) or one longer than :data:`MAX_RUN_SLUG`, or a variant
        whose scenario is invalid, e.g. ``controller: constant`` without
        ``variant.constant_input``), bad initial states, a
        ``duration`` that is not a number > 0, a ``mesh`` that is not a
        :class:`~ofrl_drake.optimal.Mesh`, a ``solver`` not in
        :data:`~ofrl_drake.optimal.SOLVERS` or not available, an existing
        table without ``resume``, or a ``resume`` whose seed, initial states,
        variants, scenario or horizon differ from the sweep in ``out`` (named
        in the message).
    OutputError
        If ``out`` cannot be written, or a file of ``out/runs/`` that belongs
        to no row of the table cannot be removed.

    Examples
    --------
    >>> rows = ablate(scenario, [Variant("baseline"), Variant("lqr", {"controller": "lqr"})],
    ...               [[-1.0, 1.0], [0.5, -0.5]])                         # doctest: +SKIP
    >>> [(r["variant"], r["optimality_ratio"]) for r in rows]             # doctest: +SKIP
    """
    check_scenario(scenario, "ablate")
    variants = variant_list(scenario, variants)
    _check_run_names(variants)
    states = initial_states_by_label(scenario, initial_states)
    x0 = next(iter(states.values())).tolist()
    duration = _check_sweep(scenario, variants, x0, duration, mesh, solver)
    keys = [(v.name, label) for v in variants for label in states]

    sweep = _Sweep(
        scenario=scenario,
        variants={v.name: v for v in variants},
        states=states,
        duration=duration,
        mesh=mesh,
        solver=solver,
        store=None if out is None else SweepStore(FILES, Path(out)),
        seed=seed,
        workers=worker_threads(client),
        dynamics=dynamics_fingerprints(scenario),
    )
    with sweep.recording(resume, retry_failed):
        todo = [k for k in keys if k not in sweep.done]
        execute(
            lambda engine: sweep.submit(engine, todo),
            sweep.finished,
            client=client,
            total=len(keys),
            done=len(keys) - len(todo),
            progress=progress,
        )
    return [sweep.done[k] for k in keys]
