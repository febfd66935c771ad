"""Bellman extrapolation and the update laws: the compiled kernels against the readable laws
(ofrl_drake.update_laws), and those against a per-point loop written from the paper."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ofrl_drake import PolynomialBasis
from ofrl_drake import update_laws as laws
from ofrl_drake.bellman import (
    Extrapolator,
    bellman_kernel,
    critic_rate,
    extrapolate,
    gamma_rate,
    kernel_layout,
    learning_condition,
    pack_symmetric,
    point_features,
    unpack_symmetric,
)
from ofrl_drake.cost import input_cost_from_D
from ofrl_drake.errors import ModelError
from ofrl_drake.examples import make_system
from ofrl_drake.learning import LearningGains, bounded_forgetting
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.policy import saturated_policy
from ofrl_drake.systems import CriticWeights, GammaGain

LBAR, NU = 3.0, 0.7


def _reference(system, basis, X, W, Q, r):
    """Per-point loop, written straight from (BE1_i), (u_app), (W_c), (gamma)."""
    N = X.shape[1]
    s1 = np.zeros(basis.size)
    S2 = np.zeros((basis.size, basis.size))
    deltas = []
    for i in range(N):
        x = X[:, i]
        grad = basis.gradient(x)
        g = system.g(x)
        D = (1 / (2 * LBAR)) * np.diag(1 / r) @ g.T @ grad.T @ W
        u = -LBAR * np.tanh(D)
        omega = grad @ (system.f(x) + g @ u)
        U = np.sum(
            2 * r * LBAR * (u * np.arctanh(u / LBAR) + LBAR / 2 * np.log(1 - u**2 / LBAR**2))
        )
        delta = W @ omega + x @ Q @ x + U
        rho = 1 + NU * omega @ omega
        s1 += omega * delta / rho / N
        S2 += np.outer(omega, omega) / rho**2 / N
        deltas.append(delta)
    return s1, S2, np.array(deltas)


@pytest.mark.parametrize(
    ("name", "W"),
    [("two_state", [0.4, 0.2, 0.8]), ("two_state", [-1.0, 3.0, 0.1]), ("coupled_two_state", None)],
)
def test_vectorized_matches_per_point_reference(name, W):
    system = make_system(name)
    basis = PolynomialBasis(system.n)
    X = uniform_points(-np.ones(system.n), np.ones(system.n), 40, seed=3)
    W = np.linspace(0.1, 0.9, basis.size) if W is None else np.asarray(W)
    Q, r = 5 * np.eye(system.n), np.linspace(1.0, 2.0, system.m)
    out = extrapolate(point_features(system, basis, X, Q), W, r, LBAR, NU)
    s1, S2, deltas = _reference(system, basis, X, W, Q, r)
    np.testing.assert_allclose(out.delta, deltas, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out.critic_sum, s1, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out.gain_sum, S2, rtol=1e-10, atol=1e-14)
    assert out.learning_condition == pytest.approx(np.linalg.eigvalsh(S2)[0], rel=1e-9)
    assert out.omega.shape == (basis.size, 40) and out.u.shape == (system.m, 40)


def test_delta_gradient_in_W_is_omega():
    """dU/du cancels the policy term, so d(delta_i)/dW = omega_i exactly (docs/paper_notes.md)."""
    system = make_system("two_state")
    basis = PolynomialBasis(2)
    F = point_features(system, basis, grid_points([-1, -1], [1, 1], [5, 5]), 5 * np.eye(2))
    W, r, h = np.array([0.4, 0.2, 0.8]), np.array([1.0]), 1e-6
    base = extrapolate(F, W, r, LBAR, NU)
    for k in range(3):
        dW = np.zeros(3)
        dW[k] = h
        fd = (
            extrapolate(F, W + dW, r, LBAR, NU).delta - extrapolate(F, W - dW, r, LBAR, NU).delta
        ) / (2 * h)
        np.testing.assert_allclose(fd, base.omega[k], rtol=1e-6, atol=1e-7)


def test_policy_matches_extrapolation_at_a_point():
    system = make_system("coupled_two_state")
    basis = PolynomialBasis(4)
    x = np.array([0.3, -0.2, 0.5, 0.1])
    W, r = np.linspace(-1, 1, basis.size), np.array([1.0, 2.0])
    u = saturated_policy(basis.gradient(x), system.g(x), W, r, LBAR)
    out = extrapolate(point_features(system, basis, x[:, None], np.eye(4)), W, r, LBAR, NU)
    np.testing.assert_allclose(u, out.u[:, 0], rtol=1e-13)


@settings(max_examples=40, deadline=None)
@given(scale=st.floats(1e-3, 1e6), seed=st.integers(0, 1000))
def test_sums_stay_finite_for_huge_weights(scale, seed):
    """|D| up to about 1e4 and beyond: U and both sums stay finite."""
    system = make_system("two_state")
    basis = PolynomialBasis(2)
    F = point_features(system, basis, grid_points([-1, -1], [1, 1], [10, 10]), 5 * np.eye(2))
    W = scale * np.random.default_rng(seed).normal(size=3)
    out = extrapolate(F, W, np.array([1.0]), LBAR, NU)
    assert np.all(np.isfinite(out.critic_sum)) and np.all(np.isfinite(out.gain_sum))
    assert np.all(np.abs(out.u) <= LBAR)


def test_U_delta_and_sums_are_finite_for_D_up_to_1e4():
    system = make_system("two_state")
    basis = PolynomialBasis(2)
    F = point_features(system, basis, grid_points([-1, -1], [1, 1], [10, 10]), 5 * np.eye(2))
    out = extrapolate(F, np.array([0.0, 0.0, 2e4]), np.array([1.0]), LBAR, NU)
    assert np.max(np.abs(out.D)) >= 1e4
    U = input_cost_from_D(out.D, np.array([1.0]), LBAR)
    for value in (U, out.delta, out.rho, out.critic_sum, out.gain_sum):
        assert np.all(np.isfinite(value))
    assert np.all(U >= 0)


def test_kernel_without_critic_sum_gives_the_same_gain_sum_bits():
    """The learning-condition pass skips the cost and log-cosh, and changes no bit of gain_sum."""
    system = make_system("coupled_two_state")  # m = 2: both inputs share the scratch rows
    basis = PolynomialBasis(system.n)
    X = uniform_points(-np.ones(4), np.ones(4), 37, seed=5)
    ex = Extrapolator(point_features(system, basis, X, np.eye(4)), np.array([1.0, 2.0]), LBAR, NU)
    W = np.random.default_rng(2).normal(size=basis.size) * 4.0  # |D| on both sides of 0.5
    full = ex(W)
    assert np.min(np.abs(full.D)) < 0.5 < np.max(np.abs(full.D))
    rows = ex.layout.per_point
    per_point = np.full((rows.rows, X.shape[1]), np.nan)
    critic_sum, gain_sum = np.full(basis.size, -7.0), np.empty((basis.size, basis.size))
    args = (W, W, ex._data, system.m, ex._weight, LBAR, NU, ex._metric, per_point)
    bellman_kernel(*args, critic_sum, gain_sum, False)
    np.testing.assert_array_equal(gain_sum, full.gain_sum)
    np.testing.assert_array_equal(per_point[rows.omega], full.omega)
    assert np.all(critic_sum == -7.0)  # untouched
    assert np.all(np.isnan(per_point[rows.delta]))  # delta untouched


def test_learning_condition_is_min_eigenvalue():
    S = np.array([[2.0, 0.5], [0.5, 1.0]])
    assert learning_condition(S) == pytest.approx(np.min(np.linalg.eigvalsh(S)), rel=1e-15)
    assert np.isnan(learning_condition(np.array([[1.0, np.inf], [np.inf, 1.0]])))


def test_learning_conditions_over_many_weights_equal_one_at_a_time():
    system = make_system("two_state")
    basis = PolynomialBasis(2)
    F = point_features(system, basis, grid_points([-1, -1], [1, 1], [10, 10]), 5 * np.eye(2))
    ex = Extrapolator(F, np.array([1.0]), LBAR, NU)
    Ws = np.random.default_rng(3).normal(size=(7, 3))
    expected = [learning_condition(ex.sums(W).gain_sum) for W in Ws]
    np.testing.assert_array_equal(ex.learning_conditions(Ws), expected)  # the same kernels
    assert ex.learning_conditions(np.empty((0, 3))).shape == (0,)
    assert np.isnan(ex.learning_conditions(np.full((1, 3), np.nan))).all()  # no LinAlgError
    with pytest.raises(ModelError, match=r"weights must have shape \(T, 3\); got \(3,\)"):
        ex.learning_conditions(Ws[0])


def test_paper_grid_is_10_by_10_on_unit_square():
    X = grid_points([-1, -1], [1, 1], [10, 10])
    assert X.shape == (2, 100)
    np.testing.assert_allclose(np.unique(X[0]), np.linspace(-1, 1, 10), rtol=1e-15)


def test_points_must_match_system_dimension():
    system = make_system("two_state")
    with pytest.raises(
        ValueError, match=r"points must have shape \(n, N\) = \(2, N\); got \(3, 4\)"
    ):
        point_features(system, PolynomialBasis(2), np.zeros((3, 4)), np.eye(2))


def test_sums_alone_equal_the_full_extrapolation():
    system = make_system("coupled_two_state")
    basis = PolynomialBasis(4)
    F = point_features(
        system, basis, uniform_points(-np.ones(4), np.ones(4), 30, seed=1), np.eye(4)
    )
    extrapolator = Extrapolator(F, np.array([1.0, 2.0]), LBAR, NU)
    W = np.linspace(-1.0, 2.0, basis.size)
    full, sums = extrapolator(W), extrapolator.sums(W)
    np.testing.assert_array_equal(sums.critic_sum, full.critic_sum)
    np.testing.assert_array_equal(sums.gain_sum, full.gain_sum)
    first = extrapolator.sums(W)
    extrapolator.sums(2 * W)  # the scratch is reused; returned sums are not
    np.testing.assert_array_equal(first.critic_sum, sums.critic_sum)


# ------------------------------------------- the readable laws (ofrl_drake.update_laws)
LAW_CASES = [("two_state", "paper"), ("two_state", "policy_iteration")]
LAW_CASES += [("coupled_two_state", "paper"), ("coupled_two_state", "policy_iteration")]


def _random_case(name, law, seed):
    """Random points, weights, R, nu and (under policy_iteration) a metric and a policy."""
    rng = np.random.default_rng(seed)
    system = make_system(name)
    basis = PolynomialBasis(system.n)
    L = basis.size
    X = uniform_points(-np.ones(system.n), np.ones(system.n), 53, seed=seed)
    F = point_features(system, basis, X, np.diag(rng.uniform(0.5, 5.0, system.n)))
    W = rng.normal(size=L) * 3.0
    W_policy = rng.normal(size=L) * 3.0 if law == "policy_iteration" else None
    metric = rng.uniform(0.2, 5.0, L) if law == "policy_iteration" else None
    r = rng.uniform(0.5, 2.0, system.m)
    return F, W, W_policy, metric, r, rng.uniform(0.1, 2.0)


def _close(actual, expected, rtol=1e-12):
    """Equal to ``rtol`` of the largest entry of ``expected`` (sums and differences cancel)."""
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * np.max(np.abs(expected)))


def _random_spd(rng, L):
    A = rng.normal(size=(L, L))
    return A @ A.T + 0.5 * np.eye(L)


@pytest.mark.parametrize("name", ["two_state", "coupled_two_state"])
def test_readable_laws_match_the_per_point_reference(name):
    system = make_system(name)
    basis = PolynomialBasis(system.n)
    X = uniform_points(-np.ones(system.n), np.ones(system.n), 40, seed=3)
    W, Q = np.linspace(-0.5, 0.9, basis.size), 5 * np.eye(system.n)
    r = np.linspace(1.0, 2.0, system.m)
    F = point_features(system, basis, X, Q)
    errors = laws.bellman_errors(F, W, laws.policy_weights("paper", W), r, LBAR)
    sums = laws.normalized_sums(errors.omega, errors.delta, laws.normalization(errors.omega, NU))
    s1, S2, deltas = _reference(system, basis, X, W, Q, r)
    np.testing.assert_allclose(errors.delta, deltas, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sums.critic_sum, s1, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sums.gain_sum, S2, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize(("name", "law"), LAW_CASES)
@pytest.mark.parametrize("seed", range(3))
def test_compiled_extrapolation_matches_the_readable_laws(name, law, seed):
    F, W, W_policy, metric, r, nu = _random_case(name, law, seed)
    W_pi = laws.policy_weights(law, W, W_policy)
    errors = laws.bellman_errors(F, W, W_pi, r, LBAR)
    rho = laws.normalization(errors.omega, nu, metric)
    expected = laws.normalized_sums(errors.omega, errors.delta, rho)
    ex = Extrapolator(F, r, LBAR, nu, metric)
    got = ex(W, W_policy)
    for field in ("D", "u", "omega", "delta"):
        _close(getattr(got, field), getattr(errors, field))
    _close(got.rho, rho)
    _close(got.critic_sum, expected.critic_sum, rtol=1e-11)
    _close(got.gain_sum, expected.gain_sum, rtol=1e-11)
    sums = ex.sums(W, W_policy)  # what the Bellman block computes
    np.testing.assert_array_equal(sums.critic_sum, got.critic_sum)
    np.testing.assert_array_equal(sums.gain_sum, got.gain_sum)
    if law == "policy_iteration":  # the errors follow W_policy, not W: the laws differ here
        assert np.max(np.abs(got.D - ex(W).D)) > 1e-3


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("L", [1, 3, 10])
def test_compiled_rates_match_the_readable_laws(seed, L):
    rng = np.random.default_rng(seed)
    Gamma = _random_spd(rng, L)
    S, s = _random_spd(rng, L), rng.normal(size=L)
    kc, beta = rng.uniform(0.01, 2.0), rng.uniform(0.0, 1.0)
    W_dot, Gamma_dot = np.empty(L), np.empty(L * (L + 1) // 2)  # Gamma packed
    critic_rate(pack_symmetric(Gamma), s, kc, W_dot)
    gamma_rate(pack_symmetric(Gamma), S.ravel(), kc, beta, Gamma_dot)
    _close(W_dot, laws.critic_rate(Gamma, s, kc))
    _close(unpack_symmetric(Gamma_dot), laws.gamma_rate(Gamma, S, kc, beta))
    assert np.max(np.abs(unpack_symmetric(Gamma_dot) - beta * Gamma)) > 1e-6  # S mattered


@pytest.mark.parametrize("L", [1, 2, 5])
def test_packed_rates_read_only_the_upper_triangle_in_its_order(L):
    """Entry (a, b), a <= b, of the packed Gamma is Gamma[a, b]: perturbing it moves
    exactly the rates a perturbed symmetric Gamma moves."""
    rng = np.random.default_rng(L)
    Gamma, S, s = _random_spd(rng, L), _random_spd(rng, L), rng.normal(size=L)
    rows, cols = np.triu_indices(L)
    for k, (a, b) in enumerate(zip(rows, cols, strict=True)):
        bumped = Gamma.copy()
        bumped[a, b] += 0.5
        bumped[b, a] = bumped[a, b]
        packed = pack_symmetric(Gamma)
        packed[k] += 0.5
        W_dot, Gamma_dot = np.empty(L), np.empty(packed.size)
        critic_rate(packed, s, 0.3, W_dot)
        gamma_rate(packed, S.ravel(), 0.3, 0.2, Gamma_dot)
        _close(W_dot, laws.critic_rate(bumped, s, 0.3))
        _close(unpack_symmetric(Gamma_dot), laws.gamma_rate(bumped, S, 0.3, 0.2))


def _block_derivative(block, state, inputs):
    context = block.CreateDefaultContext()
    context.SetContinuousState(state)
    for port, value in inputs:
        port.FixValue(context, value)
    return block.EvalTimeDerivatives(context).CopyToVector()


@pytest.mark.parametrize(("name", "law"), LAW_CASES)
@pytest.mark.parametrize("gamma_bound", [None, 1.5])
def test_blocks_follow_the_readable_update_rates(name, law, gamma_bound):
    """The compiled path the simulation takes (sums, critic and Gamma blocks): update_rates."""
    F, W, W_policy, metric, r, nu = _random_case(name, law, seed=11)
    rng = np.random.default_rng(7)
    L = W.size
    Gamma0, Gamma = _random_spd(rng, L), _random_spd(rng, L)
    gains = LearningGains(kc=0.7, nu=nu, beta=0.4, Gamma0=Gamma0, gamma_bound=gamma_bound)
    expected = laws.update_rates(
        F, W, Gamma, gains, law=law, r=r, input_bound=LBAR, W_policy=W_policy, metric=metric
    )
    sums = Extrapolator(F, r, LBAR, nu, metric).sums(W, W_policy)
    critic = CriticWeights(np.zeros(L), gains.kc)
    W_dot = _block_derivative(
        critic,
        W,
        [
            (critic.get_critic_sum_input_port(), sums.critic_sum),
            (critic.get_gamma_input_port(), pack_symmetric(Gamma)),
        ],
    )
    gamma = GammaGain(Gamma0, gains.kc, gains.beta, gamma_bound)
    Gamma_dot = _block_derivative(
        gamma, pack_symmetric(Gamma), [(gamma.get_gain_sum_input_port(), sums.gain_sum.ravel())]
    )
    _close(W_dot, expected.W_dot, rtol=1e-11)
    _close(unpack_symmetric(Gamma_dot), expected.Gamma_dot, rtol=1e-11)
    if gamma_bound is None:
        assert expected.beta == gains.beta
    else:
        ratio = np.trace(np.linalg.inv(Gamma0) @ Gamma) / L
        assert expected.beta == pytest.approx(bounded_forgetting(0.4, ratio, 1.5), rel=1e-12)
        assert expected.beta != pytest.approx(gains.beta, rel=1e-3)  # the bound acted


def test_the_paper_law_is_policy_iteration_with_the_policy_at_the_critic():
    F, W, _, _, r, nu = _random_case("coupled_two_state", "paper", seed=2)
    gains = LearningGains(kc=1.0, nu=nu, beta=0.2, Gamma0=np.eye(W.size))
    paper = laws.update_rates(F, W, np.eye(W.size), gains, law="paper", r=r, input_bound=LBAR)
    same = laws.update_rates(
        F, W, np.eye(W.size), gains, law="policy_iteration", r=r, input_bound=LBAR, W_policy=W
    )
    np.testing.assert_array_equal(paper.W_dot, same.W_dot)
    np.testing.assert_array_equal(paper.Gamma_dot, same.Gamma_dot)


def test_readable_laws_name_bad_arguments():
    F, W, _, _, r, _ = _random_case("two_state", "paper", seed=0)
    with pytest.raises(ModelError, match=r"law must be one of \['policy_iteration', 'paper'\]"):
        laws.policy_weights("gradient", W)
    with pytest.raises(ModelError, match=r"law 'policy_iteration' needs W_policy"):
        laws.policy_weights("policy_iteration", W)
    with pytest.raises(ModelError, match=r"W_policy must have shape \(L,\) = \(3,\); got \(4,\)"):
        laws.bellman_errors(F, W, np.zeros(4), r, LBAR)
    with pytest.raises(ModelError, match=r"gamma_bound = 2.0 needs Gamma0"):
        laws.forgetting_factor(0.2, np.eye(3), None, 2.0)


def test_kernel_layout_blocks_tile_both_arrays():
    """Every row of both packed arrays belongs to exactly one named block."""
    layout = kernel_layout(2, 5)
    for rows, size in [(layout.data, 2 * 2 * 5 + 5 + 1), (layout.per_point, 2 * 2 + 2 * 5 + 4)]:
        assert rows.rows == size
        covered = []
        for value in rows[:-1]:
            block = value if isinstance(value, slice) else slice(value, value + 1)
            covered.extend(range(size)[block])
        assert sorted(covered) == list(range(size))
    assert layout.data.drift == slice(20, 25) and layout.per_point.omega == slice(4, 9)


@pytest.mark.parametrize(
    ("r", "input_bound", "nu", "message"),
    [
        ([1.0], LBAR, -5.0, r"^nu must be > 0; got -5\.0\.$"),
        ([1.0], LBAR, 0.0, r"^nu must be > 0; got 0\.0\.$"),
        ([1.0], LBAR, np.nan, r"^nu must be finite; got nan\.$"),
        ([0.0], LBAR, NU, r"^r must have entries > 0; got \[0\.0\]\.$"),
        ([-1.0], LBAR, NU, r"^r must have entries > 0; got \[-1\.0\]\.$"),
        ([np.inf], LBAR, NU, r"^r must be finite; got \[inf\]\.$"),
        ([1.0, 2.0], LBAR, NU, r"^r must have length 1; got 2\.$"),
        ([1.0], 0.0, NU, r"^input_bound must be > 0; got 0\.0\.$"),
        ([1.0], -np.inf, NU, r"^input_bound must be finite; got -inf\.$"),
    ],
)
def test_the_extrapolator_rejects_constants_that_would_give_nan(r, input_bound, nu, message):
    system = make_system("two_state")
    F = point_features(system, PolynomialBasis(2), grid_points([-1, -1], [1, 1], [3, 3]), np.eye(2))
    with pytest.raises(ModelError, match=message):
        Extrapolator(F, np.asarray(r), input_bound, nu)
    with pytest.raises(ModelError, match=message):
        extrapolate(F, np.zeros(3), np.asarray(r), input_bound, nu)


_X = np.array([[0.5, -0.5, 0.0], [0.25, 0.0, 1.0]])


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (
            ("two_state", PolynomialBasis(2), _X, np.eye(2)),
            r"point_features: system must be a ControlAffineSystem; got str 'two_state'",
        ),
        (
            (None, np.eye(2), _X, np.eye(2)),
            r"point_features: system must be a ControlAffineSystem; got NoneType None",
        ),
        ((make_system("two_state"), np.eye(2), _X, np.eye(2)), r"basis must be a .*got ndarray"),
        (
            (make_system("two_state"), PolynomialBasis(3), _X, np.eye(2)),
            r"the basis is for n = 3 states but the system 'two_state' has n = 2; build it as "
            r"PolynomialBasis\(2, \.\.\.\)",
        ),
        (
            (make_system("two_state"), PolynomialBasis(2), _X, np.eye(3)),
            r"Q must be a finite \(n, n\) = \(2, 2\) matrix .*of shape \(3, 3\)",
        ),
        (
            (make_system("two_state"), PolynomialBasis(2), _X, 5.0),
            r"Q must be a finite \(n, n\) = \(2, 2\) matrix .*got 5\.0 of shape \(\)",
        ),
        (
            (make_system("two_state"), PolynomialBasis(2), _X, np.diag([1.0, np.nan])),
            r"Q must be a finite .*got \[\[1\.0, 0\.0\], \[0\.0, nan\]\]",
        ),
        (
            (make_system("two_state"), PolynomialBasis(2), _X * [[1.0, np.nan, 1.0]], np.eye(2)),
            r"point_features: the points must be finite; point 1 is \[nan, nan\]",
        ),
        (
            (make_system("two_state"), PolynomialBasis(2), [["a"], ["b"]], np.eye(2)),
            r"points and Q must be numeric arrays of shapes \(n, N\) = \(2, N\)",
        ),
    ],
)
def test_point_features_raise_on_bad_arguments(args, match):
    # Before: broadcast or matmul ValueErrors, AttributeErrors, or NaN features.
    with pytest.raises(ModelError, match=match):
        point_features(*args)


def _sums_block(nu=NU):
    from ofrl_drake.systems import BellmanExtrapolator

    features = point_features(
        make_system("two_state"),
        PolynomialBasis(2),
        grid_points([-1, -1], [1, 1], [4, 3]),
        np.eye(2),
    )
    return BellmanExtrapolator(features, np.array([1.0]), LBAR, nu)


def _fixed(block, W, Wp):
    context = block.CreateDefaultContext()
    block.get_weights_input_port().FixValue(context, W)
    block.get_policy_weights_input_port().FixValue(context, Wp)
    return context


def test_two_contexts_at_two_nu_share_one_block_without_writing_to_it(monkeypatch):
    """The nu of each context is its own: interleaved evaluations give two built blocks' bits."""
    block, at_02, at_03 = _sums_block(), _sums_block(0.2), _sums_block(0.3)
    W, Wp = np.array([0.4, 0.2, 0.8]), np.array([0.5, 0.1, 0.7])
    first, second = _fixed(block, W, Wp), _fixed(block, W, Wp)
    block.set_nu(first, 0.2)
    block.set_nu(second, 0.3)
    ref_02, ref_03 = _fixed(at_02, W, Wp), _fixed(at_03, W, Wp)
    sums = block.GetSubsystemByName("sums")
    attributes = dict(vars(sums))
    built = []
    original = Extrapolator.__init__

    def counted(self, *args, **kwargs):
        built.append(args[3])
        original(self, *args, **kwargs)

    monkeypatch.setattr(Extrapolator, "__init__", counted)
    for k in range(3):  # interleaved, with new weights each time
        Wk = W * (1 + k)
        for b, c in ((block, first), (block, second), (at_02, ref_02), (at_03, ref_03)):
            b.get_weights_input_port().FixValue(c, Wk)
        for name in ("critic_sum", "gain_sum", "learning_condition"):
            np.testing.assert_array_equal(
                block.GetOutputPort(name).Eval(first), at_02.GetOutputPort(name).Eval(ref_02)
            )
            np.testing.assert_array_equal(
                block.GetOutputPort(name).Eval(second), at_03.GetOutputPort(name).Eval(ref_03)
            )
    # A calc writes nothing to the system; each context keeps its nu's extrapolator.
    assert dict(vars(sums)) == attributes
    assert sorted(built) == [0.2, 0.3]
    np.testing.assert_array_equal(
        block.learning_condition_of(np.array([W, Wp]), second),
        at_03.learning_condition_of(np.array([W, Wp])),
    )
    assert sorted(built) == [0.2, 0.3]  # read from the context's cache, not rebuilt
    assert sums.extrapolator.nu == NU  # the block's own stays the default's
    # A clone keeps its own nu and sums, whatever the original's context does next.
    clone = second.Clone()
    block.set_nu(second, 0.2)
    np.testing.assert_array_equal(
        block.get_critic_sum_output_port().Eval(clone),
        at_03.get_critic_sum_output_port().Eval(ref_03),
    )
    np.testing.assert_array_equal(
        block.get_critic_sum_output_port().Eval(second),
        at_02.get_critic_sum_output_port().Eval(ref_02),
    )


def test_bellman_block_accessors_keep_their_port_handles(monkeypatch):
    """No lookup by name per call: the ports are kept when the diagram is built."""
    from pydrake.systems.framework import Diagram

    block = _sums_block()
    context = _fixed(block, np.array([0.4, 0.2, 0.8]), np.array([0.5, 0.1, 0.7]))

    def by_name(self, name):
        raise AssertionError(f"port {name!r} looked up by name")

    for cls in (Diagram, type(block), type(block.GetSubsystemByName("sums"))):
        monkeypatch.setattr(cls, "GetInputPort", by_name, raising=False)
        monkeypatch.setattr(cls, "GetOutputPort", by_name, raising=False)
    ports = (
        block.get_weights_input_port(),
        block.get_policy_weights_input_port(),
        block.get_critic_sum_output_port(),
        block.get_gain_sum_output_port(),
        block.get_learning_condition_output_port(),
    )
    assert [p.get_name() for p in ports] == [
        "weights",
        "policy_weights",
        "critic_sum",
        "gain_sum",
        "learning_condition",
    ]
    sums = block.extrapolation(context)
    np.testing.assert_array_equal(sums.critic_sum, ports[2].Eval(context))


def _g_one(x):
    return np.array([[0 * x[0]], [1 + 0 * x[0]]])


def _plant(f, g=_g_one, name="plant"):
    from ofrl_drake import ControlAffineSystem

    return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name=name)


def _exp_overflow(x):
    # Finite for x_1 < ~0.89, inf beyond: exp(800 x_1) overflows.
    return np.array([x[1], -x[0] - x[1] + 1e-300 * np.exp(800.0 * x[0])])


def test_point_features_refuse_an_f_that_is_inf_at_a_point():
    # Before: accepted; the run later stopped with "continuous state 5 is nan" (policy
    # iteration) or blamed a domain error of f (paper law).
    system = _plant(_exp_overflow, name="exp_overflow")
    points = grid_points([-1, -1], [1, 1], [10, 10])
    with pytest.raises(
        ModelError,
        match=r"point_features: the model's f is not finite at extrapolation point 90 "
        r"x = \[1\.0, -1\.0\] \(f\(x\) = \[-1\.0, inf\]; 10 of 100 points\) for the model "
        r"'exp_overflow'.*shrink the extrapolation points \(the scenario's points\.lower, "
        r"points\.upper\) to the region where f and g are finite",
    ):
        point_features(system, PolynomialBasis(2), points, np.eye(2))
    # The fixed-points extrapolator's features come from point_features: inside the
    # region, the same points are accepted.
    point_features(system, PolynomialBasis(2), grid_points([-1, -1], [0.8, 1], [10, 10]), np.eye(2))


def test_point_features_refuse_a_g_that_is_nan_at_a_point():
    def g(x):
        return np.array([[0 * x[0]], [np.sqrt(1.0 - x[0])]])  # NaN for x_1 > 1

    system = _plant(lambda x: np.array([x[1], -x[0]]), g, name="sqrt_g")
    with pytest.raises(
        ModelError,
        match=r"the model's g is not finite at extrapolation point 1 x = \[2\.0, 0\.0\] "
        r"\(g\(x\) = \[\[0\.0\], \[nan\]\]; 1 of 2 points\) for the model 'sqrt_g'",
    ):
        point_features(system, PolynomialBasis(2), np.array([[0.5, 2.0], [0.0, 0.0]]), np.eye(2))


def test_point_features_refuse_features_that_overflow_at_a_point():
    # f finite at x = 1e200, but grad sigma f ~ 1e400 is not a float.
    system = _plant(lambda x: np.array([x[1], -x[0]]), name="linear")
    with pytest.raises(
        ModelError,
        match=r"the feature grad sigma\(x\) f\(x\) is not finite at extrapolation point 0 "
        r"x = \[1e\+200, 0\.0\].*below the largest float",
    ):
        point_features(system, PolynomialBasis(2), np.array([[1e200], [0.0]]), np.eye(2))


def _exact_sums(omega, delta, nu, metric):
    """critic_sum and gain_sum of one point, from omega and delta, in exact rational arithmetic."""
    from fractions import Fraction

    om = [Fraction(float(v)) for v in omega]
    rho = 1 + Fraction(nu) * sum(
        Fraction(float(m)) * v * v for m, v in zip(metric, om, strict=True)
    )
    q = [v / rho for v in om]
    critic = np.array([float(v * Fraction(float(delta))) for v in q])
    gain = np.array([[float(a * b) for b in q] for a in q])
    return critic, gain


def test_an_overflowing_rho_keeps_the_point_in_the_sums():
    # Before: omega^2 overflowed, rho = inf, omega / rho = 0: critic_sum = gain_sum = 0.
    system = _plant(lambda x: np.array([x[0] ** 3 + x[1], 0 * x[0]]), name="cubic1")
    basis = PolynomialBasis(2, [3])
    F = point_features(system, basis, np.array([[1e40], [0.0]]), 5 * np.eye(2))
    out = extrapolate(F, np.full(basis.size, 0.5), np.array([1.0]), LBAR, NU)
    assert out.rho[0] == np.inf  # its true value, rounded
    critic, gain = _exact_sums(out.omega[:, 0], out.delta[0], NU, np.ones(basis.size))
    assert abs(out.critic_sum[0]) > 0.5
    # Exact to rounding, entry by entry, but for q_2 ~ 5e-321 (subnormal: fewer digits).
    np.testing.assert_allclose(out.critic_sum, critic, rtol=1e-14, atol=1e-14 * abs(critic[0]))
    np.testing.assert_allclose(out.gain_sum, gain, rtol=1e-14, atol=1e-300)


@settings(max_examples=200, deadline=None)
@given(
    exponent=st.integers(-5, 300),
    mantissas=st.lists(st.floats(0.1, 1.0), min_size=3, max_size=3),
    signs=st.lists(st.sampled_from([-1.0, 1.0]), min_size=3, max_size=3),
    W=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
    nu=st.floats(1e-3, 1e3),
    metric=st.lists(st.floats(1e-2, 1e2), min_size=3, max_size=3),
)
def test_sums_are_exact_to_rounding_at_any_omega_and_bitwise_unchanged_when_rho_is_finite(
    exponent, mantissas, signs, W, nu, metric
):
    from ofrl_drake.bellman import PointFeatures

    omega = 10.0**exponent * np.array(mantissas) * np.array(signs)
    # One point, g = 0: omega is the drift, u = 0, delta = W^T omega + 1.
    F = PointFeatures(
        points=np.zeros((2, 1)),
        drift=omega[:, None].copy(),
        input=np.zeros((1, 3, 1)),
        state_cost=np.ones(1),
    )
    W = np.array(W)
    m = np.array(metric)
    out = extrapolate(F, W, np.array([1.0]), LBAR, nu, metric=m)
    delta = out.delta[0]
    critic, gain = _exact_sums(omega, delta, nu, m)
    np.testing.assert_allclose(out.critic_sum, critic, rtol=1e-14, atol=1e-300)
    np.testing.assert_allclose(out.gain_sum, gain, rtol=1e-14, atol=1e-290)
    rho = 0.0
    with np.errstate(over="ignore"):
        for a in range(3):
            rho += m[a] * (omega[a] * omega[a])
        rho = 1.0 + nu * rho
    if np.isfinite(rho):  # the plain formula's bits
        q = omega / rho
        assert np.array_equal(out.critic_sum, q * delta)
        assert np.array_equal(out.gain_sum, np.outer(q, q))


def test_a_domain_error_anywhere_in_the_diagram_is_not_blamed_on_f_alone(
    paper_scenario, monkeypatch
):
    # Before: "the model's f or g was evaluated outside its domain", whichever function
    # of the diagram (the cost, a block) Drake's symbolic math refused.
    import dataclasses

    from pydrake.systems.analysis import Simulator

    import ofrl_drake.simulation as simulation

    class _Refusing(Simulator):
        def AdvanceTo(self, t):
            raise ValueError("log(nan) : numerical argument out of domain")

    monkeypatch.setattr(simulation, "Simulator", _Refusing)
    scenario = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(paper_scenario.simulation, duration=0.1),
        variant=dataclasses.replace(paper_scenario.variant, observer="true_state"),
    )
    result = simulation.simulate(scenario, progress=False)
    reason = result.stop.reason
    assert reason.startswith(
        "the model's f or g was evaluated outside its domain (log(nan) : numerical argument "
        "out of domain) for the model 'two_state', or another function of the diagram was"
    ), reason
    assert "left the region where f and g (and the cost) are defined" in reason
