"""The critic's learning laws beyond the paper: units, a bounded gain, safe policy updates.

The paper's laws (W_c) and (gamma) learn on its two-state example. On Drake's
plants they do not (``docs/learning.md``): the regressors ``omega_i`` are badly
scaled, the forgetting term grows Gamma without bound whenever the learning
condition is small, and nothing stops the critic from leaving the stabilising
policies. ``critic.law: policy_iteration`` (the default) changes three things
and keeps the update laws' form; ``critic.law: paper`` keeps them as printed.

**Units.** The basis functions are monomials of the state, so a weight's
units, and the size of ``omega_i``, depend on the state's units. The
normalization uses the metric ``M = diag(1 / d_l^2)`` with ``d_l = prod_j
s_j^{e_lj}`` the size of monomial ``l`` on the points' box (``s_j`` its
half-width along ``x_j``): ``rho_i = 1 + nu omega_i^T M omega_i``. In the
scaled state ``z_j = x_j / s_j`` that is the paper's ``rho``, so a plant and
its twin in other units (points, box and cost transformed alike) learn the
same policy (:func:`basis_scales`).

**A bounded least-squares gain.** Bounded-gain forgetting (Slotine and Li,
*Applied Nonlinear Control*, 1991, section 8.7.6): the forgetting factor of
(gamma) shrinks as Gamma grows,

    beta(t) = beta (1 - tr(Gamma0^{-1} Gamma) / (k0 L)),

so ``tr(Gamma0^{-1} Gamma) <= max(L, k0 L)`` for all time whatever the
learning condition (``k0 = critic.gamma_bound``), as the paper's Lemma 1
assumes; Gamma stays positive definite since ``d(Gamma^{-1})/dt = -beta(t)
Gamma^{-1} + k_c S`` with ``beta(t) <= beta`` (:func:`bounded_forgetting`).

**Policy iteration with an acceptance test.** The Bellman errors follow the
policy *in force* ``W_pi``, not the critic's moving weights, so the critic law
is linear least squares: it converges to the value of the policy in force on
the points (policy evaluation). Every ``critic.policy_period`` seconds the
critic's weights become the policy in force (policy improvement) if
:func:`check_policy` accepts them: the quadratic part ``P`` of ``V = W^T
sigma`` must be positive definite, ``V`` itself positive at every point but
the origin (which ``P > 0`` implies only for a quadratic basis), the
linearized loop ``A + B K`` of its policy ``K = -R^{-1} B^T P`` (the
linearization of ``u = -lbar tanh(D)``) must be Hurwitz, and its local cost
``tr(P_K M)``, the linearized loop's cost ``x^T P_K x`` averaged over the
points (``M`` their second moment), must not exceed that of the policy in
force. So an update never puts in force a
policy whose linearization at the target is unstable, and never makes the
local performance worse; every rejection is logged. With exact evaluation of
a linear plant this is Kleinman's iteration (Kleinman, IEEE TAC 13(1), 1968),
which passes the test at every step: it keeps stability and lowers the cost
monotonically. The paper's simultaneous law is the case ``W_pi = W``.

What was measured before choosing this test (``docs/learning.md``): without
``P > 0`` it accepted an indefinite value on the cart-pole whose policy costs
four times J*; without the local-cost condition the approximate iteration
drifted on a cart with a hardening spring to 1.09 times the LQR policy's
cost; requiring ``P`` to be a Lyapunov function of ``A + B K`` as well refused
every evaluation on that plant, since a quadratic fitted over a box of a
nonlinear plant is not the value of its linearization.

**Gains from the plant and the points** (``critic.gains: auto``,
:func:`auto_gains`): ``nu`` makes the median ``nu omega_i^T M omega_i`` one at
``W0``; ``policy_period`` is a tenth of the horizon and ``beta = 5 /
policy_period``; ``Gamma0 = (beta / k_c) S0^{-1}``, the steady state of (gamma)
at a constant ``beta`` for the gain sum ``S0 = (1/N) sum omega_i omega_i^T /
rho_i^2`` at ``W0``. The weights then settle at the rates ``beta eig(S0^{-1}
S1)`` (``S1`` has one ``rho_i`` where ``S0`` has two): at least ``beta``, and
unequal across directions (see :func:`auto_gains`).

Everything here is numpy; the blocks are :class:`~ofrl_drake.systems.GammaGain`
and :class:`~ofrl_drake.systems.PolicyGate`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.checks import positive_number
from ofrl_drake.errors import ModelError

__all__ = [
    "LAWS",
    "CriticSettings",
    "LearningGains",
    "PolicyCheck",
    "auto_gains",
    "basis_scales",
    "bounded_forgetting",
    "check_policy",
    "linear_policy_gain",
    "rho_metric",
    "second_moment",
    "spectral_abscissa",
    "value_matrix",
    "value_weights",
]

#: The critic's learning laws (``critic.law``).
LAWS = ("policy_iteration", "paper")

#: ``critic.gamma_bound`` by default: Gamma may grow to ten times Gamma0 on average.
DEFAULT_GAMMA_BOUND = 10.0

#: The policy period by default, as a fraction of the horizon.
POLICY_PERIOD_FRACTION = 0.1


def basis_scales(basis: PolynomialBasis, points: np.ndarray) -> np.ndarray:
    """``d_l = prod_j s_j^{e_lj}``: the size of each monomial on the points' box.

    ``s_j`` is the half-width of the points along ``x_j`` (half of the
    largest minus the smallest coordinate). Rescaling the state by ``T =
    diag(t_j)`` (and the points with it) multiplies ``d_l`` by ``prod_j
    t_j^{e_lj}``, the factor a weight is divided by.

    Parameters
    ----------
    basis : PolynomialBasis
    points : ndarray, shape (n, N)

    Returns
    -------
    ndarray, shape (L,)

    Raises
    ------
    ModelError
        If the points do not spread along some axis (then no scale can be read off).
    """
    points = np.asarray(points, dtype=float)
    half = 0.5 * (points.max(axis=1) - points.min(axis=1))
    if not np.all(np.isfinite(half) & (half > 0)):
        flat = [int(j) for j in np.flatnonzero(~(half > 0))]
        raise ModelError(
            f"the extrapolation points do not spread along state axes {flat}; the "
            "normalized law reads the state's scale from them. Give points a box of "
            "positive width along every axis."
        )
    return np.prod(half[None, :] ** basis.exponents, axis=1)


def rho_metric(scales: np.ndarray) -> np.ndarray:
    """The diagonal ``1 / d_l^2`` of ``M`` in ``rho_i = 1 + nu omega_i^T M omega_i``."""
    return 1.0 / np.asarray(scales, dtype=float) ** 2


def bounded_forgetting(beta: float, trace_ratio: float, bound: float) -> float:
    """Slotine and Li's bounded-gain forgetting factor ``beta (1 - trace_ratio / bound)``.

    Parameters
    ----------
    beta : float
        The largest forgetting factor.
    trace_ratio : float
        ``tr(Gamma0^{-1} Gamma) / L``: 1 at the start.
    bound : float
        ``k0``: the forgetting factor vanishes at ``trace_ratio = k0`` and is
        negative beyond, so the ratio never exceeds ``max(1, k0)``.
    """
    return beta * (1.0 - trace_ratio / bound)


def value_matrix(basis: PolynomialBasis, W: np.ndarray) -> np.ndarray:
    """``P`` with ``V(x) = x^T P x + O(|x|^3)``: the quadratic part of ``W^T sigma``.

    Parameters
    ----------
    basis : PolynomialBasis
    W : ndarray, shape (L,) or (T, L)

    Returns
    -------
    ndarray, shape (n, n) or (T, n, n)
        Symmetric; zero when the basis has no monomial of degree 2.
    """
    W = np.asarray(W, dtype=float)
    batch = W.ndim == 2
    Ws = W if batch else W[None, :]
    n = basis.n
    P = np.zeros((Ws.shape[0], n, n))
    for l, e in enumerate(basis.exponents):
        if e.sum() != 2:
            continue
        idx = np.flatnonzero(e)
        if idx.size == 1:
            i = j = int(idx[0])
            P[:, i, i] += Ws[:, l]
        else:
            i, j = (int(k) for k in idx)
            P[:, i, j] += 0.5 * Ws[:, l]
            P[:, j, i] += 0.5 * Ws[:, l]
    return P if batch else P[0]


def value_weights(basis: PolynomialBasis, P: np.ndarray) -> np.ndarray:
    """The weights ``W`` with ``W^T sigma(x) = x^T P x``: :func:`value_matrix`'s inverse.

    Monomials of other degrees get weight 0.

    Raises
    ------
    ModelError
        If the basis has no monomial of degree 2.
    """
    P = np.asarray(P, dtype=float)
    W = np.zeros(basis.size)
    found = False
    for l, e in enumerate(basis.exponents):
        if e.sum() != 2:
            continue
        found = True
        idx = np.flatnonzero(e)
        i, j = (int(idx[0]), int(idx[0])) if idx.size == 1 else (int(idx[0]), int(idx[1]))
        W[l] = P[i, i] if i == j else P[i, j] + P[j, i]
    if not found:
        raise ModelError(f"{basis!r} has no monomial of degree 2, so no quadratic value.")
    return W


def linear_policy_gain(B: np.ndarray, r: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``K = -R^{-1} B^T P``: the linearization at 0 of ``u = -lbar tanh(D)`` for ``V = x^T P x``.

    ``P`` may be a batch ``(T, n, n)``; then ``K`` is ``(T, m, n)``.
    """
    B = np.asarray(B, dtype=float)
    r = np.asarray(r, dtype=float)
    return -(B.T / r[:, None]) @ np.asarray(P, dtype=float)


def spectral_abscissa(A: np.ndarray) -> np.ndarray:
    """The largest real part of the eigenvalues of ``A`` (a batch ``(T, n, n)`` gives ``(T,)``)."""
    A = np.asarray(A, dtype=float)
    finite = np.all(np.isfinite(A), axis=(-2, -1))
    out = np.full(A.shape[:-2], np.nan)
    if np.any(finite):
        out[finite] = np.linalg.eigvals(A[finite]).real.max(axis=-1)
    return out


@dataclass(frozen=True)
class PolicyCheck:
    """What the acceptance test reads off one set of weights (:func:`check_policy`).

    Attributes
    ----------
    admissible : bool
        ``P > 0``, ``A + B K`` Hurwitz and, when the points were given, ``V =
        W^T sigma`` positive at every point but the origin.
    local_cost : float
        ``tr(P_K M)``: the cost of the policy's linearized loop averaged over
        the points, with ``P_K`` from ``(A + B K)^T P_K + P_K (A + B K) + Q +
        K^T R K = 0`` and ``M = (1/N) sum_i x_i x_i^T``; ``inf`` when not
        admissible.
    value_min_eigenvalue : float
        ``lambda_min(P)``.
    lyapunov_max_eigenvalue : float
        ``lambda_max((A + B K)^T P + P (A + B K))``: negative when ``P`` is
        also a Lyapunov function of the linearized loop (reported, not required).
    spectral_abscissa : float
        Of the linearized loop ``A + B K``.
    value_min_at_points : float
        The smallest ``V(x_i) = W^T sigma(x_i)`` over the points other than
        the origin; NaN when no points were given (or all are the origin).
    """

    admissible: bool
    local_cost: float
    value_min_eigenvalue: float
    lyapunov_max_eigenvalue: float
    spectral_abscissa: float
    value_min_at_points: float = float("nan")

    def improves_on(self, current: PolicyCheck) -> bool:
        """Whether this policy may replace ``current``: admissible, and no larger local cost.

        Costs equal to within :data:`COST_ROUNDOFF` (relative) count as equal: a
        converged policy iteration re-evaluates the same policy, and its cost
        then moves by a few units in the last place.
        """
        bound = current.local_cost * (1.0 + COST_ROUNDOFF)
        return self.admissible and self.local_cost <= bound


#: Relative round-off allowed when comparing two local costs (:meth:`PolicyCheck.improves_on`).
COST_ROUNDOFF = 1e-12


def check_policy(
    A: np.ndarray,
    B: np.ndarray,
    Q: np.ndarray,
    r: np.ndarray,
    basis: PolynomialBasis,
    W: np.ndarray,
    moment: np.ndarray,
    *,
    points: np.ndarray | None = None,
) -> PolicyCheck:
    """The acceptance test's view of the policy of ``V = W^T sigma`` at the target.

    ``P``, ``K`` and the local cost read only the quadratic part of ``V``.
    With a basis of higher degree that is not enough: a fit whose quadratic
    part is positive definite can still be negative on the points, and its
    greedy policy then drives the plant away (``docs/learning.md``). The value
    of a policy is positive wherever the running cost is, so with ``points``
    the test also requires ``V(x_i) > 0`` at every point but the origin; for
    a basis of degree 2 only, that already follows from ``P > 0``.

    Parameters
    ----------
    A, B : ndarray
        The plant's linearization at the target, ``x' = A x + B u``.
    Q : ndarray, shape (n, n)
        State weight.
    r : ndarray, shape (m,)
        Diagonal of R.
    basis : PolynomialBasis
    W : ndarray, shape (L,)
    moment : ndarray, shape (n, n)
        ``M``, the second moment of the extrapolation points.
    points : ndarray, shape (n, N), optional
        The extrapolation points, where ``V`` must be positive.

    Returns
    -------
    PolicyCheck
    """
    from scipy.linalg import solve_continuous_lyapunov

    P = value_matrix(basis, W)
    nan = float("nan")
    if not np.all(np.isfinite(P)):
        return PolicyCheck(False, float("inf"), nan, nan, nan)
    value_min_at_points, positive_at_points = nan, True
    if points is not None:
        X = np.asarray(points, dtype=float)
        away = X[:, np.any(X != 0.0, axis=0)]
        if away.shape[1]:
            value_min_at_points = float(np.min(np.asarray(W, dtype=float) @ basis(away)))
            positive_at_points = value_min_at_points > 0.0  # False for NaN too
    K = linear_policy_gain(B, r, P)
    Acl = np.asarray(A, dtype=float) + np.asarray(B, dtype=float) @ K
    lyapunov = Acl.T @ P + P @ Acl
    value_min = float(np.linalg.eigvalsh(P)[0])
    lyapunov_max = float(np.linalg.eigvalsh(0.5 * (lyapunov + lyapunov.T))[-1])
    abscissa = float(spectral_abscissa(Acl))
    admissible = bool(value_min > 0.0 and abscissa < 0.0 and positive_at_points)
    local_cost = float("inf")
    if admissible:
        stage = np.asarray(Q, dtype=float) + K.T @ (np.asarray(r, dtype=float)[:, None] * K)
        P_K = solve_continuous_lyapunov(Acl.T, -stage)
        local_cost = float(np.trace(P_K @ np.asarray(moment, dtype=float)))
    return PolicyCheck(
        admissible=admissible,
        local_cost=local_cost,
        value_min_eigenvalue=value_min,
        lyapunov_max_eigenvalue=lyapunov_max,
        spectral_abscissa=abscissa,
        value_min_at_points=value_min_at_points,
    )


def second_moment(points: np.ndarray) -> np.ndarray:
    """``M = (1/N) sum_i x_i x_i^T`` of the points ``(n, N)``."""
    points = np.asarray(points, dtype=float)
    return points @ points.T / points.shape[1]


@dataclass(frozen=True)
class LearningGains:
    """The gains of the critic and Gamma laws (given, or derived by :func:`auto_gains`).

    ``policy_period`` and ``gamma_bound`` are None under the paper's law.
    """

    kc: float
    nu: float
    beta: float
    Gamma0: np.ndarray
    policy_period: float | None = None
    gamma_bound: float | None = None


@dataclass(frozen=True)
class CriticSettings:
    """The critic's learning law and gains in force (:func:`ofrl_drake.diagram.critic_settings`).

    Attributes
    ----------
    law : str
        ``policy_iteration`` or ``paper`` (:data:`LAWS`).
    gains : LearningGains
        As given (``critic.gains: manual``) or derived (``auto``).
    metric : ndarray or None
        The diagonal of the metric of ``rho`` (None: the paper's identity).
    linearization : tuple of ndarray or None
        ``(A, B)`` at the target, for the policy acceptance test and the
        learning-health logs; None if it cannot be computed.
    """

    law: str
    gains: LearningGains
    metric: np.ndarray | None
    linearization: tuple[np.ndarray, np.ndarray] | None


def auto_gains(
    gain_sum_at: Callable[[float], np.ndarray],
    rho_terms: np.ndarray,
    horizon: float,
    policy_period: float | None = None,
) -> LearningGains:
    """Learning gains from the plant, the points and the horizon (``critic.gains: auto``).

    Parameters
    ----------
    gain_sum_at : callable
        ``nu -> S0``: the gain sum ``(1/N) sum omega_i omega_i^T / rho_i^2``
        at ``W0`` for a normalization gain ``nu``.
    rho_terms : ndarray, shape (N,)
        ``omega_i^T M omega_i`` at ``W0``.
    horizon : float
        The scenario's horizon T.
    policy_period : float, optional
        Seconds between policy improvements when the scenario gives them
        (``critic.policy_period``); by default ``T / 10``.

    Returns
    -------
    LearningGains
        ``kc = 1``; ``nu = 1 / median(rho_terms)``; ``policy_period`` as
        given, or ``T / 10``; ``beta = 5 / policy_period``;
        ``Gamma0 = (beta / kc) S0^{-1}`` with the eigenvalues of ``S0``
        floored at ``1e-9`` times its largest, so that ``Gamma0`` is symmetric
        positive definite even where the points excite a direction of the
        basis weakly; ``gamma_bound = 10``.

    Raises
    ------
    ModelError
        If every ``omega_i`` vanishes at ``W0`` (no point excites the critic),
        or ``policy_period`` is not a number > 0.

    Notes
    -----
    ``Gamma0`` is the steady state of (gamma) at the constant ``beta`` for the
    gain sum ``S0``, but the critic's weights do not converge at rate ``beta``
    in every direction. With the policy held fixed, ``critic_sum`` is affine
    in ``W`` with slope ``S1 = (1/N) sum omega_i omega_i^T / rho_i`` (one
    ``rho_i``, where ``S0`` has two), so at ``Gamma = Gamma0`` the weights
    settle at the rates ``beta eig(S0^{-1} S1)``: at least ``beta`` since
    ``rho_i >= 1`` (where the floor above is not active), and unequal across
    directions (at ``W0``: 1.57 to 4.27 ``beta`` on ``pendulum_upright``, 1.37
    to 4.91 ``beta`` on ``cart_pole``). With bounded forgetting
    (``policy_iteration``, ``gamma_bound = k0 = 10``) the forgetting factor
    is ``0.9 beta`` at ``Gamma0``, so Gamma settles near ``k0 / (k0 + 1)
    Gamma0 ~ 0.91 Gamma0``, not at ``Gamma0``. ``beta = 5 / policy_period``
    aims at an evaluation settled to ``e^-5`` before the next improvement;
    that argument is conservative whenever the smallest ``eig(S0^{-1} S1)``
    exceeds ``(k0 + 1) / k0``, as on those plants.
    """
    terms = np.asarray(rho_terms, dtype=float)
    typical = float(np.median(terms[np.isfinite(terms)])) if terms.size else 0.0
    if not typical > 0.0:
        raise ModelError(
            "critic.gains: auto: the regressors omega_i vanish at W0 at half of the points "
            "or more, so no normalization can be read off; move the points away from the "
            "origin, or set critic.gains: manual with kc, nu, beta and Gamma0."
        )
    nu = 1.0 / typical
    kc = 1.0
    if policy_period is None:
        period = POLICY_PERIOD_FRACTION * float(horizon)
    else:
        period = positive_number("critic.policy_period", policy_period)
    beta = 5.0 / period
    S0 = np.asarray(gain_sum_at(nu), dtype=float)
    S0 = 0.5 * (S0 + S0.T)
    eigenvalues, vectors = np.linalg.eigh(S0)
    floored = np.maximum(eigenvalues, 1e-9 * eigenvalues[-1])
    Gamma0 = (beta / kc) * (vectors / floored) @ vectors.T
    Gamma0 = 0.5 * (Gamma0 + Gamma0.T)
    return LearningGains(
        kc=kc,
        nu=nu,
        beta=beta,
        Gamma0=Gamma0,
        policy_period=period,
        gamma_bound=DEFAULT_GAMMA_BOUND,
    )
