"""Polynomial bases ``sigma(x)`` for the value function ``V(x) = W^T sigma(x)``.

The paper needs ``sigma(0) = 0`` and ``grad sigma(0) = 0``; monomials of total
degree two or more satisfy both, so degrees below 2 are rejected.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from pydrake.symbolic import Expression

from ofrl_drake._jit import kernel
from ofrl_drake.errors import ModelError

__all__ = ["MAX_SIZE", "PolynomialBasis", "gradient_kernel", "monomials", "value_gradient_kernel"]

_FLOAT64 = np.dtype(np.float64)

#: Most monomials a :class:`PolynomialBasis` may have (its size ``L``).
MAX_SIZE = 100_000


def _describe(value: Any) -> str:
    """``value`` for a message: an array by its dtype and shape, anything else by repr."""
    if isinstance(value, np.ndarray):
        writable = "" if value.flags.writeable else "read-only "
        return f"a {writable}array of dtype {value.dtype} and shape {value.shape}"
    return repr(value)


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


@kernel
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


@kernel
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


@kernel
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
        If ``n`` is not a positive integer, ``degrees`` is not a sequence of
        integers, is empty, repeats a degree or holds one below 2 (then
        sigma(0) = 0 or grad sigma(0) = 0 would fail), or the basis would have
        more than :data:`MAX_SIZE` monomials.

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
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise ModelError(f"PolynomialBasis: n must be a positive integer; got {n!r}.")
        try:
            if isinstance(degrees, str | bytes):
                raise TypeError
            degs = list(degrees)
        except TypeError:
            raise ModelError(
                f"PolynomialBasis: degrees must be a sequence of integers >= 2, e.g. [2] or "
                f"[2, 4]; got {degrees!r}."
            ) from None
        if not degs:
            raise ModelError("PolynomialBasis: degrees is empty; pass e.g. [2].")
        for d in degs:
            if isinstance(d, bool) or not isinstance(d, int | np.integer) or d < 2:
                raise ModelError(
                    f"PolynomialBasis: degree {d!r} is not allowed; degrees must be "
                    "integers >= 2 so that sigma(0) = 0 and grad sigma(0) = 0."
                )
        if len(set(degs)) != len(degs):
            raise ModelError(f"PolynomialBasis: degrees {degs} repeat a degree.")
        size = sum(math.comb(int(n) + int(d) - 1, int(d)) for d in degs)
        if size > MAX_SIZE:
            raise ModelError(
                f"PolynomialBasis: n = {n} and degrees {degs} give {size} monomials; at most "
                f"{MAX_SIZE} are allowed (the critic carries L weights and L (L + 1) / 2 "
                "entries of Gamma). Use fewer or lower degrees."
            )
        rows = []
        for d in degs:
            for combo in itertools.combinations_with_replacement(range(n), d):
                rows.append(np.bincount(combo, minlength=n))
        self.exponents = np.array(rows, dtype=int)
        self.size = self.exponents.shape[0]
        self._powers = self.exponents.astype(float)
        self._lowered, self._index, self._factor = _gradient_table(self.exponents)
        # value_gradient's shapes, built once (it is called per point).
        self._x_shape, self._W_shape = (int(n),), (self.size,)

    def _states(self, x: Any, method: str) -> np.ndarray:
        """``x`` as a float array of shape ``(n,)`` or ``(n, N)``, else a :class:`ModelError`."""
        try:
            arr = np.asarray(x, dtype=float)
        except (TypeError, ValueError):
            raise ModelError(
                f"PolynomialBasis.{method}: x must be a numeric array of shape (n,) = "
                f"({self.n},) or (n, N) = ({self.n}, N); got {x!r}."
            ) from None
        if not 1 <= arr.ndim <= 2 or arr.shape[0] != self.n:
            raise ModelError(
                f"PolynomialBasis.{method}: x must have shape (n,) = ({self.n},) or "
                f"(n, N) = ({self.n}, N), one column per point; got shape {arr.shape}."
            )
        return arr

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``sigma(x)``: shape ``(L,)`` for ``x`` of shape ``(n,)``, or ``(L, N)``
        for a batch ``(n, N)``.

        Raises
        ------
        ModelError
            If ``x`` is not numeric or not of shape ``(n,)`` or ``(n, N)``.
        """
        x = self._states(x, "__call__")
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

        Raises
        ------
        ModelError
            If ``x`` is not numeric or not of shape ``(n,)`` or ``(n, N)``.
        """
        x = self._states(x, "gradient")
        if x.ndim == 1:
            X = np.ascontiguousarray(x.reshape(-1, 1))
            return gradient_kernel(X, self._lowered, self._index, self._factor)[:, :, 0]
        return gradient_kernel(np.ascontiguousarray(x), self._lowered, self._index, self._factor)

    def value_gradient(
        self, x: np.ndarray, W: np.ndarray, out: np.ndarray | None = None
    ) -> np.ndarray:
        """``grad V(x) = grad sigma(x)^T W``, shape ``(n,)``, for one point ``x``.

        ``out``, if given (float, shape ``(n,)``), receives the result.

        Raises
        ------
        ModelError
            If ``x`` does not have shape ``(n,)``, ``W`` shape ``(L,)``, or
            ``out`` is not a writable float64 array of shape ``(n,)``.
        """
        try:
            x = np.asarray(x, dtype=float)
            W = np.asarray(W, dtype=float)
        except (TypeError, ValueError):
            raise ModelError(
                f"PolynomialBasis.value_gradient: x and W must be numeric arrays of shapes "
                f"(n,) = ({self.n},) and (L,) = ({self.size},); got {x!r} and {W!r}."
            ) from None
        if x.shape != self._x_shape or W.shape != self._W_shape:
            raise ModelError(
                f"PolynomialBasis.value_gradient: x must have shape (n,) = ({self.n},) and "
                f"W shape (L,) = ({self.size},); got {x.shape} and {W.shape}."
            )
        if out is None:
            result = np.empty(self.n)
        elif (
            isinstance(out, np.ndarray)
            and out.shape == self._x_shape
            and out.dtype == _FLOAT64
            and out.flags.writeable
        ):
            result = out
        else:
            raise ModelError(
                f"PolynomialBasis.value_gradient: out must be a writable float64 array of "
                f"shape (n,) = ({self.n},); got {_describe(out)}."
            )
        value_gradient_kernel(x, W, self._lowered, self._index, self._factor, result)
        return result

    @property
    def gradient_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(lowered, index, factor)`` for the compiled kernels (:func:`gradient_kernel`)."""
        return self._lowered, self._index, self._factor

    def labels(self, names: Sequence[str] | None = None) -> list[str]:
        """Readable names such as ``"x1^2"``, ``"x1 x2"``, for plots and tables.

        Raises
        ------
        ModelError
            If ``names`` is not a sequence of ``n`` names.
        """
        given: list[Any] | None = None
        if names is None:
            given = [f"x{j + 1}" for j in range(self.n)]
        else:
            try:
                given = list(names)
            except TypeError:
                pass
        if given is None or len(given) != self.n:
            raise ModelError(
                f"PolynomialBasis.labels: names must give one name per state ({self.n} in "
                f"all), e.g. {[f'x{j + 1}' for j in range(self.n)]}; got {names!r}."
            )
        out = []
        for row in self.exponents:
            parts = [given[j] if p == 1 else f"{given[j]}^{p}" for j, p in enumerate(row) if p]
            out.append(" ".join(parts))
        return out

    def __repr__(self) -> str:
        return f"PolynomialBasis(n={self.n}, degrees={list(self.degrees)}, size={self.size})"
