"""The stage cost ``Q(x) + U(u)`` of (costfunction).

``Q(x) = x^T Q x``. The saturation cost (eq: positive function) is, per input,

    U(u) = sum_k 2 r_k lbar (u_k atanh(u_k / lbar) + (lbar / 2) ln(1 - u_k^2 / lbar^2)).

At ``u = -lbar tanh(D)`` this is ``sum_k r_k lbar^2 (2 D_k tanh D_k - 2 ln cosh D_k)``,
which is finite for every ``D``; the ``u`` form overflows once ``tanh(D)``
rounds to one. So where ``D`` is known (the policy, the Bellman errors) ``U``
is evaluated from ``D`` with a stable log-cosh (:func:`tanh_log_cosh`;
docs/paper_notes.md, "stage cost");
:func:`input_cost` takes ``u`` itself, for the cost of an applied input.

The scalar laws are compiled with numba (``@njit``): :func:`tanh_abs`,
:func:`log_cosh_abs` (the two halves of :func:`tanh_log_cosh`) and
:func:`saturation_cost` are called per point inside the Bellman kernel
(:mod:`ofrl_drake.bellman`), and :func:`stage_cost_rate` is the running-cost
block's whole derivative. The array functions below are thin loops over them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydrake.symbolic import Expression, log
from pydrake.symbolic import max as symbolic_max
from pydrake.symbolic import min as symbolic_min

from ofrl_drake._jit import kernel, ufunc
from ofrl_drake.checks import nonnegative_matrix, positive_number, positive_vector
from ofrl_drake.errors import ModelError

__all__ = [
    "check_cost_arguments",
    "input_cost",
    "input_cost_from_D",
    "log_cosh",
    "log_cosh_abs",
    "saturation_cost",
    "stage_cost",
    "stage_cost_expression",
    "stage_cost_rate",
    "state_cost",
    "tanh_abs",
    "tanh_log_cosh",
]

#: Below this |D| the log-cosh is ``-log1p(-tanh^2 D) / 2``, above it
#: ``|D| - ln 2 + log1p(e^{-2|D|})``: neither form cancels on its side.
_LOG_COSH_SMALL = 0.5

_LN2 = math.log(2.0)


def check_cost_arguments(
    block: str, Q: Any, r: Any, input_bound: Any
) -> tuple[np.ndarray, np.ndarray, float]:
    """Check a running-cost block's ``Q``, ``r`` and ``input_bound``.

    Returns
    -------
    Q : ndarray, shape (n, n)
    r : ndarray, shape (m,)
    input_bound : float

    Raises
    ------
    ModelError
        If ``Q`` is not a finite symmetric positive semidefinite matrix, ``r``
        not a finite vector of entries > 0, or ``input_bound`` not a finite
        number > 0; the message starts with ``block`` (``"RunningCost: Q"``).
    """
    Q_arr = nonnegative_matrix(f"{block}: Q", Q)
    r_arr = positive_vector(f"{block}: r", r)
    lbar = positive_number(f"{block}: input_bound", input_bound)
    return Q_arr, r_arr, lbar


def state_cost(x: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``x^T Q x`` for ``x`` of shape ``(n,)`` or a batch ``(n, N)``."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        return x @ Q @ x
    return np.sum(x * (Q @ x), axis=0)


@kernel
def tanh_abs(a: float) -> tuple[float, float]:
    """``(tanh a, e^{-2a} - 1)`` for ``a >= 0``, from one ``expm1``.

    ``tanh a = -e / (2 + e)`` with ``e = expm1(-2a)`` in ``(-1, 0]``: no
    cancellation for small ``a``, and exactly one once ``e`` rounds to -1.
    Cheaper than ``math.tanh`` (measured 8 ns against 13 per call); ``e`` is
    what :func:`log_cosh_abs` needs next.
    """
    e = math.expm1(-2.0 * a)
    return -e / (2.0 + e), e


@kernel
def log_cosh_abs(a: float, tanh_a: float, e: float) -> float:
    """``ln cosh a`` for ``a >= 0``, given ``(tanh a, e) = tanh_abs(a)``: one ``log1p``.

    Below ``a = 0.5``, ``-log1p(-tanh^2 a) / 2`` (no cancellation near zero,
    ``tanh^2 a <= 0.22``); above, ``a - ln 2 + log1p(1 + e)``, where
    ``1 + e = e^{-2a} <= 0.37`` has an absolute error of ``1e-16``, harmless
    beside ``ln cosh a >= 0.12``, and rounds to 0 for large ``a``, leaving
    ``a - ln 2``. A select, not a branch, picks the argument.
    """
    small = a < _LOG_COSH_SMALL
    log1p_term = math.log1p(-tanh_a * tanh_a if small else 1.0 + e)
    return -0.5 * log1p_term if small else (a - _LN2) + log1p_term


@kernel
def tanh_log_cosh(d: float) -> tuple[float, float]:
    """``(tanh d, ln cosh d)``, both exact and finite for every real ``d``.

    Two transcendental calls: :func:`tanh_abs` (``expm1``), then
    :func:`log_cosh_abs` (``log1p``). Loops over many ``d`` call the two in
    separate passes (:func:`~ofrl_drake.bellman.bellman_kernel`): each pass
    is then a run of independent calls, where one pass waits on the ``expm1``
    before each ``log1p`` (measured 14 ns a point against 19).
    """
    a = abs(d)
    t, e = tanh_abs(a)
    return (t if d >= 0.0 else -t), log_cosh_abs(a, t, e)


@ufunc(["float64(float64)"])
def log_cosh(d: float) -> float:  # pragma: no cover - compiled
    """``ln cosh D``, exact and finite for every real ``D`` (a numpy ufunc)."""
    return tanh_log_cosh(d)[1]


@kernel
def saturation_cost(d: float, tanh_d: float, log_cosh_d: float) -> float:
    """``2 (d tanh d - ln cosh d)``: ``U / (r_k lbar^2)`` for one input at ``D_k = d``."""
    return 2.0 * (d * tanh_d - log_cosh_d)


@ufunc(["float64(float64)"])
def _saturation_cost_of_D(d: float) -> float:  # pragma: no cover - compiled
    t, lc = tanh_log_cosh(d)
    return saturation_cost(d, t, lc)


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
    per_input = _saturation_cost_of_D(D)
    weight = input_bound**2 * np.asarray(r, dtype=float)
    if D.ndim <= 2:
        return weight @ per_input
    return (weight @ per_input.reshape(D.shape[0], -1)).reshape(D.shape[1:])


@kernel
def _input_cost_of_ratio(v: float) -> float:
    """``2 v atanh v + ln(1 - v^2)`` for ``|v| <= 1``, clipped just inside the bound."""
    v = min(max(v, -1.0 + 1e-16), 1.0 - 1e-16)
    log_1mv2 = math.log1p(-v * v) if abs(v) < 0.5 else math.log1p(v) + math.log1p(-v)
    return 2.0 * v * math.atanh(v) + log_1mv2


@ufunc(["float64(float64)"])
def _input_cost_ufunc(v: float) -> float:  # pragma: no cover - compiled
    return _input_cost_of_ratio(v)


@kernel
def stage_cost_rate(
    x: np.ndarray, u: np.ndarray, Q: np.ndarray, r: np.ndarray, input_bound: float
) -> tuple[float, float]:
    """``(Q(x) + U(u), max_k |u_k| / lbar)`` at one state and input.

    The running-cost block's derivative in one compiled call; the caller
    checks the second value (see :func:`input_cost`) since ``U`` is only
    defined for ``|u_k| <= lbar``.
    """
    n = x.shape[0]
    total = 0.0
    for i in range(n):
        row = 0.0
        for j in range(n):
            row += Q[i, j] * x[j]
        total += x[i] * row
    worst = 0.0
    cost = 0.0
    for k in range(u.shape[0]):
        v = u[k] / input_bound
        worst = max(worst, abs(v))
        cost += r[k] * _input_cost_of_ratio(v)
    return total + input_bound * input_bound * cost, worst


def input_cost(u: np.ndarray, r: np.ndarray, input_bound: float) -> np.ndarray | np.float64:
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
    ratio = u / input_bound
    if np.any(np.abs(ratio) > 1.0 + 1e-12):
        raise_input_out_of_bound(u, input_bound)
    per_input = _input_cost_ufunc(ratio)
    weight = input_bound**2 * np.asarray(r, dtype=float)
    if u.ndim == 1:
        return np.float64(weight @ per_input)
    return (weight @ per_input.reshape(u.shape[0], -1)).reshape(u.shape[1:])


def raise_input_out_of_bound(u: np.ndarray, input_bound: float) -> None:
    """Raise the :class:`ModelError` of an input beyond ``lbar``."""
    raise ModelError(
        f"input_cost: |u| = {np.max(np.abs(u)):.6g} exceeds the input bound "
        f"{input_bound}; U(u) is only defined for |u_k| <= lambda_bar."
    )


def stage_cost(
    x: np.ndarray, u: np.ndarray, Q: np.ndarray, r: np.ndarray, input_bound: float
) -> np.ndarray:
    """``Q(x) + U(u)``."""
    return state_cost(x, Q) + input_cost(u, r, input_bound)


def stage_cost_expression(
    x: np.ndarray, u: np.ndarray, Q: np.ndarray, r: np.ndarray, input_bound: float
) -> object:
    """``Q(x) + U(u)`` as one ``pydrake.symbolic`` expression in ``x`` and ``u``.

    ``U`` is written ``sum_k r_k lbar^2 ((1 + v) ln(1 + v) + (1 - v) ln(1 - v))``
    with ``v = u_k / lbar`` clipped to ``1 - 1e-16`` in magnitude, the same
    function as :func:`input_cost` (Drake's expressions have no ``log1p`` or
    ``atanh``). Its error is absolute, about ``r_k lbar^2 1e-16``, rather
    than relative for tiny ``v``; an input beyond the bound is clipped, not
    refused (the validity report flags ``|u_k| > lambda_bar``).
    """
    Q = np.asarray(Q, dtype=float)
    with np.errstate(invalid="ignore"):  # numpy's object loops flag Drake expressions
        total = np.asarray(x) @ Q @ np.asarray(x)
    edge = 1.0 - 1e-16
    for k, uk in enumerate(u):
        v = symbolic_min(symbolic_max(uk / input_bound, Expression(-edge)), Expression(edge))
        per_input = (1.0 + v) * log(1.0 + v) + (1.0 - v) * log(1.0 - v)
        total = total + float(input_bound**2 * r[k]) * per_input
    return total
