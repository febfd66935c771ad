"""The learning-law math of ofrl_drake.learning, in numpy only."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import solve_continuous_are

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import Extrapolator, point_features
from ofrl_drake.errors import ModelError
from ofrl_drake.examples import make_system
from ofrl_drake.learning import (
    auto_gains,
    basis_scales,
    bounded_forgetting,
    check_policy,
    linear_policy_gain,
    rho_metric,
    spectral_abscissa,
    value_matrix,
    value_weights,
)
from ofrl_drake.points import grid_points

from .conftest import ROOT

# A double integrator: x1' = x2, x2' = u.
A = np.array([[0.0, 1.0], [0.0, 0.0]])
B = np.array([[0.0], [1.0]])
R = np.array([1.0])


def _lqr_value(Q):
    return solve_continuous_are(A, B, Q, np.diag(R))


# ------------------------------------------------------------ value matrix
@settings(max_examples=50, deadline=None)
@given(st.integers(1, 4), st.data())
def test_value_weights_invert_value_matrix(n, data):
    basis = PolynomialBasis(n, (2, 4))
    entries = data.draw(
        st.lists(st.floats(-5, 5), min_size=n * n, max_size=n * n), label="P entries"
    )
    M = np.asarray(entries).reshape(n, n)
    P = 0.5 * (M + M.T)
    W = value_weights(basis, P)
    np.testing.assert_allclose(value_matrix(basis, W), P, rtol=0, atol=1e-12)
    # and V(x) = x^T P x for the quadratic part (degree-4 weights are zero)
    x = np.linspace(-1.0, 1.0, n)
    np.testing.assert_allclose(W @ basis(x), x @ P @ x, rtol=1e-12, atol=1e-12)


def test_value_matrix_of_a_batch_matches_one_at_a_time():
    basis = PolynomialBasis(3)
    Ws = np.random.default_rng(0).normal(size=(5, basis.size))
    batch = value_matrix(basis, Ws)
    for W, P in zip(Ws, batch, strict=True):
        np.testing.assert_array_equal(value_matrix(basis, W), P)


def test_value_weights_need_a_quadratic_monomial():
    with pytest.raises(ModelError, match=r"has no monomial of degree 2"):
        value_weights(PolynomialBasis(2, (4,)), np.eye(2))


def test_linear_policy_gain_is_the_linearized_saturated_policy():
    """u = -lbar tanh(D) with D = (1/(2 lbar)) R^{-1} B^T 2 P x has du/dx = -R^{-1} B^T P."""
    P = _lqr_value(np.eye(2))
    K = linear_policy_gain(B, R, P)
    lbar, h = 3.0, 1e-6
    for e in np.eye(2):
        D = lambda x: (1 / (2 * lbar)) / R * (B.T @ (2 * P @ x))  # noqa: E731
        du = (-lbar * np.tanh(D(h * e)) + lbar * np.tanh(D(-h * e))) / (2 * h)
        np.testing.assert_allclose(du, K @ e, rtol=1e-8)


# ------------------------------------------------------------ acceptance
MOMENT = np.diag([0.3, 0.5])  # second moment of some points


def _check(P, Q=None):
    basis = PolynomialBasis(2)
    Q = np.eye(2) if Q is None else Q
    return check_policy(A, B, Q, R, basis, value_weights(basis, P), MOMENT)


def test_the_lqr_value_and_its_multiples_are_admissible_and_lqr_costs_least():
    P = _lqr_value(np.eye(2))
    lqr = _check(P)
    assert lqr.admissible and lqr.spectral_abscissa < 0
    # The local cost of the LQR policy is tr(P M): its own value.
    assert lqr.local_cost == pytest.approx(np.trace(P @ MOMENT), rel=1e-10)
    for scale in (3.0, 10.0):
        check = _check(scale * P)
        assert check.admissible and check.value_min_eigenvalue > 0 > check.lyapunov_max_eigenvalue
        assert check.local_cost > lqr.local_cost  # LQR minimizes the local cost
        assert lqr.improves_on(check) and not check.improves_on(lqr)


def test_kleinman_steps_pass_the_acceptance_test():
    """On a linear plant, exact policy evaluation then improvement is always accepted."""
    from scipy.linalg import solve_continuous_lyapunov

    Q = np.eye(2)
    P = 3.0 * _lqr_value(Q)
    current = _check(P, Q)
    for _ in range(6):
        K = -(B.T @ P) / R[0]
        Acl = A + B @ K
        P = solve_continuous_lyapunov(Acl.T, -(Q + K.T @ K * R[0]))  # value of K
        candidate = _check(P, Q)
        assert candidate.improves_on(current)
        current = candidate
    np.testing.assert_allclose(P, _lqr_value(Q), rtol=1e-6)


def _quartic_dip(weight):
    """The LQR value of the double integrator plus ``weight * x1^4`` in the basis (2, 4)."""
    basis = PolynomialBasis(2, (2, 4))
    W = value_weights(basis, _lqr_value(np.eye(2)))
    W[[tuple(e) for e in basis.exponents].index((4, 0))] = weight
    return basis, W


def test_a_value_negative_at_the_points_is_not_admissible_whatever_its_quadratic_part():
    points = grid_points([-1, -1], [1, 1], [5, 5])  # holds the origin, where V = 0
    P = _lqr_value(np.eye(2))
    basis, W = _quartic_dip(-50.0)
    quadratic_only = check_policy(A, B, np.eye(2), R, basis, W, MOMENT)
    assert quadratic_only.admissible and np.isnan(quadratic_only.value_min_at_points)
    check = check_policy(A, B, np.eye(2), R, basis, W, MOMENT, points=points)
    assert not check.admissible and check.local_cost == np.inf
    assert check.value_min_eigenvalue > 0 > check.spectral_abscissa  # the rest passes
    # The smallest V = x^T P x - 50 x1^4 over the points but the origin.
    expected = min(x @ P @ x - 50.0 * x[0] ** 4 for x in points.T if np.any(x))
    assert check.value_min_at_points == pytest.approx(expected, rel=1e-12)
    # A positive quartic term, and the quadratic value itself, pass with the same numbers.
    for weight in (0.0, 50.0):
        passed = check_policy(A, B, np.eye(2), R, *_quartic_dip(weight), MOMENT, points=points)
        assert passed.admissible
        assert passed.local_cost == pytest.approx(quadratic_only.local_cost, rel=1e-12)
    lqr = check_policy(
        A,
        B,
        np.eye(2),
        R,
        PolynomialBasis(2),
        value_weights(PolynomialBasis(2), P),
        MOMENT,
        points=points,
    )
    assert lqr.admissible
    assert lqr.value_min_at_points == pytest.approx(
        min(x @ P @ x for x in points.T if np.any(x)), rel=1e-12
    )


def test_an_indefinite_or_destabilising_value_is_rejected():
    indefinite = _check(np.diag([1.0, -1.0]))
    assert not indefinite.admissible and indefinite.value_min_eigenvalue == pytest.approx(-1.0)
    assert indefinite.local_cost == np.inf
    # P > 0 whose policy K = [0, -1e-3] leaves x1 marginal: the linearized loop is not stable.
    weak = _check(np.diag([1.0, 1e-3]))
    assert not weak.admissible and weak.spectral_abscissa >= -1e-12
    assert not weak.improves_on(indefinite)  # never accepted, whatever is in force
    basis = PolynomialBasis(2)
    nan = check_policy(A, B, np.eye(2), R, basis, np.array([np.nan, 0.0, 1.0]), MOMENT)
    assert not nan.admissible and np.isnan(nan.spectral_abscissa)
    # Anything admissible replaces a policy in force that is not.
    assert _check(_lqr_value(np.eye(2))).improves_on(weak)


def _double_integrator():
    from ofrl_drake.model import ControlAffineSystem

    return ControlAffineSystem(
        lambda x: np.array([x[1], 0 * x[0]]),
        lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[1.0, 0.0]],
    )


@pytest.mark.parametrize("degrees", [(2,), (2, 4)])
def test_policy_evaluation_of_a_linear_policy_is_its_lyapunov_value(degrees):
    """With a bound too far to bind, the fit is the policy's own value ``x^T P_K x``."""
    from scipy.linalg import solve_continuous_lyapunov

    basis = PolynomialBasis(2, degrees)
    points = grid_points([-1, -1], [1, 1], [6, 5])
    Q = np.diag([2.0, 0.5])
    features = point_features(_double_integrator(), basis, points, Q)
    P_pi = 3.0 * _lqr_value(Q)
    K = -(B.T @ P_pi) / R[0]
    Acl = A + B @ K
    P_K = solve_continuous_lyapunov(Acl.T, -(Q + K.T @ K * R[0]))
    extrapolator = Extrapolator(features, R, 1e6, 0.7, rho_metric(basis_scales(basis, points)))
    fit = extrapolator.policy_evaluation(value_weights(basis, P_pi))
    np.testing.assert_allclose(fit, value_weights(basis, P_K), rtol=1e-8, atol=1e-8)


def test_policy_evaluation_is_the_rest_point_of_the_critic_law():
    """Where the policy saturates the fit is no value of it, but critic_sum vanishes there."""
    system = make_system("two_state")
    basis = PolynomialBasis(2)
    points = grid_points([-2, -2], [2, 2], [7, 7])
    extrapolator = Extrapolator(point_features(system, basis, points, np.eye(2)), R, 0.5, 0.3)
    W_pi = np.array([2.0, 0.5, 3.0])
    assert np.mean(np.abs(extrapolator(W_pi).u) > 0.25) > 0.3  # the bound binds
    fit = extrapolator.policy_evaluation(W_pi)
    scale = np.abs(extrapolator.sums(np.zeros(3), W_pi).critic_sum).max()
    rest = extrapolator.sums(fit, W_pi).critic_sum
    np.testing.assert_allclose(rest, 0.0, atol=1e-12 * scale)
    # ... and only there: critic_sum is affine in W with an invertible slope.
    moved = extrapolator.sums(fit + np.array([0.0, 1e-3, 0.0]), W_pi).critic_sum
    assert np.abs(moved).max() > 1e-6 * scale


def test_policy_evaluation_refuses_a_fit_that_is_not_unique_or_a_bad_policy():
    basis = PolynomialBasis(2)
    at_origin = np.zeros((2, 4))  # every omega_i is zero there
    features = point_features(_double_integrator(), basis, at_origin, np.eye(2))
    with pytest.raises(ModelError, match=r"span only 0 of the 3 weights \(the learning"):
        Extrapolator(features, R, 1.0, 1.0).policy_evaluation(np.ones(3))
    points = grid_points([-1, -1], [1, 1], [3, 3])
    extrapolator = Extrapolator(
        point_features(_double_integrator(), basis, points, np.eye(2)), R, 1.0, 1.0
    )
    for bad in (np.ones(2), np.array([1.0, np.nan, 1.0])):
        with pytest.raises(ModelError, match=r"W_policy must hold 3 finite weights; got"):
            extrapolator.policy_evaluation(bad)


def test_spectral_abscissa_of_a_batch():
    mats = np.stack([np.diag([-1.0, -2.0]), np.array([[0.0, 1.0], [-1.0, 0.0]])])
    np.testing.assert_allclose(spectral_abscissa(mats), [-1.0, 0.0], atol=1e-12)


# ------------------------------------------------------ bounded forgetting
@settings(max_examples=30, deadline=None)
@given(
    st.floats(0.1, 5.0),  # beta
    st.floats(1.5, 20.0),  # bound
    st.floats(1e-4, 1e-1),  # gain sum scale
)
def test_bounded_gain_forgetting_keeps_the_trace_ratio_bounded(beta, bound, s):
    """Euler steps of Gamma' = beta(t) Gamma - kc Gamma S Gamma with a weak S: tr ratio <= bound."""
    L = 3
    G0 = np.diag([1.0, 2.0, 3.0])
    G0inv = np.linalg.inv(G0)
    S = s * np.diag([1.0, 1e-6, 0.0])  # two directions barely or never excited
    dt = 0.01 / beta

    def run(forgetting, stop=np.inf):
        """The largest trace ratio in 20000 steps (or once past ``stop``), and the last Gamma."""
        G = G0.copy()
        worst = 0.0
        for _ in range(20000):
            ratio = np.trace(G0inv @ G) / L
            worst = max(worst, ratio)
            if worst > stop:
                break
            G = G + dt * (forgetting(ratio) * G - G @ S @ G)
        return worst, G

    worst, G = run(lambda ratio: bounded_forgetting(beta, ratio, bound))
    assert worst <= bound * (1 + 1e-3)
    assert np.linalg.eigvalsh(G)[0] > 0
    # The same steps with the forgetting fixed at beta (no bound): the unexcited
    # direction grows as exp(beta t) and the trace ratio leaves the bound behind.
    unbounded, _ = run(lambda ratio: beta, stop=10.0 * bound)
    assert unbounded > 10.0 * bound, (unbounded, bound)


def test_bounded_forgetting_vanishes_at_the_bound_and_turns_negative_beyond():
    assert bounded_forgetting(0.5, 1.0, 10.0) == pytest.approx(0.45)
    assert bounded_forgetting(0.5, 10.0, 10.0) == 0.0
    assert bounded_forgetting(0.5, 12.0, 10.0) < 0.0


# ------------------------------------------------------------ units
@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.01, 100.0), min_size=2, max_size=2))
def test_normalized_bellman_sums_do_not_depend_on_the_state_units(factors):
    """The twin x' = T x of a plant, with points, cost and weights transformed alike, has
    the same rho and Bellman errors, and sums that transform as the weights do."""
    t = np.asarray(factors)
    system = make_system("two_state")
    basis = PolynomialBasis(2)
    X = grid_points([-1, -1], [1, 1], [5, 4])
    Q = np.diag([5.0, 2.0])
    W = np.array([0.4, 0.2, 0.8])
    d = basis_scales(basis, X)
    base = Extrapolator(point_features(system, basis, X, Q), R, 3.0, 0.7, rho_metric(d))(W)

    from ofrl_drake.model import ControlAffineSystem

    twin = ControlAffineSystem(
        lambda x: (
            t[:, None] * np.asarray(system.f(x / t[:, None]))
            if np.ndim(x) == 2
            else t * np.asarray(system.f(x / t))
        ),
        lambda x: (
            t[:, None, None] * np.asarray(system.g(x / t[:, None]))
            if np.ndim(x) == 2
            else t[:, None] * np.asarray(system.g(x / t))
        ),
        C=system.output_matrix / t,
        name="twin",
    )
    Xt = t[:, None] * X
    Qt = Q / np.outer(t, t)
    Dw = np.prod(t[None, :] ** basis.exponents, axis=1)  # sigma(T x) = Dw sigma(x)
    dt = basis_scales(basis, Xt)
    np.testing.assert_allclose(dt, d * Dw, rtol=1e-12)
    other = Extrapolator(point_features(twin, basis, Xt, Qt), R, 3.0, 0.7, rho_metric(dt))(W / Dw)
    np.testing.assert_allclose(other.rho, base.rho, rtol=1e-9)
    np.testing.assert_allclose(other.delta, base.delta, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(other.u, base.u, rtol=1e-9, atol=1e-12)
    # omega_twin = Dw omega: with Gamma_twin = Gamma / (Dw Dw^T) (what auto gains give), the
    # critic law maps W -> W / Dw exactly.
    np.testing.assert_allclose(other.critic_sum / Dw, base.critic_sum, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(
        other.gain_sum / np.outer(Dw, Dw), base.gain_sum, rtol=1e-9, atol=1e-14
    )


def test_basis_scales_need_points_that_spread():
    with pytest.raises(ModelError, match=r"do not spread along state axes \[1\]"):
        basis_scales(PolynomialBasis(2), np.array([[0.0, 1.0], [2.0, 2.0]]))


# ------------------------------------------------------------ auto gains
def test_auto_gains_put_gamma_at_the_steady_state_of_its_law():
    S0 = np.array([[2.0, 0.3], [0.3, 0.5]])
    gains = auto_gains(lambda nu: S0 / nu, np.array([1.0, 2.0, 4.0]), horizon=20.0)
    assert gains.nu == pytest.approx(0.5)  # 1 / median
    assert gains.policy_period == pytest.approx(2.0)
    assert gains.beta == pytest.approx(2.5)
    S = S0 / gains.nu
    # Gamma0 is the fixed point of Gamma' = beta Gamma - kc Gamma S Gamma.
    G = gains.Gamma0
    np.testing.assert_allclose(gains.beta * G - gains.kc * G @ S @ G, 0, atol=1e-12)


def test_auto_gains_rates_are_beta_times_eig_of_S0_inverse_S1_at_least_beta():
    """What the docs of ``auto_gains`` say, on ``pendulum_upright`` at ``W0``.

    With the policy held at ``W0``, ``critic_sum`` is affine in ``W`` with slope
    ``S1 = (1/N) sum omega omega^T / rho`` (one rho), so ``W`` settles at the rates
    ``eig(kc Gamma0 S1) = beta eig(S0^{-1} S1)``: at least beta (rho >= 1), unequal.
    Under bounded forgetting Gamma settles at ``k0 / (k0 + 1) Gamma0``, not Gamma0.
    """
    from scipy.integrate import solve_ivp

    from ofrl_drake import load_scenario
    from ofrl_drake.diagram import critic_settings, extrapolation_points
    from ofrl_drake.plants import resolve_system

    scenario = load_scenario(ROOT / "diagrams" / "pendulum_upright.yaml")
    system = resolve_system(scenario)
    basis = PolynomialBasis(system.n, scenario.critic.basis_degrees)
    Q, r = np.asarray(scenario.cost.Q, float), np.asarray(scenario.cost.R, float)
    features = point_features(system, basis, extrapolation_points(scenario), Q)
    critic = critic_settings(scenario, system, basis, features, r)
    g, W0 = critic.gains, np.asarray(scenario.critic.W0, float)
    assert critic.law == "policy_iteration" and g.gamma_bound == 10.0
    extrapolator = Extrapolator(features, r, scenario.input_bound, g.nu, critic.metric)
    at_W0 = extrapolator(W0, W0)
    N = at_W0.omega.shape[1]
    S1 = (at_W0.omega / at_W0.rho) @ at_W0.omega.T / N
    # The slope of critic_sum in W, the policy held at W0, is S1 (central differences).
    h = 1e-3
    slope = np.column_stack(
        [
            (
                extrapolator.sums(W0 + h * e, W0).critic_sum
                - extrapolator.sums(W0 - h * e, W0).critic_sum
            )
            / (2 * h)
            for e in np.eye(basis.size)
        ]
    )
    np.testing.assert_allclose(slope, S1, rtol=1e-9, atol=1e-9 * np.abs(S1).max())
    rates = np.linalg.eigvals(g.kc * g.Gamma0 @ S1)
    np.testing.assert_allclose(rates.imag, 0.0, atol=1e-9 * g.beta)
    relative = np.sort(rates.real) / g.beta
    np.testing.assert_allclose(relative[[0, -1]], [1.57, 4.27], atol=0.005)  # the docs' numbers
    S0 = at_W0.gain_sum
    np.testing.assert_allclose(
        np.sort(np.linalg.eigvals(np.linalg.solve(S0, S1)).real), relative, rtol=1e-6
    )
    # Bounded forgetting: 0.9 beta at Gamma0, and Gamma settles at k0 / (k0 + 1) Gamma0.
    k0, L = g.gamma_bound, basis.size
    G0inv = np.linalg.inv(g.Gamma0)
    assert bounded_forgetting(g.beta, 1.0, k0) == pytest.approx(0.9 * g.beta)

    def gamma_rate(_, z):
        G = z.reshape(L, L)
        forgetting = bounded_forgetting(g.beta, np.trace(G0inv @ G) / L, k0)
        return (forgetting * G - g.kc * G @ S0 @ G).ravel()

    settled = solve_ivp(gamma_rate, (0, 20 / g.beta), g.Gamma0.ravel(), rtol=1e-10, atol=1e-14)
    G = settled.y[:, -1].reshape(L, L)
    np.testing.assert_allclose(
        G, k0 / (k0 + 1) * g.Gamma0, rtol=1e-6, atol=1e-9 * np.abs(g.Gamma0).max()
    )


def test_auto_gains_refuse_points_that_excite_nothing():
    with pytest.raises(ModelError, match=r"regressors omega_i vanish at W0"):
        auto_gains(lambda nu: np.eye(2), np.zeros(5), horizon=1.0)


def test_equal_costs_up_to_round_off_count_as_no_rise_and_a_real_rise_is_refused():
    import dataclasses

    current = _check(3.0 * _lqr_value(np.eye(2)))
    same = dataclasses.replace(current, local_cost=np.nextafter(current.local_cost, np.inf))
    assert same.improves_on(current)  # a converged iteration: the same policy, re-evaluated
    higher = dataclasses.replace(current, local_cost=current.local_cost * (1 + 1e-9))
    assert not higher.improves_on(current)
    inadmissible = dataclasses.replace(current, admissible=False, local_cost=0.0)
    assert not inadmissible.improves_on(current)


def test_auto_gains_follow_a_given_policy_period():
    """``beta = 5 / policy_period`` for the period in force, given or T / 10; Gamma0 scales."""
    S0 = np.array([[2.0, 0.3], [0.3, 0.5]])
    terms = np.array([1.0, 2.0, 4.0])
    derived = auto_gains(lambda nu: S0 / nu, terms, horizon=20.0)
    given = auto_gains(lambda nu: S0 / nu, terms, horizon=20.0, policy_period=0.5)
    assert given.policy_period == 0.5
    assert given.beta == pytest.approx(10.0)
    np.testing.assert_allclose(given.Gamma0, derived.Gamma0 * 4.0, rtol=1e-12)
    with pytest.raises(ModelError, match=r"^critic\.policy_period must be > 0; got 0\.0"):
        auto_gains(lambda nu: S0 / nu, terms, horizon=20.0, policy_period=0.0)
