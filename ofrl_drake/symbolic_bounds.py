"""Certified bounds of many symbolic expressions over a box, refined together.

For a plant given as symbolic ``f`` and ``g`` (not a multibody structure),
:func:`ofrl_drake.jacobian_bounds.jacobian_bounds` encloses every entry of
their Jacobians over the observer box. Each entry ``J`` is enclosed over a box
``X`` with centre ``c`` by the intersection of three forms, computed in one
pass over the expression graph of all entries
(:class:`~ofrl_drake.interval_taylor.TaylorEvaluator`, no symbolic
differentiation):

* the natural interval extension ``[J](X)``;
* the mean-value form ``J(c) + [grad J](X) (X - c)``;
* the second-order Taylor form ``J(c) + grad J(c) (X - c) + 1/2 (X - c)^T
  [Hess J](X) (X - c)``, whose overestimation shrinks with the cube of the box
  width, so that expressions whose variables repeat and cancel (a rotation's
  ``sin^2 + cos^2``) still converge.

:func:`certify_expressions` refines by branch and bound: a box stays open while
some entry's enclosure on it reaches more than the tolerance beyond that
entry's inner estimate (sampled values and the values at the centres visited);
open boxes are bisected along the variable with the largest share, relative
to the tolerance, of the unsettled entries' Taylor forms (all their sides at
once while there are few). An entry that is settled on every open box leaves the refinement (its
enclosures there join its bound), and the evaluator is rebuilt for the entries
left, so the work per box follows the entries still open, not all of them.
The result is the hull of each entry's enclosures over boxes that cover the
box: always sound, tight when the refinement converged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ofrl_drake.interval import Interval, bisect_boxes, halve_every_side
from ofrl_drake.interval_taylor import TaylorEvaluator, taylor_from_jets

__all__ = ["ExpressionEnclosure", "TaylorEncloser", "certify_expressions"]

#: While ``boxes * 2**d`` stays within this, every used side is halved at once.
_BATCH = 256
#: Boxes enclosed per call: at most this many interval values (entries x
#: derivative rows x boxes) per derivative array.
_VALUES = 2_000_000
_MIN_CHUNK, _MAX_CHUNK = 64, 4096
#: Under a deadline, boxes are enclosed in chunks of about this many seconds
#: (measured on the chunk before), so the clock is read often enough to stop
#: near it; the chunks change no enclosure (each box is enclosed alone).
_CHUNK_SECONDS = 0.5


class TaylorEncloser:
    """Enclosures of expressions over many boxes at once (module docstring).

    Parameters
    ----------
    expressions : sequence of Expression
        The ``E`` expressions (twice continuously differentiable where they
        are defined, of the kinds :data:`~ofrl_drake.interval_taylor.TAYLOR_KINDS`).
    variables : sequence of Variable
        The ``n`` state variables, in the order of the rows of the boxes.

    Attributes
    ----------
    used : ndarray of int
        The variables the expressions depend on (the others are not bisected).
    n_entries : int
        ``E``.
    chunk : int
        The most boxes enclosed in one evaluation (bounds the memory).

    Raises
    ------
    UnsupportedExpressionError
        If an expression uses a kind the Taylor form does not support.
    """

    def __init__(self, expressions: Any, variables: Any) -> None:
        from ofrl_drake.interval import ExpressionEvaluator

        self.variables = tuple(variables)
        used = ExpressionEvaluator(expressions, self.variables).variables_used()
        self.used = np.array(sorted({v for u in used for v in u}), dtype=int)
        self.taylor = TaylorEvaluator(expressions, self.variables, self.used)
        self.n_entries = len(used)
        L = self.used.size
        per_box = max(1, self.n_entries * (1 + L + L * (L + 1) // 2))
        self.chunk = int(np.clip(_VALUES // per_box, _MIN_CHUNK, _MAX_CHUNK))

    def enclose(
        self, lower: np.ndarray, upper: np.ndarray
    ) -> tuple[Interval, Interval, np.ndarray]:
        """Enclose every expression over each box, and at each box's centre.

        Parameters
        ----------
        lower, upper : ndarray, shape (n, B)
            ``B`` boxes.

        Returns
        -------
        boxes : Interval
            Shape ``(E, B)``: the natural form intersected with the mean-value
            and Taylor forms (the natural form alone where those do not hold).
        centres : Interval
            Shape ``(E, B)``: each expression at each box's centre (a few ulps
            wide; NaN-free, possibly infinite where undefined).
        spread : ndarray
            Shape ``(E, L, B)``: ``mag(h_l) (mag(dJ/dx_l(c)) + sum_m
            mag([d2J/dx_l dx_m](X)) mag(h_m))`` (``h = X - c``), the share of each
            used variable in the Taylor form's width.
        """
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        centre = 0.5 * (lower + upper)
        on_boxes = self.taylor.jet(lower, upper)
        at_centres = self.taylor.jet(centre, centre, order=1)
        natural = on_boxes.value
        if not self.used.size:
            return natural, at_centres.value, np.zeros((self.n_entries, 0, lower.shape[1]))
        with np.errstate(all="ignore"):
            h = Interval(
                np.nextafter(lower[self.used] - centre[self.used], -np.inf),
                np.nextafter(upper[self.used] - centre[self.used], np.inf),
            )
            mean_value = at_centres.value
            for a in range(self.used.size):
                mean_value = mean_value + on_boxes.gradient[:, a] * h[a][None]
            taylor = taylor_from_jets(self.taylor, on_boxes, at_centres, lower, upper)
            # Each variable's share of the Taylor form's width: the first-order term
            # mag(dJ/dx_l(c)) mag(h_l) and mag(h_l) sum_m mag(H_lm(X)) mag(h_m).
            spread = at_centres.gradient.mag * h.mag[None]
            hessian = on_boxes.hessian.mag
            for p, (a, b) in enumerate(self.taylor.pairs):
                w = hessian[:, p] * (h.mag[a] * h.mag[b])[None]
                spread[:, a] += w
                if a != b:
                    spread[:, b] += w
        ok = on_boxes.valid & at_centres.valid
        lo = np.maximum(natural.lo, np.where(ok, np.maximum(mean_value.lo, taylor.lo), -np.inf))
        hi = np.minimum(natural.hi, np.where(ok, np.minimum(mean_value.hi, taylor.hi), np.inf))
        spread = np.where(ok & np.isfinite(spread), spread, np.inf)
        return Interval(lo, hi), at_centres.value, spread


@dataclass(frozen=True, eq=False)
class ExpressionEnclosure:
    """The outcome of :func:`certify_expressions`.

    Attributes
    ----------
    lo, hi : ndarray, shape (E,)
        Sound bounds of each expression over the box.
    converged : bool
        Every entry was settled within its tolerance.
    stop : str
        ``"converged"``, ``"max_boxes"`` or ``"max_wall_time"``.
    boxes : int
        Boxes enclosed (counted once per box, whatever the entries evaluated).
    seconds : float
        Wall time of the refinement.
    open_entries : ndarray of int
        The entries not settled when the refinement stopped (empty if it converged).
    """

    lo: np.ndarray
    hi: np.ndarray
    converged: bool
    stop: str
    boxes: int
    seconds: float
    open_entries: np.ndarray


def _split_side(out: np.ndarray, spread: np.ndarray, slack: np.ndarray, used: np.ndarray):
    """The side to bisect in each box: the used variable with the largest share,
    relative to the tolerance, of the Taylor forms of the entries not settled (``out``)."""
    share = np.where(out[:, None], spread / slack[:, :, None], 0.0).sum(axis=0)  # (L, B)
    share = np.where(np.isfinite(share), share, np.finfo(float).max)
    return used[np.argmax(share, axis=0)]


def certify_expressions(
    expressions: Any,
    variables: Any,
    lower: np.ndarray,
    upper: np.ndarray,
    inner_lo: np.ndarray,
    inner_hi: np.ndarray,
    *,
    tol: float,
    rtol: float,
    max_boxes: int,
    deadline: float | None = None,
) -> ExpressionEnclosure:
    """Branch and bound on the box ``[lower, upper]`` for many expressions together.

    Parameters
    ----------
    expressions : sequence of Expression
        The ``E`` expressions (see :class:`TaylorEncloser`).
    variables : sequence of Variable
        The state variables, in the order of the rows of the box.
    lower, upper : ndarray, shape (n,)
        The box.
    inner_lo, inner_hi : ndarray, shape (E,)
        Inner estimates (sampled minima and maxima); improved with the values
        at the centres visited.
    tol, rtol : float
        An entry is settled on a box when its enclosure there reaches at most
        ``max(tol, rtol * (inner_hi - inner_lo))`` beyond its inner estimate.
    max_boxes : int
        The most boxes enclosed.
    deadline : float, optional
        A ``time.monotonic()`` after which no new batch of boxes is started.

    Returns
    -------
    ExpressionEnclosure
        Always sound: each entry's bound is the hull of its enclosures over
        boxes that cover ``[lower, upper]``.

    Raises
    ------
    UnsupportedExpressionError
        If an expression uses a kind the Taylor form does not support.
    """
    start = time.monotonic()
    exprs = list(expressions)
    E = len(exprs)
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    inner_lo = np.array(inner_lo, dtype=float)
    inner_hi = np.array(inner_hi, dtype=float)
    out_lo, out_hi = np.full(E, np.inf), np.full(E, -np.inf)
    current = np.arange(E)
    encloser = TaylorEncloser(exprs, variables)
    lo, hi = lower[:, None].copy(), upper[:, None].copy()
    parents: tuple[np.ndarray, np.ndarray] | None = None  # open entries' hull on the boxes split
    evaluated = 0
    step = encloser.chunk  # boxes per call; under a deadline, set from the time of the last

    def finish(converged: bool, stop: str, *extra: tuple[np.ndarray, np.ndarray]):
        for e_lo, e_hi in extra:  # hulls over ``current``
            out_lo[current] = np.minimum(out_lo[current], e_lo)
            out_hi[current] = np.maximum(out_hi[current], e_hi)
        return ExpressionEnclosure(
            out_lo.copy(),
            out_hi.copy(),
            converged,
            stop,
            evaluated,
            time.monotonic() - start,
            np.array([] if converged else current, dtype=int),
        )

    while True:
        if not current.size:
            return finish(True, "converged")
        C = current.size
        level_lo, level_hi = np.full(C, np.inf), np.full(C, -np.inf)
        keep_lo, keep_hi, keep_spread, keep_enc_lo, keep_enc_hi = [], [], [], [], []
        s, step = 0, min(step, encloser.chunk)
        while s < lo.shape[1]:
            if parents is not None and deadline is not None and time.monotonic() > deadline:
                # The boxes not enclosed yet lie in their parents: use the parents' hull.
                return finish(False, "max_wall_time", parents, (level_lo, level_hi))
            b_lo, b_hi = lo[:, s : s + step], hi[:, s : s + step]
            began = time.monotonic()
            enc, at_c, spread = encloser.enclose(b_lo, b_hi)
            B = b_lo.shape[1]
            s += B
            evaluated += B
            if deadline is not None:  # a chunk takes at most about _CHUNK_SECONDS
                per_box = max(time.monotonic() - began, 1e-9) / B
                step = int(np.clip(_CHUNK_SECONDS / per_box, 1, encloser.chunk))
            # at_c.hi >= J(c) >= min J and at_c.lo <= max J: inner estimates.
            c_hi = np.where(np.isfinite(at_c.hi), at_c.hi, np.inf).min(axis=1)
            c_lo = np.where(np.isfinite(at_c.lo), at_c.lo, -np.inf).max(axis=1)
            inner_lo[current] = np.minimum(inner_lo[current], c_hi)
            inner_hi[current] = np.maximum(inner_hi[current], c_lo)
            level_lo = np.minimum(level_lo, enc.lo.min(axis=1))
            level_hi = np.maximum(level_hi, enc.hi.max(axis=1))
            keep_lo.append(b_lo)
            keep_hi.append(b_hi)
            keep_enc_lo.append(enc.lo)
            keep_enc_hi.append(enc.hi)
            keep_spread.append(spread)
        enc_lo, enc_hi = np.concatenate(keep_enc_lo, axis=1), np.concatenate(keep_enc_hi, axis=1)
        lo, hi = np.concatenate(keep_lo, axis=1), np.concatenate(keep_hi, axis=1)
        spread = np.concatenate(keep_spread, axis=2)
        slack = np.maximum(tol, rtol * (inner_hi[current] - inner_lo[current]))[:, None]
        out = (enc_lo < inner_lo[current, None] - slack) | (
            enc_hi > inner_hi[current, None] + slack
        )
        active = out.any(axis=0)
        # Boxes where every entry is settled, and entries settled on every box left.
        done = ~active
        if done.any():
            out_lo[current] = np.minimum(out_lo[current], enc_lo[:, done].min(axis=1))
            out_hi[current] = np.maximum(out_hi[current], enc_hi[:, done].max(axis=1))
        leaving = ~out[:, active].any(axis=1)
        if leaving.any() and active.any():
            gone = current[leaving]
            out_lo[gone] = np.minimum(out_lo[gone], enc_lo[leaving][:, active].min(axis=1))
            out_hi[gone] = np.maximum(out_hi[gone], enc_hi[leaving][:, active].max(axis=1))
        if not active.any():
            return finish(True, "converged")
        # The open entries' hull over the open boxes: their bound if the budget ends here.
        stay = ~leaving
        open_lo = enc_lo[stay][:, active].min(axis=1)
        open_hi = enc_hi[stay][:, active].max(axis=1)
        split = _split_side(
            out[stay][:, active], spread[stay][..., active], slack[stay], encloser.used
        )
        lo, hi = lo[:, active], hi[:, active]
        if leaving.any():
            current = current[stay]
            encloser = TaylorEncloser([exprs[e] for e in current], variables)
        n_active, used = lo.shape[1], encloser.used
        if not used.size:  # constant expressions: nothing to bisect, rounding is all there is
            return finish(True, "converged", (open_lo, open_hi))
        children = 2**used.size if n_active * 2**used.size <= _BATCH else 2
        if evaluated + children * n_active > max_boxes:
            return finish(False, "max_boxes", (open_lo, open_hi))
        if deadline is not None and time.monotonic() > deadline:
            return finish(False, "max_wall_time", (open_lo, open_hi))
        if children > 2:
            lo, hi = halve_every_side(lo, hi, used)
        else:
            lo, hi = bisect_boxes(lo, hi, split)
        parents = (open_lo, open_hi)
