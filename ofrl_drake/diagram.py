"""Wire the closed loop as a Drake ``Diagram``.

Blocks are connected **by port name**: every input port named in
:data:`SIGNALS` is fed by the output port of the same name on the block that
owns that signal. A replacement block therefore only has to use the same port
names, e.g. a full-state "observer" may declare an input ``state`` and output
``estimated_state``. Every block's inputs must all be fed, otherwise
:class:`~ofrl_drake.errors.SwapError` names the port.

.. code-block:: text

    plant --y-------------------> observer --estimated_state--> controller --u--+
      ^                              ^                              ^            |
      +------------------ u ---------+-------------------------------------------+
    critic --weights--> bellman --critic_sum--> critic;  bellman --gain_sum--> gamma
    gamma --gamma--> critic;  plant --state--, controller --u--> running_cost
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, System
from pydrake.systems.primitives import LogVectorOutput, VectorLogSink

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import Extrapolator, PointFeatures, point_features
from ofrl_drake.errors import ModelError, ScenarioError, SwapError
from ofrl_drake.learning import (
    DEFAULT_GAMMA_BOUND,
    POLICY_PERIOD_FRACTION,
    LearningGains,
    auto_gains,
    basis_scales,
    rho_metric,
)
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.observer import ObserverGains
from ofrl_drake.plants import resolve_system, resolve_truth
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.scenario import (
    Scenario,
    critic_gains_choice,
    validate_scenario,
    variant_choices,
)
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
from ofrl_drake.systems.world import MeasuredPlant, SampledController

__all__ = [
    "LOGGED",
    "OPTIONAL_LOGGED",
    "SIGNALS",
    "SLOTS",
    "ClosedLoop",
    "ClosedLoopParts",
    "CriticSettings",
    "build_closed_loop",
    "critic_settings",
    "design_for",
    "drake_plant",
    "extrapolation_points",
    "symbolic_blocks",
]

#: The block slots of the closed loop, in build order.
SLOTS = (
    "plant",
    "observer",
    "controller",
    "critic",
    "policy",
    "gamma",
    "bellman",
    "running_cost",
)

#: Signal name -> the slot whose output port of that name provides it.
SIGNALS = {
    "y": "plant",
    "state": "plant",
    "estimated_state": "observer",
    "u": "controller",
    "weights": "critic",
    "policy_weights": "policy",
    "gamma": "gamma",
    "critic_sum": "bellman",
    "gain_sum": "bellman",
    "learning_condition": "bellman",
    "cost": "running_cost",
}

#: Signals logged when the block providing them has them (key -> (slot, port)).
OPTIONAL_LOGGED = {
    "observer_gains": ("observer", "observer_gains"),
    "certified_box": ("observer", "certified_box"),
    "lyapunov_matrix": ("observer", "lyapunov_matrix"),
    "certificate": ("observer", "certificate"),
    "solve_failed": ("observer", "solve_failed"),
    "solve_counts": ("observer", "solve_counts"),
    "verification": ("observer", "verification"),
    "policy_updates": ("policy", "policy_updates"),
}

#: Log key -> signal name. Every variant logs these.
LOGGED = {
    "x": "state",
    "xhat": "estimated_state",
    "W": "weights",
    "W_policy": "policy_weights",
    "Gamma": "gamma",
    "u": "u",
    "learning_condition": "learning_condition",
    "cost": "cost",
}


@dataclass(frozen=True)
class CriticSettings:
    """The critic's learning law and gains in force (:func:`critic_settings`).

    Attributes
    ----------
    law : str
        ``policy_iteration`` or ``paper`` (:mod:`ofrl_drake.learning`).
    gains : LearningGains
        As given (``critic.gains: manual``) or derived (``auto``).
    metric : ndarray or None
        The diagonal of the metric of ``rho`` (None: the paper's identity).
    linearization : tuple of ndarray or None
        ``(A, B)`` at the target, for the policy acceptance test and the
        learning-health logs; None if it cannot be computed.
    """

    law: str
    gains: LearningGains
    metric: np.ndarray | None
    linearization: tuple[np.ndarray, np.ndarray] | None


@dataclass(frozen=True)
class ClosedLoopParts:
    """What a block factory may need to build a replacement block."""

    scenario: Scenario
    system: ControlAffineSystem
    basis: PolynomialBasis
    features: PointFeatures
    design: Any
    Q: np.ndarray
    r: np.ndarray
    critic: CriticSettings | None = None
    truth: ControlAffineSystem | None = None


@dataclass
class ClosedLoop:
    """A built closed loop: the diagram and handles to its named blocks."""

    diagram: Diagram
    parts: ClosedLoopParts
    blocks: dict[str, System]
    loggers: dict[str, VectorLogSink] = field(default_factory=dict)

    def __getattr__(self, name: str) -> System:
        blocks = self.__dict__.get("blocks", {})
        if name in blocks:
            return blocks[name]
        raise AttributeError(name)

    @property
    def design(self) -> Any:
        """The ``ObserverDesign`` used by the observer (None if not designed)."""
        return self.parts.design

    def resolved_scenario(self) -> Scenario:
        """The scenario with the critic's gains in force written out (``critic.gains: manual``).

        What ``scenario.yaml`` holds: running it gives the same loop whether
        the gains were given or derived.
        """
        return resolved_scenario(self.parts.scenario, self.parts.critic)

    def logs(self, root_context: Context) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The sample times ``(T,)`` and every log ``(T, size)`` in ``root_context``.

        One key per logger, plus the keys of :data:`LOGGED` that a block
        computes from the other logs after the run (see :func:`_after_run`).
        """
        logs = {}
        t = np.empty(0)
        for key, logger in self.loggers.items():
            log = logger.FindLog(root_context)
            t = np.asarray(log.sample_times())
            logs[key] = log.data().T.copy()
        if "learning_condition" not in logs:
            condition = self.blocks["bellman"].learning_condition_of(logs["W_policy"])
            logs["learning_condition"] = condition[:, None]
        return t, logs


Swap = System | Callable[[ClosedLoopParts], System]


def extrapolation_points(scenario: Scenario) -> np.ndarray:
    """The scenario's Bellman-extrapolation points, shape ``(n, N)``."""
    p = scenario.points
    if p.kind == "grid":
        return grid_points(p.lower, p.upper, p.counts)
    return uniform_points(p.lower, p.upper, p.number, p.seed)


def design_for(scenario: Scenario, system: ControlAffineSystem | None = None) -> Any:
    """The observer design of ``scenario``: certified by LMI unless gains are pinned.

    Pinned gains (``observer.L/H/K``) are wrapped with their Jacobian bounds and
    certificate, which reports honestly whether they satisfy the LMI. The
    Jacobian bounds' refinement stops after ``simulation.max_wall_time``
    (``--max-wall``) seconds, with the sound bounds reached so far.
    """
    from ofrl_drake.design import ObserverDesign, design_observer
    from ofrl_drake.jacobian_bounds import jacobian_bounds

    system = system or resolve_system(scenario)
    o = scenario.observer
    box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
    bounds = jacobian_bounds(
        system, box, o.jacobian_method, max_wall_time=scenario.simulation.max_wall_time
    )
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
        )
    return design_observer(
        system,
        box,
        scenario.input_bound,
        o.alpha,
        bounds=bounds,
        solver=o.solver,
        formulation=o.formulation,
    )


def _linearization(system: ControlAffineSystem) -> tuple[np.ndarray, np.ndarray] | None:
    """``(A, B)`` of the plant at the origin: Drake's ``Linearize`` when ``f`` and ``g``
    trace symbolically, else central differences of ``f`` and ``g(0)``; None if
    the origin is not an equilibrium."""
    from ofrl_drake.baselines import linearize_at_origin

    try:
        system.symbolic()
    except ModelError:
        f0 = np.asarray(system.f(np.zeros(system.n)), dtype=float)
        if np.max(np.abs(f0)) > 1e-9:
            return None
        h = 1e-6
        eye = np.eye(system.n)
        A = np.column_stack(
            [
                (np.asarray(system.f(h * e), float) - np.asarray(system.f(-h * e), float)) / (2 * h)
                for e in eye
            ]
        )
        return A, np.asarray(system.g(np.zeros(system.n)), dtype=float)
    try:
        linearization = linearize_at_origin(system)
    except ScenarioError:
        return None
    return np.asarray(linearization.A()), np.asarray(linearization.B())


def critic_settings(
    scenario: Scenario,
    system: ControlAffineSystem,
    basis: PolynomialBasis,
    features: PointFeatures,
    r: np.ndarray,
) -> CriticSettings:
    """The critic's law and gains in force: as the scenario gives them, or derived.

    Under ``critic.gains: auto`` the gains come from
    :func:`ofrl_drake.learning.auto_gains` at ``W0`` on the scenario's points
    and horizon. Under ``policy_iteration``, ``rho`` uses the points' metric
    (:func:`ofrl_drake.learning.basis_scales`) and the policy period and gamma
    bound default to a tenth of the horizon and
    :data:`~ofrl_drake.learning.DEFAULT_GAMMA_BOUND`.

    Raises
    ------
    ScenarioError
        If ``policy_iteration`` is asked for a plant whose origin is not an
        equilibrium (no linearization for the acceptance test), or ``auto``
        gains cannot be derived.
    """
    c = scenario.critic
    linearization = _linearization(system)
    metric = None
    if c.law == "policy_iteration":
        if linearization is None:
            raise ScenarioError(
                "critic.law: policy_iteration accepts a policy by its linearization at the "
                "target, but the origin is not an equilibrium of f; give an equilibrium "
                "(the equilibrium key) or use critic.law: paper."
            )
        try:
            metric = rho_metric(basis_scales(basis, features.points))
        except ModelError as err:
            raise ScenarioError(f"points: {err}") from None
    W0 = np.asarray(c.W0, dtype=float)
    if critic_gains_choice(c) == "auto":
        unit = Extrapolator(features, r, scenario.input_bound, 1.0, metric)(W0)
        try:
            gains = auto_gains(
                lambda nu: (
                    Extrapolator(features, r, scenario.input_bound, nu, metric).sums(W0).gain_sum
                ),
                unit.rho - 1.0,
                scenario.simulation.duration,
            )
        except ModelError as err:
            raise ScenarioError(str(err)) from None
    else:
        gains = LearningGains(
            kc=float(c.kc),
            nu=float(c.nu),
            beta=float(c.beta),
            Gamma0=np.asarray(c.Gamma0, dtype=float),
            policy_period=POLICY_PERIOD_FRACTION * scenario.simulation.duration,
            gamma_bound=DEFAULT_GAMMA_BOUND,
        )
    if c.law == "policy_iteration":
        gains = dataclasses.replace(
            gains,
            policy_period=gains.policy_period if c.policy_period is None else c.policy_period,
            gamma_bound=gains.gamma_bound if c.gamma_bound is None else c.gamma_bound,
        )
    else:
        gains = dataclasses.replace(gains, policy_period=None, gamma_bound=None)
    return CriticSettings(law=c.law, gains=gains, metric=metric, linearization=linearization)


def resolved_scenario(scenario: Scenario, critic: CriticSettings | None) -> Scenario:
    """``scenario`` with the gains of ``critic`` written out under ``critic.gains: manual``."""
    if critic is None:
        return scenario
    g = critic.gains
    return dataclasses.replace(
        scenario,
        critic=dataclasses.replace(
            scenario.critic,
            gains="manual",
            kc=float(g.kc),
            nu=float(g.nu),
            beta=float(g.beta),
            Gamma0=np.asarray(g.Gamma0, dtype=float).tolist(),
            policy_period=None if g.policy_period is None else float(g.policy_period),
            gamma_bound=None if g.gamma_bound is None else float(g.gamma_bound),
        ),
    )


def symbolic_blocks(scenario: Scenario, system: ControlAffineSystem) -> bool:
    """Whether the plant, observer, controller and running cost are C++ symbolic blocks.

    As ``scenario.simulation.blocks`` says; ``"auto"`` means whenever
    ``system.symbolic()`` succeeds.

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
                f"simulation.blocks: symbolic needs f and g that Drake can trace: {err} "
                "Or set simulation.blocks to python."
            ) from err
        return False
    return True


def _plant_block(parts: ClosedLoopParts, symbolic: bool) -> System:
    """The plant simulated: the model, or the scenario's truth.

    A multibody truth runs as its own ``MultibodyPlant`` in C++
    (:class:`~ofrl_drake.systems.DrakePlant`, body masses scaled through the
    Context); another truth as the model does, from its ``f`` and ``g``.
    """
    s = parts.scenario
    truth = parts.truth
    if truth is None:
        block = SymbolicPlant if symbolic else ControlAffinePlant
        return block(parts.system, initial_state=s.x0)
    from ofrl_drake.plants import multibody_body_names
    from ofrl_drake.systems.drake_plant import DrakePlant

    if multibody_body_names(truth) is not None:
        return DrakePlant(truth, initial_state=s.x0, body_mass_scale=s.truth.body_mass_scale)
    try:
        truth.symbolic()
    except ModelError:
        return ControlAffinePlant(truth, initial_state=s.x0)
    return SymbolicPlant(truth, initial_state=s.x0)


def _real_world(slot: str, block: System, scenario: Scenario) -> System:
    """``block`` as the scenario's sensors and actuators see it.

    See :mod:`ofrl_drake.systems.world`.
    """
    meas, act = scenario.measurement, scenario.actuation
    if slot == "plant":
        noise = list(meas.noise_std) if meas is not None else []
        period = meas.period if meas is not None else 0.0
        disturbance = list(act.disturbance) if act is not None else []
        if any(noise) or period > 0 or any(disturbance):
            return MeasuredPlant(block, noise_std=noise, period=period, disturbance=disturbance)
    if slot == "controller" and act is not None and act.period > 0:
        return SampledController(block, act.period)
    return block


def _default_block(slot: str, parts: ClosedLoopParts, symbolic: bool) -> System:
    s, c, gains = parts.scenario, parts.scenario.critic, parts.critic.gains
    if slot == "plant":
        return _plant_block(parts, symbolic)
    if slot == "observer":
        o = s.observer
        if o.schedule_period > 0:
            width = np.asarray(o.box.upper, float) - np.asarray(o.box.lower, float)
            half = np.asarray(o.schedule_half_width or 0.5 * width, float)
            return ScheduledThreeGainObserver(
                parts.system,
                parts.design,
                period=o.schedule_period,
                half_width=half,
                input_bound=s.input_bound,
                alpha=o.alpha,
                design_options={
                    "jacobian_method": o.jacobian_method,
                    "solver": o.solver,
                    "formulation": o.formulation,
                },
                initial_state=s.xhat0,
            )
        gains = ObserverGains.from_design(parts.system, parts.design)
        block = SymbolicObserver if symbolic else ThreeGainObserver
        return block(parts.system, gains, initial_state=s.xhat0, design=parts.design)
    if slot == "controller":
        block = SymbolicController if symbolic else SaturatedController
        return block(parts.system, parts.basis, parts.r, s.input_bound)
    if slot == "critic":  # Python whatever ``symbolic`` (see ofrl_drake.systems.symbolic)
        return CriticWeights(c.W0, gains.kc)
    if slot == "policy":
        if parts.critic.law == "paper":
            return PolicyPassThrough(parts.basis.size)
        A, B = parts.critic.linearization
        return PolicyGate(
            c.W0, gains.policy_period, A, B, parts.Q, parts.r, parts.basis, parts.features.points
        )
    if slot == "gamma":
        return GammaGain(np.asarray(gains.Gamma0, float), gains.kc, gains.beta, gains.gamma_bound)
    if slot == "bellman":
        return BellmanExtrapolator(
            parts.features, parts.r, s.input_bound, gains.nu, parts.critic.metric
        )
    if slot == "running_cost":
        block = SymbolicRunningCost if symbolic else RunningCost
        return block(parts.Q, parts.r, s.input_bound)
    raise AssertionError(slot)  # pragma: no cover


def _after_run(blocks: dict[str, System]) -> set[str]:
    """Keys of :data:`LOGGED` computed from the other logs after the run, not logged.

    The learning condition, when the Bellman block can compute it from the
    logged weights alone (``learning_condition_of``): every sample in one
    call, instead of one evaluation per publish (where the Bellman sums'
    cache is always stale, so each sample would redo the extrapolation).
    """
    return {"learning_condition"} if hasattr(blocks["bellman"], "learning_condition_of") else set()


def drake_plant(parts: ClosedLoopParts) -> System:
    """Plant-slot factory: the model's own multibody plant, running in C++.

    For a system built by ``ControlAffineSystem.from_multibody`` (possibly
    shifted), ``build_closed_loop(scenario, plant=drake_plant)`` puts a
    :class:`~ofrl_drake.systems.DrakePlant` in the plant slot instead of the
    :class:`~ofrl_drake.systems.ControlAffinePlant` that evaluates ``f`` and
    ``g``; it starts from ``scenario.x0`` (``simulate`` sets its velocities).
    """
    from ofrl_drake.systems.drake_plant import DrakePlant

    return DrakePlant(parts.system, initial_state=parts.scenario.x0)


def build_closed_loop(
    scenario: Scenario,
    *,
    design: Any = None,
    log_period: float | None = None,
    **swaps: Swap,
) -> ClosedLoop:
    """Build the closed-loop ``Diagram`` of ``scenario``.

    Parameters
    ----------
    scenario : Scenario
        A validated scenario (see :func:`ofrl_drake.load_scenario`).
    design : ObserverDesign, optional
        Observer design to use; by default :func:`design_for` computes it. Not
        computed at all when the ``observer`` slot is swapped.
    log_period : float, optional
        Logging period in seconds; defaults to ``scenario.simulation.log_period``.
    **swaps : System or callable
        Replace a slot (one of :data:`SLOTS`) with another block that has the
        same port names, or with a factory ``f(parts) -> System`` called with
        the :class:`ClosedLoopParts`. Swaps apply on top of the scenario's
        ``variant`` choices (:mod:`ofrl_drake.variants`).

    Returns
    -------
    ClosedLoop
        The diagram, its blocks by slot name (``loop.observer`` ...) and its
        loggers by key (:data:`LOGGED`, but for the keys computed after the
        run; :meth:`ClosedLoop.logs` returns them all).

    Raises
    ------
    SwapError
        If a swap names an unknown slot or its block's ports do not fit.

    Examples
    --------
    >>> loop = build_closed_loop(scenario)                       # doctest: +SKIP
    >>> loop = build_closed_loop(scenario, critic=CriticWeights(W0, kc=0.0))  # doctest: +SKIP
    """
    unknown = sorted(set(swaps) - set(SLOTS))
    if unknown:
        raise SwapError(f"{unknown[0]}: unknown slot; swap one of {list(SLOTS)}.")
    validate_scenario(scenario)
    system = resolve_system(scenario)
    basis = PolynomialBasis(system.n, scenario.critic.basis_degrees)
    Q = np.asarray(scenario.cost.Q, dtype=float)
    r = np.asarray(scenario.cost.R, dtype=float)
    features = point_features(system, basis, extrapolation_points(scenario), Q)
    choices = variant_choices(scenario)
    if design is None and "observer" not in swaps:
        if choices["observer"] == "three_gain":
            design = design_for(scenario, system)
        elif choices["observer"] == "linear_luenberger":
            from ofrl_drake.variants import linear_observer_design

            # Designed here, not inside the variant, so its certificate is reported.
            design = linear_observer_design(scenario, system)
    critic = critic_settings(scenario, system, basis, features, r)
    truth = resolve_truth(scenario)
    parts = ClosedLoopParts(scenario, system, basis, features, design, Q, r, critic, truth)
    from ofrl_drake.variants import variant_blocks

    swaps = {**variant_blocks(choices, parts), **swaps}

    builder = DiagramBuilder()
    blocks: dict[str, System] = {}
    symbolic = symbolic_blocks(scenario, system)
    for slot in SLOTS:
        swap = swaps.get(slot)
        if swap is None:
            block = _default_block(slot, parts, symbolic)
        elif isinstance(swap, System):
            block = swap
        elif callable(swap):
            block = swap(parts)
        else:
            raise SwapError(
                f"{slot}: a swap must be a Drake System or a factory f(parts) -> System; "
                f"got {type(swap).__name__}."
            )
        block = _real_world(slot, block, scenario)
        block.set_name(slot)
        blocks[slot] = builder.AddSystem(block)

    _connect_by_name(builder, blocks)

    period = scenario.simulation.log_period if log_period is None else log_period
    loggers = {}
    for key, signal in LOGGED.items():
        if key in _after_run(blocks):
            continue
        source = blocks[SIGNALS[signal]]
        logger = LogVectorOutput(source.GetOutputPort(signal), builder, period)
        logger.set_name(f"log_{key}")
        loggers[key] = logger
    for key, (slot, port) in OPTIONAL_LOGGED.items():
        if blocks[slot].HasOutputPort(port):
            logger = LogVectorOutput(blocks[slot].GetOutputPort(port), builder, period)
            logger.set_name(f"log_{key}")
            loggers[key] = logger
    diagram = builder.Build()
    diagram.set_name(f"closed_loop_{scenario.name}")
    return ClosedLoop(diagram=diagram, parts=parts, blocks=blocks, loggers=loggers)


def _connect_by_name(builder: DiagramBuilder, blocks: dict[str, System]) -> None:
    for signal, source_slot in SIGNALS.items():
        source = blocks[source_slot]
        if not source.HasOutputPort(signal):
            raise SwapError(
                f"{source_slot}: the block must have an output port named {signal!r}; "
                f"{source.get_name()} has none."
            )
    for slot, block in blocks.items():
        for i in range(block.num_input_ports()):
            port = block.get_input_port(i)
            name = port.get_name()
            source_slot = SIGNALS.get(name)
            if source_slot is None:
                raise SwapError(
                    f"{slot}: input port {name!r} matches no signal of the loop; "
                    f"input ports must be named one of {sorted(SIGNALS)}."
                )
            out = blocks[source_slot].GetOutputPort(name)
            if out.size() != port.size():
                raise SwapError(
                    f"{slot}: input port {name!r} has size {port.size()}, but "
                    f"{source_slot}'s output {name!r} has size {out.size()}."
                )
            builder.Connect(out, port)
