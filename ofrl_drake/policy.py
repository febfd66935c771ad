"""The saturated policy ``u = -lbar tanh(D)`` of (u_app).

``D = (1 / (2 lbar)) R^{-1} g(x)^T grad sigma(x)^T W`` (docs/paper_notes.md:
``1/2 lambda`` means ``1/(2 lbar)``). With ``grad V = grad sigma^T W`` and the per-input
scale ``s_k = 1 / (2 lbar r_k)`` this is ``D_k = s_k (g^T grad V)_k``;
:func:`saturate` is that law, compiled with numba, and
:func:`policy_kernel` adds the basis gradient, so the controller block makes
one compiled call per evaluation. :func:`policy_expression` is the same law as
``pydrake.symbolic`` expressions, which Drake evaluates in C++
(:class:`~ofrl_drake.systems.SymbolicController`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydrake.symbolic import Jacobian, tanh

from ofrl_drake._jit import kernel
from ofrl_drake.basis import PolynomialBasis, value_gradient_kernel
from ofrl_drake.checks import positive_number, positive_vector
from ofrl_drake.errors import ModelError

__all__ = [
    "check_policy_arguments",
    "policy_expression",
    "policy_kernel",
    "policy_scale",
    "saturate",
    "saturated_policy",
]


def check_policy_arguments(
    block: str, n: int, m: int, basis: PolynomialBasis, r: Any, input_bound: float
) -> np.ndarray:
    """Check a controller block's arguments; return ``r`` as a float array.

    Raises
    ------
    ModelError
        If ``basis`` is not for ``n`` states, ``r`` is not ``m`` positive
        numbers, or ``input_bound <= 0``; the message starts with ``block``.
    """
    if basis.n != n:
        raise ModelError(
            f"{block}: the basis is for n = {basis.n} states but the "
            f"system has n = {n}; build PolynomialBasis({n}, ...)."
        )
    r_arr = positive_vector(f"{block}: r", r, m)
    positive_number(f"{block}: input_bound", input_bound)
    return r_arr


def policy_scale(r: np.ndarray, input_bound: float) -> np.ndarray:
    """``s_k = 1 / (2 lbar r_k)``, so that ``D_k = s_k (g^T grad V)_k``."""
    return 1.0 / (2.0 * input_bound * np.asarray(r, dtype=float))


@kernel
def saturate(
    grad_V: np.ndarray, g: np.ndarray, scale: np.ndarray, input_bound: float, u: np.ndarray
) -> None:
    """``u_k = -lbar tanh(s_k sum_j g[j, k] grad_V[j])``, written into ``u`` (shape (m,))."""
    n, m = g.shape
    for k in range(m):
        D = 0.0
        for j in range(n):
            D += g[j, k] * grad_V[j]
        u[k] = -input_bound * math.tanh(scale[k] * D)


@kernel
def policy_kernel(
    x: np.ndarray,
    g: np.ndarray,
    W: np.ndarray,
    lowered: np.ndarray,
    index: np.ndarray,
    factor: np.ndarray,
    scale: np.ndarray,
    input_bound: float,
) -> np.ndarray:
    """``u`` at state ``x`` with input matrix ``g = g(x)``; the basis by its gradient tables.

    ``(lowered, index, factor)`` is
    :attr:`~ofrl_drake.basis.PolynomialBasis.gradient_tables`.
    """
    grad_V = np.empty(x.shape[0])
    value_gradient_kernel(x, W, lowered, index, factor, grad_V)
    u = np.empty(g.shape[1])
    saturate(grad_V, g, scale, input_bound, u)
    return u


def saturated_policy(
    grad_sigma: np.ndarray,
    g: np.ndarray,
    W: np.ndarray,
    r: np.ndarray,
    input_bound: float,
) -> np.ndarray:
    """``u = -lbar tanh(D)`` at one state.

    Parameters
    ----------
    grad_sigma : ndarray, shape (L, n)
        Basis gradient at the (estimated) state.
    g : ndarray, shape (n, m)
        Input matrix at the same state.
    W : ndarray, shape (L,)
        Critic weights.
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar > 0.

    Returns
    -------
    u : ndarray, shape (m,)
    """
    grad_V = np.asarray(W, dtype=float) @ np.asarray(grad_sigma, dtype=float)
    g = np.ascontiguousarray(g, dtype=float)
    u = np.empty(g.shape[1])
    saturate(grad_V, g, policy_scale(r, input_bound), float(input_bound), u)
    return u


def policy_expression(
    basis: PolynomialBasis,
    x: np.ndarray,
    g: np.ndarray,
    W: np.ndarray,
    r: np.ndarray,
    input_bound: float,
) -> np.ndarray:
    """``u = -lbar tanh(D)`` as ``pydrake.symbolic`` expressions.

    Parameters
    ----------
    basis : PolynomialBasis
    x : ndarray of Variable, shape (n,)
        The (estimated) state.
    g : ndarray of Expression, shape (n, m)
        The input matrix at ``x``.
    W : ndarray of Variable, shape (L,)
        Critic weights.
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar > 0.

    Returns
    -------
    ndarray of Expression, shape (m,)
        ``grad sigma`` is Drake's exact symbolic Jacobian of the monomials.
    """
    grad_sigma = Jacobian(basis.expressions(x), x)  # (L, n)
    with np.errstate(invalid="ignore"):  # numpy's object loops flag Drake expressions
        grad_V = np.asarray(W) @ grad_sigma
        D = policy_scale(r, input_bound) * (np.asarray(g).T @ grad_V)
    return np.array([-input_bound * tanh(d) for d in D], dtype=object)
