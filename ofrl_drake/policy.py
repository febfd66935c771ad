"""The saturated policy ``u = -lbar tanh(D)`` of (u_app).

``D = (1 / (2 lbar)) R^{-1} g(x)^T grad sigma(x)^T W`` (NOTES.md: ``1/2 lambda``
means ``1/(2 lbar)``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["policy_argument", "saturated_policy"]


def policy_argument(
    grad_sigma_g: np.ndarray, W: np.ndarray, r: np.ndarray, input_bound: float
) -> np.ndarray:
    """``D`` from ``b = grad sigma(x) g(x)``.

    Parameters
    ----------
    grad_sigma_g : ndarray, shape (m, L) or (m, L, N)
        ``(grad sigma g)^T`` for one point or a batch (inputs first).
    W : ndarray, shape (L,)
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float

    Returns
    -------
    D : ndarray, shape (m,) or (m, N)
    """
    denominator = 2.0 * input_bound * np.asarray(r, dtype=float)
    if grad_sigma_g.ndim == 2:
        return (grad_sigma_g @ W) / denominator
    D = np.matmul(W, grad_sigma_g)  # (m, N), a fresh array
    D /= denominator.reshape(D.shape[:1] + (1,) * (D.ndim - 1))
    return D


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
    # D = scale * g^T (grad sigma^T W): two small products, no (m, L) intermediate.
    grad_V = W @ grad_sigma  # (n,)
    D = (grad_V @ g) / (2.0 * input_bound * np.asarray(r, dtype=float))
    return -input_bound * np.tanh(D)
