"""Polynomial bases ``sigma(x)`` for the value function ``V(x) = W^T sigma(x)``.

The paper needs ``sigma(0) = 0`` and ``grad sigma(0) = 0``; monomials of total
degree two or more satisfy both, so degrees below 2 are rejected.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from ofrl_drake.errors import ModelError

__all__ = ["PolynomialBasis"]


def _gradient_table(exponents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct lowered exponents ``e - 1_j`` and the factors ``e_j``.

    Returns ``(lowered, factors)``, shapes ``(K, n)`` and ``(L n, K)``, such that
    ``grad sigma(x).ravel() = factors @ prod(x ** lowered, axis=1)``.
    """
    size, n = exponents.shape
    index: dict[tuple[int, ...], int] = {}
    entries = []
    for l, e in enumerate(exponents):
        for j in np.flatnonzero(e):
            key = tuple(int(p) - (k == j) for k, p in enumerate(e))
            entries.append((l * n + j, index.setdefault(key, len(index)), float(e[j])))
    factors = np.zeros((size * n, len(index)))
    for row, k, value in entries:
        factors[row, k] = value
    return np.array(list(index), dtype=float).reshape(-1, n), factors


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

    Raises
    ------
    ModelError
        If ``n`` is not a positive integer, or ``degrees`` is empty, repeats a
        degree or holds one below 2 (then sigma(0) = 0 or grad sigma(0) = 0
        would fail).

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
            raise ModelError(f"PolynomialBasis: n must be a positive integer; got {n!r}.")
        degs = list(degrees)
        if not degs:
            raise ModelError("PolynomialBasis: degrees is empty; pass e.g. [2].")
        for d in degs:
            if not isinstance(d, (int, np.integer)) or d < 2:
                raise ModelError(
                    f"PolynomialBasis: degree {d!r} is not allowed; degrees must be "
                    "integers >= 2 so that sigma(0) = 0 and grad sigma(0) = 0."
                )
        if len(set(degs)) != len(degs):
            raise ModelError(f"PolynomialBasis: degrees {degs} repeat a degree.")
        rows = []
        for d in degs:
            for combo in itertools.combinations_with_replacement(range(n), d):
                rows.append(np.bincount(combo, minlength=n))
        self.exponents = np.array(rows, dtype=int)
        self.size = self.exponents.shape[0]
        self._powers = self.exponents.astype(float)
        self._lowered, self._factors = _gradient_table(self.exponents)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``sigma(x)``: shape ``(L,)`` for ``x`` of shape ``(n,)``, or ``(L, N)``
        for a batch ``(n, N)``."""
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            return (x**self._powers).prod(axis=1)
        # (L, n, N) powers, product over the state axis.
        return (x[None, :, :] ** self._powers[:, :, None]).prod(axis=1)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``d sigma / d x``: shape ``(L, n)`` for one point, ``(L, n, N)`` for a batch."""
        x = np.asarray(x, dtype=float)
        # d/dx_j of x^e is e_j x^(e - 1_j): the distinct lowered monomials,
        # evaluated once, times a constant (L n, K) table of the factors e_j.
        if x.ndim == 1:
            lowered = (x**self._lowered).prod(axis=1)  # (K,)
            return (self._factors @ lowered).reshape(self.size, self.n)
        lowered = (x[None, :, :] ** self._lowered[:, :, None]).prod(axis=1)  # (K, N)
        return (self._factors @ lowered).reshape(self.size, self.n, x.shape[1])

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
