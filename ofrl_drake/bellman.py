"""Bellman-error extrapolation (BE1_i) and the sums the update laws need.

At each extrapolation point ``x_i`` (columns of ``X``, shape ``(n, N)``)::

    D_i     = (1/(2 lbar)) R^{-1} (grad sigma_i g_i)^T W
    u_i     = -lbar tanh(D_i)
    omega_i = grad sigma_i (f_i + g_i u_i)
    delta_i = W^T omega_i + Q(x_i) + U(u_i)
    rho_i   = 1 + nu omega_i^T omega_i

and the update laws (W_c), (gamma) use the means

    critic_sum = (1/N) sum_i omega_i delta_i / rho_i           (L,)
    gain_sum   = (1/N) sum_i omega_i omega_i^T / rho_i^2       (L, L)

so that ``W' = -k_c Gamma critic_sum`` and
``Gamma' = beta Gamma - k_c Gamma gain_sum Gamma``. The learning condition
(Assumption 2) is ``c = lambda_min(gain_sum)``.

Everything that does not depend on ``W`` is precomputed once per point set in
:class:`PointFeatures`; :func:`extrapolate` is then a handful of dense numpy
operations over arrays laid out ``L x N``, with no loop over points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.cost import input_cost_from_D, state_cost
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.policy import policy_argument

__all__ = [
    "BellmanExtrapolation",
    "PointFeatures",
    "extrapolate",
    "learning_condition",
    "point_features",
]


@dataclass(frozen=True)
class PointFeatures:
    """The ``W``-independent part of the extrapolation at ``N`` points.

    Attributes
    ----------
    points : ndarray, shape (n, N)
    drift : ndarray, shape (L, N)
        ``grad sigma(x_i) f(x_i)``.
    input : ndarray, shape (m, L, N)
        ``(grad sigma(x_i) g(x_i))`` with the input index first.
    state_cost : ndarray, shape (N,)
        ``Q(x_i)``.
    """

    points: np.ndarray
    drift: np.ndarray
    input: np.ndarray
    state_cost: np.ndarray

    @property
    def num_points(self) -> int:
        return self.points.shape[1]


@dataclass(frozen=True)
class BellmanExtrapolation:
    """Bellman errors at the extrapolation points and their sums.

    Attributes
    ----------
    D : ndarray, shape (m, N)
    u : ndarray, shape (m, N)
    omega : ndarray, shape (L, N)
    delta : ndarray, shape (N,)
    rho : ndarray, shape (N,)
    critic_sum : ndarray, shape (L,)
        ``(1/N) sum omega_i delta_i / rho_i``.
    gain_sum : ndarray, shape (L, L)
        ``(1/N) sum omega_i omega_i^T / rho_i^2``.
    """

    D: np.ndarray
    u: np.ndarray
    omega: np.ndarray
    delta: np.ndarray
    rho: np.ndarray
    critic_sum: np.ndarray
    gain_sum: np.ndarray

    @property
    def learning_condition(self) -> float:
        """``c = lambda_min(gain_sum)``."""
        return learning_condition(self.gain_sum)


def point_features(
    system: ControlAffineSystem,
    basis: PolynomialBasis,
    points: np.ndarray,
    Q: np.ndarray,
) -> PointFeatures:
    """Precompute everything at ``points`` (shape ``(n, N)``) that does not depend on W."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[0] != system.n:
        raise ValueError(f"points must have shape (n, N) = ({system.n}, N); got {points.shape}.")
    grad = basis.gradient(points)  # (L, n, N)
    f = system.f_batch(points)  # (n, N)
    g = system.g_batch(points)  # (n, m, N)
    drift = (grad * f[None, :, :]).sum(axis=1)  # (L, N)
    inp = (grad[:, :, None, :] * g[None, :, :, :]).sum(axis=1)  # (L, m, N)
    return PointFeatures(
        points=points,
        drift=np.ascontiguousarray(drift),
        input=np.ascontiguousarray(inp.transpose(1, 0, 2)),
        state_cost=state_cost(points, np.asarray(Q, dtype=float)),
    )


def extrapolate(
    features: PointFeatures,
    W: np.ndarray,
    r: np.ndarray,
    input_bound: float,
    nu: float,
) -> BellmanExtrapolation:
    """Bellman errors at every point for weights ``W`` and their normalized sums.

    Parameters
    ----------
    features : PointFeatures
        From :func:`point_features`.
    W : ndarray, shape (L,)
        Critic weights.
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    nu : float
        Normalization gain of ``rho_i = 1 + nu omega_i^T omega_i``.
    """
    W = np.asarray(W, dtype=float)
    D = policy_argument(features.input, W, r, input_bound)  # (m, N)
    u = -input_bound * np.tanh(D)
    omega = features.drift + (features.input * u[:, None, :]).sum(axis=0)  # (L, N)
    delta = W @ omega + features.state_cost + input_cost_from_D(D, r, input_bound)
    rho = 1.0 + nu * (omega * omega).sum(axis=0)
    n_points = omega.shape[1]
    weighted = omega / rho
    critic_sum = weighted @ delta / n_points
    gain_sum = weighted @ weighted.T / n_points
    return BellmanExtrapolation(
        D=D,
        u=u,
        omega=omega,
        delta=delta,
        rho=rho,
        critic_sum=critic_sum,
        gain_sum=gain_sum,
    )


def learning_condition(gain_sum: np.ndarray) -> float:
    """``lambda_min`` of the symmetric matrix ``gain_sum`` (Assumption 2)."""
    return float(np.linalg.eigvalsh(gain_sum)[0])
