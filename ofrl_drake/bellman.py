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
from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem

__all__ = [
    "BellmanExtrapolation",
    "Extrapolator",
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
        raise ModelError(f"points must have shape (n, N) = ({system.n}, N); got {points.shape}.")
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


class Extrapolator:
    """:func:`extrapolate` for fixed ``r``, ``lbar`` and ``nu``.

    The scalings that do not depend on ``W`` are applied to the point data
    once here, so that each call is only the ``W``-dependent work; the
    Bellman-extrapolation block holds one of these.

    Parameters
    ----------
    features : PointFeatures
        From :func:`point_features`.
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    nu : float
        Normalization gain of ``rho_i = 1 + nu omega_i^T omega_i``.
    """

    def __init__(
        self, features: PointFeatures, r: np.ndarray, input_bound: float, nu: float
    ) -> None:
        self.features = features
        self.r = np.asarray(r, dtype=float)
        self.input_bound = float(input_bound)
        self.nu = float(nu)
        # D = W @ policy_input, policy_input[k] = input[k] / (2 lbar r_k).
        denominator = 2.0 * self.input_bound * self.r
        self._policy_input = features.input / denominator[:, None, None]

    def __call__(self, W: np.ndarray) -> BellmanExtrapolation:
        """The extrapolation for critic weights ``W`` (shape ``(L,)``)."""
        f = self.features
        W = np.asarray(W, dtype=float)
        D = np.matmul(W, self._policy_input)  # (m, N)
        tanh_D = np.tanh(D)
        u = -self.input_bound * tanh_D
        omega = f.drift.copy()  # (L, N)
        for k in range(u.shape[0]):  # a loop over inputs, not points
            omega += f.input[k] * u[k]
        delta = W @ omega
        delta += f.state_cost
        delta += input_cost_from_D(D, self.r, self.input_bound, tanh_D=tanh_D)
        rho = (omega * omega).sum(axis=0)
        rho *= self.nu
        rho += 1.0
        weighted = omega / rho
        n_points = omega.shape[1]
        return BellmanExtrapolation(
            D=D,
            u=u,
            omega=omega,
            delta=delta,
            rho=rho,
            critic_sum=(weighted @ delta) / n_points,
            gain_sum=(weighted @ weighted.T) / n_points,
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

    See Also
    --------
    Extrapolator : the same for many ``W`` with fixed ``r``, ``lbar``, ``nu``.
    """
    return Extrapolator(features, r, input_bound, nu)(W)


def learning_condition(gain_sum: np.ndarray) -> float:
    """``lambda_min`` of the symmetric matrix ``gain_sum`` (Assumption 2)."""
    return float(np.linalg.eigvalsh(gain_sum)[0])
