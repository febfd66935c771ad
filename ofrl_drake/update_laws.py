"""The critic's and Gamma's update laws in plain numpy, written as the equations.

This is the readable form of the laws, vectorized over the points. The
simulation runs the compiled fast path: :func:`ofrl_drake.bellman.bellman_kernel`
(one pass over the points for both sums), :func:`ofrl_drake.bellman.critic_rate`
and :func:`ofrl_drake.bellman.gamma_rate` inside the blocks
:class:`~ofrl_drake.systems.BellmanExtrapolator`,
:class:`~ofrl_drake.systems.CriticWeights` and
:class:`~ofrl_drake.systems.GammaGain`. ``tests/test_bellman.py`` checks those
against the functions here on random data, under both laws.

At each extrapolation point ``x_i``, ``i = 1..N``, with the precomputed
``grad sigma_i f_i``, ``grad sigma_i g_i`` and ``Q(x_i)``
(:class:`~ofrl_drake.bellman.PointFeatures`), the Bellman errors are

    D_i     = (1 / (2 lbar)) R^{-1} (grad sigma_i g_i)^T W_pi        (m,)
    u_i     = -lbar tanh(D_i)                                       (u_app)
    omega_i = grad sigma_i (f_i + g_i u_i)                          (L,)
    delta_i = W^T omega_i + Q(x_i) + U(u_i)                         (BE1_i)

normalized by ``rho_i = 1 + nu omega_i^T M omega_i`` into the regressor
``q_i = omega_i / rho_i``, whose means over the points are

    critic_sum = (1/N) sum_i q_i delta_i        = (1/N) sum_i omega_i delta_i / rho_i
    gain_sum   = (1/N) sum_i q_i q_i^T          = (1/N) sum_i omega_i omega_i^T / rho_i^2

and the laws are

    W'      = -k_c Gamma critic_sum                                   (W_c)
    Gamma'  = beta(t) Gamma - k_c Gamma gain_sum Gamma                (gamma)

with ``beta(t) = beta``, or with bounded-gain forgetting (``k0 = gamma_bound``,
:func:`ofrl_drake.learning.bounded_forgetting`)

    beta(t) = beta (1 - tr(Gamma0^{-1} Gamma) / (k0 L)).

The two laws (``critic.law``) differ in the policy the errors follow:
``paper`` takes ``W_pi = W``, the critic's own weights, as printed;
``policy_iteration`` takes ``W_pi`` the policy in force (and the simulation
passes the points' metric ``M``, :func:`ofrl_drake.learning.rho_metric`, where
the paper's ``M`` is the identity). See :mod:`ofrl_drake.learning`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ofrl_drake.bellman import BellmanSums, PointFeatures
from ofrl_drake.cost import input_cost_from_D
from ofrl_drake.errors import ModelError
from ofrl_drake.learning import LAWS, LearningGains, bounded_forgetting

__all__ = [
    "BellmanErrors",
    "UpdateRates",
    "bellman_errors",
    "critic_rate",
    "forgetting_factor",
    "gamma_rate",
    "normalization",
    "normalized_regressor",
    "normalized_sums",
    "policy_weights",
    "update_rates",
]


@dataclass(frozen=True)
class BellmanErrors:
    """The Bellman errors at ``N`` points and what they are made of.

    Attributes
    ----------
    D : ndarray, shape (m, N)
        ``(1 / (2 lbar)) R^{-1} (grad sigma_i g_i)^T W_pi``.
    u : ndarray, shape (m, N)
        ``-lbar tanh(D_i)``.
    omega : ndarray, shape (L, N)
        ``grad sigma_i (f_i + g_i u_i)``.
    delta : ndarray, shape (N,)
        ``W^T omega_i + Q(x_i) + U(u_i)``.
    """

    D: np.ndarray
    u: np.ndarray
    omega: np.ndarray
    delta: np.ndarray


@dataclass(frozen=True)
class UpdateRates:
    """The right-hand sides of (W_c) and (gamma), and the sums they use.

    Attributes
    ----------
    W_dot : ndarray, shape (L,)
    Gamma_dot : ndarray, shape (L, L)
    sums : BellmanSums
        ``critic_sum`` and ``gain_sum``.
    beta : float
        The forgetting factor ``beta(t)`` in force.
    """

    W_dot: np.ndarray
    Gamma_dot: np.ndarray
    sums: BellmanSums
    beta: float


def _weights(name: str, W: np.ndarray, size: int) -> np.ndarray:
    W = np.asarray(W, dtype=float)
    if W.shape != (size,):
        raise ModelError(f"{name} must have shape (L,) = ({size},); got {W.shape}.")
    return W


def policy_weights(law: str, W: np.ndarray, W_policy: np.ndarray | None = None) -> np.ndarray:
    """``W_pi``, the weights of the policy the Bellman errors follow under ``law``.

    ``paper``: the critic's own ``W``. ``policy_iteration``: ``W_policy``,
    the policy in force.

    Raises
    ------
    ModelError
        If ``law`` is not one of :data:`ofrl_drake.learning.LAWS`, or
        ``policy_iteration`` is given no ``W_policy``.
    """
    if law not in LAWS:
        raise ModelError(f"law must be one of {list(LAWS)}; got {law!r}.")
    if law == "paper":
        return np.asarray(W, dtype=float)
    if W_policy is None:
        raise ModelError(
            "law 'policy_iteration' needs W_policy, the weights of the policy in force; "
            "pass W_policy, or use law 'paper' for the critic's own weights."
        )
    return np.asarray(W_policy, dtype=float)


def bellman_errors(
    features: PointFeatures,
    W: np.ndarray,
    W_policy: np.ndarray,
    r: np.ndarray,
    input_bound: float,
) -> BellmanErrors:
    """(BE1_i) at every point: the value's weights ``W``, the policy's ``W_policy``.

    Parameters
    ----------
    features : PointFeatures
        ``grad sigma_i f_i`` (``drift``, (L, N)), ``grad sigma_i g_i``
        (``input``, (m, L, N), input index first) and ``Q(x_i)``.
    W : ndarray, shape (L,)
        The weights of the value in ``delta_i``.
    W_policy : ndarray, shape (L,)
        ``W_pi``, the weights of the policy ``u_i`` (:func:`policy_weights`).
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    """
    grad_sigma_g = features.input  # (m, L, N): [k, a, i] = (grad sigma_i g_i)_{a k}
    L = features.drift.shape[0]
    W = _weights("W", W, L)
    W_pi = _weights("W_policy", W_policy, L)
    r = np.asarray(r, dtype=float)
    D = np.einsum("kai,a->ki", grad_sigma_g, W_pi) / (2.0 * input_bound * r[:, None])
    u = -input_bound * np.tanh(D)
    omega = features.drift + np.einsum("kai,ki->ai", grad_sigma_g, u)
    U = input_cost_from_D(D, r, input_bound)  # U(u_i), from D_i: finite for every D
    delta = W @ omega + features.state_cost + U
    return BellmanErrors(D=D, u=u, omega=omega, delta=delta)


def normalization(omega: np.ndarray, nu: float, metric: np.ndarray | None = None) -> np.ndarray:
    """``rho_i = 1 + nu omega_i^T M omega_i``, with ``M = diag(metric)`` (default identity).

    Parameters
    ----------
    omega : ndarray, shape (L, N)
    nu : float
    metric : ndarray, shape (L,), optional

    Returns
    -------
    ndarray, shape (N,)
    """
    M = np.ones(omega.shape[0]) if metric is None else np.asarray(metric, dtype=float)
    return 1.0 + nu * np.einsum("ai,a,ai->i", omega, M, omega)


def normalized_regressor(omega: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """``q_i = omega_i / rho_i``, shape (L, N)."""
    return omega / rho


def normalized_sums(omega: np.ndarray, delta: np.ndarray, rho: np.ndarray) -> BellmanSums:
    """``critic_sum = (1/N) sum_i q_i delta_i`` and ``gain_sum = (1/N) sum_i q_i q_i^T``.

    With ``q_i = omega_i / rho_i`` (:func:`normalized_regressor`); ``omega``
    (L, N), ``delta`` and ``rho`` (N,).
    """
    q = normalized_regressor(omega, rho)
    N = q.shape[1]
    return BellmanSums(critic_sum=q @ delta / N, gain_sum=q @ q.T / N)


def critic_rate(Gamma: np.ndarray, critic_sum: np.ndarray, kc: float) -> np.ndarray:
    """(W_c): ``W' = -k_c Gamma critic_sum``; ``Gamma`` (L, L), ``critic_sum`` (L,)."""
    return -kc * (Gamma @ critic_sum)


def forgetting_factor(
    beta: float,
    Gamma: np.ndarray,
    Gamma0: np.ndarray | None = None,
    gamma_bound: float | None = None,
) -> float:
    """``beta(t)``: ``beta``, or ``beta (1 - tr(Gamma0^{-1} Gamma) / (k0 L))`` given ``k0``.

    ``k0 = gamma_bound``: bounded-gain forgetting
    (:func:`ofrl_drake.learning.bounded_forgetting`); None keeps ``beta``.

    Raises
    ------
    ModelError
        If ``gamma_bound`` is given without ``Gamma0``.
    """
    if gamma_bound is None:
        return float(beta)
    if Gamma0 is None:
        raise ModelError(
            f"gamma_bound = {gamma_bound} needs Gamma0, the initial gain it bounds Gamma "
            "against; pass Gamma0, or gamma_bound=None for a constant beta."
        )
    L = Gamma.shape[0]
    trace_ratio = np.trace(np.linalg.solve(Gamma0, Gamma)) / L
    return bounded_forgetting(float(beta), float(trace_ratio), float(gamma_bound))


def gamma_rate(Gamma: np.ndarray, gain_sum: np.ndarray, kc: float, beta: float) -> np.ndarray:
    """(gamma): ``Gamma' = beta Gamma - k_c Gamma gain_sum Gamma``.

    ``Gamma`` is taken as its symmetric part ``(Gamma + Gamma^T) / 2``, so
    that round-off never makes it drift from symmetry; the compiled law
    carries Gamma packed (its upper triangle, ``bellman.pack_symmetric``),
    which is symmetric by construction.

    Parameters
    ----------
    Gamma, gain_sum : ndarray, shape (L, L)
    kc : float
    beta : float
        ``beta(t)`` (:func:`forgetting_factor`).
    """
    G = 0.5 * (Gamma + Gamma.T)
    return beta * G - kc * (G @ gain_sum @ G)


def update_rates(
    features: PointFeatures,
    W: np.ndarray,
    Gamma: np.ndarray,
    gains: LearningGains,
    *,
    law: str,
    r: np.ndarray,
    input_bound: float,
    W_policy: np.ndarray | None = None,
    metric: np.ndarray | None = None,
) -> UpdateRates:
    """``W'`` and ``Gamma'`` at the critic's state ``(W, Gamma)``, from the points up.

    Parameters
    ----------
    features : PointFeatures
    W : ndarray, shape (L,)
        The critic's weights.
    Gamma : ndarray, shape (L, L)
    gains : LearningGains
        ``kc``, ``nu``, ``beta``, ``Gamma0`` and ``gamma_bound`` (None: constant ``beta``).
    law : str
        ``paper`` or ``policy_iteration`` (:func:`policy_weights`).
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    W_policy : ndarray, shape (L,), optional
        The policy in force; needed by ``policy_iteration``, unused by ``paper``.
    metric : ndarray, shape (L,), optional
        Diagonal of ``M`` in ``rho`` (default identity).
    """
    W_pi = policy_weights(law, W, W_policy)
    errors = bellman_errors(features, W, W_pi, r, input_bound)
    rho = normalization(errors.omega, gains.nu, metric)
    sums = normalized_sums(errors.omega, errors.delta, rho)
    Gamma = np.asarray(Gamma, dtype=float)
    beta = forgetting_factor(gains.beta, Gamma, gains.Gamma0, gains.gamma_bound)
    return UpdateRates(
        W_dot=critic_rate(Gamma, sums.critic_sum, gains.kc),
        Gamma_dot=gamma_rate(Gamma, sums.gain_sum, gains.kc, beta),
        sums=sums,
        beta=beta,
    )
