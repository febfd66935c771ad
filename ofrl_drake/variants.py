"""Slot choices for ablations: which block fills each part of the closed loop.

A :class:`~ofrl_drake.scenario.VariantConfig` names one choice per slot::

    observer:   three_gain | linear_luenberger | drake_luenberger | kalman | true_state
    controller: learned | lqr | frozen_critic | constant
    points:     grid | uniform | around_estimate
    gamma:      least_squares | constant

Each choice is a factory ``f(parts) -> {block_slot: System}`` registered in
:data:`VARIANT_FACTORIES`; :func:`~ofrl_drake.build_closed_loop` applies them
before explicit swaps. The baseline (``three_gain``, ``learned``, the
scenario's own ``points.kind``, ``least_squares``) builds the default blocks.

What each choice builds:

``observer``
    ``three_gain``: the certified three-gain observer (default).
    ``linear_luenberger``: the same observer with ``H = K = 0``, its ``L``
    certified by the same LMI (:func:`linear_observer_design`);
    under the ``polytopic`` formulation, whose designs have ``H = K = 0``
    anyway, it coincides with ``three_gain``.
    ``drake_luenberger``: Drake's ``LuenbergerObserver`` on the linearization
    at the origin, poles of ``A - L C`` at
    :func:`~ofrl_drake.baselines.luenberger_poles` ``(alpha, n)``.
    ``kalman``: Drake's ``SteadyStateKalmanFilter`` gain on the same
    linearization: measurement covariance from ``measurement``, process
    covariance from what the linearization misses on the observer box.
    ``true_state``: full-state feedback, ``xhat = x``.
``controller``
    ``learned``: the saturated policy of the learned critic (default).
    ``lqr``: Drake's LQR on the linearization with the scenario's ``Q`` and
    ``R``, clipped at ``lambda_bar``; the critic and Gamma still learn and log.
    ``frozen_critic``: ``W`` fixed at ``W(0)``.
    ``constant``: the input held at ``variant.constant_input``, ignoring the
    estimate; the critic and Gamma still learn and log.
``points``
    ``grid`` (``points.counts``) and ``uniform`` (``points.number`` and
    ``points.seed``) in the box ``points.lower .. points.upper``, whatever
    ``points.kind`` says; ``around_estimate``: the scenario's points, as offsets
    from the centre of their box, moving with ``xhat``.
``gamma``
    ``least_squares``: Gamma with forgetting (default); ``constant``: Gamma(0).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from pydrake.systems.framework import System

from ofrl_drake.baselines import (
    linearize_at_origin,
    luenberger_gain,
    luenberger_poles,
    point_offsets,
)
from ofrl_drake.bellman import point_features
from ofrl_drake.errors import ScenarioError
from ofrl_drake.observer import ObserverGains
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.systems import BellmanExtrapolator, CriticWeights, GammaGain, ThreeGainObserver
from ofrl_drake.systems.baselines import (
    ConstantController,
    FullStateObserver,
    LinearizedLuenbergerObserver,
    MovingBellmanExtrapolator,
    SaturatedLqrController,
)

if TYPE_CHECKING:  # annotations only: the wiring imports run diagram -> variants
    from ofrl_drake.design import ObserverDesign
    from ofrl_drake.diagram import ClosedLoopParts
    from ofrl_drake.model import ControlAffineSystem
    from ofrl_drake.scenario import Scenario

__all__ = [
    "BASELINE",
    "NEEDS_PARAMETERS",
    "VARIANT_FACTORIES",
    "linear_observer_design",
    "register_variant",
    "variant_blocks",
]

Factory = Callable[["ClosedLoopParts"], dict[str, System]]

#: The paper's method: every slot at its default.
BASELINE = {
    "observer": "three_gain",
    "controller": "learned",
    "points": "grid",
    "gamma": "least_squares",
}


def _default(_parts: ClosedLoopParts) -> dict[str, System]:
    return {}


# ---------------------------------------------------------------- observer
def linear_observer_design(scenario: Scenario, system: ControlAffineSystem) -> ObserverDesign:
    """The scenario's observer design with ``H = K = 0`` and ``L`` from the same LMI.

    Same box, input bound, decay rate, Jacobian method, solver and
    formulation as :func:`ofrl_drake.diagram.design_for`, with
    ``injection_gains=False``. The ``polytopic`` formulation has ``H = K = 0``
    already, so there it returns the three-gain design itself; under ``paper``
    it is a linear Luenberger gain certified by (lmi2).

    Returns
    -------
    ObserverDesign

    Raises
    ------
    ObserverDesignInfeasible
        If the LMI has no solution with ``H = K = 0``.
    """
    from ofrl_drake.design import design_observer

    o = scenario.observer
    return design_observer(
        system,
        (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float)),
        scenario.input_bound,
        o.alpha,
        jacobian_method=o.jacobian_method,
        solver=o.solver,
        formulation=o.formulation,
        injection_gains=False,
    )


def _linear_luenberger(parts: ClosedLoopParts) -> dict[str, System]:
    design = parts.design or linear_observer_design(parts.scenario, parts.system)
    gains = ObserverGains.from_design(parts.system, design)
    return {
        "observer": ThreeGainObserver(
            parts.system, gains, initial_state=parts.scenario.xhat0, design=design
        )
    }


def _drake_luenberger(parts: ClosedLoopParts) -> dict[str, System]:
    linearization = linearize_at_origin(parts.system)
    poles = luenberger_poles(parts.scenario.observer.alpha, parts.system.n)
    gain = luenberger_gain(linearization.A(), linearization.C(), poles)
    return {
        "observer": LinearizedLuenbergerObserver(
            linearization,
            gain,
            initial_state=parts.scenario.xhat0,
            alpha=parts.scenario.observer.alpha,
        )
    }


def _kalman(parts: ClosedLoopParts) -> dict[str, System]:
    """Drake's steady-state Kalman filter on the linearization at the target.

    ``V = diag(noise_std^2)`` from ``measurement``, floored at ``(1e-3 w_j)^2``
    with ``w_j`` the width of output ``j`` over the observer box (``V`` must be
    positive definite; an exact sensor is trusted a thousand times its range).
    The process noise is what the linear model misses on the observer box,
    ``W = mean_i r_i r_i^T`` with ``r_i = f(x_i) - A x_i`` at 200 states drawn
    in it (seed 0), plus ``B diag(d^2) B^T`` for ``actuation.disturbance``.
    """
    from pydrake.systems.estimators import SteadyStateKalmanFilter

    s = parts.scenario
    linearization = linearize_at_origin(parts.system)
    A, B, C = linearization.A(), linearization.B(), linearization.C()
    lower = np.asarray(s.observer.box.lower, dtype=float)
    upper = np.asarray(s.observer.box.upper, dtype=float)
    X = uniform_points(lower, upper, 200, seed=0)
    residual = parts.system.f_batch(X) - A @ X
    W = residual @ residual.T / X.shape[1] + 1e-12 * np.eye(A.shape[0])
    if s.actuation is not None and s.actuation.disturbance:
        d = np.asarray(s.actuation.disturbance, dtype=float)
        W = W + B @ np.diag(d**2) @ B.T
    widths = np.abs(C) @ (upper - lower)
    noise = np.zeros(C.shape[0])
    if s.measurement is not None and s.measurement.noise_std:
        noise = np.asarray(s.measurement.noise_std, dtype=float)
    V = np.diag(np.maximum(noise, 1e-3 * widths) ** 2)
    gain = SteadyStateKalmanFilter(A, C, W, V)
    return {"observer": LinearizedLuenbergerObserver(linearization, gain, initial_state=s.xhat0)}


def _true_state(parts: ClosedLoopParts) -> dict[str, System]:
    return {"observer": FullStateObserver(parts.system.n)}


# -------------------------------------------------------------- controller
def _lqr(parts: ClosedLoopParts) -> dict[str, System]:
    linearization = linearize_at_origin(parts.system)
    return {
        "controller": SaturatedLqrController(
            linearization, parts.Q, np.diag(parts.r), parts.scenario.input_bound
        )
    }


def _constant(parts: ClosedLoopParts) -> dict[str, System]:
    return {"controller": ConstantController(parts.scenario.variant.constant_input)}


def _frozen_critic(parts: ClosedLoopParts) -> dict[str, System]:
    return {"critic": CriticWeights(parts.scenario.critic.W0, kc=0.0)}


# ------------------------------------------------------------------ points
def _bellman_at(parts: ClosedLoopParts, points: np.ndarray) -> BellmanExtrapolator:
    s = parts.scenario
    features = point_features(parts.system, parts.basis, points, parts.Q)
    return BellmanExtrapolator(
        features, parts.r, s.input_bound, parts.critic.gains.nu, parts.critic.metric
    )


def _grid(parts: ClosedLoopParts) -> dict[str, System]:
    p = parts.scenario.points
    if p.kind == "grid":
        return {}  # the default block already uses the grid
    if len(p.counts) != parts.system.n:
        raise ScenarioError(
            f"variant.points: 'grid' needs points.counts with {parts.system.n} positive "
            f"integers; got {p.counts}."
        )
    return {"bellman": _bellman_at(parts, grid_points(p.lower, p.upper, p.counts))}


def _uniform(parts: ClosedLoopParts) -> dict[str, System]:
    p = parts.scenario.points
    if p.kind == "uniform":
        return {}  # the default block already uses these points
    return {"bellman": _bellman_at(parts, uniform_points(p.lower, p.upper, p.number, p.seed))}


def _around_estimate(parts: ClosedLoopParts) -> dict[str, System]:
    s, p = parts.scenario, parts.scenario.points
    offsets = point_offsets(parts.features.points, np.asarray(p.lower), np.asarray(p.upper))
    return {
        "bellman": MovingBellmanExtrapolator(
            parts.system,
            parts.basis,
            offsets,
            parts.Q,
            parts.r,
            s.input_bound,
            parts.critic.gains.nu,
            parts.critic.metric,
        )
    }


# ------------------------------------------------------------------- gamma
def _constant_gamma(parts: ClosedLoopParts) -> dict[str, System]:
    return {"gamma": GammaGain(np.asarray(parts.critic.gains.Gamma0, float), kc=0.0, beta=0.0)}


VARIANT_FACTORIES: dict[str, dict[str, Factory]] = {
    "observer": {
        "three_gain": _default,
        "linear_luenberger": _linear_luenberger,
        "drake_luenberger": _drake_luenberger,
        "kalman": _kalman,
        "true_state": _true_state,
    },
    "controller": {
        "learned": _default,
        "lqr": _lqr,
        "frozen_critic": _frozen_critic,
        "constant": _constant,
    },
    "points": {"grid": _grid, "uniform": _uniform, "around_estimate": _around_estimate},
    "gamma": {"least_squares": _default, "constant": _constant_gamma},
}


#: (slot, choice) pairs that need values from the scenario (``variant.constant_input``);
#: :func:`~ofrl_drake.ablation.default_variants` leaves them out.
NEEDS_PARAMETERS = {("controller", "constant")}


def register_variant(slot: str, choice: str, factory: Factory) -> None:
    """Add a choice for ``slot``; ``factory(parts)`` returns the blocks it replaces."""
    if slot not in VARIANT_FACTORIES:
        raise ScenarioError(f"variant.{slot}: unknown slot; slots are {sorted(VARIANT_FACTORIES)}.")
    VARIANT_FACTORIES[slot][choice] = factory


def variant_blocks(choices: dict[str, str], parts: ClosedLoopParts) -> dict[str, System]:
    """Blocks replaced by the chosen variants, keyed by block slot."""
    blocks: dict[str, System] = {}
    for slot, choice in choices.items():
        try:
            factory = VARIANT_FACTORIES[slot][choice]
        except KeyError:
            options = sorted(VARIANT_FACTORIES.get(slot, {}))
            raise ScenarioError(
                f"variant.{slot}: unknown choice {choice!r}; choose one of {options}."
            ) from None
        blocks.update(factory(parts))
    return blocks
