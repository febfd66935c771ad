"""The control-affine plant model ``x' = f(x) + g(x) u``, ``y = C x``.

``f`` and ``g`` are written once, with numpy operations (``np.cos``,
``np.exp``, ``**``, ...), and are then usable on

* a single state ``x`` of shape ``(n,)`` (floats, Drake ``AutoDiffXd`` or
  ``symbolic.Expression``), and
* a batch of states ``X`` of shape ``(n, N)`` (one column per point), which is
  how the Bellman extrapolation evaluates them without a Python loop.

Write constants that must broadcast over a batch as ``0 * x[0]`` or
``np.zeros_like(x[0])`` rather than a bare ``0``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from ofrl_drake.errors import ModelError

__all__ = ["ControlAffineSystem"]

ArrayFunction = Callable[[np.ndarray], np.ndarray]


def _probe_point(n: int) -> np.ndarray:
    """A deterministic, generic point: nonzero, distinct entries."""
    return 0.1 + 0.05 * np.arange(n, dtype=float)


class ControlAffineSystem:
    """A control-affine system ``x' = f(x) + g(x) u`` with output ``y = C x``.

    Parameters
    ----------
    f : callable
        Drift, ``f(x) -> (n,)``; also ``f(X) -> (n, N)`` for ``X`` of shape
        ``(n, N)``.
    g : callable
        Input matrix, ``g(x) -> (n, m)``; also ``g(X) -> (n, m, N)``.
    C : array_like, shape (q, n)
        Output matrix.
    name : str, optional
        A label used in diagrams and reports.

    Attributes
    ----------
    n, m, q : int
        State, input and output dimensions, found once at construction by
        calling ``f`` and ``g`` on a probe point.
    vectorized : bool
        True if ``f`` and ``g`` accept a batch ``(n, N)`` of states. If not, the
        batch methods fall back to a (slower) loop and a warning is issued.

    Raises
    ------
    ValueError
        If ``C`` is not a finite 2-D array, or ``f``/``g`` return values of the
        wrong shape or non-finite values at the probe point.

    Examples
    --------
    >>> import numpy as np
    >>> sys = ControlAffineSystem(
    ...     f=lambda x: np.array([x[1], -x[0]]),
    ...     g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
    ...     C=[[1.0, 0.0]],
    ... )
    >>> (sys.n, sys.m, sys.q)
    (2, 1, 1)
    """

    def __init__(
        self,
        f: ArrayFunction,
        g: ArrayFunction,
        C: np.ndarray,
        *,
        name: str = "control_affine_system",
    ) -> None:
        self.f = f
        self.g = g
        self.C = C
        self.name = name

        C_arr = np.asarray(C, dtype=float)
        if C_arr.ndim != 2 or C_arr.shape[0] < 1 or C_arr.shape[1] < 1:
            raise ModelError(
                f"C must be a 2-D array of shape (q, n); got shape {C_arr.shape}. "
                "Pass C as a list of rows, e.g. [[0.0, 1.0]]."
            )
        if not np.all(np.isfinite(C_arr)):
            raise ModelError(f"C must be finite; got {C_arr.tolist()}.")
        self._C = C_arr
        self.q, self.n = C_arr.shape

        x = _probe_point(self.n)
        fx = self._call("f", f, x)
        if fx.shape != (self.n,):
            raise ModelError(
                f"f(x) must return shape (n,) = ({self.n},) to match C with "
                f"n = {self.n} columns; got shape {fx.shape}. Check f or C."
            )
        gx = self._call("g", g, x)
        if gx.ndim != 2 or gx.shape[0] != self.n or gx.shape[1] < 1:
            raise ModelError(
                f"g(x) must return shape (n, m) = ({self.n}, m) to match C with "
                f"n = {self.n} columns; got shape {gx.shape}. Return a 2-D array, "
                "e.g. np.array([[0 * x[0]], [1 + 0 * x[0]]]) for m = 1."
            )
        self.m = gx.shape[1]
        self.vectorized = self._check_batch()

    # ------------------------------------------------------------------ checks
    def _call(self, name: str, fn: ArrayFunction, x: np.ndarray) -> np.ndarray:
        try:
            value = np.asarray(fn(x), dtype=float)
        except Exception as err:
            raise ModelError(
                f"{name}(x) failed at the probe point x = {x.tolist()}: {err}"
            ) from err
        if not np.all(np.isfinite(value)):
            raise ModelError(
                f"{name}(x) returned non-finite values {value.tolist()} at the "
                f"probe point x = {x.tolist()}; {name} must be finite."
            )
        return value

    def _check_batch(self) -> bool:
        X = np.stack([_probe_point(self.n), -2.0 * _probe_point(self.n)], axis=1)
        try:
            fX = np.asarray(self.f(X), dtype=float)
            gX = np.asarray(self.g(X), dtype=float)
            ok = fX.shape == (self.n, 2) and gX.shape == (self.n, self.m, 2)
            ok = ok and np.allclose(fX[:, 0], self._call("f", self.f, X[:, 0]))
            ok = ok and np.allclose(gX[..., 1], self._call("g", self.g, X[:, 1]))
        except Exception:
            ok = False
        if not ok:
            warnings.warn(
                f"{self.name}: f and g do not accept a batch of states of shape "
                "(n, N); falling back to a Python loop over points. Write "
                "constants as 0 * x[0] so they broadcast.",
                stacklevel=3,
            )
        return ok

    # --------------------------------------------------------------- evaluate
    @property
    def output_matrix(self) -> np.ndarray:
        """``C`` as a float array of shape ``(q, n)``."""
        return self._C

    def f_batch(self, X: np.ndarray) -> np.ndarray:
        """Drift at each column of ``X`` (shape ``(n, N)``): shape ``(n, N)``."""
        if self.vectorized:
            return np.asarray(self.f(X), dtype=float).reshape(self.n, X.shape[1])
        return np.stack([np.asarray(self.f(x), float) for x in X.T], axis=-1)

    def g_batch(self, X: np.ndarray) -> np.ndarray:
        """Input matrix at each column of ``X``: shape ``(n, m, N)``."""
        if self.vectorized:
            return np.asarray(self.g(X), dtype=float).reshape(self.n, self.m, X.shape[1])
        return np.stack([np.asarray(self.g(x), float) for x in X.T], axis=-1)

    def dynamics(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``f(x) + g(x) u`` for one state (any scalar type)."""
        return self.f(x) + self.g(x) @ u

    def output(self, x: np.ndarray) -> np.ndarray:
        """``C x``."""
        return self._C @ x

    def __repr__(self) -> str:
        return f"ControlAffineSystem(name={self.name!r}, n={self.n}, m={self.m}, q={self.q})"
