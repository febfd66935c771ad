"""The slot registry: every block of the closed loop, and which factory builds it.

The closed loop has one block per name of :data:`SLOTS`. Four of them are
chosen by name, the same names in a scenario's ``variant:`` section, in an
ablation's ``variants:`` file, in :func:`register_variant` and as string swaps
of :func:`~ofrl_drake.build_closed_loop` (``observer="kalman"``):
:data:`VARIANT_FACTORIES` maps each such slot to its choices, the default
(:data:`BASELINE`) being an entry like any other::

    observer:   three_gain | linear_luenberger | drake_luenberger | kalman | true_state
    controller: learned | lqr | frozen_critic | constant
    points:     grid | uniform | around_estimate      (builds the bellman block)
    gamma:      least_squares | constant

A choice builds its slot's block (:data:`SLOT_BLOCKS`; ``points`` picks the
points of the ``bellman`` block) and may replace one of the blocks no slot
chooses, :data:`FIXED_BLOCKS` (``frozen_critic`` replaces the critic). What
each choice builds is described in :mod:`ofrl_drake.variants`, where the
factories are. :func:`slot_blocks` is the one place that turns the choices
into blocks.

This module sits below :mod:`ofrl_drake.scenario` (whose validator reads the
names) and :mod:`ofrl_drake.diagram` (which builds from the factories); it
imports neither.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from pydrake.systems.framework import System

import ofrl_drake.variants as variants
from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import PointFeatures
from ofrl_drake.errors import ScenarioError, SwapError
from ofrl_drake.learning import CriticSettings
from ofrl_drake.model import ControlAffineSystem

if TYPE_CHECKING:  # annotations only: the scenario and the wiring import this module
    from ofrl_drake.design import ObserverDesign
    from ofrl_drake.scenario import Scenario

__all__ = [
    "BASELINE",
    "FIXED_BLOCKS",
    "NEEDS_PARAMETERS",
    "SLOTS",
    "SLOT_BLOCKS",
    "VARIANT_FACTORIES",
    "Choice",
    "ClosedLoopParts",
    "chosen_design",
    "register_variant",
    "slot_blocks",
]

#: The blocks of the closed loop, in build order (the keys of ``ClosedLoop.blocks``).
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


@dataclass(frozen=True)
class ClosedLoopParts:
    """What a block factory may need to build a block.

    Attributes
    ----------
    scenario : Scenario
    system : ControlAffineSystem
        The model.
    basis : PolynomialBasis
    features : PointFeatures
        At the scenario's own points (``points.kind``).
    design : ObserverDesign or None
        The observer design: given to ``build_closed_loop``, or what the chosen
        observer needs (:attr:`Choice.design`); None if neither.
    Q, r : ndarray
        The state cost matrix and the input weights.
    critic : CriticSettings
        The learning law and gains in force.
    truth : ControlAffineSystem or None
        The plant simulated, when it is not the model.
    symbolic : bool
        Whether the plant, observer, controller and running cost are C++
        symbolic blocks (:func:`ofrl_drake.diagram.symbolic_blocks`).
    """

    scenario: Scenario
    system: ControlAffineSystem
    basis: PolynomialBasis
    features: PointFeatures
    design: ObserverDesign | None
    Q: np.ndarray
    r: np.ndarray
    critic: CriticSettings
    truth: ControlAffineSystem | None = None
    symbolic: bool = False


#: ``factory(parts) -> {block: System}``: a choice as :func:`register_variant` takes it.
Factory = Callable[[ClosedLoopParts], dict[str, System]]
#: ``builder(parts) -> System``: one block.
BlockFactory = Callable[[ClosedLoopParts], System]
#: ``design(scenario, system) -> ObserverDesign``.
DesignFactory = Callable[["Scenario", ControlAffineSystem], "ObserverDesign"]


@dataclass(frozen=True)
class Choice:
    """A registry entry whose blocks are known before it builds them.

    Calling it is the :data:`Factory` contract (``choice(parts)`` returns every
    block); :func:`slot_blocks` instead builds only the blocks that are not
    swapped, and computes the ``design`` only if one of them is built.

    Attributes
    ----------
    blocks : dict
        Block name (one of :data:`SLOTS`) -> ``builder(parts) -> System``.
    design : callable or None
        ``design(scenario, system)``: the observer design these blocks need,
        computed before they are built and reported as ``ClosedLoop.design``.
    """

    blocks: dict[str, BlockFactory]
    design: DesignFactory | None = None

    def __call__(self, parts: ClosedLoopParts) -> dict[str, System]:
        return {block: build(parts) for block, build in self.blocks.items()}


#: The block each chosen slot builds.
SLOT_BLOCKS = {
    "observer": "observer",
    "controller": "controller",
    "points": "bellman",
    "gamma": "gamma",
}

#: The blocks no slot chooses, each built one way (unless swapped or replaced by a choice).
FIXED_BLOCKS: dict[str, BlockFactory] = {
    "plant": variants.plant,
    "critic": variants.learning_critic,
    "policy": variants.policy,
    "running_cost": variants.running_cost,
}

#: Slot -> choice -> :class:`Choice` or :data:`Factory`. The one list of choices.
VARIANT_FACTORIES: dict[str, dict[str, Choice | Factory]] = {
    "observer": {
        "three_gain": Choice({"observer": variants.three_gain}, design=variants.design_for),
        "linear_luenberger": Choice(
            {"observer": variants.linear_luenberger}, design=variants.linear_observer_design
        ),
        "drake_luenberger": Choice({"observer": variants.drake_luenberger}),
        "kalman": Choice({"observer": variants.kalman}),
        "true_state": Choice({"observer": variants.true_state}),
    },
    "controller": {
        "learned": Choice({"controller": variants.learned_controller}),
        "lqr": Choice({"controller": variants.lqr}),
        "frozen_critic": Choice(
            {"controller": variants.learned_controller, "critic": variants.frozen_critic}
        ),
        "constant": Choice({"controller": variants.constant_controller}),
    },
    "points": {
        "grid": Choice({"bellman": variants.grid}),
        "uniform": Choice({"bellman": variants.uniform}),
        "around_estimate": Choice({"bellman": variants.around_estimate}),
    },
    "gamma": {
        "least_squares": Choice({"gamma": variants.least_squares_gamma}),
        "constant": Choice({"gamma": variants.constant_gamma}),
    },
}

#: The paper's method: every slot at its default entry. A scenario's ``points``
#: default is its own ``points.kind`` (:func:`~ofrl_drake.scenario.variant_choices`).
BASELINE = {
    "observer": "three_gain",
    "controller": "learned",
    "points": "grid",
    "gamma": "least_squares",
}

#: (slot, choice) pairs that need values from the scenario (``variant.constant_input``);
#: :func:`~ofrl_drake.ablation_grid.default_variants` leaves them out.
NEEDS_PARAMETERS = {("controller", "constant")}


def register_variant(slot: str, choice: str, factory: Choice | Factory) -> None:
    """Add ``choice`` to ``slot``: a scenario's ``variant.<slot>: <choice>`` then builds it.

    Parameters
    ----------
    slot : str
        One of :data:`VARIANT_FACTORIES` (``observer``, ``controller``, ``points``, ``gamma``).
    choice : str
        Its name in scenario files, ablation files and string swaps.
    factory : Choice or callable
        ``factory(parts)`` returns ``{block: System}``: the slot's own block
        (:data:`SLOT_BLOCKS`), and any of :data:`FIXED_BLOCKS` it replaces. A
        :class:`Choice` names its blocks up front, and may need an observer design.

    Raises
    ------
    ScenarioError
        If ``slot`` is not a slot with choices, ``choice`` is not a non-empty
        name, ``factory`` is not callable, or a :class:`Choice` lacks the
        slot's block or builds another slot's.
    """
    if slot not in VARIANT_FACTORIES:
        raise ScenarioError(f"variant.{slot}: unknown slot; slots are {sorted(VARIANT_FACTORIES)}.")
    if not isinstance(choice, str) or not choice:
        raise ScenarioError(f"variant.{slot}: a choice needs a non-empty name; got {choice!r}.")
    if not callable(factory):
        raise ScenarioError(
            f"variant.{slot}.{choice}: the factory must be callable, f(parts) -> "
            f"{{block: System}}; got {type(factory).__name__}."
        )
    if isinstance(factory, Choice):
        own = SLOT_BLOCKS[slot]
        allowed = {own, *FIXED_BLOCKS}
        if own not in factory.blocks or set(factory.blocks) - allowed:
            raise ScenarioError(
                f"variant.{slot}.{choice}: a Choice builds its {own!r} block and may replace "
                f"{sorted(FIXED_BLOCKS)}; got blocks {sorted(factory.blocks)}."
            )
    VARIANT_FACTORIES[slot][choice] = factory


def _entry(slot: str, choice: str) -> Choice | Factory:
    try:
        return VARIANT_FACTORIES[slot][choice]
    except KeyError:
        options = sorted(VARIANT_FACTORIES.get(slot, {}))
        raise ScenarioError(
            f"variant.{slot}: unknown choice {choice!r}; choose one of {options}."
        ) from None


def chosen_design(choices: Mapping[str, str], swapped: set[str]) -> DesignFactory | None:
    """The design the chosen entries need for the blocks they build (not ``swapped``).

    Raises
    ------
    SwapError
        If two chosen entries each need a design.
    """
    needs = [
        (slot, entry.design)
        for slot, entry in ((s, _entry(s, c)) for s, c in choices.items())
        if isinstance(entry, Choice) and entry.design is not None and set(entry.blocks) - swapped
    ]
    if len(needs) > 1:
        raise SwapError(
            f"variant: the choices of {[slot for slot, _ in needs]} each need an observer "
            "design; at most one may."
        )
    return needs[0][1] if needs else None


def slot_blocks(
    choices: Mapping[str, str], parts: ClosedLoopParts, swapped: set[str]
) -> dict[str, System]:
    """Every block but the ``swapped`` ones, built by the chosen entries and :data:`FIXED_BLOCKS`.

    Parameters
    ----------
    choices : mapping
        Slot -> choice, one per slot of :data:`VARIANT_FACTORIES`.
    parts : ClosedLoopParts
    swapped : set of str
        Blocks given to ``build_closed_loop``: not built here.

    Returns
    -------
    dict
        Block name -> System, for every block of :data:`SLOTS` not in ``swapped``.

    Raises
    ------
    ScenarioError
        If a choice is unknown.
    SwapError
        If a choice builds no block for its slot, a block that is not a fixed
        one, or a block another choice builds.
    """
    blocks: dict[str, System] = {}
    owner: dict[str, str] = {}
    for slot, choice in choices.items():
        entry = _entry(slot, choice)
        if isinstance(entry, Choice):
            built = {b: build(parts) for b, build in entry.blocks.items() if b not in swapped}
        else:  # builds all its blocks; the swapped ones are dropped
            built = _blocks_of(slot, choice, entry, parts)
        for block, system in built.items():
            if block in swapped:
                continue
            if block in owner:
                raise SwapError(
                    f"variant.{slot}: {choice!r} builds the {block} block, which "
                    f"variant.{owner[block]} builds too; choose one of them."
                )
            blocks[block] = system
            owner[block] = f"{slot} ({choice!r})"
    for block, build in FIXED_BLOCKS.items():
        if block not in blocks and block not in swapped:
            blocks[block] = build(parts)
    return blocks


def _blocks_of(
    slot: str, choice: str, factory: Factory, parts: ClosedLoopParts
) -> dict[str, System]:
    """The blocks a plain factory returns: its slot's own, and fixed blocks it replaces."""
    built = factory(parts)
    own = SLOT_BLOCKS[slot]
    if not isinstance(built, Mapping) or own not in built:
        raise SwapError(
            f"variant.{slot}: {choice!r} must return a mapping with its {own!r} block, "
            f"{{'{own}': System}}, plus any of {sorted(FIXED_BLOCKS)} it replaces; got {built!r}."
        )
    stray = sorted(set(built) - {own, *FIXED_BLOCKS})
    if stray:
        raise SwapError(
            f"variant.{slot}: {choice!r} returns a {stray[0]!r} block; a choice builds its "
            f"{own!r} block and may replace {sorted(FIXED_BLOCKS)}, no other."
        )
    return dict(built)
