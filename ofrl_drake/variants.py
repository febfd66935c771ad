"""Slot choices for ablations: which block fills each part of the closed loop.

A :class:`~ofrl_drake.scenario.VariantConfig` names one choice per slot::

    observer:   three_gain | linear_luenberger | drake_luenberger | true_state
    controller: learned | lqr | frozen_critic
    points:     grid | uniform | around_estimate
    gamma:      least_squares | constant

Each choice is a factory ``f(parts) -> {block_slot: System}`` registered in
:data:`VARIANT_FACTORIES`; :func:`~ofrl_drake.build_closed_loop` applies them
before explicit swaps. The baseline (``three_gain``, ``learned``, the
scenario's own ``points.kind``, ``least_squares``) builds the default blocks.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from pydrake.systems.framework import System

from ofrl_drake.errors import ScenarioError
from ofrl_drake.systems import CriticWeights, GammaGain

if TYPE_CHECKING:
    from ofrl_drake.diagram import ClosedLoopParts

__all__ = ["BASELINE", "VARIANT_FACTORIES", "register_variant", "variant_blocks"]

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


def _frozen_critic(parts: ClosedLoopParts) -> dict[str, System]:
    return {"critic": CriticWeights(parts.scenario.critic.W0, kc=0.0)}


def _constant_gamma(parts: ClosedLoopParts) -> dict[str, System]:
    return {"gamma": GammaGain(np.asarray(parts.scenario.critic.Gamma0, float), kc=0.0, beta=0.0)}


VARIANT_FACTORIES: dict[str, dict[str, Factory]] = {
    "observer": {"three_gain": _default},
    "controller": {"learned": _default, "frozen_critic": _frozen_critic},
    # Grid and uniform points are resolved from points.kind in the scenario.
    "points": {"grid": _default, "uniform": _default},
    "gamma": {"least_squares": _default, "constant": _constant_gamma},
}


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
