"""Interval matrix products and interval linear systems, many at once.

An interval matrix ``[A]`` and interval right-hand sides ``[b]`` stand for every
``A`` and ``b`` with entries in them; :class:`IntervalLinearSystem` encloses the
solution set ``{x : A x = b, A in [A], b in [b]}`` (for each right-hand side
column) by the standard preconditioned interval Gauss-Seidel method
(Neumaier, *Interval Methods for Systems of Equations*, 1990, ch. 4):

1. Precondition with ``C``, a floating-point inverse of the midpoint of ``[A]``
   (any ``C`` is sound; the midpoint inverse makes ``C [A]`` close to ``I``).
2. Take an approximate solution ``x~ = C mid([b])``. Every solution is
   ``x = x~ + e`` where ``e = C (b - A x~) + (I - C A) e``, so with
   ``z = C ([b] - [A] x~)`` and ``beta = || |I - C [A]| ||_inf < 1`` every
   ``e`` satisfies ``||e||_inf <= ||z||_inf / (1 - beta)``: a first enclosure.
   ``beta < 1`` also proves every ``A`` in ``[A]`` nonsingular.
3. Refine it by Gauss-Seidel sweeps on ``G e = z``, ``G = C [A]``: row ``i``
   gives ``e_i in (z_i - sum_{j != i} G_ij e_j) / G_ii``, intersected with the
   current ``e_i`` (each exact ``e`` stays inside, by induction).

Where ``beta >= 1`` (``[A]`` too wide, or it may hold a singular matrix) the
enclosure is the whole line. Every product and sum is rounded outward
(:class:`ofrl_drake.interval.Interval`), so the enclosure is rigorous.

Shapes: matrices are ``(k, l, *S)`` and right-hand sides ``(k, r, *S)``; the
trailing ``S`` (usually ``(B,)``, one system per box) is carried along, so one
call solves ``B`` systems with numpy operations over all of them.
"""

from __future__ import annotations

import numpy as np

from ofrl_drake.errors import ModelError
from ofrl_drake.interval import Interval

__all__ = ["IntervalLinearSystem", "interval_matmul"]

#: Gauss-Seidel sweeps after the norm-bound enclosure.
GAUSS_SEIDEL_SWEEPS = 2


def interval_matmul(A: Interval, X: Interval) -> Interval:
    """``[A] [X]`` with outward rounding.

    Parameters
    ----------
    A : Interval
        Shape ``(k, l, *S)``.
    X : Interval
        Shape ``(l, r, *S)``.

    Returns
    -------
    Interval
        Shape ``(k, r, *S)``; holds ``A X`` for every ``A`` in ``[A]``, ``X`` in ``[X]``.
    """
    l = np.shape(A.lo)[1]
    total = A[:, 0:1] * X[0:1]
    for j in range(1, l):
        total = total + A[:, j : j + 1] * X[j : j + 1]
    return total


def _gauss_seidel(G: Interval, rhs: Interval, start: Interval, sweeps: int) -> Interval:
    """Interval Gauss-Seidel sweeps on ``G y = rhs`` from the enclosure ``start``.

    Row ``i``: ``y_i in (rhs_i - sum_{j != i} G_ij y_j) / G_ii``, intersected with
    the current ``y_i``; every solution inside ``start`` stays inside.
    """
    k = np.shape(G.lo)[0]
    y_lo = [np.array(start.lo[i]) for i in range(k)]
    y_hi = [np.array(start.hi[i]) for i in range(k)]
    for _ in range(sweeps):
        for i in range(k):
            s = rhs[i]
            for j in range(k):
                if j != i:
                    s = s - G[i, j][None] * Interval(y_lo[j], y_hi[j])
            new = s / G[i, i][None]
            lo_i = np.maximum(y_lo[i], new.lo)
            hi_i = np.minimum(y_hi[i], new.hi)
            keep = lo_i <= hi_i  # an empty intersection cannot hold a solution; stay safe
            y_lo[i] = np.where(keep, lo_i, y_lo[i])
            y_hi[i] = np.where(keep, hi_i, y_hi[i])
    return Interval(np.stack(y_lo), np.stack(y_hi))


def _point(a: np.ndarray) -> Interval:
    return Interval(a, a)


def _inverse(mid: np.ndarray) -> np.ndarray:
    """Floating-point inverses of ``mid`` (``(k, k, *S)``); identity where none is finite.

    Only a preconditioner: any finite matrix keeps the enclosure sound.
    """
    k = mid.shape[0]
    stack = np.moveaxis(mid, (0, 1), (-2, -1))
    eye = np.eye(k)
    finite = np.all(np.isfinite(stack), axis=(-2, -1))
    stack = np.where(finite[..., None, None], stack, eye)
    with np.errstate(all="ignore"):
        try:
            inv = np.linalg.inv(stack)
        except np.linalg.LinAlgError:  # some midpoint is exactly singular
            inv = np.linalg.pinv(stack)
    inv = np.where(np.all(np.isfinite(inv), axis=(-2, -1))[..., None, None], inv, eye)
    return np.moveaxis(inv, (-2, -1), (0, 1))


class IntervalLinearSystem:
    """The interval matrix ``[A]``, preconditioned once, for solving ``[A] x = [b]``.

    Parameters
    ----------
    A : Interval
        ``k x k`` interval matrices, shape ``(k, k, *S)``; infinite ends are allowed
        (those systems are not solved: their enclosures are the whole line).
    sweeps : int
        Gauss-Seidel sweeps after the first enclosure.

    Attributes
    ----------
    A : Interval
        As given.
    sweeps : int
        As given.
    beta : ndarray, shape S
        An upper bound of ``|| |I - C [A]| ||_inf``; the systems with ``beta < 1``
        are solved, the others give the whole line.

    Examples
    --------
    >>> import numpy as np
    >>> A = Interval(np.array([[2.0, -0.1], [0.1, 1.9]]), np.array([[2.1, 0.1], [0.2, 2.0]]))
    >>> b = Interval(np.array([[1.0], [0.9]]), np.array([[1.1], [1.0]]))
    >>> x = IntervalLinearSystem(A).solve(b)
    >>> bool(np.all(x.contains(np.linalg.solve(A.lo, b.lo))))
    True
    """

    def __init__(self, A: Interval, sweeps: int = GAUSS_SEIDEL_SWEEPS) -> None:
        self.A = A
        self.sweeps = sweeps
        lo, hi = np.asarray(A.lo, dtype=float), np.asarray(A.hi, dtype=float)
        k = lo.shape[0]
        if lo.ndim < 2 or lo.shape[1] != k or lo.shape != hi.shape:
            raise ModelError(
                f"A must hold square interval matrices, shape (k, k, ...); got lo {lo.shape} "
                f"and hi {hi.shape}."
            )
        self._k = k
        with np.errstate(all="ignore"):
            self._C = _inverse(0.5 * lo + 0.5 * hi)
        self._G = interval_matmul(_point(self._C), A)
        eye = np.eye(k).reshape((k, k) + (1,) * (lo.ndim - 2))
        E = _point(np.broadcast_to(eye, lo.shape)) - self._G
        mag = E.mag
        rows = _point(mag[:, 0])
        for j in range(1, k):
            rows = rows + _point(mag[:, j])
        beta = rows.hi.max(axis=0)
        self.beta = np.where(np.isnan(beta), np.inf, beta)
        self._ok = self.beta < 1.0

    def solve(self, b: Interval) -> Interval:
        """Enclose ``{A^-1 b : A in [A], b in [b]}`` for each column of ``[b]``.

        Parameters
        ----------
        b : Interval
            Shape ``(k, r, *S)``.

        Returns
        -------
        Interval
            Shape ``(k, r, *S)``: for every ``A`` in ``[A]`` and ``b`` in ``[b]``,
            ``A^-1 b`` lies inside; the whole line where ``beta >= 1``.
        """
        b_lo, b_hi = np.asarray(b.lo, dtype=float), np.asarray(b.hi, dtype=float)
        with np.errstate(all="ignore"):
            b_mid = 0.5 * b_lo + 0.5 * b_hi
            b_mid = np.where(np.isfinite(b_mid), b_mid, 0.0)
            x_t = np.einsum("ij...,jr...->ir...", self._C, b_mid)
        x_t = np.where(np.isfinite(x_t), x_t, 0.0)
        z = interval_matmul(_point(self._C), b - interval_matmul(self.A, _point(x_t)))
        # ||e|| <= ||z|| / (1 - beta), rounded up; only where beta < 1.
        z_mag = z.mag.max(axis=0)
        radius = (_point(z_mag) / (1.0 - _point(np.broadcast_to(self.beta, z_mag.shape[1:])))).hi
        ok = self._ok & np.isfinite(radius)
        radius = np.where(ok, radius, np.inf)
        e = _gauss_seidel(
            self._G,
            z,
            Interval(np.broadcast_to(-radius, z.lo.shape), np.broadcast_to(radius, z.lo.shape)),
            self.sweeps,
        )
        x = _point(x_t) + e
        whole = ~np.broadcast_to(ok, x_t.shape)
        return Interval(np.where(whole, -np.inf, x.lo), np.where(whole, np.inf, x.hi))

    def select(self, index: slice) -> IntervalLinearSystem:
        """The systems ``S[index]`` (trailing axis), sharing this preconditioning."""
        out = IntervalLinearSystem.__new__(IntervalLinearSystem)
        out.A = self.A[:, :, index]
        out.sweeps = self.sweeps
        out._k = self._k
        out._C = self._C[:, :, index]
        out._G = self._G[:, :, index]
        out.beta = self.beta[index]
        out._ok = self._ok[index]
        return out
