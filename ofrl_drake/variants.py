"""The block factories of the slot registry: every block of the closed loop is built here.

:mod:`ofrl_drake.slots` says which factory builds which block for which
choice; each factory takes the :class:`~ofrl_drake.slots.ClosedLoopParts` and
returns one Drake ``System``, and each block class is built by one function.

What each choice builds:

``observer``
    ``three_gain``: the certified three-gain observer (default; re-designed
    along the run when ``observer.schedule_period > 0``), its design from
    :func:`design_for`.
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
    ``frozen_critic``: the learned controller with ``W`` fixed at ``W(0)``
    (it replaces the critic block).
    ``constant``: the input held at ``variant.constant_input``, ignoring the
    estimate; the critic and Gamma still learn and log.
``points`` (the ``bellman`` block)
    ``grid`` (``points.counts``) and ``uniform`` (``points.number`` and
    ``points.seed``) in the box ``points.lower .. points.upper``, whatever
    ``points.kind`` says; ``around_estimate``: the scenario's points, as offsets
    from the centre of their box, moving with ``xhat``.
``gamma``
    ``least_squares``: Gamma with forgetting (default); ``constant``: Gamma(0).

The fixed blocks, which no slot chooses: the plant (the model, or the
scenario's ``truth``), the critic learning at ``kc``, the policy (the gate of
``policy_iteration``, a pass-through under ``paper``) and the running cost.
The plant, observer, controller and running cost are C++ symbolic blocks when
``parts.symbolic`` (:func:`ofrl_drake.diagram.symbolic_blocks`).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike
from pydrake.systems.framework import System

from ofrl_drake.baselines import (
    linearize_at_origin,
    luenberger_gain,
    luenberger_poles,
    point_offsets,
)
from ofrl_drake.bellman import PointFeatures, point_features
from ofrl_drake.checks import point_text
from ofrl_drake.drake_typing import DrakeArray
from ofrl_drake.errors import ModelError, ScenarioError, lmi_time_left
from ofrl_drake.observer import ObserverGains
from ofrl_drake.plants import resolve_system
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.systems import (
    BellmanExtrapolator,
    ControlAffinePlant,
    CriticWeights,
    GammaGain,
    PolicyGate,
    PolicyPassThrough,
    RunningCost,
    SaturatedController,
    ScheduledThreeGainObserver,
    SymbolicController,
    SymbolicObserver,
    SymbolicPlant,
    SymbolicRunningCost,
    ThreeGainObserver,
)
from ofrl_drake.systems.baselines import (
    ConstantController,
    FullStateObserver,
    LinearizedLuenbergerObserver,
    MovingBellmanExtrapolator,
    SaturatedLqrController,
)

if TYPE_CHECKING:  # annotations only: the registry imports this module
    from ofrl_drake.basis import PolynomialBasis
    from ofrl_drake.design import ObserverDesign
    from ofrl_drake.jacobian_bounds import JacobianBounds
    from ofrl_drake.model import ControlAffineSystem
    from ofrl_drake.scenario import Scenario
    from ofrl_drake.slots import ClosedLoopParts

__all__ = [
    "around_estimate",
    "constant_controller",
    "constant_gamma",
    "controller_block",
    "design_for",
    "drake_luenberger",
    "frozen_critic",
    "grid",
    "kalman",
    "learned_controller",
    "learning_critic",
    "least_squares_gamma",
    "linear_luenberger",
    "linear_observer_design",
    "lqr",
    "plant",
    "plant_block",
    "policy",
    "running_cost",
    "running_cost_block",
    "three_gain",
    "true_state",
    "uniform",
]


# ------------------------------------------------------------------- plant
def plant_block(system: ControlAffineSystem, x0: ArrayLike, symbolic: bool) -> System:
    """``system`` simulated from its ``f`` and ``g``: C++ symbolic if ``symbolic``, else Python.

    ``x0`` is the Python block's default state; the symbolic block's is zero
    (:class:`~ofrl_drake.systems.SymbolicPlant`). A run writes its own x(0)
    either way (``set_state``).
    """
    if symbolic:
        return SymbolicPlant(system)
    return ControlAffinePlant(system, initial_state=x0)


def symbolic_blocks(scenario: Scenario, system: ControlAffineSystem, role: str = "") -> bool:
    """Whether ``system``'s blocks are C++ symbolic blocks (else Python).

    As ``scenario.simulation.blocks`` says for the plant, observer, controller
    and running cost; ``"auto"`` means whenever ``system.symbolic()``
    succeeds. ``role`` names the system in the refusal (``"the truth's "``).

    Raises
    ------
    ScenarioError
        If ``blocks`` is ``"symbolic"`` and ``f`` or ``g`` cannot be traced.
    """
    choice = scenario.simulation.blocks
    if choice == "python":
        return False
    try:
        system.symbolic()
    except ModelError as err:
        if choice == "symbolic":
            raise ScenarioError(
                f"simulation.blocks: symbolic needs {role}f and g that Drake can trace: {err} "
                "Or set simulation.blocks to python."
            ) from err
        return False
    return True


def plant(parts: ClosedLoopParts) -> System:
    """The plant simulated: the model, or the scenario's truth.

    A multibody truth runs as its own ``MultibodyPlant`` in C++
    (:class:`~ofrl_drake.systems.DrakePlant`, body masses scaled through the
    Context); another truth as the model does, from its ``f`` and ``g``, as
    ``simulation.blocks`` says (:func:`symbolic_blocks`).
    """
    s = parts.scenario
    truth = parts.truth
    if truth is None:
        return plant_block(parts.system, s.x0, parts.symbolic)
    from ofrl_drake.plants import multibody_body_names
    from ofrl_drake.systems.drake_plant import DrakePlant

    if multibody_body_names(truth) is not None:
        scale = None if s.truth is None else s.truth.body_mass_scale
        return DrakePlant(truth, initial_state=s.x0, body_mass_scale=scale)
    return plant_block(truth, s.x0, symbolic_blocks(s, truth, "the truth's "))


# ---------------------------------------------------------------- observer
def scenario_bounds(scenario: Scenario, system: ControlAffineSystem) -> JacobianBounds:
    """The Jacobian bounds of ``system`` over the observer box, by the scenario's method.

    The symbolic Jacobians and the refinement stop after
    ``simulation.max_wall_time`` (``--max-wall``) seconds, the refinement with
    the sound bounds reached so far, and at the tolerances
    ``observer.jacobian_tol`` and ``observer.jacobian_rtol`` when given.
    """
    from ofrl_drake.jacobian_bounds import DEFAULT_TOL, jacobian_bounds

    o = scenario.observer
    box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
    return jacobian_bounds(
        system,
        box,
        o.jacobian_method,
        max_wall_time=scenario.simulation.max_wall_time,
        tol=DEFAULT_TOL if o.jacobian_tol is None else float(o.jacobian_tol),
        rtol=None if o.jacobian_rtol is None else float(o.jacobian_rtol),
    )


def _time_left(scenario: Scenario, start: float) -> float | None:
    """Seconds of the design's ``max_wall_time`` left since ``start`` (None: no limit).

    Raises
    ------
    WallTimeExceeded
        If the Jacobian bounds used the whole budget, leaving nothing for the LMI.
    """
    return lmi_time_left(
        scenario.simulation.max_wall_time,
        start,
        "max_wall_time (--max-wall)",
        "allow more wall time, shrink the observer box, or loosen observer.jacobian_tol",
    )


def design_for(scenario: Scenario, system: ControlAffineSystem | None = None) -> ObserverDesign:
    """The observer design of ``scenario``: certified by LMI unless gains are pinned.

    Pinned gains (``observer.L/H/K``) are wrapped with their Jacobian bounds and
    certificate, which reports honestly whether they satisfy the LMI.
    ``simulation.max_wall_time`` (``--max-wall``) bounds the whole design: the
    Jacobian bounds (:func:`scenario_bounds`) and then the LMI solve, which gets
    the time they leave as its solver's time limit.

    Raises
    ------
    WallTimeExceeded
        If the design does not finish within ``simulation.max_wall_time``.
    ObserverDesignInfeasible
        If no certified gains exist (or the pinned ones are not certified).
    """
    from ofrl_drake.design import ObserverDesign

    start = time.monotonic()
    system = system or resolve_system(scenario)
    o = scenario.observer
    box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
    bounds = scenario_bounds(scenario, system)
    time_limit = _time_left(scenario, start)
    if o.L is not None:
        return ObserverDesign.from_gains(
            system,
            box,
            scenario.input_bound,
            o.alpha,
            L=np.asarray(o.L, float),
            H=np.asarray(o.H, float),
            K=np.asarray(o.K, float),
            bounds=bounds,
            formulation=o.formulation,
            time_limit=time_limit,
        )
    return _solved_design(scenario, system, bounds, time_limit)


def _solved_design(
    scenario: Scenario,
    system: ControlAffineSystem,
    bounds: JacobianBounds,
    time_limit: float | None,
    **options: Any,
) -> ObserverDesign:
    """The scenario's LMI design (``options`` for :func:`~ofrl_drake.design.design_observer`).

    When it is infeasible because the output cannot see a mode that decays slower
    than alpha, the error says so in place of the usual hint (:func:`_undetectable_note`).
    """
    from ofrl_drake.design import FORMULATIONS, ObserverDesignInfeasible, design_observer

    o = scenario.observer
    box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
    try:
        return design_observer(
            system,
            box,
            scenario.input_bound,
            o.alpha,
            bounds=bounds,
            solver=o.solver,
            formulation=o.formulation,
            time_limit=time_limit,
            **options,
        )
    except ObserverDesignInfeasible as err:
        if not FORMULATIONS[o.formulation].proves_decay:
            raise  # (lmi2) reads no Jacobian at a point: a mode there does not bound it
        note = _undetectable_note(system, box, scenario.input_bound, float(o.alpha))
        if note is None:
            raise
        # The usual hint (a smaller alpha, box or input bound) cannot help here.
        head = str(err).split("; try ", 1)[0]
        raise ObserverDesignInfeasible(
            f"{head}. {note}",
            alpha=err.alpha,
            box=err.box,
            input_bound=err.input_bound,
            status=err.status,
            solver=err.solver,
            formulation=err.formulation,
        ) from None


def _undetectable_note(
    system: ControlAffineSystem,
    box: tuple[np.ndarray, np.ndarray],
    input_bound: float,
    alpha: float,
) -> str | None:
    """Why no gains can exist, when a mode the output does not see decays slower than alpha.

    At any ``(x, u)`` an eigenvalue of ``A = d(f + g u)/dx`` that ``y = C x`` does not
    see (:func:`~ofrl_drake.unobservable.unobservable_modes`) is an eigenvalue of the
    error's linearization whatever the gains, so no design certifies a rate above
    ``-Re(lambda)``. Checked at the box's center, with ``u`` at 0 and at each input
    bound; None when every such mode there decays faster than ``alpha``.
    """
    from ofrl_drake.unobservable import linearization, unobservable_modes

    center = 0.5 * (np.asarray(box[0], float) + np.asarray(box[1], float))
    inputs = [np.zeros(system.m)]
    for k in range(system.m):
        for sign in (1.0, -1.0):
            inputs.append(sign * input_bound * np.eye(system.m)[k])
    for u in inputs:
        try:
            A = linearization(system, center, u)
        except (ModelError, ValueError, ArithmeticError):
            return None
        if not np.all(np.isfinite(A)):
            return None
        slow = [
            lam for lam in unobservable_modes(A, system.output_matrix, 1e-9) if lam.real > -alpha
        ]
        if slow:
            lam = max(slow, key=lambda mode: mode.real)
            shown = f"{lam.real:.4g}" if abs(lam.imag) < 1e-12 else f"{lam:.4g}"
            return (
                f"No gains can reach it: at x = {point_text(center)}, u = {point_text(u)} the "
                f"mode lambda = {shown} of the linearization d(f + g u)/dx is not seen in "
                "y = C x (PBH test), so the error decays there no faster than "
                f"exp({lam.real:.4g} t) whatever L, H, K, and no design certifies alpha > "
                f"{-lam.real:.4g}; measure a state that sees this mode (plant C)."
            )
    return None


def linear_observer_design(scenario: Scenario, system: ControlAffineSystem) -> ObserverDesign:
    """The scenario's observer design with ``H = K = 0`` and ``L`` from the same LMI.

    Same box, input bound, decay rate, Jacobian method, solver, formulation and
    wall-time budget as :func:`design_for`, with ``injection_gains=False``. The
    ``polytopic`` formulation has ``H = K = 0`` already, so there it returns
    the three-gain design itself; under ``paper`` it is a linear Luenberger
    gain certified by (lmi2).

    Returns
    -------
    ObserverDesign

    Raises
    ------
    ObserverDesignInfeasible
        If the LMI has no solution with ``H = K = 0``.
    WallTimeExceeded
        If the design does not finish within ``simulation.max_wall_time``.
    """
    start = time.monotonic()
    bounds = scenario_bounds(scenario, system)
    return _solved_design(
        scenario, system, bounds, _time_left(scenario, start), injection_gains=False
    )


def _observer_design(parts: ClosedLoopParts) -> ObserverDesign:
    """``parts.design``, which the three-gain observers run.

    Raises
    ------
    ScenarioError
        If there is none: neither given to ``build_closed_loop`` nor computed
        for the chosen observer (a :class:`~ofrl_drake.slots.Choice` without
        ``design``).
    """
    if parts.design is None:
        raise ScenarioError(
            f"variant.observer: {parts.scenario.variant.observer!r} builds a three-gain "
            "observer, which runs an observer design, and none was given or computed; pass "
            "design= to build_closed_loop, or register the choice as a Choice with "
            "design=ofrl_drake.variants.design_for."
        )
    return parts.design


def _gain_observer(parts: ClosedLoopParts, symbolic: bool) -> System:
    """The three-gain observer with the gains of ``parts.design``."""
    design = _observer_design(parts)
    gains = ObserverGains.from_design(parts.system, design)
    if symbolic:  # its default estimate is zero; a run writes xhat(0)
        return SymbolicObserver(parts.system, gains, design=design)
    return ThreeGainObserver(parts.system, gains, initial_state=parts.scenario.xhat0, design=design)


def three_gain(parts: ClosedLoopParts) -> System:
    """The certified three-gain observer of ``parts.design`` (scheduled if the scenario says)."""
    s = parts.scenario
    o = s.observer
    if o.schedule_period > 0:
        width = np.asarray(o.box.upper, float) - np.asarray(o.box.lower, float)
        half = np.asarray(o.schedule_half_width or 0.5 * width, float)
        return ScheduledThreeGainObserver(
            parts.system,
            _observer_design(parts),
            period=o.schedule_period,
            half_width=half,
            input_bound=s.input_bound,
            alpha=o.alpha,
            design_options={
                "jacobian_method": o.jacobian_method,
                "solver": o.solver,
                "formulation": o.formulation,
                # No one re-solve may outlast the run's whole budget; one that
                # would keeps the gains in force and counts as failed.
                "time_limit": s.simulation.max_wall_time,
            },
            initial_state=s.xhat0,
        )
    return _gain_observer(parts, parts.symbolic)


def linear_luenberger(parts: ClosedLoopParts) -> System:
    """The three-gain observer with ``H = K = 0`` (:func:`linear_observer_design`), in Python."""
    return _gain_observer(parts, symbolic=False)


def drake_luenberger(parts: ClosedLoopParts) -> System:
    """Drake's Luenberger observer on the linearization, poles from ``observer.alpha``."""
    linearization = linearize_at_origin(parts.system)
    poles = luenberger_poles(parts.scenario.observer.alpha, parts.system.n)
    A: DrakeArray = linearization.A()
    C: DrakeArray = linearization.C()
    gain = luenberger_gain(A, C, poles)
    return LinearizedLuenbergerObserver(linearization, gain, alpha=parts.scenario.observer.alpha)


def kalman(parts: ClosedLoopParts) -> System:
    """Drake's steady-state Kalman filter on the linearization at the target.

    The measurement noise intensity is ``V = diag(noise_std^2) * period``
    from ``measurement``: noise drawn once per sample and held for ``period``
    has the spectral density of continuous white noise of that intensity below
    the sampling rate, so a faster sensor with the same ``noise_std`` is
    trusted more. Each ``noise_std_j`` is floored at ``1e-3 w_j`` with ``w_j``
    the width of output ``j`` over the observer box (``V`` must be positive
    definite; an exact sensor is trusted a thousand times its range), and a
    continuous sensor (``period`` 0, no noise) counts as ``period = 1 s``.
    The process noise is what the linear model misses on the observer box,
    ``W = mean_i r_i r_i^T`` with ``r_i = f(x_i) - A x_i`` at 200 states drawn
    in it (seed 0), plus ``B diag(d^2) B^T`` for ``actuation.disturbance``.
    """
    from pydrake.systems.estimators import SteadyStateKalmanFilter

    s = parts.scenario
    linearization = linearize_at_origin(parts.system)
    A: DrakeArray = linearization.A()
    B: DrakeArray = linearization.B()
    C: DrakeArray = linearization.C()
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
    period = 1.0
    if s.measurement is not None:
        if s.measurement.noise_std:
            noise = np.asarray(s.measurement.noise_std, dtype=float)
        if s.measurement.period > 0:
            period = float(s.measurement.period)
    V = np.diag(np.maximum(noise, 1e-3 * widths) ** 2 * period)
    gain: DrakeArray = SteadyStateKalmanFilter(A, C, W, V)
    return LinearizedLuenbergerObserver(linearization, gain)


def true_state(parts: ClosedLoopParts) -> System:
    """Full-state feedback: ``xhat = x``."""
    return FullStateObserver(parts.system.n)


# -------------------------------------------------------------- controller
def controller_block(
    system: ControlAffineSystem,
    basis: PolynomialBasis,
    r: np.ndarray,
    input_bound: float,
    symbolic: bool,
) -> System:
    """The saturated policy of the weights at its ``policy_weights`` input."""
    block = SymbolicController if symbolic else SaturatedController
    return block(system, basis, r, input_bound)


def learned_controller(parts: ClosedLoopParts) -> System:
    """The saturated policy of the policy weights."""
    return controller_block(
        parts.system, parts.basis, parts.r, parts.scenario.input_bound, parts.symbolic
    )


def lqr(parts: ClosedLoopParts) -> System:
    """Drake's LQR on the linearization at the origin, clipped at the input bound."""
    linearization = linearize_at_origin(parts.system)
    return SaturatedLqrController(
        linearization, parts.Q, np.diag(parts.r), parts.scenario.input_bound
    )


def constant_controller(parts: ClosedLoopParts) -> System:
    """The input held at ``variant.constant_input``."""
    return ConstantController(parts.scenario.variant.constant_input)


# ------------------------------------------------------------------ critic
def _critic(parts: ClosedLoopParts, kc: float) -> System:
    return CriticWeights(parts.scenario.critic.W0, kc)


def learning_critic(parts: ClosedLoopParts) -> System:
    """The critic ``W`` from ``critic.W0``, learning at the gain ``kc`` in force."""
    return _critic(parts, parts.critic.gains.kc)


def frozen_critic(parts: ClosedLoopParts) -> System:
    """The critic held at ``critic.W0`` (``kc = 0``)."""
    return _critic(parts, 0.0)


def policy(parts: ClosedLoopParts) -> System:
    """The policy gate of ``policy_iteration``; a pass-through under ``critic.law: paper``."""
    critic = parts.critic
    if critic.law == "paper":
        return PolicyPassThrough(parts.basis.size)
    if critic.linearization is None or critic.gains.policy_period is None:
        raise ScenarioError(
            f"critic.law: {critic.law} puts policies in force by a test on the linearization "
            f"at the target every policy period; the critic settings have linearization "
            f"{'None' if critic.linearization is None else 'given'} and policy_period "
            f"{critic.gains.policy_period}. Build them with ofrl_drake.diagram.critic_settings."
        )
    A, B = critic.linearization
    return PolicyGate(
        parts.scenario.critic.W0,
        critic.gains.policy_period,
        A,
        B,
        parts.Q,
        parts.r,
        parts.basis,
        parts.features.points,
    )


# ------------------------------------------------------------------ points
def _bellman(parts: ClosedLoopParts, features: PointFeatures) -> System:
    """The Bellman extrapolation at the points of ``features``."""
    gains = parts.critic.gains
    return BellmanExtrapolator(
        features, parts.r, parts.scenario.input_bound, gains.nu, parts.critic.metric
    )


def grid(parts: ClosedLoopParts) -> System:
    """The Bellman block at the grid ``points.counts`` in the points' box."""
    p = parts.scenario.points
    if p.kind == "grid":
        return _bellman(parts, parts.features)
    if len(p.counts) != parts.system.n:
        raise ScenarioError(
            f"variant.points: 'grid' needs points.counts with {parts.system.n} positive "
            f"integers; got {p.counts}."
        )
    points = grid_points(p.lower, p.upper, p.counts)
    return _bellman(parts, point_features(parts.system, parts.basis, points, parts.Q))


def uniform(parts: ClosedLoopParts) -> System:
    """The Bellman block at ``points.number`` uniform draws (``points.seed``) in the box."""
    p = parts.scenario.points
    if p.kind == "uniform":
        return _bellman(parts, parts.features)
    points = uniform_points(p.lower, p.upper, p.number, p.seed)
    return _bellman(parts, point_features(parts.system, parts.basis, points, parts.Q))


def around_estimate(parts: ClosedLoopParts) -> System:
    """The scenario's points as offsets from their box's centre, moving with ``xhat``."""
    s, p = parts.scenario, parts.scenario.points
    offsets = point_offsets(parts.features.points, np.asarray(p.lower), np.asarray(p.upper))
    return MovingBellmanExtrapolator(
        parts.system,
        parts.basis,
        offsets,
        parts.Q,
        parts.r,
        s.input_bound,
        parts.critic.gains.nu,
        parts.critic.metric,
    )


# ------------------------------------------------------------------- gamma
def _gamma(parts: ClosedLoopParts, *, learning: bool) -> System:
    gains = parts.critic.gains
    kc, beta, bound = (gains.kc, gains.beta, gains.gamma_bound) if learning else (0.0, 0.0, None)
    return GammaGain(np.asarray(gains.Gamma0, float), kc, beta, bound)


def least_squares_gamma(parts: ClosedLoopParts) -> System:
    """Gamma with forgetting at the gains in force."""
    return _gamma(parts, learning=True)


def constant_gamma(parts: ClosedLoopParts) -> System:
    """Gamma held at ``Gamma(0)``."""
    return _gamma(parts, learning=False)


# ------------------------------------------------------------ running cost
def running_cost_block(Q: np.ndarray, r: np.ndarray, input_bound: float, symbolic: bool) -> System:
    """The integral of ``x^T Q x`` plus the saturated input cost."""
    block = SymbolicRunningCost if symbolic else RunningCost
    return block(Q, r, input_bound)


def running_cost(parts: ClosedLoopParts) -> System:
    """The running cost of the scenario's ``Q``, ``R`` and input bound."""
    return running_cost_block(parts.Q, parts.r, parts.scenario.input_bound, parts.symbolic)
