"""Scenario variants and the fused baseline that matches each one.

Every benchmark case is a :class:`~ofrl_drake.scenario.Scenario` (the paper's,
or a copy with more points, a larger basis, another integrator...) run three
ways: through the Drake diagram with :func:`ofrl_drake.simulate`, and through
two hand-written right-hand sides under ``solve_ivp``: the stronger baseline
:class:`~benchmarks.precomputed_numpy.PrecomputedClosedLoop` (everything that
depends only on the points or the gains precomputed) and
:class:`~benchmarks.fused_numpy.FusedClosedLoop`. Accuracy is judged against a
tight DOP853 solution of the fused equations.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from benchmarks.fused_numpy import SYSTEMS, FusedClosedLoop
from benchmarks.precomputed_numpy import PrecomputedClosedLoop
from ofrl_drake.diagram import extrapolation_points
from ofrl_drake.scenario import Scenario

__all__ = [
    "REFERENCE_TOLERANCE",
    "Reference",
    "fused_loop",
    "gains_resolved",
    "initial_state",
    "log_times",
    "precomputed_loop",
    "reference",
    "with_basis",
    "with_duration",
    "with_grid",
    "with_integrator",
    "with_point_count",
]

#: rtol = atol of the DOP853 reference solution.
REFERENCE_TOLERANCE = 1e-12


def with_duration(scenario: Scenario, duration: float | None) -> Scenario:
    """``scenario`` with another horizon (unchanged if ``duration`` is None)."""
    if duration is None:
        return scenario
    return dataclasses.replace(
        scenario, simulation=dataclasses.replace(scenario.simulation, duration=duration)
    )


def with_integrator(
    scenario: Scenario, integrator: str, accuracy: float, log_period: float | None = None
) -> Scenario:
    """``scenario`` simulated with another Drake integrator, accuracy and log period."""
    simulation = dataclasses.replace(scenario.simulation, integrator=integrator, accuracy=accuracy)
    if log_period is not None:
        simulation = dataclasses.replace(simulation, log_period=log_period)
    return dataclasses.replace(scenario, simulation=simulation)


def with_grid(scenario: Scenario, counts: list[int]) -> Scenario:
    """``scenario`` with a tensor grid of ``prod(counts)`` extrapolation points."""
    points = dataclasses.replace(scenario.points, kind="grid", counts=list(counts))
    return dataclasses.replace(scenario, points=points)


def with_basis(scenario: Scenario, degrees: list[int]) -> Scenario:
    """``scenario`` with basis degrees ``degrees``.

    The new monomials start at zero weight; a given ``Gamma0`` becomes its
    mean diagonal times the identity (with ``critic.gains: auto`` the gains
    are derived for the new basis as for any scenario).
    """
    from ofrl_drake.basis import PolynomialBasis

    old = PolynomialBasis(len(scenario.x0), scenario.critic.basis_degrees)
    new = PolynomialBasis(len(scenario.x0), degrees)
    weights = dict(zip(map(tuple, old.exponents.tolist()), scenario.critic.W0, strict=True))
    W0 = [float(weights.get(tuple(e), 0.0)) for e in new.exponents.tolist()]
    critic = dataclasses.replace(scenario.critic, basis_degrees=list(degrees), W0=W0)
    if scenario.critic.Gamma0 is not None:
        gamma = float(np.mean(np.diag(np.asarray(scenario.critic.Gamma0, dtype=float))))
        critic = dataclasses.replace(critic, Gamma0=(gamma * np.eye(new.size)).tolist())
    return dataclasses.replace(scenario, critic=critic)


def with_point_count(scenario: Scenario, number: int) -> Scenario:
    """``scenario`` with ``number`` uniformly drawn points (its own box and seed)."""
    points = dataclasses.replace(scenario.points, kind="uniform", number=int(number))
    return dataclasses.replace(scenario, points=points)


def gains_resolved(scenario: Scenario) -> Scenario:
    """``scenario`` with its learning gains written out (``critic.gains: manual``).

    ``critic.gains: auto`` derives the gains from the horizon (the policy
    period is a tenth of it, the forgetting factor five over that): resolved
    at the scenario's own horizon first, a shortened benchmark run simulates
    the start of the same loop instead of a different one.
    """
    from ofrl_drake.diagram import build_closed_loop

    return build_closed_loop(scenario).resolved_scenario()


def _loop_arguments(scenario: Scenario, design: Any) -> dict[str, Any]:
    """The keyword arguments both baselines' loops take: scenario data and gains."""
    b = design.bounds
    return {
        "system": scenario.system,
        "points": extrapolation_points(scenario),
        "degrees": list(scenario.critic.basis_degrees),
        "Q": np.asarray(scenario.cost.Q, dtype=float),
        "r": np.asarray(scenario.cost.R, dtype=float),
        "input_bound": scenario.input_bound,
        "kc": scenario.critic.kc,
        "nu": scenario.critic.nu,
        "beta": scenario.critic.beta,
        "L": np.asarray(design.L),
        "H": np.asarray(design.H),
        "K": np.asarray(design.K),
        "Mf1": np.asarray(b.Mf1),
        "Mg1": np.asarray(b.Mg1),
        "Mg2": np.asarray(b.Mg2),
    }


def fused_loop(scenario: Scenario, design: Any) -> FusedClosedLoop:
    """The fused numpy closed loop of ``scenario`` with the gains of ``design``."""
    return FusedClosedLoop(**_loop_arguments(scenario, design))


def precomputed_loop(scenario: Scenario, design: Any) -> PrecomputedClosedLoop:
    """The stronger baseline's closed loop of ``scenario`` with the gains of ``design``.

    ``f`` and ``g`` at the points come from the fused baseline's batch
    functions (:data:`~benchmarks.fused_numpy.SYSTEMS`), not from
    :mod:`ofrl_drake`.
    """
    arguments = _loop_arguments(scenario, design)
    f, g, _ = SYSTEMS[scenario.system]
    X = arguments["points"]
    return PrecomputedClosedLoop(**arguments, f_points=f(X), g_points=g(X))


def initial_state(scenario: Scenario, loop: FusedClosedLoop | PrecomputedClosedLoop) -> np.ndarray:
    """``z(0)`` of either baseline's loop for ``scenario``."""
    c = scenario.critic
    return loop.initial_state(
        np.asarray(scenario.x0, float),
        np.asarray(scenario.xhat0, float),
        np.asarray(c.W0, float),
        np.asarray(c.Gamma0, float),
    )


@dataclass(frozen=True)
class Reference:
    """W of a tight DOP853 solution, with its dense output.

    Attributes
    ----------
    times : ndarray, shape (K,)
        The scenario's log times (``0, log_period, ...`` up to the horizon):
        where the baseline is sampled.
    W : ndarray, shape (K, L)
        W at ``times``.
    solution : callable
        ``solution(t)`` is the reference state at times ``t`` (DOP853's dense
        output, 7th order, so its interpolation error is far below the
        tolerances compared).
    loop : FusedClosedLoop
        To pick W out of a state.
    """

    times: np.ndarray
    W: np.ndarray
    solution: Any
    loop: FusedClosedLoop

    def errors(self, times: np.ndarray, W: np.ndarray) -> tuple[float, float]:
        """``(|W(T) - W_ref(T)|_inf, max_k |W(t_k) - W_ref(t_k)|_inf)`` of a run.

        ``times``, ``W`` are the run's samples; the maximum is over every one
        of them, the reference evaluated at exactly those times.
        """
        times = np.asarray(times, dtype=float)
        reference = self.solution(times)
        W_ref = reference[2 * self.loop.n : 2 * self.loop.n + self.loop.size].T
        diff = np.abs(np.asarray(W) - W_ref)
        return float(diff[-1].max()), float(diff.max())


def log_times(scenario: Scenario) -> np.ndarray:
    """``0, log_period, 2 log_period, ...`` up to the horizon: the logged times."""
    duration, period = scenario.simulation.duration, scenario.simulation.log_period
    count = int(np.floor(duration / period + 1e-9))
    times = np.minimum(period * np.arange(count + 1), duration)  # no round-off past the end
    return times if times[-1] >= duration - 1e-12 else np.append(times, duration)


def reference(scenario: Scenario, design: Any) -> Reference:
    """DOP853 at rtol = atol = 1e-12 with dense output; W at the scenario's log times."""
    loop = fused_loop(scenario, design)
    duration = scenario.simulation.duration
    sol = loop.solve(
        initial_state(scenario, loop),
        duration,
        method="DOP853",
        rtol=REFERENCE_TOLERANCE,
        atol=REFERENCE_TOLERANCE,
        dense_output=True,
    )
    if not sol.success:  # pragma: no cover - DOP853 does not fail on this problem
        raise RuntimeError(f"reference solve failed: {sol.message}")
    times = log_times(scenario)
    W = sol.sol(times)[2 * loop.n : 2 * loop.n + loop.size].T
    return Reference(times=times, W=W, solution=sol.sol, loop=loop)
