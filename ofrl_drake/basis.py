"""Polynomial bases ``sigma(x)`` for the value function ``V(x) = W^T sigma(x)``.

The paper needs ``sigma(0) = 0`` and ``grad sigma(0) = 0``; monomials of total
degree two or more satisfy both, so degrees below 2 are rejected.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
from numba import njit
from pydrake.symbolic import Expression

from ofrl_drake._jit import JIT
from ofrl_drake.errors import ModelError

__all__ = ["PolynomialBasis", "gradient_kernel", "monomials", "value_gradient_kernel"]


def _gradient_table(exponents: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct lowered exponents ``e - 1_j`` and where each gradient entry takes one.

    Returns ``(lowered, index, factor)``, shapes ``(K, n)``, ``(L, n)`` and
    ``(L, n)``, such that ``d sigma_l / d x_j = factor[l, j] * prod(x ** lowered[index[l, j]])``
    (``factor`` is the exponent ``e_j``; entries with ``e_j = 0`` have factor 0
    and index 0).
    """
    size, n = exponents.shape
    keys: dict[tuple[int, ...], int] = {}
    index = np.zeros((size, n), dtype=np.int64)
    factor = np.zeros((size, n))
    for l, e in enumerate(exponents):
        for j in np.flatnonzero(e):
            key = tuple(int(p) - (k == j) for k, p in enumerate(e))
            index[l, j] = keys.setdefault(key, len(keys))
            factor[l, j] = float(e[j])
    lowered = np.array(list(keys), dtype=np.int64).reshape(-1, n)
    return lowered, index, factor


@njit(**JIT)
def monomials(x: np.ndarray, exponents: np.ndarray, out: np.ndarray) -> None:
    """``out[k] = prod_j x_j ** exponents[k, j]`` at one point ``x`` (integer powers)."""
    for k in range(exponents.shape[0]):
        p = 1.0
        for j in range(x.shape[0]):
            e = exponents[k, j]
            if e == 1:
                p *= x[j]
            elif e > 1:
                p *= x[j] ** e
        out[k] = p


@njit(**JIT)
def gradient_kernel(
    X: np.ndarray, lowered: np.ndarray, index: np.ndarray, factor: np.ndarray
) -> np.ndarray:
    """``d sigma / d x`` at the columns of ``X`` (shape ``(n, N)``): shape ``(L, n, N)``."""
    size, n = index.shape
    N = X.shape[1]
    out = np.empty((size, n, N))
    mono = np.empty(lowered.shape[0])
    x = np.empty(n)
    for i in range(N):
        for j in range(n):
            x[j] = X[j, i]
        monomials(x, lowered, mono)
        for l in range(size):
            for j in range(n):
                out[l, j, i] = factor[l, j] * mono[index[l, j]]
    return out


@njit(**JIT)
def value_gradient_kernel(
    x: np.ndarray,
    W: np.ndarray,
    lowered: np.ndarray,
    index: np.ndarray,
    factor: np.ndarray,
    out: np.ndarray,
) -> None:
    """``out = grad sigma(x)^T W`` (shape ``(n,)``), the gradient of ``V = W^T sigma``."""
    size, n = index.shape
    mono = np.empty(lowered.shape[0])
    monomials(x, lowered, mono)
    for j in range(n):
        out[j] = 0.0
    for l in range(size):
        w = W[l]
        for j in range(n):
            out[j] += w * factor[l, j] * mono[index[l, j]]


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
        self._lowered, self._index, self._factor = _gradient_table(self.exponents)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``sigma(x)``: shape ``(L,)`` for ``x`` of shape ``(n,)``, or ``(L, N)``
        for a batch ``(n, N)``."""
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            return (x**self._powers).prod(axis=1)
        # (L, n, N) powers, product over the state axis.
        return (x[None, :, :] ** self._powers[:, :, None]).prod(axis=1)

    def expressions(self, x: np.ndarray) -> np.ndarray:
        """``sigma(x)`` as ``pydrake.symbolic`` expressions of the variables ``x`` (n,)."""
        monomials = []
        for e in self.exponents:
            monomial = Expression(1.0)
            for j in range(self.n):
                if e[j]:
                    monomial = monomial * x[j] ** int(e[j])
            monomials.append(monomial)
        return np.array(monomials, dtype=object)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``d sigma / d x``: shape ``(L, n)`` for one point, ``(L, n, N)`` for a batch.

        Compiled (:func:`gradient_kernel`): ``d/dx_j`` of ``x^e`` is
        ``e_j x^(e - 1_j)``, each distinct lowered monomial evaluated once.
        """
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            X = np.ascontiguousarray(x.reshape(-1, 1))
            return gradient_kernel(X, self._lowered, self._index, self._factor)[:, :, 0]
        return gradient_kernel(np.ascontiguousarray(x), self._lowered, self._index, self._factor)

    def value_gradient(
        self, x: np.ndarray, W: np.ndarray, out: np.ndarray | None = None
    ) -> np.ndarray:
        """``grad V(x) = grad sigma(x)^T W``, shape ``(n,)``, for one point ``x``.

        ``out``, if given (float, shape ``(n,)``), receives the result.
        """
        result = np.empty(self.n) if out is None else out
        value_gradient_kernel(
            np.asarray(x, dtype=float),
            np.asarray(W, dtype=float),
            self._lowered,
            self._index,
            self._factor,
            result,
        )
        return result

    @property
    def gradient_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(lowered, index, factor)`` for the compiled kernels (:func:`gradient_kernel`)."""
        return self._lowered, self._index, self._factor

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
