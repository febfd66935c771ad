"""The stage cost ``Q(x) + U(u)`` of (costfunction).

``Q(x) = x^T Q x``. The saturation cost (eq: positive function) is, per input,

    U(u) = sum_k 2 r_k lbar (u_k atanh(u_k / lbar) + (lbar / 2) ln(1 - u_k^2 / lbar^2)).

At ``u = -lbar tanh(D)`` this is ``sum_k r_k lbar^2 (2 D_k tanh D_k - 2 ln cosh D_k)``,
which is finite for every ``D``; the ``u`` form overflows once ``tanh(D)``
rounds to one. So where ``D`` is known (the policy, the Bellman errors) ``U``
is evaluated from ``D`` with a stable log-cosh (NOTES.md, "stage cost");
:func:`input_cost` takes ``u`` itself, for the cost of an applied input.
"""

from __future__ import annotations

import math

import numpy as np

from ofrl_drake.errors import ModelError

__all__ = ["input_cost", "input_cost_from_D", "log_cosh", "stage_cost", "state_cost"]

#: Beyond this |D|, ln cosh D = |D| - ln 2 to double precision (e^{-2|D|} < 1e-34).
_LOG_COSH_LINEAR = 40.0


def state_cost(x: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``x^T Q x`` for ``x`` of shape ``(n,)`` or a batch ``(n, N)``."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        return x @ Q @ x
    return np.sum(x * (Q @ x), axis=0)


def log_cosh(D: np.ndarray) -> np.ndarray:
    """``ln cosh D``, exact and finite for every real ``D``."""
    a = np.abs(D)
    # ln cosh a = log1p(2 sinh^2(a/2)) has no cancellation near zero; past
    # a = 40 it is a - ln 2 to double precision, so clamp there (no overflow of
    # sinh) and add the linear remainder.
    clamped = np.minimum(a, _LOG_COSH_LINEAR)
    s = np.sinh(0.5 * clamped)
    return np.log1p(2.0 * s * s) + (a - clamped)


def input_cost_from_D(
    D: np.ndarray, r: np.ndarray, input_bound: float, tanh_D: np.ndarray | None = None
) -> np.ndarray:
    """``U(-lbar tanh D)`` summed over inputs (axis 0).

    Parameters
    ----------
    D : ndarray, shape (m,) or (m, N)
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    tanh_D : ndarray, optional
        ``tanh(D)``, if the caller already has it.
    """
    D = np.asarray(D, dtype=float)
    per_input = D * (np.tanh(D) if tanh_D is None else tanh_D)
    per_input -= log_cosh(D)
    weight = (2.0 * input_bound**2) * np.asarray(r, dtype=float)
    if D.ndim <= 2:
        return weight @ per_input
    return (weight @ per_input.reshape(D.shape[0], -1)).reshape(D.shape[1:])


def input_cost(u: np.ndarray, r: np.ndarray, input_bound: float) -> np.ndarray:
    """``U(u)`` for an input with ``|u_k| <= lbar``.

    With ``v = u / lbar`` this is ``sum_k r_k lbar^2 (2 v_k atanh v_k + ln(1 - v_k^2))``,
    with ``ln(1 - v^2)`` taken as ``log1p(-v^2)`` for small ``|v|`` and as
    ``log1p(v) + log1p(-v)`` near the bound, so it is accurate at both ends.
    Inputs exactly at the bound, where ``atanh`` is infinite, are clipped to
    just inside it, so the result is large but finite. Prefer
    :func:`input_cost_from_D` when ``D`` is at hand.

    Raises
    ------
    ModelError
        If some ``|u_k| > lbar``: no finite cost exists there.
    """
    u = np.asarray(u, dtype=float)
    if u.ndim == 1:
        # One input vector, evaluated at every derivative evaluation of the
        # running cost: scalar ``math`` beats numpy calls on a handful of entries.
        ratios = [uk / input_bound for uk in u.tolist()]
        if any(abs(v) > 1.0 + 1e-12 for v in ratios):
            _raise_out_of_bound(u, input_bound)
        total = 0.0
        for v, rk in zip(ratios, np.asarray(r, dtype=float).tolist(), strict=True):
            v = min(max(v, -1.0 + 1e-16), 1.0 - 1e-16)
            log_1mv2 = math.log1p(-v * v) if abs(v) < 0.5 else math.log1p(v) + math.log1p(-v)
            total += rk * (2.0 * v * math.atanh(v) + log_1mv2)
        return np.float64(input_bound**2 * total)
    ratio = u / input_bound
    if np.any(np.abs(ratio) > 1.0 + 1e-12):
        _raise_out_of_bound(u, input_bound)
    v = np.clip(ratio, -1.0 + 1e-16, 1.0 - 1e-16)
    log_1mv2 = np.where(np.abs(v) < 0.5, np.log1p(-v * v), np.log1p(v) + np.log1p(-v))
    per_input = 2.0 * v * np.arctanh(v) + log_1mv2
    weight = input_bound**2 * np.asarray(r, dtype=float)
    return (weight @ per_input.reshape(u.shape[0], -1)).reshape(u.shape[1:])


def _raise_out_of_bound(u: np.ndarray, input_bound: float) -> None:
    raise ModelError(
        f"input_cost: |u| = {np.max(np.abs(u)):.6g} exceeds the input bound "
        f"{input_bound}; U(u) is only defined for |u_k| <= lambda_bar."
    )


def stage_cost(
    x: np.ndarray, u: np.ndarray, Q: np.ndarray, r: np.ndarray, input_bound: float
) -> np.ndarray:
    """``Q(x) + U(u)``."""
    return state_cost(x, Q) + input_cost(u, r, input_bound)
