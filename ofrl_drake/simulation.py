"""Simulate a scenario with Drake's ``Simulator`` and collect the logs."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import sys
import time
import zipfile
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorConfig
from pydrake.systems.framework import Context, System

from ofrl_drake.atomic import atomic_file, ensure_parent
from ofrl_drake.bellman import unpack_symmetric
from ofrl_drake.checks import (
    json_ready,
    number_from_json,
    number_to_json,
    object_from_json,
    optional_number_from_json,
    positive_number,
    string_from_json,
    vector_to_json,
)
from ofrl_drake.diagram import LOGGED, ClosedLoop, build_closed_loop
from ofrl_drake.errors import (
    ModelError,
    RunFolderError,
    ScenarioError,
    SwapError,
    is_domain_error,
    one_line,
)
from ofrl_drake.guard import (
    STATUS_OK,
    IntegratorStalled,
    RunGuard,
    StallWatchdog,
    StopReport,
    stall_limit,
)
from ofrl_drake.observer import unpack_gains
from ofrl_drake.observer_certificate import ObserverCertificate, certificate_of
from ofrl_drake.progress import ProgressBar
from ofrl_drake.provenance import provenance
from ofrl_drake.scenario import (
    Scenario,
    abort_box,
    check_scenario,
    critic_gains_choice,
    load_scenario,
)
from ofrl_drake.validity import BoxSchedule, ValidityReport, validity_report

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = [
    "EXTRA_LOGS_FILE",
    "ORIGINAL_KEYS",
    "RUN_CRITIC_VALUES",
    "RUN_MEASUREMENT_VALUES",
    "RUN_VALUES",
    "SAMPLED_KEYS",
    "SHIFTED_KEYS",
    "SUMMARY_FILE",
    "SUMMARY_KEYS",
    "TRAJECTORIES_FILE",
    "TRAJECTORY_KEYS",
    "SimulationResult",
    "damaged_run_file",
    "read_run_arrays",
    "read_run_series",
    "simulate",
    "simulator_config",
    "summary_entry",
]

_T = TypeVar("_T")

#: Number of dimensions of each array of ``trajectories.npz``, time first, in order.
_TRAJECTORY_NDIM = {
    "t": 1,
    "x": 2,
    "xhat": 2,
    "W": 2,
    "W_policy": 2,
    "Gamma": 3,
    "u": 2,
    "learning_condition": 1,
    "cost": 1,
}
#: Keys of ``trajectories.npz``, in order.
TRAJECTORY_KEYS = tuple(_TRAJECTORY_NDIM)

#: Files :meth:`SimulationResult.save` writes and :meth:`SimulationResult.load` reads.
TRAJECTORIES_FILE = "trajectories.npz"
SUMMARY_FILE = "summary.json"
#: File written by :meth:`SimulationResult.save` when there are extra logs.
EXTRA_LOGS_FILE = "extra_logs.npz"

#: Keys :meth:`SimulationResult.original` shifts back to the plant's own coordinates.
ORIGINAL_KEYS = ("x", "xhat", "u")

#: Keys of ``trajectories.npz`` that hold, for a run with an equilibrium, ``x - x*``,
#: ``xhat - x*`` and ``u - u*`` as the result held them. ``x``, ``xhat`` and ``u`` there
#: are in the plant's own coordinates, ``x*`` plus those, rounded: subtracting ``x*``
#: again gives them back only to within that rounding.
SHIFTED_KEYS = {key: f"{key}_shifted" for key in ORIGINAL_KEYS}

#: Entries of ``summary.json`` that :meth:`SimulationResult.summary` computes from the
#: result itself; every other entry is one of its :attr:`~SimulationResult.reports`.
SUMMARY_KEYS = (
    "scenario",
    "status",
    "final_time",
    "final_state",
    "final_state_norm",
    "final_estimation_error",
    "final_estimation_error_norm",
    "final_weights",
    "final_gamma_eigenvalues",
    "min_learning_condition",
    "final_cost",
    "wall_time",
    "integrator",
    "units",
    "equilibrium",
    "stop",
    "provenance",
    "validity",
    "observer_design",
    "extra_logs",
    "failed_solves",
    "observer_resolves",
)

#: Keys :meth:`SimulationResult.at` reads: the logged arrays and the estimation error.
SAMPLED_KEYS = (*TRAJECTORY_KEYS, "e")


@dataclass
class SimulationResult:
    """Logged trajectories of one closed-loop run, as numpy arrays (time first).

    Attributes
    ----------
    t : ndarray, shape (T,)
    x, xhat : ndarray, shape (T, n)
    W : ndarray, shape (T, L)
        The critic's weights.
    W_policy : ndarray, shape (T, L)
        The weights of the policy in force, which the controller acts on:
        ``W`` itself under the paper's law.
    Gamma : ndarray, shape (T, L, L)
    u : ndarray, shape (T, m)
    learning_condition : ndarray, shape (T,)
        ``c(t)`` of Assumption 2.
    cost : ndarray, shape (T,)
        ``J(t) = int_0^t Q(x) + U(u) dt``.
    wall_time : float
        Seconds spent in ``Simulator.Initialize`` and ``AdvanceTo``.
    integrator : dict
        Integrator settings and statistics.
    validity : ValidityReport
        When x or xhat left the certified box in force or ``|u_k|`` exceeded
        lambda_bar (or the smaller input bound the observer's design is
        certified for); its ``box_check`` and ``note`` say which box applied,
        or why none did.
    design : dict or None
        The observer design as a JSON-ready dict, with its certificate.
    extra : dict of ndarray
        Further logs of the loop beyond :data:`~ofrl_drake.diagram.LOGGED`
        (e.g. ``observer_gains`` of a scheduled observer), time first.
    state_units, input_units : tuple of str or None
        The model's units (``ControlAffineSystem.state_units``), for the figures
        and ``summary.json``; None when the model does not know them.
    x_equilibrium, u_equilibrium : ndarray or None
        The scenario's equilibrium ``(x*, u*)``, when it has one. ``x``,
        ``xhat`` and ``u`` are then the method's coordinates ``x - x*`` and
        ``u - u*``; :meth:`original` gives the plant's own, which the saved
        files and figures show.
    stop : StopReport or None
        How the run ended (:mod:`ofrl_drake.guard`): ``status`` ``ok``,
        ``diverged`` or ``timeout``, the reason, time and state. When the
        guard stopped the run, the logs end at that time.
    provenance : dict
        Start time, command line and package versions
        (:func:`~ofrl_drake.provenance.provenance`).
    reports : dict
        Further entries of ``summary.json`` that studies add after the run,
        e.g. ``learning_curve`` and ``learning_health``
        (:meth:`ofrl_drake.learning_curve.LearningReport.to_dict`).
    """

    t: np.ndarray
    x: np.ndarray
    xhat: np.ndarray
    W: np.ndarray
    W_policy: np.ndarray
    Gamma: np.ndarray
    u: np.ndarray
    learning_condition: np.ndarray
    cost: np.ndarray
    wall_time: float = 0.0
    integrator: dict[str, Any] = field(default_factory=dict)
    validity: ValidityReport | None = None
    design: dict[str, Any] | None = None
    scenario_name: str = ""
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    x_equilibrium: np.ndarray | None = None
    u_equilibrium: np.ndarray | None = None
    state_units: tuple[str, ...] | None = None
    input_units: tuple[str, ...] | None = None

    def original(self, key: str) -> np.ndarray:
        """``x``, ``xhat`` or ``u`` in the plant's own coordinates (``+ x*``, ``+ u*``).

        Raises
        ------
        ModelError
            If ``key`` is not one of :data:`ORIGINAL_KEYS`.
        """
        if key not in ORIGINAL_KEYS:
            raise ModelError(
                f"SimulationResult.original: no log {key!r} has the plant's own coordinates; "
                f"choose one of {list(ORIGINAL_KEYS)} (the others are read as result.{{key}})."
            )
        offset = self.u_equilibrium if key == "u" else self.x_equilibrium
        data = getattr(self, key)
        return data if offset is None else data + offset

    stop: StopReport | None = None
    provenance: dict[str, Any] = field(default_factory=dict)
    reports: dict[str, Any] = field(default_factory=dict)

    @property
    def regulated(self) -> bool | None:
        """Whether the run reached its target (``summary.json`` → ``regulation``).

        None for a result that was not scored (built by hand).
        """
        return self.reports.get("regulated")

    @property
    def status(self) -> str:
        """``ok`` (reached the horizon), ``diverged`` or ``timeout`` (see :attr:`stop`)."""
        return self.stop.status if self.stop is not None else STATUS_OK

    @property
    def stopped(self) -> str | None:
        """``"status: reason"`` when the guard cut the run short, else None.

        The logs of such a run end at :attr:`stop`'s time, not at the horizon,
        so its ``J(T)``, ``x(T)`` and averages over the run are not comparable
        with a whole run's.
        """
        if self.stop is None or self.status == STATUS_OK:
            return None
        return f"{self.status}: {self.stop.reason}"

    @property
    def e(self) -> np.ndarray:
        """Estimation error ``x - xhat``, shape (T, n)."""
        return self.x - self.xhat

    def at(self, key: str, time: float) -> np.ndarray:
        """The logged ``key`` at the sample nearest to ``time``.

        Raises
        ------
        ModelError
            If ``key`` is not one of :data:`SAMPLED_KEYS`, ``time`` is not a
            finite number ``>= 0``, or no sample lies within half a log period
            of ``time``. (A ``ValueError``, as before.)
        """
        if key not in SAMPLED_KEYS:
            raise ModelError(
                f"SimulationResult.at: no log {key!r}; choose one of {list(SAMPLED_KEYS)} "
                "(further logs are in result.extra)."
            )
        time = positive_number("SimulationResult.at: time", time, allow_zero=True)
        i = int(np.argmin(np.abs(self.t - time)))
        spacing = np.min(np.diff(self.t)) if self.t.size > 1 else 0.0
        if abs(self.t[i] - time) > 0.5 * spacing + 1e-9:
            raise ModelError(f"no sample of {key!r} at t = {time}; the log ends at {self.t[-1]}.")
        return getattr(self, key)[i]

    def solve_counts(self) -> dict[str, Any] | None:
        """Observer re-solves run and failed up to the last sample; None if not logged.

        Read from the ``solve_counts`` log of an observer that re-designs its
        gains (:class:`~ofrl_drake.systems.ScheduledThreeGainObserver`), which
        counts every re-solve, so the numbers are exact.
        """
        if "solve_counts" not in self.extra:
            return None
        counts = np.asarray(self.extra["solve_counts"]).reshape(self.t.size, 2)
        run, failed = (int(c) for c in np.rint(counts[-1]))
        flagged = np.flatnonzero(np.diff(counts[:, 1], prepend=0.0) > 0)
        return {
            "resolves": run,
            "failed_solves": failed,
            "at_time": float(self.t[-1]),
            "first_failure_logged_at": float(self.t[flagged[0]]) if flagged.size else None,
        }

    def summary(self) -> dict[str, Any]:
        """The contents of ``summary.json``.

        Besides the final values it holds ``validity`` (when checked),
        ``observer_design`` (when designed), ``extra_logs`` (the keys of
        :data:`EXTRA_LOGS_FILE`) and, when the observer re-solves its design,
        ``failed_solves`` and ``observer_resolves`` (:meth:`solve_counts`).
        With an equilibrium, ``final_state`` is in the plant's own coordinates,
        ``final_state_norm`` is ``|x(T) - x*|`` and ``equilibrium`` holds
        ``x*`` and ``u*``.
        """
        Gamma_T = 0.5 * (self.Gamma[-1] + self.Gamma[-1].T)
        out = {
            "scenario": self.scenario_name,
            "status": self.status,
            "final_time": float(self.t[-1]),
            "final_state": self.original("x")[-1].tolist(),
            "final_state_norm": float(np.linalg.norm(self.x[-1])),
            "final_estimation_error": self.e[-1].tolist(),
            "final_estimation_error_norm": float(np.linalg.norm(self.e[-1])),
            "final_weights": self.W[-1].tolist(),
            "final_gamma_eigenvalues": (
                np.linalg.eigvalsh(Gamma_T).tolist()
                if np.isfinite(Gamma_T).all()
                else [None] * len(Gamma_T)  # a run stopped on a non-finite Gamma
            ),
            "min_learning_condition": float(np.min(self.learning_condition)),
            "final_cost": float(self.cost[-1]),
            "wall_time": self.wall_time,
            "integrator": self.integrator,
        }
        if self.state_units is not None or self.input_units is not None:
            out["units"] = {
                "state": None if self.state_units is None else list(self.state_units),
                "input": None if self.input_units is None else list(self.input_units),
            }
        if self.x_equilibrium is not None:
            out["equilibrium"] = {
                "x": np.asarray(self.x_equilibrium, float).tolist(),
                "u": np.asarray(self.u_equilibrium, float).tolist(),
            }
        if self.stop is not None:
            out["stop"] = self.stop.to_dict()
            if self.x_equilibrium is not None:  # in the plant's own coordinates, as above
                for key in ("x", "xhat"):
                    shifted = np.asarray(self.stop.x if key == "x" else self.stop.xhat, float)
                    out["stop"][key] = vector_to_json(shifted + self.x_equilibrium)
        if self.provenance:
            out["provenance"] = self.provenance
        if self.validity is not None:
            out["validity"] = self.validity.to_dict()
        if self.design is not None:
            out["observer_design"] = self.design
        keys = self._extra_log_arrays()
        if keys:
            out["extra_logs"] = sorted(keys)
        counts = self.solve_counts()
        if counts is not None:
            out["failed_solves"] = counts["failed_solves"]
            out["observer_resolves"] = counts
        out.update(self.reports)
        return out

    def _extra_log_arrays(self) -> dict[str, np.ndarray]:
        """What :data:`EXTRA_LOGS_FILE` holds: ``t`` and the extra logs."""
        arrays = {k: np.asarray(v) for k, v in self.extra.items()}
        if arrays:
            arrays = {"t": np.asarray(self.t), **arrays}
        return arrays

    def save(self, directory: str | Path) -> None:
        """Write the result's files into ``directory``.

        * ``trajectories.npz``: :data:`TRAJECTORY_KEYS`, with ``x``, ``xhat``
          and ``u`` in the plant's own coordinates, and ``x_equilibrium``,
          ``u_equilibrium`` and :data:`SHIFTED_KEYS` (the coordinates the
          result holds, for :meth:`load`) when there is an equilibrium;
        * ``extra_logs.npz`` (only if there are extra logs): ``t`` and every
          key of :attr:`extra` under its own name (a stale file from an
          earlier save is removed when there are none);
        * ``summary.json``: :meth:`summary`, as strict JSON: a number that is
          not finite (the NaN state of a diverged run) is ``null``.

        Each file is written to a temporary file in ``directory`` and renamed
        into place, so none is ever left half-written.

        Raises
        ------
        OutputError
            If ``directory`` (or a folder above it) is a file, or cannot be
            created or written.
        """
        directory = Path(directory)
        ensure_parent(directory / TRAJECTORIES_FILE, "SimulationResult.save: directory")
        with atomic_file(directory / TRAJECTORIES_FILE, "wb") as fh:
            arrays = {k: getattr(self, k) for k in TRAJECTORY_KEYS}
            if self.x_equilibrium is not None:
                arrays.update({k: self.original(k) for k in ORIGINAL_KEYS})
                arrays["x_equilibrium"] = np.asarray(self.x_equilibrium, float)
                arrays["u_equilibrium"] = np.asarray(self.u_equilibrium, float)
                arrays.update({SHIFTED_KEYS[k]: getattr(self, k) for k in ORIGINAL_KEYS})
            np.savez(fh, **arrays)
        # dict[str, Any]: numpy's stub reads a **dict of arrays as savez's allow_pickle too
        extra: dict[str, Any] = self._extra_log_arrays()
        if extra:
            with atomic_file(directory / EXTRA_LOGS_FILE, "wb") as fh:
                np.savez(fh, **extra)
        else:
            with contextlib.suppress(FileNotFoundError):
                (directory / EXTRA_LOGS_FILE).unlink()
        with atomic_file(directory / SUMMARY_FILE, "w") as fh:
            json.dump(json_ready(self.summary()), fh, indent=2, allow_nan=False)
            fh.write("\n")

    @classmethod
    def load(cls, directory: str | Path) -> SimulationResult:
        """The result :meth:`save` wrote into ``directory``: its inverse.

        ``directory`` is the ``--out`` folder of ``ofrl-drake run``, or one
        :meth:`save` wrote. The arrays are those the result held, bit for
        bit: with an equilibrium, ``x``, ``xhat`` and ``u`` are again the
        method's coordinates ``x - x*``, ``u - u*`` (:data:`SHIFTED_KEYS`; a
        folder written before those were saved gives the plant's own minus
        ``x*``, to within rounding), so :meth:`original` and the figures show
        the plant's own. ``summary.json`` gives the scenario's name,
        ``wall_time``, ``integrator`` (its ``accuracy``), the units (None
        when it has none), ``stop`` (its ``x`` and ``xhat`` shifted back by
        ``x*``, to within rounding), ``provenance``, ``validity``, the
        observer design and, as :attr:`reports`, every other entry
        (``regulation``, ``learning_curve``, ``learning_health``, ...);
        ``extra_logs.npz`` gives :attr:`extra`. So ``load(d).summary()`` is
        what ``summary.json`` holds.

        Raises
        ------
        RunFolderError
            If ``directory`` is not a folder or lacks ``trajectories.npz`` or
            ``summary.json`` (not a run folder); if a file is not a readable
            ``.npz`` archive, resp. JSON object (truncated, damaged, pickled
            objects); if an array of :data:`TRAJECTORY_KEYS` is missing, not
            real numbers (complex, text), has the wrong number of dimensions,
            another length than ``t`` or another width than its partner
            (``xhat`` and ``x``, ``W_policy`` and ``W``, ``Gamma`` and ``W``);
            if ``t`` is not floats, finite and non-decreasing; if the equilibrium
            does not fit ``x`` and ``u``, or ``x* +`` a shifted array is not
            its partner in the plant's coordinates (an edited file); if
            ``extra_logs.npz`` does not hold what ``summary.json`` lists, or
            other samples; or if an entry of ``summary.json`` the result
            holds has the wrong type or size (``integrator`` -> ``accuracy``
            not a number > 0). The message names the file and the fix.
        """
        directory = Path(directory)
        if not directory.is_dir():
            raise RunFolderError(
                f"{directory}: not a folder, so not a run folder; {_RUN_FOLDER_FIX}."
            )
        path = directory / TRAJECTORIES_FILE
        arrays = read_run_arrays(path)
        logs = _trajectories(arrays, path)
        summary_path = directory / SUMMARY_FILE
        summary = _read_summary(summary_path)
        n, m = logs["x"].shape[1], logs["u"].shape[1]
        x_eq = arrays.get("x_equilibrium")

        def entry(key: str, convert: Callable[[Any], _T]) -> _T | None:
            return summary_entry(summary_path, summary, key, convert)

        units = entry("units", lambda d: (_units_of(d["state"], n), _units_of(d["input"], m)))
        result = cls(
            **logs,
            wall_time=entry("wall_time", number_from_json) or 0.0,
            integrator=entry("integrator", _integrator_from_json) or {},
            validity=entry("validity", ValidityReport.from_dict),
            design=entry("observer_design", object_from_json),
            scenario_name=entry("scenario", string_from_json) or "",
            extra=_read_extra_logs(directory, logs["t"], summary.get("extra_logs")),
            state_units=None if units is None else units[0],
            input_units=None if units is None else units[1],
            stop=entry("stop", lambda d: _shifted_stop(StopReport.from_dict(d, n), x_eq)),
            provenance=entry("provenance", object_from_json) or {},
            reports={k: v for k, v in summary.items() if k not in SUMMARY_KEYS},
        )
        if "x_equilibrium" in arrays:
            result.x_equilibrium = arrays["x_equilibrium"]
            result.u_equilibrium = arrays["u_equilibrium"]
        if summary.get("status", result.status) != result.status:
            raise RunFolderError(
                f"{summary_path}: status = {summary['status']!r} but stop says "
                f"{result.status!r}; {_REWRITE_FIX}."
            )
        return result


def simulator_config(scenario: Scenario) -> SimulatorConfig:
    """Drake ``SimulatorConfig`` from ``scenario.simulation``."""
    s = scenario.simulation
    return SimulatorConfig(
        integration_scheme=s.integrator,
        max_step_size=s.max_step,
        accuracy=s.accuracy,
        use_error_control=True,
        target_realtime_rate=0.0,
        publish_every_time_step=False,
    )


def _same(a: Any, b: Any) -> bool:
    """Equality of scenario values that may hold lists or numpy arrays."""
    if a is b:
        return True
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(
            _same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    try:
        return bool(a == b)
    except (TypeError, ValueError):  # numpy arrays: element-wise ==
        try:
            return bool(np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float)))
        except (TypeError, ValueError):
            return False


#: Scenario fields a run writes into the context: ``simulate(scenario, loop=...)``
#: accepts a scenario that differs from the loop's own in these only.
RUN_VALUES = ("x0", "xhat0")
#: ``critic`` fields a run writes into the context under ``critic.gains: manual``.
RUN_CRITIC_VALUES = ("W0", "Gamma0")
#: ``measurement`` fields a run writes into the context (the noise seed).
RUN_MEASUREMENT_VALUES = ("seed",)


def _differing(built: Any, scenario: Any) -> list[str]:
    """The fields of two scenarios that differ, by name."""
    if dataclasses.is_dataclass(built) and type(built) is type(scenario):
        return [
            f.name
            for f in dataclasses.fields(built)
            if not _same(getattr(built, f.name), getattr(scenario, f.name))
        ]
    return [] if _same(built, scenario) else ["type"]


def _check_loop_arguments(
    scenario: Scenario, loop: ClosedLoop, design: ObserverDesign | None, swaps: dict[str, Any]
) -> None:
    """Raise if ``simulate(scenario, loop=loop, ...)`` got arguments it would ignore.

    The scenario may differ from the loop's own only in what a run writes
    into the context (:meth:`~ofrl_drake.diagram.ClosedLoop.set_initial_values`,
    the noise seed): :data:`RUN_VALUES`, :data:`RUN_MEASUREMENT_VALUES`, and
    :data:`RUN_CRITIC_VALUES` when both scenarios give the critic's gains
    (``critic.gains: manual``; under ``auto`` they are derived from ``W0``).
    """
    if design is not None:
        raise SwapError(
            "design: simulate(..., loop=...) runs the loop as built, with the observer "
            "design it was built with; pass design= to build_closed_loop(scenario, "
            "design=...) instead, or drop loop= to build the loop here."
        )
    if swaps:
        name = sorted(swaps)[0]
        raise SwapError(
            f"{name}: simulate(..., loop=...) cannot swap blocks of a loop that is already "
            f"built; pass {name}=... to build_closed_loop(scenario, {name}=...) instead, or "
            "drop loop= to build the loop here."
        )
    built = loop.parts.scenario
    if built is scenario:
        return
    differing: list[str] = []
    for name in _differing(built, scenario):
        if name in RUN_VALUES:
            continue
        if name == "critic":
            fields = _differing(built.critic, scenario.critic)
            manual = critic_gains_choice(built.critic) == "manual"
            if manual and critic_gains_choice(scenario.critic) == "manual":
                fields = [f for f in fields if f not in RUN_CRITIC_VALUES]
            differing.extend(f"critic.{f}" for f in fields)
            continue
        if name == "measurement" and built.measurement is not None:
            fields = _differing(built.measurement, scenario.measurement)
            if scenario.measurement is not None:
                fields = [f for f in fields if f not in RUN_MEASUREMENT_VALUES]
            differing.extend(f"measurement.{f}" for f in fields)
            continue
        differing.append(name)
    if differing:
        raise ScenarioError(
            f"scenario: the loop was built from a different scenario (it differs in "
            f"{', '.join(differing)}); pass the scenario the loop was built from "
            "(loop.parts.scenario), or rebuild the loop with build_closed_loop(scenario)."
        )


def _check_parameters(loop: ClosedLoop, parameters: object) -> None:
    """Refuse ``parameters`` that are not a root context of ``loop.diagram``.

    Drake copies parameters only between contexts of the same diagram (it
    aborts the interpreter otherwise), so this is checked first.
    """
    fix = (
        "pass loop.diagram.CreateDefaultContext() (with the gains set through the blocks' "
        "setters), or omit parameters= to run at the loop's own gains"
    )
    if not isinstance(parameters, Context):
        raise SwapError(
            f"parameters: expected a Context of loop.diagram; got {type(parameters).__name__}; "
            f"{fix}."
        )
    try:
        loop.diagram.ValidateContext(parameters)
    except RuntimeError:
        raise SwapError(
            f"parameters: the context is not a root context of this loop's diagram "
            f"{loop.diagram.get_name()!r} (a context of another loop or system, or a block's "
            f"subcontext); {fix}."
        ) from None


def _certified_input_bound(scenario: Scenario, cert: ObserverCertificate) -> float:
    """The bound ``|u_k|`` is checked against: the scenario's, or the certificate's if smaller.

    The observer's certificate (``cert``) holds only for ``|u_k| <=`` its
    design's ``input_bound`` (``cert.design["input_bound"]``, when it has one).
    """
    bound = scenario.input_bound
    certified = (cert.design or {}).get("input_bound")
    if certified is None:
        return bound
    certified = positive_number("observer_certificate().design['input_bound']", certified)
    return min(certified, bound)


def _certified_region(
    loop: ClosedLoop, cert: ObserverCertificate, logs: dict[str, np.ndarray], t: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray] | BoxSchedule | None, str | None]:
    """The box x and xhat are checked against, and a note for the report.

    ``cert`` is what the observer block certifies, asked of the block through
    its :meth:`observer_certificate`
    (:func:`~ofrl_drake.observer_certificate.certificate_of`), whatever its
    class: a ``"design"`` holds on its fixed box; a ``"scheduled"`` observer
    is checked, sample by sample, against the box of the design in force,
    which it logs on ``certified_box``; any other has no certified box, and
    the note says why.
    """
    observer: System = loop.blocks["observer"]
    if cert.kind == "scheduled" and "certified_box" in logs:
        schedule = BoxSchedule.from_samples(t, logs["certified_box"])
        note = f"{cert.note} ({schedule.times.size - 1} box changes), not against one fixed box"
        return schedule, note
    if cert.box is not None:
        return (np.asarray(cert.box.lower, float), np.asarray(cert.box.upper, float)), None
    if cert.kind == "none" and loop.design is not None:
        return None, (
            f"the observer block ({type(observer).__name__}) does not run the observer "
            "design's gains: box checks not applicable; only |u_k| <= lambda_bar was checked"
        )
    return None, cert.note


def _design_dict(loop: ClosedLoop, cert: ObserverCertificate) -> dict[str, Any] | None:
    """The observer's design or local certificate, as reported in ``summary.json``.

    What the observer block certifies (``cert``); the loop's design when the
    block certifies nothing (it is still reported, though the block does not
    run it).
    """
    if cert.design is not None:
        return cert.design
    return loop.design.to_dict() if loop.design is not None else None


def simulate(
    scenario: Scenario | str | Path,
    *,
    design: ObserverDesign | None = None,
    progress: bool | None = None,
    loop: ClosedLoop | None = None,
    parameters: Context | None = None,
    **swaps: Any,
) -> SimulationResult:
    """Build and simulate ``scenario``'s closed loop over its horizon.

    Every run is watched by a :class:`~ofrl_drake.guard.RunGuard`, the
    ``Simulator``'s monitor, which takes no steps of its own: the run stops early
    with status ``diverged`` (a non-finite state, x or xhat outside
    ``simulation.abort_box``, or an integrator that gives up) or ``timeout``
    (``simulation.max_wall_time`` exceeded). A stopped run is returned, not
    raised: its logs end at the stop and ``result.status`` / ``result.stop`` say
    why.

    Parameters
    ----------
    scenario : Scenario, str or Path
        The scenario, or the path of its YAML file (loaded with
        :func:`~ofrl_drake.load_scenario`).
    design : ObserverDesign, optional
        Observer design; computed from the scenario if omitted. Not allowed
        with ``loop``.
    progress : bool, optional
        Draw a progress bar on stderr; by default only when stderr is a terminal.
        The bar is drawn by the guard, so the trajectories are the same, bit for
        bit, with and without it.
    loop : ClosedLoop, optional
        An already-built loop to simulate, from a fresh context. It must have
        been built from ``scenario`` but for the values a run writes into the
        context: ``x0``, ``xhat0``, ``measurement.seed`` and, when the critic's
        gains are given (``critic.gains: manual``), ``critic.W0`` and
        ``critic.Gamma0`` (:meth:`~ofrl_drake.diagram.ClosedLoop.set_initial_values`).
        So one built loop runs from many initial states, under many noise
        seeds. ``design`` and ``swaps`` must then be omitted (give them to
        :func:`~ofrl_drake.build_closed_loop`).
    parameters : Context, optional
        A context of ``loop.diagram`` whose parameters the run uses, e.g. the
        learning gains set with the blocks' setters
        (``loop.critic.set_kc(loop.critic.GetMyMutableContextFromRoot(context), kc)``,
        ``set_beta``, ``set_gamma_bound``, ``set_nu``); only with ``loop``. The
        state comes from the scenario; ``parameters`` is not modified.
    **swaps
        Block replacements, as for :func:`~ofrl_drake.build_closed_loop`.
        Not allowed with ``loop``.

    Returns
    -------
    SimulationResult
        Its ``validity`` always checks ``|u_k| <= lambda_bar`` (or the
        smaller input bound of the observer's design, which the note then
        names); x, xhat and, when H or K is nonzero, the injection points
        ``xhat + H ytil`` and ``xhat + K ytil`` are checked against the
        certified box when the observer has one (see :mod:`ofrl_drake.validity`).

    Raises
    ------
    SwapError
        If ``loop`` is not a ClosedLoop, or is given together with ``design``
        or a swap; if ``parameters`` is given without ``loop``, or is not a
        context of ``loop.diagram``.
    ScenarioError
        If ``scenario`` is neither a Scenario nor a path (also a
        ``TypeError``), or ``loop`` was built from a scenario that differs
        from ``scenario`` in more than the values a run writes into the
        context.
    DesignError
        If ``design`` is not an ``ObserverDesign`` certified for the
        scenario's ``input_bound`` (see :func:`~ofrl_drake.build_closed_loop`).
    ObserverDesignInfeasible
        If ``design`` and ``loop`` are omitted and the scenario's LMI has no
        certified solution (or its pinned gains are not certified).
    WallTimeExceeded
        If the observer design does not finish within
        ``simulation.max_wall_time`` (a run that does not is stopped with
        status ``timeout`` instead).
    ModelError
        If the plant's ``f`` or ``g`` returns the wrong shape or non-finite
        values where the design or a block evaluates it.
    """
    if isinstance(scenario, (str, Path)):
        scenario = load_scenario(scenario)
    check_scenario(scenario, "simulate", paths=True)
    if loop is not None and not isinstance(loop, ClosedLoop):
        raise SwapError(
            f"loop: expected a ClosedLoop; got {type(loop).__name__}. Build one with "
            "build_closed_loop(scenario), or omit loop= to build it here."
        )
    if loop is None:
        if parameters is not None:
            raise SwapError(
                "parameters: a context of a built loop's diagram; pass loop= too (the loop "
                "built with build_closed_loop(scenario) that the context belongs to)."
            )
        loop = build_closed_loop(scenario, design=design, **swaps)
    else:
        _check_loop_arguments(scenario, loop, design, swaps)
        if parameters is not None:
            _check_parameters(loop, parameters)
    simulator = Simulator(loop.diagram)
    ApplySimulatorConfig(simulator_config(scenario), simulator)
    seeds = _initialize_context(loop, scenario, simulator.get_mutable_context(), parameters)
    duration = scenario.simulation.duration
    show = sys.stderr.isatty() if progress is None else progress
    guard = RunGuard(
        loop.diagram,
        loop.blocks["plant"],
        loop.blocks["observer"],
        abort_box(scenario),
        scenario.simulation.max_wall_time,
        ProgressBar(duration, sys.stderr) if show else None,
        relative=scenario.equilibrium is not None,
    )
    # The guard is a monitor: it sees every step and changes none (see ofrl_drake.guard).
    simulator.set_monitor(guard)
    origin = provenance()
    if seeds:
        origin["seeds"] = seeds
    start = time.perf_counter()
    guard.start()
    simulator.Initialize()
    if not guard.stopped:
        watchdog = StallWatchdog(
            guard,
            simulator.get_integrator(),
            stall_limit(simulator.get_context().num_continuous_states()),
        )
        try:
            with watchdog:
                simulator.AdvanceTo(duration)
        except IntegratorStalled:
            assert watchdog.fired is not None  # only the watchdog raises it
            guard.fail(watchdog.fired[1], watchdog.fired[0], within_step=True)
        except RuntimeError as err:
            if not _is_integrator_failure(err):
                raise
            guard.fail(f"the integrator gave up: {one_line(err)}")
        except ValueError as err:
            if not is_domain_error(err):
                raise
            cause = one_line(err, 200)
            # Drake does not say which function of the diagram raised: the
            # model's f or g, or another one (the cost's log, a block's output).
            guard.fail(
                f"the model's f or g was evaluated outside its domain ({cause}) for the model "
                f"{loop.parts.system.name!r}, or another function of the diagram was (Drake "
                "does not say which; the cost, for one): the state (or the estimate, or an "
                "extrapolation point) left the region where f and g (and the cost) are "
                "defined; restrict x0, the points box or simulation.abort_box to that region"
            )
    wall = time.perf_counter() - start
    stop = guard.report(simulator.get_context())
    if not stop.ok and not guard.within_step:  # a stopped step's context holds a stage
        _flush_logs(loop, simulator.get_context())

    t, logs = loop.logs(simulator.get_context())
    integ = simulator.get_integrator()
    stats = {
        "scheme": scenario.simulation.integrator,
        "accuracy": scenario.simulation.accuracy,
        "max_step": scenario.simulation.max_step,
        "num_steps": int(integ.get_num_steps_taken()),
        "num_derivative_evaluations": int(integ.get_num_derivative_evaluations()),
        "num_step_shrinkages_from_error_control": int(
            integ.get_num_step_shrinkages_from_error_control()
        ),
        "smallest_step": number_to_json(integ.get_smallest_adapted_step_size_taken()),
        "largest_step": number_to_json(integ.get_largest_step_size_taken()),
    }
    # Asked once: a design's certificate recomputes its corner eigenvalues.
    cert = certificate_of(loop.blocks["observer"])
    design_dict = _design_dict(loop, cert)
    result = SimulationResult(
        t=np.asarray(t),
        x=logs["x"],
        xhat=logs["xhat"],
        W=logs["W"],
        W_policy=logs["W_policy"],
        Gamma=unpack_symmetric(logs["Gamma"]),  # logged packed (GammaGain)
        u=logs["u"],
        learning_condition=logs["learning_condition"][:, 0],
        cost=logs["cost"][:, 0],
        wall_time=wall,
        integrator=stats,
        design=design_dict,
        scenario_name=scenario.name,
        state_units=_units(loop.parts.system.state_units),
        input_units=_units(loop.parts.system.input_units),
        extra={k: v for k, v in logs.items() if k not in LOGGED},
        stop=stop,
        provenance=origin,
    )
    system = loop.parts.system
    if system.is_shifted:  # recorded even at x* = 0, u* = 0: the scenario gave one
        x_eq, u_eq = system.equilibrium
        result.x_equilibrium = np.asarray(x_eq, float)
        result.u_equilibrium = np.asarray(u_eq, float)
    if loop.parts.truth is not None:
        from ofrl_drake.model_error import model_mismatch

        o = scenario.observer
        result.reports["model_error"] = model_mismatch(
            loop.parts.system,
            loop.parts.truth,
            (o.box.lower, o.box.upper),
            body_mass_scale=None if scenario.truth is None else scenario.truth.body_mass_scale,
        ).to_dict()
    from ofrl_drake.ablation_metrics import regulation

    o = scenario.observer
    result.reports["regulation"] = regulation(
        result.status,
        result.x[-1],
        (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float)),
        scenario.simulation.regulation_tolerance,
        result.xhat[-1],
    )
    result.reports["regulated"] = result.reports["regulation"]["regulated"]
    box, note = _certified_region(loop, cert, logs, result.t)
    input_bound = _certified_input_bound(scenario, cert)
    if input_bound != scenario.input_bound:
        bound_note = (
            f"|u_k| checked against the observer design's input_bound = {input_bound:g}, "
            f"below the scenario's input_bound = {scenario.input_bound:g}"
        )
        note = bound_note if note is None else f"{note}; {bound_note}"
    gains = _injection_gains(loop, cert, logs)
    result.validity = validity_report(
        result.t,
        result.x,
        result.xhat,
        result.u,
        box,
        input_bound,
        note=note,
        C=gains.get("C"),
        H=gains.get("H"),
        K=gains.get("K"),
    )
    return result


def _injection_gains(
    loop: ClosedLoop, cert: ObserverCertificate, logs: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """``C``, ``H`` and ``K`` for the validity report's injection points; empty: none apply.

    A ``"design"`` certificate's fixed gains; a ``"scheduled"`` observer's gains
    in force at each sample, from its ``observer_gains`` log (``[vec(L), vec(H),
    vec(K)]``, row-major: :func:`~ofrl_drake.observer.unpack_gains`). A design
    dict without ``H`` and ``K`` (a user's own certificate may omit them) leaves
    them unchecked (``injection_check == "no_gains"``); any other certificate
    has no box to check them against.
    """
    C = np.asarray(loop.parts.system.output_matrix, dtype=float)
    q, n = C.shape
    if cert.kind == "scheduled" and "observer_gains" in logs:
        _, H, K = unpack_gains(logs["observer_gains"], n, q)
        return {"C": C, "H": H, "K": K}
    design = cert.design if cert.kind == "design" else None
    if design is not None and "H" in design and "K" in design:
        return {
            "C": np.asarray(design.get("C", C), dtype=float),
            "H": np.asarray(design["H"], dtype=float),
            "K": np.asarray(design["K"], dtype=float),
        }
    return {}  # a design dict without H and K (a user's certificate): not checked


def _initialize_context(
    loop: ClosedLoop, scenario: Scenario, context: Any, parameters: Context | None = None
) -> dict[str, int]:
    """Seed the noise, set the parameters, the initial values and the holds.

    With measurement noise, ``SetRandomContext`` draws every ``RandomSource``'s
    seed from ``RandomGenerator(measurement.seed)``: the same seed gives the
    same noise, bit for bit. ``parameters`` (a context of the diagram) gives
    its parameters. Then the run's initial values are written
    (:meth:`~ofrl_drake.diagram.ClosedLoop.set_initial_values`, after each
    block has set what its default context cannot hold: a multibody truth's
    velocities and masses, where ``parameters`` did not set a mass), and
    the holds start at their input's value
    (:func:`ofrl_drake.systems.world.start_holds`).

    Returns
    -------
    dict
        The seeds used, for the provenance (empty without noise).
    """
    from pydrake.common import RandomGenerator

    from ofrl_drake.systems.world import start_holds

    seeds: dict[str, int] = {}
    meas = scenario.measurement
    if meas is not None and any(v > 0 for v in meas.noise_std):
        loop.diagram.SetRandomContext(context, RandomGenerator(int(meas.seed)))
        seeds["measurement"] = int(meas.seed)
    if parameters is not None:
        context.get_mutable_parameters().SetFrom(parameters.get_parameters())
    loop.set_initial_values(context, scenario)
    for block in loop.blocks.values():
        start_holds(block, block.GetMyMutableContextFromRoot(context))
    return seeds


def _units(units: Any) -> tuple[str, ...] | None:
    return None if units is None else tuple(str(u) for u in units)


def _is_integrator_failure(err: RuntimeError) -> bool:
    """True for Drake's own integrator errors (a step size it cannot take)."""
    text = str(err).lower()
    return "step" in text and ("integrator" in text or "error control" in text)


def _flush_logs(loop: ClosedLoop, root_context: Any) -> None:
    """Log the state at which the guard stopped the run, unless already logged."""
    for logger in loop.loggers.values():
        context = logger.GetMyContextFromRoot(root_context)
        times = logger.FindLog(root_context).sample_times()
        if times.size == 0 or times[-1] < root_context.get_time():
            logger.ForcedPublish(context)


#: What to do about a folder that is not a run folder.
_RUN_FOLDER_FIX = (
    "give the --out folder of ofrl-drake run (or one SimulationResult.save wrote), which "
    f"holds {TRAJECTORIES_FILE} and {SUMMARY_FILE}"
)
#: How to write a run folder again.
_RERUN = "ofrl-drake run RUN_DIR/scenario.yaml --out NEW_DIR"
#: What to do about a damaged run folder.
_REWRITE_FIX = (
    f"the file is damaged or was not written by SimulationResult.save; write the run again "
    f"({_RERUN})"
)


def damaged_run_file(path: str | Path, why: str) -> RunFolderError:
    """The error for the file ``path`` of a run folder that is damaged: ``why``, then the fix.

    One message for every reader of a run folder (:meth:`SimulationResult.load`,
    ``ofrl-drake plot``): ``"<path>: <why>; the file is damaged or was not
    written by SimulationResult.save; write the run again (...)."``
    """
    return RunFolderError(f"{path}: {why}; {_REWRITE_FIX}.")


def _run_file(path: Path) -> Path:
    """``path`` of a run folder, refused when it is missing or not a regular file.

    Raises
    ------
    RunFolderError
        If ``path`` does not exist (for ``trajectories.npz`` and
        ``summary.json``: the folder is not a run folder; for another file:
        the run folder lacks it) or is not a regular file (a folder, a FIFO:
        never opened).
    """
    if not path.exists() and path.name in (TRAJECTORIES_FILE, SUMMARY_FILE):
        raise RunFolderError(
            f"{path}: no such file, so {path.parent} is not a run folder; {_RUN_FOLDER_FIX}."
        )
    if not path.exists():
        raise RunFolderError(
            f"{path}: no such file, though the run folder needs it (removed?); write the run "
            f"again ({_RERUN})."
        )
    if not path.is_file():
        raise RunFolderError(f"{path}: not a regular file; {_REWRITE_FIX}.")
    return path


def read_run_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` archive ``path`` of a run folder, each numeric.

    What :meth:`SimulationResult.load` reads ``trajectories.npz`` and
    ``extra_logs.npz`` with (``ofrl-drake plot``: ``learning_health.npz``).

    Raises
    ------
    RunFolderError
        If the file is missing, not an ``.npz`` archive (truncated, damaged, a
        CRC error), holds pickled objects, or an array that is not real
        numbers (floats, integers or booleans: not complex, not text).
    """
    path = _run_file(Path(path))
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):  # a .npy file gives one array
            raise ValueError("one .npy array, not an .npz archive of the run's arrays")
        with data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        why = one_line(err, 200)
        raise RunFolderError(
            f"{path}: not a readable .npz archive ({why}); {_REWRITE_FIX}."
        ) from None
    for key, value in arrays.items():
        if not any(
            np.issubdtype(value.dtype, real) for real in (np.floating, np.integer, np.bool_)
        ):
            raise damaged_run_file(path, f"{key} holds {value.dtype} values, not real numbers")
    return arrays


def _trajectories(arrays: dict[str, np.ndarray], path: Path) -> dict[str, np.ndarray]:
    """The logs of ``trajectories.npz`` in the result's coordinates, their shapes checked.

    Raises
    ------
    RunFolderError
        See :meth:`SimulationResult.load`.
    """
    missing = [key for key in TRAJECTORY_KEYS if key not in arrays]
    if missing:
        raise RunFolderError(
            f"{path}: no {', '.join(missing)}; a run's trajectories hold "
            f"{list(TRAJECTORY_KEYS)}; {_REWRITE_FIX}."
        )
    logs = {key: arrays[key] for key in TRAJECTORY_KEYS}
    for key, ndim in _TRAJECTORY_NDIM.items():
        if logs[key].ndim != ndim:
            raise RunFolderError(
                f"{path}: {key} has shape {logs[key].shape}; expected {ndim} "
                f"dimension{'s' if ndim > 1 else ''}, time first; {_REWRITE_FIX}."
            )
    t = logs["t"]
    T = t.size
    if T == 0:
        raise RunFolderError(f"{path}: t is empty, a run logs at least one sample; {_REWRITE_FIX}.")
    if not np.issubdtype(t.dtype, np.floating):
        raise damaged_run_file(path, f"t holds {t.dtype} values, not the float times of a run")
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise damaged_run_file(path, f"t[{bad}] = {t[bad]}; a run's times are finite")
    if np.any(np.diff(t) < 0):
        bad = int(np.flatnonzero(np.diff(t) < 0)[0])
        raise damaged_run_file(
            path,
            f"t[{bad + 1}] = {t[bad + 1]:g} comes before t[{bad}] = {t[bad]:g}; a run's "
            "times do not decrease",
        )
    for key in TRAJECTORY_KEYS:
        if logs[key].shape[0] != T:
            raise RunFolderError(
                f"{path}: {key} has {logs[key].shape[0]} samples but t has {T}; {_REWRITE_FIX}."
            )
    L = logs["W"].shape[1]
    for key, shape in (
        ("xhat", logs["x"].shape),
        ("W_policy", logs["W"].shape),
        ("Gamma", (T, L, L)),
    ):
        if logs[key].shape != shape:
            raise RunFolderError(
                f"{path}: {key} has shape {logs[key].shape}; expected {shape} (from x and W); "
                f"{_REWRITE_FIX}."
            )
    has_x, has_u = "x_equilibrium" in arrays, "u_equilibrium" in arrays
    if not (has_x or has_u):
        return logs
    sizes = {"x": logs["x"].shape[1], "u": logs["u"].shape[1]}
    for key in ("x", "u"):
        eq = arrays.get(f"{key}_equilibrium")
        if eq is None or eq.shape != (sizes[key],):
            shown = "missing" if eq is None else f"of shape {eq.shape}"
            raise RunFolderError(
                f"{path}: {key}_equilibrium is {shown}; expected shape ({sizes[key]},) "
                f"beside {'u' if key == 'x' else 'x'}_equilibrium; {_REWRITE_FIX}."
            )
    for key in ORIGINAL_KEYS:
        offset = arrays["u_equilibrium" if key == "u" else "x_equilibrium"]
        shifted = arrays.get(SHIFTED_KEYS[key])
        if shifted is None:  # written before the shifted logs were saved: within rounding
            logs[key] = logs[key] - offset
            continue
        if shifted.shape != logs[key].shape or not np.array_equal(
            shifted + offset, logs[key], equal_nan=True
        ):
            raise RunFolderError(
                f"{path}: {SHIFTED_KEYS[key]} + the equilibrium is not {key} (the file was "
                f"edited or is damaged; edit neither by hand); {_REWRITE_FIX}."
            )
        logs[key] = shifted
    return logs


def summary_entry(
    path: Path, summary: dict[str, Any], key: str, convert: Callable[[Any], _T]
) -> _T | None:
    """``convert(summary[key])`` of the ``summary.json`` at ``path``; None when there is none.

    Raises
    ------
    RunFolderError
        If ``convert`` raises ``TypeError``, ``ValueError``, ``KeyError`` or
        ``AttributeError`` (an entry of the wrong type or size), naming the
        file, the key, the value and the fix.
    """
    if key not in summary:
        return None
    try:
        return convert(summary[key])
    except (TypeError, ValueError, KeyError, AttributeError) as err:
        shown = repr(summary[key])
        shown = shown if len(shown) <= 80 else f"{shown[:77]}..."
        raise RunFolderError(
            f"{path}: {key} = {shown} cannot be read back ({err}); {_REWRITE_FIX}."
        ) from None


def _read_summary(path: Path) -> dict[str, Any]:
    """``summary.json`` of a run folder, a JSON object.

    Raises
    ------
    RunFolderError
        If the file is missing, unreadable, not JSON, or not an object.
    """
    _run_file(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        why = one_line(err, 200)
        raise RunFolderError(f"{path}: not readable JSON ({why}); {_REWRITE_FIX}.") from None
    if not isinstance(data, dict):
        raise RunFolderError(
            f"{path}: a JSON {type(data).__name__}, not an object of the run's entries; "
            f"{_REWRITE_FIX}."
        )
    return data


def read_run_series(
    path: str | Path, t: np.ndarray, required: Sequence[str] = ()
) -> dict[str, np.ndarray]:
    """The arrays of the ``.npz`` file ``path`` of a run folder, each sampled at ``t``.

    Files that hold series logged beside ``trajectories.npz`` and its times
    ``t``: ``extra_logs.npz``, ``learning_health.npz``. The file's own ``t``
    is dropped from the arrays returned.

    Raises
    ------
    RunFolderError
        As :func:`read_run_arrays`; if the file has no ``t`` or no array of
        ``required``, its ``t`` is not ``t`` (another run's file), or an
        array does not have ``t.size`` samples first.
    """
    path = Path(path)
    arrays = read_run_arrays(path)
    missing = [key for key in ("t", *required) if key not in arrays]
    if missing:
        raise RunFolderError(f"{path}: no {', '.join(missing)}; {_REWRITE_FIX}.")
    if not np.array_equal(arrays["t"], t):
        raise RunFolderError(
            f"{path}: its t is not the t of {TRAJECTORIES_FILE} (another run's file?); "
            f"{_REWRITE_FIX}."
        )
    for key, value in arrays.items():
        if value.ndim == 0 or value.shape[0] != t.size:
            raise RunFolderError(
                f"{path}: {key} has shape {value.shape}, not {t.size} samples first; "
                f"{_REWRITE_FIX}."
            )
    return {key: value for key, value in arrays.items() if key != "t"}


def _read_extra_logs(directory: Path, t: np.ndarray, listed: Any) -> dict[str, np.ndarray]:
    """:data:`EXTRA_LOGS_FILE` of a run folder, checked against what ``summary.json`` lists.

    Raises
    ------
    RunFolderError
        If the file is missing while ``listed`` names logs, holds other keys
        than ``listed`` (or any when none are listed), or is refused by
        :func:`read_run_series`.
    """
    path = directory / EXTRA_LOGS_FILE
    if listed is None and not path.exists():
        return {}
    logs = read_run_series(path, t)  # refused when missing: summary.json lists logs
    held = sorted(["t", *logs])
    if not isinstance(listed, list) or held != sorted(map(str, listed)):
        raise RunFolderError(
            f"{path}: holds {held} but {SUMMARY_FILE} lists extra_logs = {listed!r}; "
            f"{_REWRITE_FIX}."
        )
    return logs


def _units_of(value: Any, size: int) -> tuple[str, ...] | None:
    """Units of ``size`` entries (``summary.json`` → ``units``), or None."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != size:
        raise ValueError(f"expected {size} units, one per entry")
    return tuple(string_from_json(u) for u in value)


def _shifted_stop(stop: StopReport, x_equilibrium: np.ndarray | None) -> StopReport:
    """``stop`` as ``summary.json`` holds it (the plant's own x, xhat), in the result's own."""
    if x_equilibrium is None:
        return stop
    x, xhat = (np.asarray(v, float) - x_equilibrium for v in (stop.x, stop.xhat))
    return dataclasses.replace(stop, x=x.tolist(), xhat=xhat.tolist())


def _integrator_from_json(value: Any) -> dict[str, Any]:
    """``summary.json`` -> ``integrator``, its ``accuracy`` (the figures draw it) a number > 0."""
    integrator = object_from_json(value)
    accuracy = optional_number_from_json(integrator.get("accuracy"))
    if accuracy is not None and not (math.isfinite(accuracy) and accuracy > 0):
        raise ValueError(f"accuracy {accuracy} is not a number > 0")
    return integrator
