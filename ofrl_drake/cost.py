"""The stage cost ``Q(x) + U(u)`` of (costfunction).

``Q(x) = x^T Q x``. The saturation cost (eq: positive function) is, per input,

    U(u) = sum_k 2 r_k lbar (u_k atanh(u_k / lbar) + (lbar / 2) ln(1 - u_k^2 / lbar^2)).

At ``u = -lbar tanh(D)`` this is ``sum_k r_k lbar^2 (2 D_k tanh D_k - 2 ln cosh D_k)``,
which is finite for every ``D``; the ``u`` form overflows once ``tanh(D)``
rounds to one. So ``U`` is evaluated from ``D`` with a stable log-cosh
(NOTES.md, "stage cost").
"""

from __future__ import annotations

import numpy as np

__all__ = ["input_cost", "input_cost_from_D", "log_cosh", "stage_cost", "state_cost"]

_LOG2 = float(np.log(2.0))


def state_cost(x: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``x^T Q x`` for ``x`` of shape ``(n,)`` or a batch ``(n, N)``."""
    x = np.asarray(x, dtype=float)
    return np.einsum("i...,ij,j...->...", x, Q, x)


def log_cosh(D: np.ndarray) -> np.ndarray:
    """``ln cosh D``, exact and finite for every real ``D``."""
    a = np.abs(D)
    # Near zero, ln cosh a = log1p(2 sinh^2(a/2)) avoids cancellation; far from
    # zero, a + log1p(exp(-2a)) - ln 2 avoids overflow of cosh.
    with np.errstate(over="ignore"):
        small = np.log1p(2.0 * np.sinh(np.minimum(a, 1.0) / 2.0) ** 2)
    large = a + np.log1p(np.exp(-2.0 * a)) - _LOG2
    return np.where(a < 1.0, small, large)


def input_cost_from_D(D: np.ndarray, r: np.ndarray, input_bound: float) -> np.ndarray:
    """``U(-lbar tanh D)`` summed over inputs (axis 0).

    Parameters
    ----------
    D : ndarray, shape (m,) or (m, N)
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    """
    D = np.asarray(D, dtype=float)
    r = np.asarray(r, dtype=float).reshape(-1, *([1] * (D.ndim - 1)))
    per_input = r * input_bound**2 * (2.0 * D * np.tanh(D) - 2.0 * log_cosh(D))
    return per_input.sum(axis=0)


def input_cost(u: np.ndarray, r: np.ndarray, input_bound: float) -> np.ndarray:
    """``U(u)`` for an input with ``|u_k| <= lbar``.

    Inputs exactly at the bound, where ``atanh`` is infinite, are clipped to
    just inside it, so the result is large but finite. Prefer
    :func:`input_cost_from_D` when ``D`` is at hand.

    Raises
    ------
    ValueError
        If some ``|u_k| > lbar``: no finite cost exists there.
    """
    u = np.asarray(u, dtype=float)
    ratio = u / input_bound
    if np.any(np.abs(ratio) > 1.0 + 1e-12):
        raise ValueError(
            f"input_cost: |u| = {np.max(np.abs(u)):.6g} exceeds the input bound "
            f"{input_bound}; U(u) is only defined for |u_k| <= lambda_bar."
        )
    ratio = np.clip(ratio, -1.0 + 1e-16, 1.0 - 1e-16)
    return input_cost_from_D(-np.arctanh(ratio), r, input_bound)


def stage_cost(
    x: np.ndarray, u: np.ndarray, Q: np.ndarray, r: np.ndarray, input_bound: float
) -> np.ndarray:
    """``Q(x) + U(u)``."""
    return state_cost(x, Q) + input_cost(u, r, input_bound)
