"""What an observer block certifies: the one question ``simulate()`` asks it.

Every observer block answers ``observer_certificate() -> ObserverCertificate``
(:class:`ofrl_drake.contracts.CertifiedObserver`): the design (or local
certificate) it runs, as reported in ``summary.json``, and the box on which it
holds, which x and xhat are checked against. The simulation asks
:func:`certificate_of` and never looks at the block's class; a block without
the method (a user's own) certifies nothing.

Kinds:

``"design"``
    An LMI design whose certificate holds on one fixed :attr:`~ObserverCertificate.box`.
``"scheduled"``
    Designs re-solved along the run; the box of the design in force is logged
    sample by sample on the block's ``certified_box`` output.
``"local"``
    A certificate of the linearized error dynamics only; no box.
``"none"``
    Nothing certified (the true state, or a block without a design).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ofrl_drake.contracts import CertifiedObserver
from ofrl_drake.errors import ModelError
from ofrl_drake.jacobian_bounds import Box

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = ["KINDS", "ObserverCertificate", "certificate_of"]

KINDS = ("design", "scheduled", "local", "none")


@dataclass(frozen=True)
class ObserverCertificate:
    """What an observer block certifies, and where.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    design : dict or None
        The design or local certificate, JSON-ready (``summary.json`` →
        ``observer_design``); None when nothing is certified.
    box : Box or None
        The fixed box x and xhat must stay in (kind ``"design"`` only).
    note : str or None
        Why there is no fixed box, as the validity report words it.
    """

    kind: str
    design: dict[str, Any] | None = None
    box: Box | None = None
    note: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ModelError(f"certificate kind must be one of {KINDS}; got {self.kind!r}.")
        if (self.box is not None) != (self.kind == "design"):
            raise ModelError(
                f"a certificate of kind {self.kind!r} "
                + ("needs a box." if self.kind == "design" else "has no fixed box.")
            )

    @classmethod
    def none(cls, block_name: str) -> ObserverCertificate:
        """Nothing certified by the observer block ``block_name``."""
        return cls(
            "none",
            note=(
                f"no observer design (observer block {block_name}): box checks not "
                "applicable; only |u_k| <= lambda_bar was checked"
            ),
        )

    @classmethod
    def of_design(cls, design: ObserverDesign | None, block_name: str) -> ObserverCertificate:
        """The certificate of an observer block running ``design``'s gains.

        ``design`` is an ``ObserverDesign`` (kind ``"design"``, with its box) or
        None (nothing certified by the block ``block_name``).
        """
        if design is None:
            return cls.none(block_name)
        return cls("design", design=design.to_dict(), box=design.box)


def certificate_of(block: object) -> ObserverCertificate:
    """``block.observer_certificate()``, or "none" for a block without one.

    Raises
    ------
    ModelError
        If the method returns something other than an :class:`ObserverCertificate`.
    """
    if not isinstance(block, CertifiedObserver) or not callable(block.observer_certificate):
        return ObserverCertificate.none(type(block).__name__)
    cert: object = block.observer_certificate()
    if not isinstance(cert, ObserverCertificate):
        raise ModelError(
            f"{type(block).__name__}.observer_certificate() must return an "
            f"ObserverCertificate; got {type(cert).__name__}."
        )
    return cert
