"""Ablation sweeps: every variant from every initial state, against the optimum.

A sweep runs each :class:`Variant` (one choice per slot, see
:mod:`ofrl_drake.variants`) from each initial state, measures the run
(:mod:`ofrl_drake.ablation_metrics`) and divides its cost by the optimal cost
``J*`` from the same initial state (:mod:`ofrl_drake.optimal`).

Engine
------
With a Dask ``distributed.Client`` the runs are Dask tasks. A task carries only
picklable data (the :class:`~ofrl_drake.scenario.Scenario` dataclass, the
variant's choices, the initial state) and builds its Drake diagram inside the
worker; nothing of Drake is pickled. Without a client the same tasks run one
after another in this process. ``J*`` is one task per initial state, warm-started
from the first run of a variant with the learned controller from that state.
Workers import ``ofrl_drake`` themselves, so a choice added with
:func:`~ofrl_drake.slots.register_variant` must be registered in the workers
too (e.g. in a module they import), not only in the driver.

Streaming and resume
--------------------
With ``out`` given, each row is appended to ``out/ablation.csv`` as soon as
its run and its ``J*`` are known, then flushed and fsynced, so a killed sweep
loses no finished row. ``resume=True`` reads the rows already there (dropping
a torn last line) and runs only the missing (variant, initial state) pairs.
Converged ``J*`` values are cached in ``out/optimal/``, one JSON file per
scenario-problem hash and initial state, and each run's trajectories are kept
in ``out/runs/`` for the figures (:mod:`ofrl_drake.ablation_report`).

A run that raises is recorded with its error on one line (``status``); the
sweep goes on. If the run is fine but ``J*`` did not converge, ``status`` is
``optimal_cost unavailable: <solver status>`` and ``optimal_cost`` and
``optimality_ratio`` are NaN. Numbers are written with ``repr`` (``nan``,
``inf`` for a run that never settled), so they read back exactly.

Initial states
--------------
Initial states are given as true states ``x0``; the estimate starts at
``xhat0 = x0 + (scenario.xhat0 - scenario.x0)``, the scenario's own initial
estimation error. :func:`sample_initial_states` draws ``x0`` in the part of the
observer box where both ``x0`` and that ``xhat0`` lie in the box, so the
observer certificate applies from ``t = 0``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ofrl_drake.ablation_metrics import optimality_ratio, run_metrics
from ofrl_drake.atomic import atomic_file, atomic_write_text, check_output_folder, ensure_parent
from ofrl_drake.errors import OfrlError
from ofrl_drake.optimal import (
    Mesh,
    OptimalControlResult,
    OptimalCostCache,
    Trajectory,
    optimal_control,
)
from ofrl_drake.scenario import Scenario, VariantConfig, variant_choices
from ofrl_drake.sweep import (
    DaskEngine,
    Progress,
    RowWriter,
    SerialEngine,
    TableError,
    first_difference,
    format_row,
    read_table,
)

__all__ = [
    "CSV_COLUMNS",
    "AblationError",
    "RunOutcome",
    "Variant",
    "ablate",
    "default_variants",
    "initial_state_label",
    "load_run",
    "load_variants",
    "read_rows",
    "run_variant",
    "sample_initial_states",
    "scenario_key",
    "solve_optimal_task",
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
_TEXT_COLUMNS = ("variant", "initial_state", "regulated", "status")
_METRICS = (
    "cost",
    "final_state_norm",
    "settling_time",
    "rms_estimation_error",
    "min_learning_condition",
    "time_outside_box",
    "initial_policy_cost",
    "final_policy_cost",
)
CSV_NAME = "ablation.csv"
PLAN_NAME = "ablation.json"


class AblationError(OfrlError):
    """A sweep was asked for with bad input (variants, initial states, output)."""


# ---------------------------------------------------------------- variants
@dataclass(frozen=True)
class Variant:
    """A named set of slot choices; slots it does not name keep the scenario's.

    Attributes
    ----------
    name : str
        The label in the table (``baseline``, ``observer=true_state``, ...).
    choices : dict of str to str
        Slot -> choice, e.g. ``{"observer": "true_state"}``.
    """

    name: str
    choices: dict[str, str] = field(default_factory=dict)

    def full_choices(self, scenario: Scenario) -> dict[str, str]:
        """Every slot's choice: the scenario's, overridden by this variant's."""
        return {**variant_choices(scenario), **self.choices}


def _check_choices(name: str, choices: Any) -> dict[str, str]:
    from ofrl_drake.slots import VARIANT_FACTORIES

    if not isinstance(choices, Mapping):
        raise AblationError(
            f"variants.{name}: expected a mapping of slot: choice; got {choices!r}."
        )
    for slot, choice in choices.items():
        if slot not in VARIANT_FACTORIES:
            raise AblationError(
                f"variants.{name}.{slot}: unknown slot; slots are {sorted(VARIANT_FACTORIES)}."
            )
        if choice not in VARIANT_FACTORIES[slot]:
            raise AblationError(
                f"variants.{name}.{slot}: unknown choice {choice!r}; choose one of "
                f"{sorted(VARIANT_FACTORIES[slot])}."
            )
    return {str(k): str(v) for k, v in choices.items()}


def default_variants(scenario: Scenario) -> list[Variant]:
    """The baseline (the scenario's own choices) and every single-slot swap.

    For the paper's scenario: ``baseline`` plus ``observer=linear_luenberger``,
    ``observer=drake_luenberger``, ``observer=true_state``, ``controller=lqr``,
    ``controller=frozen_critic``, ``points=uniform``, ``points=around_estimate``
    and ``gamma=constant``. Choices that need scenario values
    (:data:`~ofrl_drake.slots.NEEDS_PARAMETERS`, e.g. ``controller=constant``)
    are left out.
    """
    from ofrl_drake.slots import NEEDS_PARAMETERS, VARIANT_FACTORIES

    base = variant_choices(scenario)
    out = [Variant("baseline", {})]
    for slot, options in VARIANT_FACTORIES.items():
        for choice in options:
            if choice != base[slot] and (slot, choice) not in NEEDS_PARAMETERS:
                out.append(Variant(f"{slot}={choice}", {slot: choice}))
    return out


def load_variants(path: str | os.PathLike[str]) -> list[Variant]:
    """Read variants from YAML: a mapping ``name: {slot: choice, ...}``.

    Example::

        baseline: {}
        full_state: {observer: true_state}
        lqr_full_state: {observer: true_state, controller: lqr}

    Raises
    ------
    AblationError
        If the file is missing, not a mapping, or names an unknown slot or choice.
    """
    from pydrake.common.yaml import yaml_load

    path = Path(path)
    if not path.is_file():
        raise AblationError(f"{path}: no such variants file.")
    try:
        data = yaml_load(filename=str(path))
    except Exception as err:
        raise AblationError(f"{path}: not valid YAML: {err}".replace("\n", " ")) from None
    if not isinstance(data, Mapping) or not data:
        raise AblationError(
            f"{path}: expected a mapping of variant name -> {{slot: choice}}; got {data!r}."
        )
    try:
        return [Variant(str(name), _check_choices(str(name), c or {})) for name, c in data.items()]
    except AblationError as err:
        raise AblationError(f"{path}: {err}") from None


def _variants(scenario: Scenario, variants: Any) -> list[Variant]:
    if variants is None:
        return default_variants(scenario)
    if isinstance(variants, Mapping):
        variants = [Variant(str(k), dict(v or {})) for k, v in variants.items()]
    out = list(variants)
    names = [v.name for v in out]
    if not out or len(set(names)) != len(names):
        raise AblationError(f"variants: need at least one, with distinct names; got {names}.")
    return out


# ---------------------------------------------------------- initial states
def initial_state_label(x0: Sequence[float]) -> str:
    """The ``initial_state`` column: ``x0`` as a JSON list, e.g. ``[-1.0, 1.0]``."""
    return json.dumps([float(v) for v in x0])


def sample_initial_states(scenario: Scenario, count: int, seed: int) -> np.ndarray:
    """The scenario's ``x0`` followed by ``count`` states drawn from ``seed``.

    Draws are uniform in the sub-box of the observer box where both ``x0`` and
    ``xhat0 = x0 + (scenario.xhat0 - scenario.x0)`` stay in the box, rounded to
    six decimals so their labels are short and exact.

    Returns
    -------
    ndarray, shape (count + 1, n)

    Raises
    ------
    AblationError
        If ``count < 0`` or the initial estimation error is wider than the box.
    """
    if int(count) != count or count < 0:
        raise AblationError(f"--initial-states: must be an integer >= 0; got {count!r}.")
    x0 = np.asarray(scenario.x0, dtype=float)
    offset = np.asarray(scenario.xhat0, dtype=float) - x0
    lower = np.asarray(scenario.observer.box.lower, dtype=float)
    upper = np.asarray(scenario.observer.box.upper, dtype=float)
    lo = np.maximum(lower, lower - offset)
    hi = np.minimum(upper, upper - offset)
    if np.any(lo >= hi):
        i = int(np.argmax(lo >= hi))
        raise AblationError(
            f"initial states: xhat0 - x0 = {offset.tolist()} is as wide as the observer box "
            f"in axis {i}; no x0 keeps both x0 and xhat0 inside it."
        )
    rng = np.random.default_rng(seed)
    draws = np.round(lo + (hi - lo) * rng.random((int(count), x0.size)), 6)
    return np.vstack([x0[None, :], draws])


def _scenario_for(
    scenario: Scenario, variant: Variant, x0: Sequence[float], duration: float | None
) -> Scenario:
    x0 = np.asarray(x0, dtype=float)
    offset = np.asarray(scenario.xhat0, dtype=float) - np.asarray(scenario.x0, dtype=float)
    choices = variant.full_choices(scenario)
    simulation = scenario.simulation
    if duration is not None:
        simulation = dataclasses.replace(simulation, duration=float(duration))
    return dataclasses.replace(
        scenario,
        x0=x0.tolist(),
        xhat0=(x0 + offset).tolist(),
        variant=VariantConfig(**choices),
        simulation=simulation,
    )


# ------------------------------------------------------------------ tasks
@dataclass(frozen=True)
class RunOutcome:
    """What one run returns from its worker: metrics, status and trajectories.

    Attributes
    ----------
    variant, initial_state : str
        The row's key.
    metrics : dict of str to float
        The trajectory metrics (:func:`~ofrl_drake.ablation_metrics.run_metrics`);
        NaN if the run failed.
    status : str
        ``"ok"`` or the error, on one line.
    wall_time : float
        Seconds to build, simulate and measure.
    learned : bool
        True if the variant uses the learned controller (a J* warm start).
    logs : dict of str to ndarray
        ``t, x, xhat, u, cost`` (empty if the run failed).
    regulated : bool
        The run's verdict (:func:`~ofrl_drake.ablation_metrics.regulation`).
    """

    variant: str
    initial_state: str
    metrics: dict[str, float]
    status: str
    wall_time: float
    learned: bool
    logs: dict[str, np.ndarray] = field(default_factory=dict)
    regulated: bool = False

    def warm_start(self) -> Trajectory | None:
        """The run as a :class:`~ofrl_drake.optimal.Trajectory`, if it reached its horizon."""
        if not self.logs or self.status.startswith(("diverged", "timeout")):
            return None
        return Trajectory(
            t=self.logs["t"], x=self.logs["x"], u=self.logs["u"], cost=self.logs["cost"]
        )


def _one_line(err: BaseException) -> str:
    return f"{type(err).__name__}: {' '.join(str(err).split())}"


def run_variant(
    scenario: Scenario, variant: Variant, x0: Sequence[float], duration: float | None = None
) -> RunOutcome:
    """Build and simulate one variant from ``x0``; never raises.

    Runs inside a worker: the Drake diagram is built here from the scenario
    data. Any exception becomes the outcome's ``status``.
    """
    from ofrl_drake.diagram import build_closed_loop
    from ofrl_drake.simulation import simulate

    label = initial_state_label(x0)
    learned = variant.full_choices(scenario)["controller"] == "learned"
    start = time.perf_counter()
    regulated = False
    try:
        s = _scenario_for(scenario, variant, x0, duration)
        loop = build_closed_loop(s)
        result = simulate(s, loop=loop, progress=False)
        box = (np.asarray(s.observer.box.lower), np.asarray(s.observer.box.upper))
        metrics = {**run_metrics(result, box), **_policy_costs(loop, result, s)}
        regulated = bool(result.regulated)
        status = "ok"
        if result.status != "ok":
            # Stopped by the guard: the metrics of a truncated run are not comparable.
            status = f"{result.status}: {result.stop.reason}"
            metrics = dict.fromkeys(_METRICS, math.nan)
        elif not (np.all(np.isfinite(result.x)) and np.all(np.isfinite(result.cost))):
            status = "diverged: non-finite state or cost"
        logs = {k: np.asarray(getattr(result, k)) for k in ("t", "x", "xhat", "u", "cost")}
    except Exception as err:
        metrics = dict.fromkeys(_METRICS, math.nan)
        status = _one_line(err)
        logs = {}
    return RunOutcome(
        variant=variant.name,
        initial_state=label,
        metrics=metrics,
        status=status,
        wall_time=time.perf_counter() - start,
        learned=learned,
        logs=logs,
        regulated=regulated,
    )


def _policy_costs(loop: Any, result: Any, scenario: Scenario) -> dict[str, float]:
    """The policy in force at 0 and at the run's end, each fed the true state from x0.

    What learning buys, apart from the observer: the critic frozen at
    ``W_pi(0)`` and ``W_pi(T)``, over the scenario's horizon
    (:func:`ofrl_drake.learning_curve.evaluate_policy`). NaN for a controller
    that does not act on the critic (``lqr``, ``constant``).
    """
    from ofrl_drake.learning_curve import evaluate_policy

    if variant_choices(scenario)["controller"] not in ("learned", "frozen_critic"):
        return {"initial_policy_cost": math.nan, "final_policy_cost": math.nan}
    return {
        "initial_policy_cost": evaluate_policy(loop, result.W_policy[0]).cost,
        "final_policy_cost": evaluate_policy(loop, result.W_policy[-1]).cost,
    }


def solve_optimal_task(
    scenario: Scenario,
    x0: Sequence[float],
    warm: RunOutcome | Trajectory | None,
    duration: float | None = None,
    mesh: Mesh | None = None,
    solver: str | None = None,
) -> OptimalControlResult:
    """``J*`` from ``x0``, warm-started from a run; never raises."""
    if duration is not None:
        scenario = dataclasses.replace(
            scenario,
            simulation=dataclasses.replace(scenario.simulation, duration=float(duration)),
        )
    warm_start = warm.warm_start() if isinstance(warm, RunOutcome) else warm
    try:
        return optimal_control(scenario, x0, warm_start=warm_start, mesh=mesh, solver=solver)
    except Exception as err:
        return _failed_optimum(x0, scenario.simulation.duration, _one_line(err))


def _failed_optimum(x0: Sequence[float], duration: float, status: str) -> OptimalControlResult:
    return OptimalControlResult(
        x0=tuple(float(v) for v in x0),
        cost=math.nan,
        converged=False,
        status=status,
        duration=float(duration),
        solver="",
        solve_time=0.0,
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
        "status": " ".join(str(status).split()),
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
    try:
        return read_table(path, CSV_COLUMNS, _TEXT_COLUMNS, repair=repair, kind="ablation table")
    except TableError as err:
        raise AblationError(str(err)) from None


def _run_file(runs_dir: Path, variant: str, label: str) -> Path:
    slug = re.sub(r"[^A-Za-z0-9_.=-]+", "_", variant)
    digest = hashlib.sha256(label.encode()).hexdigest()[:12]
    return runs_dir / f"{slug}__{digest}.npz"


def _save_run(runs_dir: Path, outcome: RunOutcome) -> None:
    if not outcome.logs:
        return
    path = _run_file(runs_dir, outcome.variant, outcome.initial_state)
    with atomic_file(path, "wb") as fh:
        np.savez(
            fh,
            variant=outcome.variant,
            initial_state=outcome.initial_state,
            learned=outcome.learned,
            status=outcome.status,
            **outcome.logs,
        )


def load_run(runs_dir: str | os.PathLike[str], variant: str, label: str) -> dict[str, Any] | None:
    """The saved trajectories of one run (``t, x, xhat, u, cost``), or None."""
    path = _run_file(Path(runs_dir), variant, label)
    if not path.is_file():
        return None
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def scenario_key(scenario: Scenario) -> str:
    """A hash of every field of ``scenario``."""
    text = json.dumps(dataclasses.asdict(scenario), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


# ----------------------------------------------------------------- engines
# -------------------------------------------------------------------- API
def _plan(
    scenario: Scenario,
    duration: float | None,
    labels: Sequence[str],
    variants: Sequence[Variant],
    seed: int | None,
) -> dict[str, Any]:
    """The contents of ``ablation.json``: what defines the sweep."""
    return {
        "scenario": scenario.name,
        "scenario_key": scenario_key(scenario),
        "duration": scenario.simulation.duration if duration is None else float(duration),
        "seed": seed,
        "initial_states": list(labels),
        "variants": {v.name: dict(v.choices) for v in variants},
        "scenario_values": dataclasses.asdict(scenario),
    }


def _resume_mismatch(old: Mapping[str, Any], new: Mapping[str, Any]) -> str | None:
    """Why a ``--resume`` with plan ``new`` cannot continue the sweep of plan ``old``."""

    def lookup(values: Any, path: str) -> Any:
        for key in path.split("."):
            values = values.get(key) if isinstance(values, Mapping) else None
        return values

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
        where = first_difference(old["scenario_values"], new["scenario_values"])
        if where is not None:
            return (
                f"the scenario differs in {where} ({lookup(old['scenario_values'], where)!r} "
                f"in the folder, {lookup(new['scenario_values'], where)!r} now)"
            )
    if old.get("scenario_key") != new["scenario_key"]:
        return f"the folder holds a sweep of another scenario ({old.get('scenario')!r})"
    return None


def _plan_file(out: Path, plan: Mapping[str, Any], resume: bool) -> None:
    path = out / PLAN_NAME
    if resume and path.is_file():
        try:
            old = json.loads(path.read_text())
        except (ValueError, UnicodeDecodeError):
            raise AblationError(
                f"--resume: {path} is not valid JSON (cut short?); it records the sweep that "
                f"{CSV_NAME} belongs to. Restore it, or move the folder away and start again."
            ) from None
        why = _resume_mismatch(old, json.loads(json.dumps(plan)))
        if why is not None:
            raise AblationError(
                f"--resume: {why}; resume with the sweep's own arguments, or choose another --out."
            )
        return
    atomic_write_text(path, json.dumps(plan, indent=2) + "\n")


@dataclass
class _Sweep:
    """The state of one sweep while its tasks finish: rows, optima, pending runs."""

    scenario: Scenario
    variants: dict[str, Variant]
    states: dict[str, np.ndarray]
    duration: float | None
    mesh: Mesh | None
    solver: str | None
    out_dir: Path | None
    seed: int | None = None
    done: dict[tuple[str, str], dict[str, Any]] = field(default_factory=dict)
    optimum: dict[str, OptimalControlResult] = field(default_factory=dict)
    pending: dict[str, list[RunOutcome]] = field(default_factory=dict)
    writer: RowWriter | None = None
    cache: OptimalCostCache | None = None

    @property
    def horizon_scenario(self) -> Scenario:
        """The scenario with the sweep's horizon (the key of cached optima)."""
        if self.duration is None:
            return self.scenario
        simulation = dataclasses.replace(self.scenario.simulation, duration=self.duration)
        return dataclasses.replace(self.scenario, simulation=simulation)

    def open(self, resume: bool, retry_failed: bool = False) -> None:
        """Read the rows and optima already on disk; open the table for appending.

        With ``retry_failed``, rows whose status is not ``ok`` are dropped from
        the table (rewritten whole) so that their runs are done again.
        """
        if self.out_dir is None:
            return
        if (self.out_dir / CSV_NAME).exists() and not (self.out_dir / PLAN_NAME).exists():
            raise AblationError(
                f"--out: {self.out_dir / PLAN_NAME} is missing; it records the sweep that "
                f"{CSV_NAME} belongs to, so it cannot be resumed. Restore it, or move "
                f"{CSV_NAME} away to start a new sweep in {self.out_dir}."
            )
        check_output_folder(self.out_dir, marker=PLAN_NAME, command="ablate", error=AblationError)
        ensure_parent(self.out_dir / PLAN_NAME)
        table = self.out_dir / CSV_NAME
        if table.exists() and not resume:
            raise AblationError(
                f"{table} exists; pass --resume to complete it, or choose another --out."
            )
        plan = _plan(
            self.scenario, self.duration, list(self.states), list(self.variants.values()), self.seed
        )
        _plan_file(self.out_dir, plan, resume)
        if table.exists():
            rows = read_rows(table, repair=True)
            if retry_failed:
                kept = [r for r in rows if r["status"] == "ok"]
                if len(kept) < len(rows):
                    text = ",".join(CSV_COLUMNS) + "\n"
                    text += "".join(format_row(r, CSV_COLUMNS, _TEXT_COLUMNS) for r in kept)
                    atomic_write_text(table, text)
                rows = kept
            for row in rows:
                self.done[(row["variant"], row["initial_state"])] = row
        self.writer = RowWriter(table, CSV_COLUMNS, _TEXT_COLUMNS)
        self.cache = OptimalCostCache(self.out_dir / "optimal", self.mesh, self.solver)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()

    def submit(self, engine: Any, todo: Sequence[tuple[str, str]]) -> dict[Any, tuple]:
        """Submit the runs of ``todo`` and the missing optima; return handle -> task."""
        tasks: dict[Any, tuple] = {}
        for label, x0 in self.states.items():
            mine = [self.variants[name] for name, lab in todo if lab == label]
            if not mine:
                continue
            if self.cache is not None and label not in self.optimum:
                cached = self.cache.get(self.horizon_scenario, x0)
                if cached is not None:
                    self.optimum[label] = cached
            # A run with the learned controller first: it warm-starts J*.
            learned = [v for v in mine if v.full_choices(self.scenario)["controller"] == "learned"]
            order = learned[:1] + [v for v in mine if v not in learned[:1]]
            for i, variant in enumerate(order):
                args = (self.scenario, variant, tuple(x0), self.duration)
                handle = engine.submit(run_variant, *args)
                tasks[handle] = ("run", (variant.name, label))
                if i == 0 and label not in self.optimum:
                    warm = engine.ref(handle) if learned else self._saved_warm_start(label)
                    args = (self.scenario, tuple(x0), warm, self.duration, self.mesh, self.solver)
                    tasks[engine.submit(solve_optimal_task, *args)] = ("optimal", label)
        return tasks

    def _saved_warm_start(self, label: str) -> Trajectory | None:
        if self.out_dir is None:
            return None
        for v in self.variants.values():
            if v.full_choices(self.scenario)["controller"] != "learned":
                continue
            logs = load_run(self.out_dir / "runs", v.name, label)
            if logs is not None and str(logs.get("status", "ok")) == "ok":
                return Trajectory(t=logs["t"], x=logs["x"], u=logs["u"], cost=logs["cost"])
        return None

    def finished(self, task: tuple, value: Any, err: BaseException | None) -> list[dict]:
        """Record a finished task; return the rows it completes."""
        kind, key = task
        reason = _one_line(err) if err is not None else "no result"
        if kind == "optimal":
            if err is not None or value is None:
                horizon = self.horizon_scenario.simulation.duration
                value = _failed_optimum(self.states[key], horizon, reason)
            self.optimum[key] = value
            if self.cache is not None:
                self.cache.put(self.horizon_scenario, value)
            ready = self.pending.pop(key, [])
        else:
            if err is not None or value is None:
                nan = dict.fromkeys(_METRICS, math.nan)
                value = RunOutcome(key[0], key[1], nan, reason, 0.0, False)
            if self.out_dir is not None:
                _save_run(self.out_dir / "runs", value)
            if value.initial_state not in self.optimum:
                self.pending.setdefault(value.initial_state, []).append(value)
                return []
            ready = [value]
        rows = []
        for outcome in ready:
            row = _row(outcome, self.optimum[outcome.initial_state])
            self.done[(row["variant"], row["initial_state"])] = row
            if self.writer is not None:
                self.writer.write(row)
            rows.append(row)
        return rows


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
        Default :func:`default_variants`. A mapping ``name -> {slot: choice}``
        is accepted too.
    initial_states : array_like, shape (K, n), optional
        True initial states ``x0`` (the estimate starts at ``x0 + scenario.xhat0
        - scenario.x0``). Default: the scenario's ``x0`` only.
    client : distributed.Client, optional
        Run on this Dask cluster; without one, run serially in this process.
    out : str or Path, optional
        Directory for ``ablation.csv`` (streamed), ``optimal/`` (cached ``J*``)
        and ``runs/`` (trajectories). Without it nothing is written.
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
        (:func:`sample_initial_states`); recorded in ``ablation.json`` so a
        ``resume`` with another seed is refused by name.
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
        For bad variants or initial states, an existing table without
        ``resume``, or a ``resume`` whose seed, initial states, variants,
        scenario or horizon differ from the sweep in ``out`` (named in the message).

    Examples
    --------
    >>> rows = ablate(scenario, [Variant("baseline"), Variant("lqr", {"controller": "lqr"})],
    ...               [[-1.0, 1.0], [0.5, -0.5]])                         # doctest: +SKIP
    >>> [(r["variant"], r["optimality_ratio"]) for r in rows]             # doctest: +SKIP
    """
    variants = _variants(scenario, variants)
    if initial_states is None:
        initial_states = [scenario.x0]
    states = np.atleast_2d(np.asarray(initial_states, dtype=float))
    n = len(scenario.x0)
    if states.ndim != 2 or states.shape[1] != n or not np.all(np.isfinite(states)):
        raise AblationError(
            f"initial states: expected finite rows of {n} numbers; got shape {states.shape}."
        )
    labels = [initial_state_label(x) for x in states]
    if len(set(labels)) != len(labels):
        raise AblationError(f"initial states: repeated states in {labels}.")
    keys = [(v.name, label) for v in variants for label in labels]

    sweep = _Sweep(
        scenario=scenario,
        variants={v.name: v for v in variants},
        states=dict(zip(labels, states, strict=True)),
        duration=None if duration is None else float(duration),
        mesh=mesh,
        solver=solver,
        out_dir=None if out is None else Path(out),
        seed=seed,
    )
    sweep.open(resume, retry_failed)
    todo = [k for k in keys if k not in sweep.done]
    engine = SerialEngine() if client is None else DaskEngine(client)
    show = sys.stderr.isatty() if progress is None else progress
    bar = Progress(len(keys), len(keys) - len(todo), show)
    try:
        tasks = sweep.submit(engine, todo)
        for handle, value, err in engine.completed():
            for _ in sweep.finished(tasks[handle], value, err):
                bar.advance()
    finally:
        bar.close()
        sweep.close()
    return [sweep.done[k] for k in keys]
