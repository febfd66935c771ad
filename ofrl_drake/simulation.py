"""Simulate a scenario with Drake's ``Simulator`` and collect the logs."""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorConfig

from ofrl_drake.diagram import LOGGED, ClosedLoop, build_closed_loop
from ofrl_drake.scenario import Scenario
from ofrl_drake.validity import ValidityReport, validity_report

__all__ = ["TRAJECTORY_KEYS", "SimulationResult", "simulate", "simulator_config"]

#: Keys of ``trajectories.npz``, in order.
TRAJECTORY_KEYS = ("t", "x", "xhat", "W", "Gamma", "u", "learning_condition", "cost")


@dataclass
class SimulationResult:
    """Logged trajectories of one closed-loop run, as numpy arrays (time first).

    Attributes
    ----------
    t : ndarray, shape (T,)
    x, xhat : ndarray, shape (T, n)
    W : ndarray, shape (T, L)
    Gamma : ndarray, shape (T, L, L)
    u : ndarray, shape (T, m)
    learning_condition : ndarray, shape (T,)
        ``c(t)`` of Assumption 2.
    cost : ndarray, shape (T,)
        ``J(t) = int_0^t Q(x) + U(u) dt``.
    wall_time : float
        Seconds spent in ``Simulator.AdvanceTo``.
    integrator : dict
        Integrator settings and statistics.
    validity : ValidityReport
        When x or xhat left the certified box or ``|u_k|`` exceeded lambda_bar.
    design : dict or None
        The observer design as a JSON-ready dict, with its certificate.
    extra : dict of ndarray
        Further logs of the loop beyond :data:`~ofrl_drake.diagram.LOGGED`
        (e.g. ``observer_gains`` of a scheduled observer), time first.
    """

    t: np.ndarray
    x: np.ndarray
    xhat: np.ndarray
    W: np.ndarray
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

    @property
    def e(self) -> np.ndarray:
        """Estimation error ``x - xhat``, shape (T, n)."""
        return self.x - self.xhat

    def at(self, key: str, time: float) -> np.ndarray:
        """The logged ``key`` at the sample nearest to ``time``.

        Raises
        ------
        ValueError
            If no sample lies within half a log period of ``time``.
        """
        i = int(np.argmin(np.abs(self.t - time)))
        spacing = np.min(np.diff(self.t)) if self.t.size > 1 else 0.0
        if abs(self.t[i] - time) > 0.5 * spacing + 1e-9:
            raise ValueError(f"no sample of {key!r} at t = {time}; the log ends at {self.t[-1]}.")
        return getattr(self, key)[i]

    def summary(self) -> dict[str, Any]:
        """The contents of ``summary.json``."""
        Gamma_T = 0.5 * (self.Gamma[-1] + self.Gamma[-1].T)
        out = {
            "scenario": self.scenario_name,
            "final_time": float(self.t[-1]),
            "final_state": self.x[-1].tolist(),
            "final_state_norm": float(np.linalg.norm(self.x[-1])),
            "final_estimation_error": self.e[-1].tolist(),
            "final_estimation_error_norm": float(np.linalg.norm(self.e[-1])),
            "final_weights": self.W[-1].tolist(),
            "final_gamma_eigenvalues": np.linalg.eigvalsh(Gamma_T).tolist(),
            "min_learning_condition": float(np.min(self.learning_condition)),
            "final_cost": float(self.cost[-1]),
            "wall_time": self.wall_time,
            "integrator": self.integrator,
        }
        if self.validity is not None:
            out["validity"] = self.validity.to_dict()
        if self.design is not None:
            out["observer_design"] = self.design
        return out

    def save(self, directory: str | Path) -> None:
        """Write ``trajectories.npz`` and ``summary.json`` into ``directory``."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        np.savez(directory / "trajectories.npz", **{k: getattr(self, k) for k in TRAJECTORY_KEYS})
        with open(directory / "summary.json", "w") as fh:
            json.dump(self.summary(), fh, indent=2)
            fh.write("\n")


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


def _progress(fraction: float, start: float) -> None:
    width = 30
    done = round(width * fraction)
    elapsed = time.perf_counter() - start
    sys.stderr.write(
        f"\r[{'#' * done}{'.' * (width - done)}] {100 * fraction:5.1f}%  {elapsed:6.1f} s"
    )
    sys.stderr.flush()


def simulate(
    scenario: Scenario,
    *,
    design: Any = None,
    progress: bool | None = None,
    loop: ClosedLoop | None = None,
    **swaps: Any,
) -> SimulationResult:
    """Build and simulate ``scenario``'s closed loop over its horizon.

    Parameters
    ----------
    scenario : Scenario
    design : ObserverDesign, optional
        Observer design; computed from the scenario if omitted.
    progress : bool, optional
        Draw a progress bar on stderr; by default only when stderr is a terminal.
    loop : ClosedLoop, optional
        An already-built loop to simulate (then ``design`` and ``swaps`` are unused).
    **swaps
        Block replacements, as for :func:`~ofrl_drake.build_closed_loop`.

    Returns
    -------
    SimulationResult
    """
    if loop is None:
        loop = build_closed_loop(scenario, design=design, **swaps)
    simulator = Simulator(loop.diagram)
    ApplySimulatorConfig(simulator_config(scenario), simulator)
    simulator.Initialize()
    duration = scenario.simulation.duration
    show = sys.stderr.isatty() if progress is None else progress

    start = time.perf_counter()
    if show:
        chunks = 100
        for k in range(1, chunks + 1):
            simulator.AdvanceTo(duration * k / chunks)
            _progress(k / chunks, start)
        sys.stderr.write("\n")
    else:
        simulator.AdvanceTo(duration)
    wall = time.perf_counter() - start

    context = simulator.get_context()
    logs = {}
    t = None
    for key, logger in loop.loggers.items():
        log = logger.FindLog(context)
        t = log.sample_times()
        logs[key] = log.data().T.copy()
    L = logs["W"].shape[1]
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
        "smallest_step": _finite(integ.get_smallest_adapted_step_size_taken()),
        "largest_step": _finite(integ.get_largest_step_size_taken()),
    }
    design_dict = None
    box = None
    if loop.design is not None:
        design_dict = loop.design.to_dict()
        box = (np.asarray(loop.design.box.lower), np.asarray(loop.design.box.upper))
    result = SimulationResult(
        t=np.asarray(t),
        x=logs["x"],
        xhat=logs["xhat"],
        W=logs["W"],
        Gamma=logs["Gamma"].reshape(-1, L, L),
        u=logs["u"],
        learning_condition=logs["learning_condition"][:, 0],
        cost=logs["cost"][:, 0],
        wall_time=wall,
        integrator=stats,
        design=design_dict,
        scenario_name=scenario.name,
        extra={k: v for k, v in logs.items() if k not in LOGGED},
    )
    if box is not None:
        result.validity = validity_report(
            result.t, result.x, result.xhat, result.u, box, scenario.input_bound
        )
    return result


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None
