"""Branch and bound over boxes: the one refinement behind every certified bound.

Certified Jacobian bounds (:mod:`ofrl_drake.jacobian_bounds`) enclose ``E``
entries (functions of the state) over a box. An *encloser* (:class:`Encloser`)
encloses every entry over many boxes at once and at each box's centre; the
three enclosers are :class:`~ofrl_drake.multibody_bounds.MultibodyJacobianEncloser`
(multibody plants), :class:`~ofrl_drake.symbolic_bounds.TaylorEncloser` (symbolic
entries) and the per-entry one of :mod:`ofrl_drake.jacobian_bounds`. One
function, :func:`refine`, turns any of them into bounds:

1. Enclose the open boxes, a chunk (``encloser.chunk`` boxes) at a time.
2. Improve each entry's inner estimate ``[inner_lo, inner_hi]`` (sampled
   values) with its values at the box centres: ``h(c)`` is a value of ``h``.
3. Settle, chunk by chunk, every box on which each entry's enclosure reaches at
   most ``slack = max(tol, rtol * (inner_hi - inner_lo))`` beyond the inner
   estimate; its enclosures join the bounds, and the box is dropped.
4. Split the boxes left: every used side at once, as many times over as
   keeps the children within :data:`_BATCH` boxes and within what is left of
   ``max_boxes`` (one evaluation costs about the same for a few hundred boxes
   as for one, so the first level after the whole box goes straight to a
   grid of up to :data:`_BATCH` boxes instead of passing through 4, 16, 64,
   ... boxes in 2-d), else each box in two, along the variable that adds most
   width, relative to the slack, to the entries not settled (the encloser's
   ``spread``), or, without a spread, along its side widest relative to the box.
5. Stop when no box is left (converged), or when the next level would exceed
   ``max_boxes`` or the ``deadline`` has passed.

Soundness: every point of the box lies in a box that was settled, is still
open, or (when the clock stops a level midway) was not enclosed yet and lies in
its parent. The bound of each entry is the hull of the enclosures of exactly
those boxes (the parents' hull for the last kind), so it always holds.

Memory stays bounded: only one chunk's enclosures are held at a time; a level
keeps only the open boxes' corners and split sides. Under a deadline, each
chunk is enclosed in slices that take about :data:`_CHUNK_SECONDS` (measured on
the slice before), so the clock is read often; each box is enclosed alone and
settling is per chunk, so the slices change no bound.

An encloser that can be restricted to some of its entries
(:class:`RestrictableEncloser`) lets the entries settled on every open box
leave the refinement at the end of a level (their bound is then their hull
over those boxes), so the work per box follows the entries still open. Other
enclosers keep enclosing every entry, which may tighten the entries settled
early further.

The module is plain numpy.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from ofrl_drake.interval import Interval

__all__ = [
    "STOPS",
    "Encloser",
    "Refinement",
    "RestrictableEncloser",
    "bisect_boxes",
    "halve_every_side",
    "refine",
]

#: Why :func:`refine` stopped.
STOPS = ("converged", "max_boxes", "max_wall_time")
#: While ``open boxes * 2**d`` stays within this, every used side is halved at once
#: (as many times over as stays within it).
_BATCH = 256
#: Under a deadline, boxes are enclosed in slices of about this many seconds.
_CHUNK_SECONDS = 0.5


class Encloser(Protocol):
    """Interval enclosures of ``E`` entries over many boxes at once.

    Attributes
    ----------
    used : ndarray of int
        The state variables the entries depend on (the others are not split).
    n_entries : int
        ``E``.
    chunk : int
        The most boxes enclosed and settled together (bounds the memory).
    """

    used: np.ndarray
    n_entries: int
    chunk: int

    def enclose(
        self, lower: np.ndarray, upper: np.ndarray
    ) -> tuple[Interval, Interval, np.ndarray | None]:
        """Enclose every entry over the boxes ``[lower[:, b], upper[:, b]]`` and at their centres.

        Parameters
        ----------
        lower, upper : ndarray, shape (n, B)
            The corners of ``B`` boxes.

        Returns
        -------
        boxes : Interval
            Shape ``(E, B)``: each entry over each box (sound).
        centres : Interval
            Shape ``(E, B)``: each entry at each box's centre (NaN-free; an
            infinite end where the entry is undefined there).
        spread : ndarray or None
            Shape ``(E, L, B)`` with ``L = len(used)``: the width each used
            variable adds to each entry's enclosure (the side to split is the
            one that adds most); None to split along the widest side.
        """
        ...


@runtime_checkable
class RestrictableEncloser(Encloser, Protocol):
    """An :class:`Encloser` that can drop entries (their work with them)."""

    def restrict(self, entries: np.ndarray) -> Encloser:
        """The encloser of the entries ``entries`` (positions in this one), in that order."""
        ...


@dataclass(frozen=True, eq=False)
class Refinement:
    """The outcome of :func:`refine`.

    Attributes
    ----------
    lo, hi : ndarray, shape (E,)
        Sound bounds of each entry over the box (read-only; possibly infinite
        when the budget ran out before an enclosure became finite).
    converged : bool
        Every entry was settled within its slack on every box.
    stop : str
        One of :data:`STOPS`.
    boxes : int
        Boxes enclosed (once per box, whatever the number of entries).
    seconds : float
        Wall time of the refinement.
    open_entries : ndarray of int
        The entries not settled when the refinement stopped (empty if it converged).
    finest : float
        The smallest side reached, relative to the box (``1``: not split).
    """

    lo: np.ndarray
    hi: np.ndarray
    converged: bool
    stop: str
    boxes: int
    seconds: float
    open_entries: np.ndarray
    finest: float

    @property
    def budget(self) -> str:
        """What the refinement spent and why it stopped, for messages."""
        return f"{self.boxes} boxes in {self.seconds:.3g} s, stopped by {self.stop}"


# Boxes are held column-wise: ``lo``, ``hi`` of shape (d, B) for B boxes.
def bisect_boxes(
    lo: np.ndarray, hi: np.ndarray, split: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Split box ``b`` in two along its side ``split[b]``: ``2 B`` boxes, lower halves first."""
    cols = np.arange(lo.shape[1])
    mid = 0.5 * (lo[split, cols] + hi[split, cols])
    lo_right = lo.copy()
    lo_right[split, cols] = mid
    hi_left = hi.copy()
    hi_left[split, cols] = mid
    return np.concatenate([lo, lo_right], axis=1), np.concatenate([hi_left, hi], axis=1)


def halve_every_side(
    lo: np.ndarray, hi: np.ndarray, used: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Split each box into ``2**d`` boxes, halving each of its ``d`` sides in ``used``."""
    for j in used:
        mid = 0.5 * (lo[j] + hi[j])
        lo_right = lo.copy()
        lo_right[j] = mid
        hi_left = hi.copy()
        hi_left[j] = mid
        lo, hi = np.concatenate([lo, lo_right], axis=1), np.concatenate([hi_left, hi], axis=1)
    return lo, hi


def _halvings(n_open: int, d: int, room: int) -> int:
    """How many times to halve every one of the ``d`` used sides of ``n_open`` boxes.

    The most ``k`` with ``n_open * 2**(k d) <= room`` (0: bisect each box instead).
    """
    k = 0
    while n_open * 2 ** ((k + 1) * d) <= room:
        k += 1
    return k


def _split_side(
    out: np.ndarray,
    spread: np.ndarray | None,
    slack: np.ndarray,
    used: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    width: np.ndarray,
) -> np.ndarray:
    """The side to split in each box ``(lo, hi)``, shape (B,).

    With a ``spread``: the used variable with the largest share, relative to
    the ``slack``, of the width of the entries not settled (``out``, shape
    (E, B)); where some shares are not finite (an enclosure that could not be
    formed, e.g. a mass matrix not proven invertible on the box), the widest
    of those sides. Without: the used side widest relative to the whole box
    ``width``.
    """
    relative = (hi[used] - lo[used]) / width[used, None]  # (L, B)
    if spread is None:
        return used[np.argmax(relative, axis=0)]
    share = np.where(out[:, None], spread / slack[:, :, None], 0.0).sum(axis=0)  # (L, B)
    unknown = ~np.isfinite(share)
    finite_pick = np.argmax(np.where(unknown, 0.0, share), axis=0)
    # A tie at infinity went to the first variable: the boxes were cut along it alone.
    unknown_pick = np.argmax(np.where(unknown, relative, -1.0), axis=0)
    return used[np.where(unknown.any(axis=0), unknown_pick, finite_pick)]


@dataclass
class _Chunk:
    """One chunk's enclosures (entries x boxes); fewer boxes if the clock stopped it."""

    lo: np.ndarray
    hi: np.ndarray
    centre_lo: np.ndarray  # per box, a lower end of each entry's value at the centre
    centre_hi: np.ndarray
    spread: np.ndarray | None
    late: bool  # the deadline passed before every box of the chunk was enclosed


class _Slicer:
    """Encloses a chunk in slices timed to about :data:`_CHUNK_SECONDS` under a deadline."""

    def __init__(self, deadline: float | None, chunk: int) -> None:
        self.deadline = deadline
        self.step = chunk  # boxes per slice; under a deadline, set from the last slice's time

    def enclose(self, encloser: Encloser, lo: np.ndarray, hi: np.ndarray, may_stop: bool) -> _Chunk:
        """Enclose the boxes ``(lo, hi)``; with ``may_stop``, stop at the deadline."""
        parts = []
        s = 0
        late = False
        while s < lo.shape[1]:
            if may_stop and self.deadline is not None and time.monotonic() > self.deadline:
                late = True
                break
            step = min(self.step, encloser.chunk)
            began = time.monotonic()
            parts.append(encloser.enclose(lo[:, s : s + step], hi[:, s : s + step]))
            B = min(step, lo.shape[1] - s)
            s += B
            if self.deadline is not None:
                per_box = max(time.monotonic() - began, 1e-9) / B
                self.step = int(np.clip(_CHUNK_SECONDS / per_box, 1, encloser.chunk))
        E = encloser.n_entries
        if not parts:
            empty = np.empty((E, 0))
            return _Chunk(empty, empty, empty, empty, None, late)
        if len(parts) == 1:  # no copies: the usual case without a deadline
            boxes, centres, spread = parts[0]
            return _Chunk(boxes.lo, boxes.hi, centres.lo, centres.hi, spread, late)
        spreads = [p[2] for p in parts if p[2] is not None]
        return _Chunk(
            np.concatenate([p[0].lo for p in parts], axis=1),
            np.concatenate([p[0].hi for p in parts], axis=1),
            np.concatenate([p[1].lo for p in parts], axis=1),
            np.concatenate([p[1].hi for p in parts], axis=1),
            np.concatenate(spreads, axis=2) if len(spreads) == len(parts) else None,
            late,
        )


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def refine(
    encloser: Encloser,
    lower: np.ndarray,
    upper: np.ndarray,
    inner_lo: np.ndarray,
    inner_hi: np.ndarray,
    *,
    tol: float,
    rtol: float,
    max_boxes: int,
    deadline: float | None = None,
) -> Refinement:
    """Branch and bound on the box ``[lower, upper]`` for every entry of ``encloser``.

    Parameters
    ----------
    encloser : Encloser
        The entries' enclosures (a :class:`RestrictableEncloser` lets settled
        entries leave, module docstring).
    lower, upper : ndarray, shape (n,)
        The box.
    inner_lo, inner_hi : ndarray, shape (E,)
        Inner estimates (sampled minima and maxima); improved with the values
        at the centres visited.
    tol, rtol : float
        An entry is settled on a box when its enclosure there reaches at most
        ``max(tol, rtol * (inner_hi - inner_lo))`` beyond its inner estimate;
        a box is settled when every entry is.
    max_boxes : int
        The most boxes enclosed.
    deadline : float, optional
        A ``time.monotonic()`` after which no further boxes are enclosed (the
        first box always is).

    Returns
    -------
    Refinement
        Always sound: each entry's bound is the hull of its enclosures over
        boxes that cover ``[lower, upper]``.
    """
    start = time.monotonic()
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    width = upper - lower
    sides = np.flatnonzero(width > 0)
    E = encloser.n_entries
    inner_lo = np.array(inner_lo, dtype=float)
    inner_hi = np.array(inner_hi, dtype=float)
    bound_lo, bound_hi = np.full(E, np.inf), np.full(E, -np.inf)  # settled boxes' hull
    current = np.arange(E)  # the entries ``encloser`` encloses, in its order
    open_entries = current  # those not yet settled on every open box
    lo, hi = lower[:, None].copy(), upper[:, None].copy()
    parents: tuple[np.ndarray, np.ndarray] | None = None  # hull over the boxes just split
    slicer = _Slicer(deadline, encloser.chunk)
    evaluated = 0
    finest = 1.0

    def finish(converged: bool, stop: str, *hulls: tuple[np.ndarray, np.ndarray]) -> Refinement:
        """The bounds: the settled hull joined with ``hulls`` (over ``current``)."""
        out_lo, out_hi = bound_lo.copy(), bound_hi.copy()
        for h_lo, h_hi in hulls:
            out_lo[current] = np.minimum(out_lo[current], h_lo)
            out_hi[current] = np.maximum(out_hi[current], h_hi)
        return Refinement(
            _frozen(out_lo),
            _frozen(out_hi),
            converged,
            stop,
            evaluated,
            time.monotonic() - start,
            np.array([] if converged else open_entries, dtype=int),
            finest,
        )

    while True:
        # One level: enclose and settle the open boxes chunk by chunk.
        C = current.size
        level_lo, level_hi = np.full(C, np.inf), np.full(C, -np.inf)  # the boxes left open
        still_open = np.zeros(C, dtype=bool)  # entries not settled on some box left open
        keep_lo, keep_hi, keep_split = [], [], []
        for s in range(0, lo.shape[1], encloser.chunk):
            b_lo, b_hi = lo[:, s : s + encloser.chunk], hi[:, s : s + encloser.chunk]
            enc = slicer.enclose(encloser, b_lo, b_hi, may_stop=parents is not None)
            evaluated += enc.lo.shape[1]
            if enc.late:
                # The boxes not enclosed yet lie in their parents: use the parents' hull.
                assert parents is not None
                part = (enc.lo.min(axis=1, initial=np.inf), enc.hi.max(axis=1, initial=-np.inf))
                return finish(False, "max_wall_time", parents, (level_lo, level_hi), part)
            # centre_hi >= h(c) >= min h and centre_lo <= max h: inner estimates.
            c_hi = np.where(np.isfinite(enc.centre_hi), enc.centre_hi, np.inf).min(axis=1)
            c_lo = np.where(np.isfinite(enc.centre_lo), enc.centre_lo, -np.inf).max(axis=1)
            inner_lo[current] = np.minimum(inner_lo[current], c_hi)
            inner_hi[current] = np.maximum(inner_hi[current], c_lo)
            slack = np.maximum(tol, rtol * (inner_hi[current] - inner_lo[current]))[:, None]
            out = (enc.lo < inner_lo[current, None] - slack) | (
                enc.hi > inner_hi[current, None] + slack
            )
            active = out.any(axis=0)
            if (~active).any():
                bound_lo[current] = np.minimum(bound_lo[current], enc.lo[:, ~active].min(axis=1))
                bound_hi[current] = np.maximum(bound_hi[current], enc.hi[:, ~active].max(axis=1))
            if active.any():
                level_lo = np.minimum(level_lo, enc.lo[:, active].min(axis=1))
                level_hi = np.maximum(level_hi, enc.hi[:, active].max(axis=1))
                still_open |= out[:, active].any(axis=1)
                keep_lo.append(b_lo[:, active])
                keep_hi.append(b_hi[:, active])
                spread = None if enc.spread is None else enc.spread[..., active]
                keep_split.append(
                    _split_side(
                        out[:, active],
                        spread,
                        slack,
                        encloser.used,
                        b_lo[:, active],
                        b_hi[:, active],
                        width,
                    )
                )
        if not keep_lo:
            return finish(True, "converged")
        lo, hi = np.concatenate(keep_lo, axis=1), np.concatenate(keep_hi, axis=1)
        split = np.concatenate(keep_split)
        open_entries = current[still_open]
        if isinstance(encloser, RestrictableEncloser) and not still_open.all():
            # Entries settled on every open box leave with their hull over those boxes.
            gone = current[~still_open]
            bound_lo[gone] = np.minimum(bound_lo[gone], level_lo[~still_open])
            bound_hi[gone] = np.maximum(bound_hi[gone], level_hi[~still_open])
            encloser = encloser.restrict(np.flatnonzero(still_open))
            current = open_entries
            level_lo, level_hi = level_lo[still_open], level_hi[still_open]
        used = encloser.used
        if not used.size:  # constant entries: nothing to split, rounding is all there is
            return finish(True, "converged", (level_lo, level_hi))
        n_open = lo.shape[1]
        halvings = _halvings(n_open, used.size, min(_BATCH, max_boxes - evaluated))
        children = 2 ** (halvings * used.size) if halvings else 2
        if evaluated + children * n_open > max_boxes:
            return finish(False, "max_boxes", (level_lo, level_hi))
        if deadline is not None and time.monotonic() > deadline:
            return finish(False, "max_wall_time", (level_lo, level_hi))
        if halvings:
            for _ in range(halvings):
                lo, hi = halve_every_side(lo, hi, used)
        else:
            lo, hi = bisect_boxes(lo, hi, split)
        finest = min(finest, float(((hi[sides] - lo[sides]) / width[sides, None]).min()))
        parents = (level_lo, level_hi)
