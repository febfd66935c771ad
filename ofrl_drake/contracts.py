"""The slot contracts: what the loop may ask of a block beyond its ports.

A closed loop's slots (``plant``, ``observer``, ``critic``, ``bellman``, ...)
take any Drake ``System`` with the slot's named ports. A few capabilities are
asked for by name on top of the ports; each is a :class:`typing.Protocol`
here, so that the wiring and the simulation ask "does this block offer it?"
(``isinstance(block, CertifiedObserver)``) and never "is it one of ours?":

* :class:`CertifiedObserver`: ``observer_certificate()``, what an observer
  block certifies (:func:`ofrl_drake.observer_certificate.certificate_of`);
* :class:`LearningConditionSource`: ``learning_condition_of(W)``, a
  ``bellman`` block's ``learning_condition`` output for logged weights;
* :class:`ContextInitializer`: ``initialize_context(context)``, a block whose
  context needs more than its default state (a multibody plant's);
* :class:`HoldStarter`: ``start_holds(context)``, a block with a sample and
  hold that starts at its input's value once the state is set;
* :class:`PlantStateSetter`, :class:`EstimateSetter`, :class:`WeightsSetter`,
  :class:`PolicyWeightsSetter`, :class:`InitialGammaSetter`: write ``x``,
  ``xhat``, the critic's weights, the policy's weights or ``Gamma(0)`` into the
  block's own context (how a run starts the loop,
  :meth:`ofrl_drake.diagram.ClosedLoop.set_initial_values`).

All are ``runtime_checkable``: ``isinstance`` checks that the methods exist,
not their signatures (the annotations state those for a type checker).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:  # annotations only
    from pydrake.systems.framework import Context

    from ofrl_drake.observer_certificate import ObserverCertificate

__all__ = [
    "CertifiedObserver",
    "ContextInitializer",
    "EstimateSetter",
    "HoldStarter",
    "InitialGammaSetter",
    "LearningConditionSource",
    "PlantStateSetter",
    "PolicyWeightsSetter",
    "WeightsSetter",
]


@runtime_checkable
class CertifiedObserver(Protocol):
    """An observer block that reports what it certifies, and where."""

    def observer_certificate(self) -> ObserverCertificate:
        """The design (or local certificate) the block runs and its box."""
        ...


@runtime_checkable
class LearningConditionSource(Protocol):
    """A ``bellman`` block that can recompute its ``learning_condition`` output."""

    def learning_condition_of(
        self, weights: np.ndarray, context: Context | None = None
    ) -> np.ndarray:
        """The output for many policy weights at once, ``(T, L)`` -> ``(T,)``.

        At the parameters in ``context``, the block's own (its defaults without one).
        """
        ...


@runtime_checkable
class ContextInitializer(Protocol):
    """A block whose context must be set up beyond its declared default state."""

    def initialize_context(self, context: Context) -> None:
        """Set up ``context``, this block's own context, before a run."""
        ...


@runtime_checkable
class HoldStarter(Protocol):
    """A block whose sample-and-hold must start at its input's value."""

    def start_holds(self, context: Context) -> None:
        """Start the holds in ``context``, this block's own, once it holds the initial state."""
        ...


@runtime_checkable
class PlantStateSetter(Protocol):
    """A plant block whose state ``x`` can be written into its context."""

    def set_state(self, context: Context, x: ArrayLike) -> None:
        """Set the state to ``x`` in ``context``, this block's own context."""
        ...


@runtime_checkable
class EstimateSetter(Protocol):
    """An observer block whose estimate ``xhat`` can be written into its context."""

    def set_estimated_state(self, context: Context, xhat: ArrayLike) -> None:
        """Set the estimate to ``xhat`` in ``context``, this block's own context."""
        ...


@runtime_checkable
class WeightsSetter(Protocol):
    """A critic block whose weights can be written into its context."""

    def set_weights(self, context: Context, W: ArrayLike) -> None:
        """Set the weights to ``W`` in ``context``, this block's own context."""
        ...


@runtime_checkable
class PolicyWeightsSetter(Protocol):
    """A policy block whose policy in force can be written into its context."""

    def set_policy_weights(self, context: Context, W: ArrayLike) -> None:
        """Put the policy of weights ``W`` in force in ``context``, this block's own context."""
        ...


@runtime_checkable
class InitialGammaSetter(Protocol):
    """A Gamma block whose ``Gamma(0)`` can be written into its context."""

    def set_initial_gamma(self, context: Context, gamma: ArrayLike) -> None:
        """Start from ``Gamma(0) = gamma`` in ``context``, this block's own context."""
        ...
