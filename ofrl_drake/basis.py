"""Polynomial bases ``sigma(x)`` for the value function ``V(x) = W^T sigma(x)``.

The paper needs ``sigma(0) = 0`` and ``grad sigma(0) = 0``; monomials of total
degree two or more satisfy both, so degrees below 2 are rejected.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

__all__ = ["PolynomialBasis"]


class PolynomialBasis:
    """All monomials of the given total degrees, with analytic gradients.

    Monomials of one degree are ordered as
    ``itertools.combinations_with_replacement``; degrees in the order given.
    For ``n = 2`` and ``degrees = (2,)`` that is exactly
    ``[x1^2, x1 x2, x2^2]``, the paper's basis.

    Parameters
    ----------
    n : int
        State dimension.
    degrees : sequence of int, default (2,)
        Total degrees to include; each must be >= 2.

    Attributes
    ----------
    exponents : ndarray of int, shape (L, n)
        ``exponents[l, j]`` is the power of ``x_j`` in monomial ``l``.
    size : int
        The number of basis functions L.

    Examples
    --------
    >>> import numpy as np
    >>> basis = PolynomialBasis(2)
    >>> basis(np.array([2.0, 3.0]))
    array([4., 6., 9.])
    """

    def __init__(self, n: int, degrees: Sequence[int] = (2,)) -> None:
        self.n = n
        self.degrees = degrees
        if not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"PolynomialBasis: n must be a positive integer; got {n!r}.")
        degs = list(degrees)
        if not degs:
            raise ValueError("PolynomialBasis: degrees is empty; pass e.g. [2].")
        for d in degs:
            if not isinstance(d, (int, np.integer)) or d < 2:
                raise ValueError(
                    f"PolynomialBasis: degree {d!r} is not allowed; degrees must be "
                    "integers >= 2 so that sigma(0) = 0 and grad sigma(0) = 0."
                )
        if len(set(degs)) != len(degs):
            raise ValueError(f"PolynomialBasis: degrees {degs} repeat a degree.")
        rows = []
        for d in degs:
            for combo in itertools.combinations_with_replacement(range(n), d):
                rows.append(np.bincount(combo, minlength=n))
        self.exponents = np.array(rows, dtype=int)
        self.size = self.exponents.shape[0]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``sigma(x)``: shape ``(L,)`` for ``x`` of shape ``(n,)``, or ``(L, N)``
        for a batch ``(n, N)``."""
        x = np.asarray(x, dtype=float)
        # (L, n, ...) powers, product over the state axis.
        powers = x[None, ...] ** self.exponents.reshape(self.size, self.n, *([1] * (x.ndim - 1)))
        return powers.prod(axis=1)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``d sigma / d x``: shape ``(L, n)`` for one point, ``(L, n, N)`` for a batch."""
        x = np.asarray(x, dtype=float)
        extra = [1] * (x.ndim - 1)
        E = self.exponents.reshape(self.size, self.n, *extra)
        powers = x[None, ...] ** E  # (L, n, ...)
        # d/dx_j of prod_k x_k^E_k = E_j x_j^(E_j - 1) prod_{k != j} x_k^E_k.
        lowered = np.where(E > 0, x[None, ...] ** np.maximum(E - 1, 0), 0.0) * E
        grad = np.empty((self.size, self.n, *x.shape[1:]))
        for j in range(self.n):  # loop over state dimension, not over points
            others = np.delete(powers, j, axis=1).prod(axis=1)
            grad[:, j] = lowered[:, j] * others
        return grad

    def labels(self, names: Sequence[str] | None = None) -> list[str]:
        """Readable names such as ``"x1^2"``, ``"x1 x2"``, for plots and tables."""
        names = list(names) if names is not None else [f"x{j + 1}" for j in range(self.n)]
        out = []
        for row in self.exponents:
            parts = [names[j] if p == 1 else f"{names[j]}^{p}" for j, p in enumerate(row) if p]
            out.append(" ".join(parts))
        return out

    def __repr__(self) -> str:
        return f"PolynomialBasis(n={self.n}, degrees={list(self.degrees)}, size={self.size})"
