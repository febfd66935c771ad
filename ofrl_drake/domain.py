"""Prove that expressions are defined at every point of a box.

An interval enclosure (:mod:`ofrl_drake.interval`) of a function defined on
part of the real line only (``log``, ``sqrt``, ``asin``, ``acos``, a power with
a real exponent) holds where the function is defined, as in IEEE 1788. A
certificate over a box needs more: ``f``, ``g`` and their Jacobians must be
defined at every state of it, or the mean-value argument behind the observer's
error dynamics has nothing to stand on. A plant whose ``f`` is undefined on a
strip of the box thinner than the samples' spacing would otherwise get finite
certified bounds.

:func:`prove_defined` splits the boxes that
:meth:`~ofrl_drake.interval.ExpressionEvaluator.possibly_undefined` flags
until each is proven defined (enclosures overestimate, so a flag may be
false), shown undefined (a box wholly outside a function's domain, or a box
centre where an expression is not finite), or the budget of levels and boxes
runs out. Each flagged box is halved along the one axis that clears the most
of its halves, the widest (relative to the given box) among ties, so that a
thin undefined strip is cornered in about ``log2(width / strip)`` levels
whatever the dimension.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ofrl_drake.checks import point_text
from ofrl_drake.errors import OfrlError, WallTimeExceeded
from ofrl_drake.interval import ExpressionEvaluator, IntervalDomainError

__all__ = ["DefinedProof", "UndefinedOnBoxError", "prove_defined"]


class UndefinedOnBoxError(OfrlError):
    """Expressions are, or cannot be proven not to be, undefined somewhere in a box."""


@dataclass(frozen=True)
class DefinedProof:
    """How :func:`prove_defined` proved the expressions defined on the box.

    Attributes
    ----------
    levels : int
        Levels of halving needed (0: the whole box at once).
    boxes : int
        Boxes evaluated, the candidate halves included.
    """

    levels: int
    boxes: int


def _box_text(lo: np.ndarray, hi: np.ndarray) -> str:
    return f"[{point_text(lo, 6)}, {point_text(hi, 6)}]"


def _witness(
    evaluator: ExpressionEvaluator, lo: np.ndarray, hi: np.ndarray, names: Sequence[str]
) -> None:
    """Raise if an expression is not finite at the centre of a box (columns)."""
    centres = 0.5 * (lo + hi)
    values = evaluator(centres).reshape(-1, centres.shape[1])
    bad = ~np.isfinite(values)
    if bad.any():
        e, b = (int(i[0]) for i in np.nonzero(bad))
        raise UndefinedOnBoxError(
            f"{names[e]} is {values[e, b]} at x = {point_text(centres[:, b], 6)}, a state of "
            "the box: f and g must be defined (and finite) at every state of it. Shrink the box to "
            "exclude such states, or write f and g so that they are defined there."
        )


def prove_defined(
    evaluator: ExpressionEvaluator,
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    names: Sequence[str] | None = None,
    max_levels: int = 64,
    max_boxes: int = 4096,
    deadline: float | None = None,
) -> DefinedProof:
    """Prove every expression of ``evaluator`` defined at every point of a box.

    Parameters
    ----------
    evaluator : ExpressionEvaluator
        The expressions (``f``, ``g`` and the Jacobian entries, say).
    lower, upper : ndarray, shape (n,)
        The box.
    names : sequence of str, optional
        A name for each expression (flattened), used in the errors. Default:
        ``expression i``.
    max_levels : int
        Most levels of halving.
    max_boxes : int
        Most flagged boxes carried from one level to the next.
    deadline : float, optional
        A ``time.monotonic()`` instant after which no further level starts.

    Returns
    -------
    DefinedProof
        How many levels and boxes the proof took.

    Raises
    ------
    UndefinedOnBoxError
        If an expression is undefined on a part of the box (the message names
        a state or a sub-box), or the budget runs out with boxes still flagged
        (the message names the function, its argument's enclosure, and the
        sub-box they lie in).
    WallTimeExceeded
        If ``deadline`` passes with boxes still flagged.
    """
    lo = np.asarray(lower, dtype=float).reshape(-1, 1)
    hi = np.asarray(upper, dtype=float).reshape(-1, 1)
    n = lo.shape[0]
    size = int(np.prod(evaluator.shape))
    labels = list(names) if names is not None else [f"expression {i}" for i in range(size)]
    width = (hi - lo)[:, 0]
    scale = np.where(width > 0, width, 1.0)[:, None]
    try:
        flagged, reasons = evaluator.possibly_undefined(lo, hi)
    except IntervalDomainError as err:
        raise UndefinedOnBoxError(f"f or g is undefined on the whole box: {err}") from err
    boxes = 1
    for level in range(max_levels + 1):
        if level:
            # A half wholly outside a domain would hold its parent's centre, where
            # _witness found every expression finite: this cannot raise.
            flagged, reasons = evaluator.possibly_undefined(lo, hi)
        if not flagged.any():
            return DefinedProof(level, boxes)
        lo, hi = lo[:, flagged], hi[:, flagged]
        _witness(evaluator, lo, hi, labels)
        stop = None
        if level == max_levels:
            stop = f"after {max_levels} levels of halving"
        elif lo.shape[1] > max_boxes:
            stop = f"with {lo.shape[1]} boxes flagged (at most {max_boxes})"
        elif deadline is not None and time.monotonic() > deadline:
            raise WallTimeExceeded(
                f"f and g were not proven defined on the box {_box_text(lower, upper)} by the "
                f"deadline (max_wall_time, --max-wall): {lo.shape[1]} boxes still flagged, "
                f"the first by {reasons[0]}; allow more wall time or shrink the box.",
                step="definedness of f and g",
            )
        if stop is not None:
            raise UndefinedOnBoxError(
                f"f and g could not be proven defined at every state of the box "
                f"{_box_text(lower, upper)}: {stop}, {reasons[0]} on "
                f"{_box_text(lo.min(axis=1), hi.max(axis=1))} and no state found where it "
                "is not. Shrink the box away from where the function's argument meets the "
                "edge of its domain (after inexact roundings, a value at the edge cannot be "
                "told apart from one just beyond it), or write f and g so that they are "
                "defined on the whole box."
            )
        # Both halves of every flagged box along every axis, one evaluation.
        B = lo.shape[1]
        mid = 0.5 * (lo + hi)
        c_lo = np.repeat(lo[:, None, :], 2 * n, axis=1)  # (n, 2n, B): axis d, low then high
        c_hi = np.repeat(hi[:, None, :], 2 * n, axis=1)
        for d in range(n):
            c_hi[d, 2 * d] = mid[d]
            c_lo[d, 2 * d + 1] = mid[d]
        c_flags, _ = evaluator.possibly_undefined(c_lo.reshape(n, -1), c_hi.reshape(n, -1))
        boxes += 2 * n * B
        still = c_flags.reshape(n, 2, B).sum(axis=1)  # halves still flagged, (n, B)
        splittable = (mid > lo) & (mid < hi)
        relative = (hi - lo) / scale
        # Fewest halves still flagged first, then the widest relative side.
        score = np.where(splittable, still - relative / (1.0 + relative.max()), np.inf)
        axis = np.argmin(score, axis=0)
        cols = np.arange(B)
        low_lo, low_hi = lo.copy(), hi.copy()
        high_lo, high_hi = lo.copy(), hi.copy()
        low_hi[axis, cols] = mid[axis, cols]
        high_lo[axis, cols] = mid[axis, cols]
        lo = np.concatenate([low_lo, high_lo], axis=1)
        hi = np.concatenate([low_hi, high_hi], axis=1)
    raise AssertionError("unreachable: the last level returns or raises")
