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

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, System
from pydrake.systems.primitives import LogVectorOutput, VectorLogSink

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import PointFeatures, point_features
from ofrl_drake.errors import ModelError, ScenarioError, SwapError
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.observer import ObserverGains
from ofrl_drake.plants import resolve_system
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.scenario import Scenario, validate_scenario, variant_choices
from ofrl_drake.systems import (
    BellmanExtrapolator,
    ControlAffinePlant,
    CriticWeights,
    GammaGain,
    RunningCost,
    SaturatedController,
    ScheduledThreeGainObserver,
    SymbolicController,
    SymbolicObserver,
    SymbolicPlant,
    SymbolicRunningCost,
    ThreeGainObserver,
)

__all__ = [
    "LOGGED",
    "OPTIONAL_LOGGED",
    "SIGNALS",
    "SLOTS",
    "ClosedLoop",
    "ClosedLoopParts",
    "build_closed_loop",
    "design_for",
    "drake_plant",
    "extrapolation_points",
    "symbolic_blocks",
]

#: The block slots of the closed loop, in build order.
SLOTS = ("plant", "observer", "controller", "critic", "gamma", "bellman", "running_cost")

#: Signal name -> the slot whose output port of that name provides it.
SIGNALS = {
    "y": "plant",
    "state": "plant",
    "estimated_state": "observer",
    "u": "controller",
    "weights": "critic",
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
}

#: Log key -> signal name. Every variant logs these.
LOGGED = {
    "x": "state",
    "xhat": "estimated_state",
    "W": "weights",
    "Gamma": "gamma",
    "u": "u",
    "learning_condition": "learning_condition",
    "cost": "cost",
}


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
            condition = self.blocks["bellman"].learning_condition_of(logs["W"])
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
    certificate, which reports honestly whether they satisfy the LMI.
    """
    from ofrl_drake.design import ObserverDesign, design_observer

    system = system or resolve_system(scenario)
    o = scenario.observer
    box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
    if o.L is not None:
        return ObserverDesign.from_gains(
            system,
            box,
            scenario.input_bound,
            o.alpha,
            L=np.asarray(o.L, float),
            H=np.asarray(o.H, float),
            K=np.asarray(o.K, float),
            jacobian_method=o.jacobian_method,
            formulation=o.formulation,
        )
    return design_observer(
        system,
        box,
        scenario.input_bound,
        o.alpha,
        jacobian_method=o.jacobian_method,
        solver=o.solver,
        formulation=o.formulation,
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


def _default_block(slot: str, parts: ClosedLoopParts, symbolic: bool) -> System:
    s, c = parts.scenario, parts.scenario.critic
    if slot == "plant":
        if symbolic:
            return SymbolicPlant(parts.system, initial_state=s.x0)
        return ControlAffinePlant(parts.system, initial_state=s.x0)
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
        return CriticWeights(c.W0, c.kc)
    if slot == "gamma":
        return GammaGain(np.asarray(c.Gamma0, float), c.kc, c.beta)
    if slot == "bellman":
        return BellmanExtrapolator(parts.features, parts.r, s.input_bound, c.nu)
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
    ``g``; it starts from ``scenario.x0``, whose velocities must be zero.
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
    parts = ClosedLoopParts(scenario, system, basis, features, design, Q, r)
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
