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
import inspect
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, System
from pydrake.systems.primitives import LogVectorOutput, VectorLogSink

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import Extrapolator, PointFeatures, point_features
from ofrl_drake.checks import positive_number
from ofrl_drake.contracts import (
    EstimateSetter,
    InitialGammaSetter,
    LearningConditionSource,
    PlantStateSetter,
    PolicyWeightsSetter,
    WeightsSetter,
)
from ofrl_drake.drake_typing import DrakeArray, input_port_names, output_port_names
from ofrl_drake.errors import (
    InitialPolicyWarning,
    ModelError,
    ScenarioError,
    SwapError,
    TargetWarning,
)
from ofrl_drake.learning import (
    DEFAULT_GAMMA_BOUND,
    POLICY_PERIOD_FRACTION,
    CriticSettings,  # defined with the gains it holds; public here too (__all__)
    LearningGains,
    auto_gains,
    basis_scales,
    check_policy,
    rho_metric,
    second_moment,
)
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.plants import resolve_system, resolve_truth
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.scenario import (
    Scenario,
    check_scenario,
    critic_gains_choice,
    manual_gains,
    validate_scenario,
    variant_choices,
)
from ofrl_drake.slots import (
    SLOTS,
    VARIANT_FACTORIES,
    ClosedLoopParts,
    chosen_design,
    slot_blocks,
)
from ofrl_drake.systems.world import MeasuredPlant, SampledController, initialize_context
from ofrl_drake.variants import symbolic_blocks

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = [
    "INITIAL_VALUES",
    "LOGGED",
    "OPTIONAL_LOGGED",
    "SIGNALS",
    "ClosedLoop",
    "CriticSettings",
    "build_closed_loop",
    "critic_settings",
    "drake_plant",
    "extrapolation_points",
    "initial_value_setter",
    "initial_values",
    "symbolic_blocks",
]

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


#: Slot -> (setter, value): the initial value a run writes into each block's context,
#: through the block's setter ``setter(context, value)`` (a Protocol of
#: :mod:`ofrl_drake.contracts`, :func:`initial_value_setter`); values of :func:`initial_values`.
INITIAL_VALUES = {
    "plant": ("set_state", "x0"),
    "observer": ("set_estimated_state", "xhat0"),
    "critic": ("set_weights", "W0"),
    "policy": ("set_policy_weights", "W0"),
    "gamma": ("set_initial_gamma", "Gamma0"),
}


@dataclass
class ClosedLoop:
    """A built closed loop: the diagram and handles to its named blocks.

    The loop holds no run: a run's initial values (x0, xhat0, W0, Gamma0) go
    into a context (:meth:`set_initial_values`), and the learning gains are
    numeric parameters of the critic, Gamma and Bellman blocks (``set_kc``,
    ``set_beta``, ``set_gamma_bound``, ``set_nu``), so one built loop runs
    from any initial state and at any gains.

    Attributes
    ----------
    diagram : Diagram
        The closed loop, as Drake's ``Diagram`` (simulate it with a
        ``Simulator``, or with :func:`~ofrl_drake.simulate` and ``loop=``).
    parts : ClosedLoopParts
        What the blocks were built from: the scenario (with the choices
        given by name), the model, the basis, the points' features, the
        observer design, Q and r, the critic's settings, the truth and
        whether the blocks are symbolic (:class:`~ofrl_drake.slots.ClosedLoopParts`).
    blocks : dict of str to System
        The blocks by slot name (:data:`~ofrl_drake.slots.SLOTS`); also the
        properties ``loop.plant``, ``loop.observer`` ...
    loggers : dict of str to VectorLogSink
        Drake's loggers by log key (:data:`LOGGED`, and :data:`OPTIONAL_LOGGED`
        where a block has the port); :meth:`logs` reads them from a context.
    swapped : frozenset of str
        The slots given to :func:`build_closed_loop` as a block or a factory:
        they start from their own initial values unless a run asks for others.
    """

    diagram: Diagram
    parts: ClosedLoopParts
    blocks: dict[str, System]
    loggers: dict[str, VectorLogSink] = field(default_factory=dict)
    swapped: frozenset[str] = frozenset()

    # The blocks by slot (:data:`~ofrl_drake.slots.SLOTS`), as ``loop.blocks[slot]``.
    # Any System with the slot's ports fills a slot: what a block offers beyond
    # them is asked through the Protocols of :mod:`ofrl_drake.contracts`.
    @property
    def plant(self) -> System:
        """The ``plant`` block (outputs ``y`` and ``state``)."""
        return self.blocks["plant"]

    @property
    def observer(self) -> System:
        """The ``observer`` block (output ``estimated_state``)."""
        return self.blocks["observer"]

    @property
    def controller(self) -> System:
        """The ``controller`` block (output ``u``)."""
        return self.blocks["controller"]

    @property
    def critic(self) -> System:
        """The ``critic`` block (output ``weights``)."""
        return self.blocks["critic"]

    @property
    def policy(self) -> System:
        """The ``policy`` block (output ``policy_weights``)."""
        return self.blocks["policy"]

    @property
    def gamma(self) -> System:
        """The ``gamma`` block (output ``gamma``)."""
        return self.blocks["gamma"]

    @property
    def bellman(self) -> System:
        """The ``bellman`` block (outputs ``critic_sum``, ``gain_sum``, ``learning_condition``)."""
        return self.blocks["bellman"]

    @property
    def running_cost(self) -> System:
        """The ``running_cost`` block (output ``cost``)."""
        return self.blocks["running_cost"]

    @property
    def design(self) -> ObserverDesign | None:
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
        logs: dict[str, np.ndarray] = {}
        t: np.ndarray = np.empty(0)
        for key, logger in self.loggers.items():
            log = logger.FindLog(root_context)
            times: DrakeArray = log.sample_times()
            data: DrakeArray = log.data()
            t = np.asarray(times)
            logs[key] = data.T.copy()
        bellman = self.bellman
        if "learning_condition" not in logs and isinstance(bellman, LearningConditionSource):
            condition = bellman.learning_condition_of(
                logs["W_policy"], bellman.GetMyContextFromRoot(root_context)
            )
            logs["learning_condition"] = condition[:, None]
        return t, logs

    def initial_values(self, scenario: Scenario | None = None) -> dict[str, np.ndarray]:
        """x0, xhat0, W0 and Gamma0 of a run of ``scenario`` (default: the loop's own).

        See :func:`initial_values`; under ``critic.gains: auto`` Gamma0 is the
        one derived when the loop was built.
        """
        return initial_values(scenario or self.parts.scenario, self.parts.critic)

    def set_initial_values(self, root_context: Context, scenario: Scenario | None = None) -> None:
        """Write the initial values of a run of ``scenario`` into ``root_context``.

        First each block sets what its default context cannot hold
        (:func:`ofrl_drake.systems.world.initialize_context`: a multibody
        truth's velocities and scaled body masses; a mass the context already
        holds other than the body's default is kept). Then each block of
        :data:`INITIAL_VALUES` gets its value through its own
        setter (``loop.plant.set_state(context, x0)`` ...). A block swapped in
        (:attr:`swapped`) keeps its own initial value when the run's is the
        loop's own (the scenario it was built from); a stateless block
        (the full-state observer) has nothing to set.

        Parameters
        ----------
        root_context : Context
            A context of :attr:`diagram`.
        scenario : Scenario, optional
            The run's scenario (default: the loop's own,
            ``loop.parts.scenario``); its ``x0``, ``xhat0``, ``critic.W0`` and,
            under ``critic.gains: manual``, ``critic.Gamma0`` are written.

        Raises
        ------
        SwapError
            If a block without the setter would have to start from another
            value than the loop's own.
        """
        for block in self.blocks.values():
            initialize_context(block, block.GetMyMutableContextFromRoot(root_context))
        values = self.initial_values(scenario)
        own = self.initial_values() if scenario is not None else values
        for slot, (name, key) in INITIAL_VALUES.items():
            block = self.blocks[slot]
            same = np.array_equal(values[key], own[key])
            if slot in self.swapped and same:
                continue  # a block given to build_closed_loop starts from its own values
            setter = initial_value_setter(slot, block)
            if setter is None:
                if same or _stateless(block):
                    continue
                raise SwapError(
                    f"{slot}: the block {type(block).__name__} has no {name}(context, value), "
                    f"so a run cannot start it from {key} = {values[key].tolist()}; give it "
                    "one, or build a loop from the run's scenario."
                )
            setter(block.GetMyMutableContextFromRoot(root_context), values[key])


def initial_value_setter(slot: str, block: System) -> Callable[[Context, ArrayLike], None] | None:
    """``block``'s setter of the initial value of ``slot`` (:data:`INITIAL_VALUES`).

    The setter that :data:`INITIAL_VALUES` names, when ``block`` has it: its
    Protocol in :mod:`ofrl_drake.contracts`. None for a slot without an
    initial value, or a block without the setter.
    """
    if slot == "plant" and isinstance(block, PlantStateSetter):
        return block.set_state
    if slot == "observer" and isinstance(block, EstimateSetter):
        return block.set_estimated_state
    if slot == "critic" and isinstance(block, WeightsSetter):
        return block.set_weights
    if slot == "policy" and isinstance(block, PolicyWeightsSetter):
        return block.set_policy_weights
    if slot == "gamma" and isinstance(block, InitialGammaSetter):
        return block.set_initial_gamma
    return None


def _stateless(block: System) -> bool:
    return (
        block.num_continuous_states() == 0
        and block.num_discrete_state_groups() == 0
        and block.num_abstract_states() == 0
    )


def initial_values(scenario: Scenario, critic: CriticSettings | None) -> dict[str, np.ndarray]:
    """The initial values of a run of ``scenario``: ``x0``, ``xhat0``, ``W0`` and ``Gamma0``.

    ``Gamma0`` is the scenario's under ``critic.gains: manual``, else the one
    of ``critic`` (the gains in force, derived under ``auto``).
    """
    c = scenario.critic
    gamma0: ArrayLike | None = c.Gamma0
    if critic is not None and critic_gains_choice(c) != "manual":
        gamma0 = critic.gains.Gamma0
    return {
        "x0": np.asarray(scenario.x0, dtype=float),
        "xhat0": np.asarray(scenario.xhat0, dtype=float),
        "W0": np.asarray(c.W0, dtype=float),
        "Gamma0": np.asarray(gamma0, dtype=float),
    }


Swap = System | Callable[[ClosedLoopParts], System]


def extrapolation_points(scenario: Scenario) -> np.ndarray:
    """The scenario's Bellman-extrapolation points, shape ``(n, N)``."""
    p = scenario.points
    if p.kind == "grid":
        return grid_points(p.lower, p.upper, p.counts)
    return uniform_points(p.lower, p.upper, p.number, p.seed)


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
    if linearization is None:
        # The greedy policy is zero where dV/dx is (at the origin, for a basis of degree
        # >= 2), so f(0) != 0 keeps the loop from ever resting at the target.
        f0 = np.asarray(system.f(np.zeros(system.n)), dtype=float).tolist()
        fix = (
            "give the target as an equilibrium, equilibrium: {x: x*, u: u*} with "
            "f(x*) + g(x*) u* = 0 (docs/own_plant.md)"
        )
        if c.law == "policy_iteration":
            raise ScenarioError(
                f"the origin is not an equilibrium of f (f(0) = {f0}): the policy is zero "
                "there, so no law can hold the plant at the target, and critic.law: "
                f"policy_iteration needs its linearization there; {fix}."
            )
        warnings.warn(
            f"the origin is not an equilibrium of f (f(0) = {f0}): the policy is zero there, "
            f"so the loop cannot come to rest at the target; {fix}.",
            TargetWarning,
            stacklevel=_stacklevel_outside_the_package(),
        )
    if c.law == "policy_iteration":
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
                c.policy_period if c.law == "policy_iteration" else None,
            )
        except ModelError as err:
            raise ScenarioError(str(err)) from None
    else:
        kc, nu, beta, Gamma0 = manual_gains(c)
        gains = LearningGains(
            kc=float(kc),
            nu=float(nu),
            beta=float(beta),
            Gamma0=np.asarray(Gamma0, dtype=float),
            policy_period=POLICY_PERIOD_FRACTION * scenario.simulation.duration,
            gamma_bound=DEFAULT_GAMMA_BOUND,
        )
    if c.law == "policy_iteration":
        gains = dataclasses.replace(
            gains,
            policy_period=gains.policy_period if c.policy_period is None else c.policy_period,
            gamma_bound=gains.gamma_bound if c.gamma_bound is None else c.gamma_bound,
        )
        _warn_if_not_admissible(scenario, basis, features, r, linearization, W0)
    else:
        gains = dataclasses.replace(gains, policy_period=None, gamma_bound=None)
    return CriticSettings(law=c.law, gains=gains, metric=metric, linearization=linearization)


def _warn_if_not_admissible(
    scenario: Scenario,
    basis: PolynomialBasis,
    features: PointFeatures,
    r: np.ndarray,
    linearization: tuple[np.ndarray, np.ndarray] | None,
    W0: np.ndarray,
) -> None:
    """Warn when policy iteration starts from a policy its acceptance test calls inadmissible.

    Kleinman's iteration needs a stabilizing start: until the gate accepts an
    admissible candidate the loop runs ``W0``'s policy, whose linearized loop
    is unstable or whose value is not positive definite.
    """
    if linearization is None:  # refused before: policy iteration needs one
        return
    A, B = linearization
    Q = np.asarray(scenario.cost.Q, dtype=float)
    check = check_policy(
        A, B, Q, r, basis, W0, second_moment(features.points), points=features.points
    )
    if check.admissible:
        return
    failed = []
    if not check.value_min_eigenvalue > 0.0:
        failed.append(
            "the smallest eigenvalue of its value's quadratic part is "
            f"{check.value_min_eigenvalue:.3g} (must be > 0)"
        )
    if check.value_min_at_points <= 0.0:
        failed.append(
            "the smallest of its values W0^T sigma(x_i) at the extrapolation points is "
            f"{check.value_min_at_points:.3g} (must be > 0)"
        )
    if not check.spectral_abscissa < 0.0:
        failed.append(
            f"the spectral abscissa of its linearized loop is {check.spectral_abscissa:.3g} "
            "(must be < 0)"
        )
    warnings.warn(
        f"critic.W0: policy iteration starts from a policy its gate would not accept: "
        f"{' and '.join(failed) or 'it is not admissible'}; the loop runs this policy until "
        "the gate accepts an admissible update. Start from a stabilizing W0, e.g. the LQR "
        "value (ofrl_drake.learning_curve.lqr_weights(loop)).",
        InitialPolicyWarning,
        stacklevel=_stacklevel_outside_the_package(),
    )


def _stacklevel_outside_the_package() -> int:
    """The ``stacklevel`` at which a warning names its caller's first frame outside ofrl_drake."""
    package = str(Path(__file__).resolve().parent)
    frame = inspect.currentframe()
    level = 0
    while frame is not None and str(Path(frame.f_code.co_filename).resolve()).startswith(package):
        frame = frame.f_back
        level += 1
    return max(level, 1)


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


def _real_world(slot: str, scenario: Scenario) -> Callable[[System], System] | None:
    """What wraps ``slot``'s block as the scenario's sensors and actuators see it; None: nothing.

    :class:`~ofrl_drake.systems.world.MeasuredPlant` for the plant (noise,
    sampling or a disturbance), :class:`~ofrl_drake.systems.world.SampledController`
    for a sampled controller; see :mod:`ofrl_drake.systems.world`. The ports
    that a wrapper reads from its block are :func:`_check_ports`' to check.
    """
    meas, act = scenario.measurement, scenario.actuation
    if slot == "plant":
        noise = list(meas.noise_std) if meas is not None else []
        period = meas.period if meas is not None else 0.0
        disturbance = list(act.disturbance) if act is not None else []
        if any(noise) or period > 0 or any(disturbance):
            return lambda block: MeasuredPlant(
                block, noise_std=noise, period=period, disturbance=disturbance
            )
    if slot == "controller" and act is not None and act.period > 0:
        hold = act.period
        return lambda block: SampledController(block, hold)
    return None


#: Input ports that a wrapper of :func:`_real_world` reads from the block it wraps,
#: beyond the slot's outputs of :data:`SIGNALS`: the plant's ``u`` (plus the disturbance).
_WRAPPED_INPUTS = {"plant": ("u",)}


def _check_ports(slot: str, block: System, wrapped: bool) -> None:
    """Refuse a ``block`` for ``slot`` without a port that the loop reads from it.

    Every output of :data:`SIGNALS` that ``slot`` provides, and, when
    ``wrapped`` (:func:`_real_world`), the inputs :data:`_WRAPPED_INPUTS` that the
    wrapper feeds. Checked on every block before any is wrapped or built in,
    where Drake would only raise its ``RuntimeError``.
    """
    name = type(block).__name__
    if block.get_name():
        name += f" {block.get_name()!r}"
    for signal, provider in SIGNALS.items():
        if provider == slot and not block.HasOutputPort(signal):
            have = output_port_names(block)
            raise SwapError(
                f"{slot}: the block must have an output port named {signal!r}; {name} has "
                f"none (its output ports: {have}). Name the port {signal!r}."
            )
    for port in _WRAPPED_INPUTS.get(slot, ()) if wrapped else ():
        if not block.HasInputPort(port):
            have = input_port_names(block)
            raise SwapError(
                f"{slot}: the block must have an input port named {port!r}, which the "
                f"scenario's measurement and actuation feed; {name} has none (its input "
                f"ports: {have}). Name the port {port!r}, or drop those keys."
            )


def _after_run(blocks: dict[str, System]) -> set[str]:
    """Keys of :data:`LOGGED` computed from the other logs after the run, not logged.

    The learning condition, when the Bellman block can compute it from the
    logged weights alone (``learning_condition_of``): every sample in one
    call, instead of one evaluation per publish (where the Bellman sums'
    cache is always stale, so each sample would redo the extrapolation).
    """
    return (
        {"learning_condition"} if isinstance(blocks["bellman"], LearningConditionSource) else set()
    )


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


def _check_design(design: object, scenario: Scenario, system: ControlAffineSystem) -> None:
    """Refuse a ``design=`` that is not an ``ObserverDesign`` certified for ``scenario``'s loop.

    Its sizes and output matrix must be the model's (a design for another
    measurement would report a certificate that does not apply to the loop
    that ran), and the controller saturates at the scenario's
    ``input_bound``, so a design certified for a smaller one would be claimed
    where it does not hold.
    """
    from ofrl_drake.design import DesignError, ObserverDesign

    if not isinstance(design, ObserverDesign):
        raise DesignError(
            f"design: expected an ObserverDesign; got {type(design).__name__}. Make one with "
            "ofrl_drake.variants.design_for(scenario) or ofrl_drake.design.design_observer, "
            "or omit design= to use the scenario's own."
        )
    n, m = design.bounds.Mg1.shape[0], design.bounds.Mg1.shape[2]
    C = np.asarray(design.C, dtype=float)
    if (n, m) != (system.n, system.m) or not np.array_equal(C, system.output_matrix):
        raise DesignError(
            f"design: made for a plant with n = {n} states, m = {m} inputs and C = "
            f"{C.tolist()}, but the scenario's model {system.name!r} has n = {system.n}, "
            f"m = {system.m} and C = {system.output_matrix.tolist()}, so its certificate would "
            "not apply to the loop; design for this scenario (design_for(scenario)), or "
            "omit design= to use the scenario's own."
        )
    if design.input_bound < scenario.input_bound:
        raise DesignError(
            f"design: certified for |u_k| <= input_bound = {design.input_bound:g}, but the "
            f"scenario's controller saturates at input_bound = {scenario.input_bound:g}, "
            "so the certificate would not hold along the run; design for an input bound of "
            f"at least {scenario.input_bound:g} (design_for(scenario)), or lower the "
            "scenario's input_bound."
        )


def _log_period(scenario: Scenario, log_period: float | None) -> float:
    """The loggers' period: ``scenario.simulation.log_period``, or ``log_period`` if given.

    A given ``log_period`` is checked by the scenario's own rule for
    ``simulation.log_period`` (:func:`~ofrl_drake.scenario.validate_scenario`).
    """
    own = scenario.simulation.log_period
    if log_period is None:
        return own
    try:  # a number first (numpy scalars too), then the scenario's rule for it
        period = positive_number("log_period", log_period)
    except ModelError as err:
        raise ScenarioError(f"{err} Or omit log_period to log every {own:g} s.") from None
    simulation = dataclasses.replace(scenario.simulation, log_period=period)
    try:
        validate_scenario(dataclasses.replace(scenario, simulation=simulation))
    except ScenarioError as err:
        raise ScenarioError(
            f"log_period: {log_period!r} is refused, as in the scenario: {err} Or omit "
            f"log_period to log every simulation.log_period = {own:g} s."
        ) from None
    return period


def _factory_block(slot: str, factory: Callable[..., Any], parts: ClosedLoopParts) -> System:
    """The block that a swap's ``factory(parts)`` builds, checked to be a Drake System."""
    try:
        inspect.signature(factory).bind(parts)
    except TypeError:
        raise SwapError(
            f"{slot}: the factory {_callable_name(factory)} cannot be called with one "
            "argument; a factory is f(parts) -> System, called with the ClosedLoopParts."
        ) from None
    except ValueError:  # no signature to inspect (some builtins): just call it
        pass
    block = factory(parts)
    if not isinstance(block, System):
        raise SwapError(
            f"{slot}: the factory {_callable_name(factory)} returned "
            f"{type(block).__name__}, not a Drake System; a factory f(parts) must return "
            "the block for the slot."
        )
    return block


def _callable_name(factory: Callable[..., Any]) -> str:
    return getattr(factory, "__qualname__", None) or type(factory).__name__


def build_closed_loop(
    scenario: Scenario,
    *,
    design: ObserverDesign | None = None,
    log_period: float | None = None,
    **swaps: Swap | str,
) -> ClosedLoop:
    """Build the closed-loop ``Diagram`` of ``scenario``.

    Every block comes from the slot registry (:mod:`ofrl_drake.slots`): the
    scenario's ``variant`` choices, and the fixed blocks, unless swapped here.

    Parameters
    ----------
    scenario : Scenario
        A validated scenario (see :func:`ofrl_drake.load_scenario`).
    design : ObserverDesign, optional
        Observer design to use; by default the chosen observer's own
        (:func:`~ofrl_drake.variants.design_for` for ``three_gain``). Not
        computed at all when the ``observer`` block is swapped. It must be
        certified for the scenario's inputs: ``design.input_bound >=
        scenario.input_bound``, where the controller saturates.
    log_period : float, optional
        Logging period in seconds; defaults to ``scenario.simulation.log_period``,
        and is held to its rule (> 0, finite, at most ``simulation.duration``).
    **swaps : System, callable or str
        A block (one of :data:`~ofrl_drake.slots.SLOTS`) replaced by another
        with the same port names, or by a factory ``f(parts) -> System``
        called with the :class:`~ofrl_drake.slots.ClosedLoopParts`; or a
        slot's choice by name, as in the scenario's ``variant`` section
        (``observer="kalman"``, ``points="uniform"``), which it overrides.
        A swapped block is renamed to its slot (``block.get_name()`` is then
        ``"critic"``...) and becomes part of the returned diagram: Drake
        builds a block into one diagram only, so a block cannot be swapped
        into a second loop, nor into two slots; pass a fresh block each time,
        or a factory, which builds one per call.

    Returns
    -------
    ClosedLoop
        The diagram, its blocks by slot name (``loop.observer`` ...) and its
        loggers by key (:data:`LOGGED`, but for the keys computed after the
        run; :meth:`ClosedLoop.logs` returns them all). Its scenario
        (``loop.parts.scenario``) holds the choices given by name.

    Raises
    ------
    SwapError
        If a swap names an unknown block or slot, is neither a System nor a
        factory, its factory cannot take ``parts`` or returns no System, its
        block's ports do not fit (an output of :data:`SIGNALS` missing, or,
        when the scenario's ``measurement`` or ``actuation`` wraps the plant,
        its input ``u``), or its block is already part of a diagram or of
        another slot.
    ScenarioError
        If ``scenario`` is not a Scenario (a path: load it with
        :func:`~ofrl_drake.load_scenario`), or it, a choice given by name or
        ``log_period`` is not valid.
    DesignError
        If ``design`` is not an ``ObserverDesign``, or is certified for a
        smaller input bound than the scenario's ``input_bound``.
    ObserverDesignInfeasible
        If ``design`` is omitted and the scenario's LMI has no certified
        solution (or its pinned gains ``observer.L/H/K`` are not certified).
    WallTimeExceeded
        If ``design`` is omitted and the design does not finish within
        ``simulation.max_wall_time``.
    ModelError
        If the plant's ``f`` or ``g`` returns the wrong shape or non-finite
        values where the design or a block evaluates it.

    Examples
    --------
    >>> loop = build_closed_loop(scenario)                       # doctest: +SKIP
    >>> loop = build_closed_loop(scenario, critic=CriticWeights(W0, kc=0.0))  # doctest: +SKIP
    >>> loop = build_closed_loop(scenario, observer="kalman")     # doctest: +SKIP
    """
    check_scenario(scenario, "build_closed_loop")
    # Choices by name: values of the str fields of VariantConfig (the keys checked below).
    named: dict[str, Any] = {key: value for key, value in swaps.items() if isinstance(value, str)}
    for key in sorted(named):
        if key not in VARIANT_FACTORIES:
            raise SwapError(
                f"{key}: no choices by name; name a choice of one of {sorted(VARIANT_FACTORIES)}, "
                "or swap a block with a System or a factory."
            )
    for key in sorted(set(swaps) - set(named) - set(SLOTS)):
        hint = ""
        if key in VARIANT_FACTORIES:
            hint = f" ({key!r} is chosen by name, one of {sorted(VARIANT_FACTORIES[key])})"
        raise SwapError(f"{key}: unknown slot; swap one of {list(SLOTS)}{hint}.")
    given = {key: value for key, value in swaps.items() if key not in named and value is not None}
    if named:
        scenario = dataclasses.replace(
            scenario, variant=dataclasses.replace(scenario.variant, **named)
        )
    validate_scenario(scenario)
    period = _log_period(scenario, log_period)
    system = resolve_system(scenario)
    if design is not None:
        _check_design(design, scenario, system)
    basis = PolynomialBasis(system.n, scenario.critic.basis_degrees)
    Q = np.asarray(scenario.cost.Q, dtype=float)
    r = np.asarray(scenario.cost.R, dtype=float)
    features = point_features(system, basis, extrapolation_points(scenario), Q)
    choices = variant_choices(scenario)
    swapped = set(given)
    if design is None:
        make_design = chosen_design(choices, swapped)
        if make_design is not None:
            design = make_design(scenario, system)
    critic = critic_settings(scenario, system, basis, features, r)
    truth = resolve_truth(scenario)
    symbolic = symbolic_blocks(scenario, system)
    parts = ClosedLoopParts(
        scenario, system, basis, features, design, Q, r, critic, truth, symbolic
    )
    built = slot_blocks(choices, parts, swapped)

    chosen: dict[str, System] = {}
    for slot in SLOTS:
        swap = given.get(slot)
        if swap is None:
            block = built[slot]
        elif isinstance(swap, System):
            block = swap
        elif callable(swap):
            block = _factory_block(slot, swap, parts)
        else:
            raise SwapError(
                f"{slot}: a swap must be a Drake System or a factory f(parts) -> System; "
                f"got {type(swap).__name__}."
            )
        _check_unused(slot, block, chosen)
        chosen[slot] = block

    # Every block checked first: a refused swap leaves the user's blocks untouched
    # (a wrapper of the real world would build the block into itself).
    wrappers = {slot: _real_world(slot, scenario) for slot in chosen}
    for slot, block in chosen.items():
        _check_ports(slot, block, wrapped=wrappers[slot] is not None)
    builder = DiagramBuilder()
    blocks: dict[str, System] = {}
    for slot, block in chosen.items():
        wrap = wrappers[slot]
        if wrap is not None:
            block = wrap(block)
        block.set_name(slot)
        blocks[slot] = builder.AddSystem(block)

    _connect_by_name(builder, blocks)

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
    return ClosedLoop(
        diagram=diagram, parts=parts, blocks=blocks, loggers=loggers, swapped=frozenset(given)
    )


def _in_a_diagram(block: System) -> bool:
    """Whether ``block`` has been built into a diagram (it has a parent).

    Drake's path name of a block is its parents' names and its own, joined by
    ``::`` (``"::closed_loop_paper::critic"``); a block without a parent has
    its own name only.
    """
    return block.GetSystemPathname() != "::" + block.GetSystemName()


def _check_unused(slot: str, block: System, chosen: dict[str, System]) -> None:
    """Refuse a ``block`` for ``slot`` that another slot (``chosen``) or diagram holds."""
    fix = "pass a fresh block, or a factory f(parts) -> System that builds a new one each call"
    other = next((name for name, held in chosen.items() if held is block), None)
    if other is not None:
        raise SwapError(
            f"{slot}: the block is already the {other} block (the same object); a block "
            f"fills one slot only: {fix}."
        )
    if _in_a_diagram(block):
        raise SwapError(
            f"{slot}: the block {block.GetSystemPathname()!r} is already part of a diagram "
            f"(an earlier build_closed_loop, or a diagram of your own), and Drake builds a "
            f"block into one diagram only: {fix}."
        )


def _connect_by_name(builder: DiagramBuilder, blocks: dict[str, System]) -> None:
    """Feed every input port of ``blocks`` from the output of its name (:data:`SIGNALS`).

    The outputs are there: :func:`_check_ports` checked them before the build.
    """
    for slot, block in blocks.items():
        for i in range(block.num_input_ports()):
            port = block.get_input_port(i)
            name = port.get_name()
            feeder = SIGNALS.get(name)
            if feeder is None:
                raise SwapError(
                    f"{slot}: input port {name!r} matches no signal of the loop; "
                    f"input ports must be named one of {sorted(SIGNALS)}."
                )
            out = blocks[feeder].GetOutputPort(name)
            if out.size() != port.size():
                raise SwapError(
                    f"{slot}: input port {name!r} has size {port.size()}, but "
                    f"{feeder}'s output {name!r} has size {out.size()}."
                )
            builder.Connect(out, port)
