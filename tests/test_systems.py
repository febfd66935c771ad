"""Each Drake block: ports, state counts, and derivatives against closed forms."""

import re

import numpy as np
import pytest

from ofrl_drake import PolynomialBasis
from ofrl_drake.bellman import (
    Extrapolator,
    extrapolate,
    pack_symmetric,
    point_features,
    unpack_symmetric,
)
from ofrl_drake.errors import ModelError
from ofrl_drake.examples import make_system
from ofrl_drake.observer import ObserverGains
from ofrl_drake.points import grid_points
from ofrl_drake.systems import (
    BellmanExtrapolator,
    ControlAffinePlant,
    CriticWeights,
    GammaGain,
    RunningCost,
    SaturatedController,
    SaturatedLqrController,
    ScheduledThreeGainObserver,
    ThreeGainObserver,
)
from ofrl_drake.systems.world import MeasuredPlant
from tests.block_helpers import ports, random_gains

GRID = [np.array([a, b]) for a in (-1.5, -0.2, 0.0, 0.7, 1.9) for b in (-1.0, 0.3, 1.6)]


@pytest.mark.parametrize("name", ["two_state", "coupled_two_state"])
def test_block_structure(name):
    system = make_system(name)
    n, m, q = system.n, system.m, system.q
    basis = PolynomialBasis(n)
    L = basis.size
    P = L * (L + 1) // 2  # Gamma's upper triangle
    features = point_features(
        system, basis, grid_points(-np.ones(n), np.ones(n), [3] * n), np.eye(n)
    )
    r = np.ones(m)
    cases = [
        (ControlAffinePlant(system), ({"u": m}, {"state": n, "y": q}), n),
        (
            ThreeGainObserver(system, random_gains(system)),
            ({"y": q, "u": m}, {"estimated_state": n}),
            n,
        ),
        (CriticWeights(np.zeros(L), 0.01), ({"critic_sum": L, "gamma": P}, {"weights": L}), L),
        (GammaGain(np.eye(L), 0.01, 0.2), ({"gain_sum": L * L}, {"gamma": P}), P),
        (
            SaturatedController(system, basis, r, 3.0),
            ({"estimated_state": n, "policy_weights": L}, {"u": m}),
            0,
        ),
        (
            BellmanExtrapolator(features, r, 3.0, 0.7),
            (
                {"weights": L, "policy_weights": L},
                {"critic_sum": L, "gain_sum": L * L, "learning_condition": 1},
            ),
            0,
        ),
        (RunningCost(np.eye(n), r, 3.0), ({"state": n, "u": m}, {"cost": 1}), 1),
    ]
    for block, (ins, outs), num_states in cases:
        assert ports(block) == (ins, outs), type(block).__name__
        assert block.num_continuous_states() == num_states, type(block).__name__


def test_accessors_return_the_named_ports():
    system = make_system("two_state")
    plant = ControlAffinePlant(system)
    assert plant.get_y_output_port().get_name() == "y"
    assert plant.get_state_output_port().get_name() == "state"
    assert plant.get_u_input_port().get_name() == "u"
    obs = ThreeGainObserver(system, random_gains(system))
    assert obs.get_estimated_state_output_port().get_name() == "estimated_state"
    assert obs.get_y_input_port().get_name() == "y" and obs.get_u_input_port().get_name() == "u"


def test_state_outputs_have_no_direct_feedthrough():
    system = make_system("two_state")
    for block in (ControlAffinePlant(system), ThreeGainObserver(system, random_gains(system))):
        assert not any(
            block.HasDirectFeedthrough(i, j)
            for i in range(block.num_input_ports())
            for j in range(block.num_output_ports())
        )


def _derivatives(block, state, inputs):
    context = block.CreateDefaultContext()
    context.SetContinuousState(state)
    for name, value in inputs.items():
        block.GetInputPort(name).FixValue(context, value)
    return block.EvalTimeDerivatives(context).CopyToVector()


@pytest.mark.parametrize("x", GRID)
def test_plant_derivative_closed_form(x):
    system = make_system("two_state")
    u = np.array([0.7])
    c = np.cos(2 * x[0]) + 2
    expected = [-x[0] + x[1], -x[0] - 0.5 * x[1] * (1 - c**2) + c * u[0]]
    np.testing.assert_allclose(
        _derivatives(ControlAffinePlant(system), x, {"u": u}), expected, rtol=1e-14, atol=1e-14
    )


def _expected_observer_rhs(system, gains, xhat, y, u):
    """The paper's form (eq:observerdynamics_x) with the sign-correct sector, summed over inputs.

    ``M_ug1(u) = sum_k min(M_g1[..., k] u_k, M_g2[..., k] u_k)``; ``u`` has shape (m,).
    """
    ytil = y - system.output_matrix @ xhat
    Mug1 = sum(
        np.minimum(gains.Mg1[..., k] * u[k], gains.Mg2[..., k] * u[k]) for k in range(system.m)
    )

    def fbar(z):
        return system.f(z) - gains.Mf1 @ z

    def gbar(z):
        return system.g(z) @ u - Mug1 @ z

    return (
        gains.Mf1 @ xhat
        + Mug1 @ xhat
        + fbar(xhat + gains.H @ ytil)
        + gbar(xhat + gains.K @ ytil)
        + gains.L @ ytil
    )


@pytest.mark.parametrize("xhat", GRID)
@pytest.mark.parametrize("u", [-2.0, 0.0, 1.5])
def test_observer_derivative_closed_form(xhat, u):
    """The paper's form (eq:observerdynamics_x) with the sign-correct sector."""
    system = make_system("two_state")
    gains = random_gains(system, seed=4)
    y, uu = np.array([0.4]), np.array([u])
    expected = _expected_observer_rhs(system, gains, xhat, y, uu)
    got = _derivatives(ThreeGainObserver(system, gains), xhat, {"y": y, "u": uu})
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_critic_and_gamma_derivatives_closed_form(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    Gamma = A @ A.T + np.eye(3)
    S = rng.normal(size=(3, 3))
    S = S @ S.T
    s = rng.normal(size=3)
    W = rng.normal(size=3)
    kc, beta = 0.01, 0.2
    packed = pack_symmetric(Gamma)
    dW = _derivatives(CriticWeights(np.zeros(3), kc), W, {"critic_sum": s, "gamma": packed})
    np.testing.assert_allclose(dW, -kc * Gamma @ s, rtol=1e-13)
    dG = _derivatives(GammaGain(np.eye(3), kc, beta), packed, {"gain_sum": S.ravel()})
    assert dG.shape == (6,)  # the upper triangle only
    expected = beta * Gamma - kc * Gamma @ S @ Gamma
    np.testing.assert_allclose(unpack_symmetric(dG), expected, rtol=1e-12, atol=1e-14)


def test_gamma_is_packed_as_its_upper_triangle_row_by_row():
    G0 = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.25], [0.5, 0.25, 2.0]])
    block = GammaGain(G0, 0.0, 0.0)
    context = block.CreateDefaultContext()
    packed = block.get_gamma_output_port().Eval(context)
    np.testing.assert_array_equal(packed, [4.0, 1.0, 0.5, 3.0, 0.25, 2.0])
    np.testing.assert_array_equal(unpack_symmetric(packed), G0)
    np.testing.assert_array_equal(pack_symmetric(unpack_symmetric(packed)), packed)
    # A batch of logged samples (T, L (L + 1) / 2) unpacks to (T, L, L).
    assert unpack_symmetric(np.tile(packed, (5, 1))).shape == (5, 3, 3)
    with pytest.raises(ModelError, match=r"L \(L \+ 1\) / 2 entries; 5 is not such a number"):
        unpack_symmetric(np.ones(5))
    with pytest.raises(ModelError, match=r"needs square matrices \(\.\.\., L, L\); got \(2, 3\)"):
        pack_symmetric(np.ones((2, 3)))


@pytest.mark.parametrize("x", GRID)
def test_controller_output_closed_form(x):
    system = make_system("two_state")
    W = np.array([0.4, 0.2, 0.8])
    ctrl = SaturatedController(system, PolynomialBasis(2), np.array([2.0]), 3.0)
    context = ctrl.CreateDefaultContext()
    ctrl.get_estimated_state_input_port().FixValue(context, x)
    ctrl.get_policy_weights_input_port().FixValue(context, W)
    grad_V = np.array([2 * W[0] * x[0] + W[1] * x[1], W[1] * x[0] + 2 * W[2] * x[1]])
    D = (1 / (2 * 3.0)) * (1 / 2.0) * (np.cos(2 * x[0]) + 2) * grad_V[1]
    np.testing.assert_allclose(
        ctrl.get_u_output_port().Eval(context), [-3.0 * np.tanh(D)], rtol=1e-14
    )


@pytest.mark.parametrize("x", GRID[:5])
def test_running_cost_derivative_closed_form(x):
    u = np.array([1.2])
    rate = _derivatives(
        RunningCost(5 * np.eye(2), np.array([1.0]), 3.0), [0.0], {"state": x, "u": u}
    )
    U = 2 * 3.0 * (u[0] * np.arctanh(u[0] / 3) + 1.5 * np.log(1 - u[0] ** 2 / 9))
    np.testing.assert_allclose(rate, [5 * x @ x + U], rtol=1e-12)


def test_bellman_outputs_share_one_extrapolation(monkeypatch):
    system = make_system("two_state")
    basis = PolynomialBasis(2)
    features = point_features(system, basis, grid_points([-1, -1], [1, 1], [4, 4]), np.eye(2))
    block = BellmanExtrapolator(features, np.ones(1), 3.0, 0.7)
    calls = []
    original = Extrapolator.sums_into

    def counted(self, W, critic_sum, gain_sum, W_policy=None):
        calls.append(1)
        original(self, W, critic_sum, gain_sum, W_policy)

    monkeypatch.setattr(Extrapolator, "sums_into", counted)
    context = block.CreateDefaultContext()
    W = np.array([0.4, 0.2, 0.8])
    block.get_weights_input_port().FixValue(context, W)
    block.get_policy_weights_input_port().FixValue(context, W)
    first = block.extrapolation(context)
    critic_sum = block.get_critic_sum_output_port().Eval(context)
    gain_sum = block.get_gain_sum_output_port().Eval(context)
    condition = block.get_learning_condition_output_port().Eval(context)[0]
    assert len(calls) == 1  # three outputs, one extrapolation
    expected = extrapolate(features, W, np.ones(1), 3.0, 0.7)
    np.testing.assert_allclose(critic_sum, expected.critic_sum, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(gain_sum, expected.gain_sum.ravel(), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(first.gain_sum, expected.gain_sum, rtol=1e-14, atol=1e-15)
    assert condition == pytest.approx(np.linalg.eigvalsh(expected.gain_sum)[0], rel=1e-12)
    block.get_weights_input_port().FixValue(context, np.array([1.0, 0.0, 1.0]))
    block.get_policy_weights_input_port().FixValue(context, np.array([1.0, 0.0, 1.0]))
    block.get_critic_sum_output_port().Eval(context)
    assert len(calls) == 2  # an input change invalidates


def test_gain_shape_errors_name_the_gain():
    system = make_system("two_state")
    with pytest.raises(ModelError, match=r"observer gain L must have shape \(2, 1\); got \(1, 2\)"):
        ObserverGains.from_arrays(
            system,
            np.zeros((1, 2)),
            np.zeros((2, 1)),
            np.zeros((2, 1)),
            np.zeros((2, 2)),
            np.zeros((2, 2, 1)),
            np.zeros((2, 2, 1)),
        )


MIMO_GRID = [
    np.array([a, b, c, d])
    for a in (-1.5, 0.4)
    for b in (-0.7, 1.1)
    for c in (-0.3, 1.8)
    for d in (0.0, -1.2)
]


@pytest.mark.parametrize("xhat", MIMO_GRID)
@pytest.mark.parametrize("u", [np.array([-2.0, 1.5]), np.array([2.5, -0.5]), np.array([0.0, -3.0])])
def test_mimo_observer_derivative_closed_form(xhat, u):
    """m = 2 with mixed-sign inputs: the sector sums min/max per input."""
    system = make_system("coupled_two_state")
    gains = random_gains(system, seed=7)
    y = np.array([0.4, -0.2])
    expected = _expected_observer_rhs(system, gains, xhat, y, u)
    got = _derivatives(ThreeGainObserver(system, gains), xhat, {"y": y, "u": u})
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("x", MIMO_GRID)
def test_mimo_controller_output_closed_form(x):
    """u_k = -lbar tanh(g_k(x)^T grad V(x) / (2 lbar r_k)) with r = [1, 2]."""
    system = make_system("coupled_two_state")
    basis = PolynomialBasis(4)
    W = np.linspace(-0.5, 1.0, basis.size)
    r = np.array([1.0, 2.0])
    ctrl = SaturatedController(system, basis, r, 3.0)
    context = ctrl.CreateDefaultContext()
    ctrl.get_estimated_state_input_port().FixValue(context, x)
    ctrl.get_policy_weights_input_port().FixValue(context, W)
    # grad V by central differences of V = W^T sigma, independent of basis.gradient.
    h = 1e-6
    grad_V = np.array([(W @ basis(x + h * e) - W @ basis(x - h * e)) / (2 * h) for e in np.eye(4)])
    D = (system.g(x).T @ grad_V) / (2 * 3.0 * r)
    np.testing.assert_allclose(
        ctrl.get_u_output_port().Eval(context), -3.0 * np.tanh(D), rtol=1e-7, atol=1e-9
    )


BAD_BLOCK_ARGUMENTS = [
    (lambda: CriticWeights([0.0, np.nan], 0.1), r"CriticWeights: initial_weights must be finite"),
    (lambda: CriticWeights(np.zeros((2, 2)), 0.1), r"initial_weights must be a non-empty 1-D"),
    (lambda: CriticWeights(np.zeros(3), -1.0), r"CriticWeights: kc must be >= 0; got -1.0"),
    (lambda: GammaGain(np.array([[1.0, 2.0], [0.0, 1.0]]), 0.1, 0.2), r"initial_gamma must be sym"),
    (lambda: GammaGain(-np.eye(2), 0.1, 0.2), r"initial_gamma must be positive definite"),
    (lambda: GammaGain(np.ones((2, 3)), 0.1, 0.2), r"initial_gamma must be a square matrix"),
    (lambda: GammaGain(np.eye(2), 0.1, -0.2), r"GammaGain: beta must be >= 0; got -0.2"),
    (lambda: RunningCost(-np.eye(2), [1.0], 3.0), r"RunningCost: Q must be positive semidefinite"),
    (lambda: RunningCost(np.eye(2), [0.0], 3.0), r"RunningCost: r must have entries > 0"),
    (lambda: RunningCost(np.eye(2), [1.0], 0.0), r"RunningCost: input_bound must be > 0; got 0"),
]


@pytest.mark.parametrize(("make", "message"), BAD_BLOCK_ARGUMENTS)
def test_block_constructors_reject_bad_arguments(make, message):
    with pytest.raises(ModelError, match=message):
        make()


def test_controller_rejects_mismatched_basis_input_weights_and_bound():
    system = make_system("two_state")
    with pytest.raises(ModelError, match=r"basis is for n = 3 states but the system has n = 2"):
        SaturatedController(system, PolynomialBasis(3), np.array([1.0]), 3.0)
    with pytest.raises(ModelError, match=r"SaturatedController: r must have length 1; got 2"):
        SaturatedController(system, PolynomialBasis(2), np.array([1.0, 1.0]), 3.0)
    with pytest.raises(ModelError, match=r"SaturatedController: input_bound must be > 0"):
        SaturatedController(system, PolynomialBasis(2), np.array([1.0]), -3.0)


def test_frozen_blocks_are_allowed():
    """kc = 0 (frozen critic) and kc = beta = 0 (constant Gamma) are ablations, not errors."""
    assert CriticWeights(np.zeros(3), 0.0).num_continuous_states() == 3
    assert GammaGain(np.eye(3), 0.0, 0.0).num_continuous_states() == 6  # packed


def test_running_cost_rejects_an_input_beyond_the_bound():
    block = RunningCost(np.eye(2), np.array([1.0]), 3.0)
    context = block.CreateDefaultContext()
    block.get_state_input_port().FixValue(context, np.array([0.1, 0.2]))
    block.get_u_input_port().FixValue(context, np.array([3.5]))
    with pytest.raises(ModelError, match=r"\|u\| = 3.5 exceeds the input bound 3.0"):
        block.EvalTimeDerivatives(context)


@pytest.mark.parametrize("kc", [0.0, 2.5])
def test_critic_set_weights_and_derivative(kc):
    W0 = np.array([0.4, -0.2, 0.8, 1.5])
    block = CriticWeights(W0, kc)
    rng = np.random.default_rng(5)
    Gamma = rng.normal(size=(4, 4))
    Gamma = Gamma + Gamma.T
    inputs = {"critic_sum": rng.normal(size=4), "gamma": pack_symmetric(Gamma)}
    W = rng.normal(size=4)
    context = block.CreateDefaultContext()
    np.testing.assert_array_equal(block.get_weights_output_port().Eval(context), W0)
    for port, value in inputs.items():
        block.GetInputPort(port).FixValue(context, value)
    block.set_weights(context, W)
    np.testing.assert_array_equal(block.get_weights_output_port().Eval(context), W)
    rate = block.EvalTimeDerivatives(context).CopyToVector()
    expected = -kc * Gamma @ inputs["critic_sum"]
    np.testing.assert_allclose(rate, expected, rtol=1e-14, atol=1e-15)


# ------------------------------------------------- gains as context parameters
def _parameter_block_derivative(block, state, inputs, set_values):
    """The derivative of ``block`` at ``state``, after ``set_values(context)``."""
    context = block.CreateDefaultContext()
    set_values(context)
    for name, value in inputs.items():
        block.GetInputPort(name).FixValue(context, value)
    context.SetContinuousState(state)
    return block.EvalTimeDerivatives(context).CopyToVector()


def test_gains_in_the_context_give_the_derivative_of_a_block_built_with_them():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(3, 3))
    Gamma = A @ A.T + np.eye(3)
    S = rng.normal(size=(3, 3))
    S = S @ S.T
    s, W = rng.normal(size=3), rng.normal(size=3)
    G0 = 2.0 * np.eye(3) + 0.1
    critic_inputs = {"critic_sum": s, "gamma": pack_symmetric(Gamma)}
    critic = CriticWeights(np.zeros(3), 0.01)
    got = _parameter_block_derivative(critic, W, critic_inputs, lambda c: critic.set_kc(c, 0.3))
    built = _derivatives(CriticWeights(np.zeros(3), 0.3), W, critic_inputs)
    np.testing.assert_array_equal(got, built)

    gamma = GammaGain(np.eye(3), 0.01, 0.2)

    def gains(context):
        gamma.set_kc(context, 0.05)
        gamma.set_beta(context, 0.7)
        gamma.set_gamma_bound(context, 4.0)
        gamma.set_initial_gamma(context, G0)  # the reference of bounded forgetting too

    got = _parameter_block_derivative(gamma, pack_symmetric(Gamma), {"gain_sum": S.ravel()}, gains)
    built = _derivatives(
        GammaGain(G0, 0.05, 0.7, 4.0), pack_symmetric(Gamma), {"gain_sum": S.ravel()}
    )
    np.testing.assert_array_equal(got, built)
    context = gamma.CreateDefaultContext()
    gains(context)
    assert gamma.get_gains(context) == (0.05, 0.7, 4.0)
    np.testing.assert_array_equal(gamma.get_gamma_output_port().Eval(context), pack_symmetric(G0))
    gamma.set_gamma_bound(context, None)
    assert gamma.get_gains(context) == (0.05, 0.7, None)
    assert gamma.get_gains(gamma.CreateDefaultContext()) == (0.01, 0.2, None)


def test_nu_in_the_context_gives_the_sums_of_a_block_built_with_it():
    system, basis = make_system("two_state"), PolynomialBasis(2)
    features = point_features(system, basis, grid_points([-1, -1], [1, 1], [4, 3]), np.eye(2))
    r, W, Wp = np.array([1.0]), np.array([0.4, 0.2, 0.8]), np.array([0.5, 0.1, 0.7])
    block = BellmanExtrapolator(features, r, 3.0, 0.7)
    context = block.CreateDefaultContext()
    block.get_weights_input_port().FixValue(context, W)
    block.get_policy_weights_input_port().FixValue(context, Wp)
    built = BellmanExtrapolator(features, r, 3.0, 0.2)
    built_context = built.CreateDefaultContext()
    built.get_weights_input_port().FixValue(built_context, W)
    built.get_policy_weights_input_port().FixValue(built_context, Wp)
    default = block.get_critic_sum_output_port().Eval(context).copy()
    block.set_nu(context, 0.2)  # invalidates the cached sums
    assert block.get_nu(context) == 0.2
    for name in ("critic_sum", "gain_sum", "learning_condition"):
        np.testing.assert_array_equal(
            block.GetOutputPort(name).Eval(context), built.GetOutputPort(name).Eval(built_context)
        )
    assert not np.array_equal(default, block.get_critic_sum_output_port().Eval(context))
    weights = np.array([W, Wp, 2 * W])
    np.testing.assert_array_equal(
        block.learning_condition_of(weights, context), built.learning_condition_of(weights)
    )
    with pytest.raises(ModelError, match=r"BellmanExtrapolator: nu must be > 0; got -1.0"):
        block.set_nu(context, -1.0)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: CriticWeights(np.zeros(2), 0.1).set_kc(None, -1.0), r"kc must be >= 0; got -1.0"),
        (lambda: GammaGain(np.eye(2), 0.1, 0.2).set_beta(None, np.nan), r"beta must be finite"),
        (
            lambda: GammaGain(np.eye(2), 0.1, 0.2).set_gamma_bound(None, 0.0),
            r"GammaGain: gamma_bound must be > 0; got 0.0",
        ),
        (
            lambda: GammaGain(np.eye(2), 0.1, 0.2).set_initial_gamma(None, -np.eye(2)),
            r"GammaGain: Gamma\(0\) must be positive definite",
        ),
        (
            lambda: CriticWeights(np.zeros(2), 0.1).set_weights(None, [1.0, 2.0, 3.0]),
            r"CriticWeights: W must have length 2; got 3",
        ),
    ],
)
def test_setters_name_the_bad_value(call, message):
    with pytest.raises(ModelError, match=message):
        call()


def _documented_ports(block):
    """The input and output port names of the ``.. pydrake_system::`` block of its class."""
    doc = type(block).__doc__
    lists = re.search(r"input_ports:\n(.*?)output_ports:\n(.*?)\n\n", doc, re.S)
    assert lists is not None, type(block).__name__
    return tuple(re.findall(r"^\s*- (\w+)$", text, re.M) for text in lists.groups())


def test_docstrings_list_the_ports_in_declaration_order():
    system = make_system("coupled_two_state")
    basis = PolynomialBasis(system.n)
    n = system.n
    features = point_features(
        system, basis, grid_points(-np.ones(n), np.ones(n), [2] * n), np.eye(n)
    )
    r = np.ones(system.m)
    blocks = [
        ControlAffinePlant(system),
        ThreeGainObserver(system, random_gains(system)),
        CriticWeights(np.zeros(basis.size), 0.01),
        GammaGain(np.eye(basis.size), 0.01, 0.2),
        SaturatedController(system, basis, r, 3.0),
        BellmanExtrapolator(features, r, 3.0, 0.7),
        RunningCost(np.eye(system.n), r, 3.0),
    ]
    for block in blocks:
        declared = (
            [block.get_input_port(i).get_name() for i in range(block.num_input_ports())],
            [block.get_output_port(i).get_name() for i in range(block.num_output_ports())],
        )
        assert _documented_ports(block) == tuple(declared), type(block).__name__


def _scheduled_observer(system, design, initial_state):
    return ScheduledThreeGainObserver(
        system,
        design,
        period=1.0,
        half_width=[1.0, 1.0],
        input_bound=3.0,
        alpha=0.1,
        initial_state=initial_state,
    )


INITIAL_STATE_BLOCKS = {
    "ControlAffinePlant": lambda system, design, x0: ControlAffinePlant(system, initial_state=x0),
    "ThreeGainObserver": lambda system, design, x0: ThreeGainObserver(
        system, random_gains(system), initial_state=x0
    ),
    "ScheduledThreeGainObserver": _scheduled_observer,
}


@pytest.mark.parametrize("owner", sorted(INITIAL_STATE_BLOCKS))
@pytest.mark.parametrize(
    ("initial_state", "message"),
    [
        ([1.0, 2.0, 3.0], r"initial_state must have length 2; got 3\.$"),
        ([np.inf, 0.0], r"initial_state must be finite; got \[inf, 0\.0\]\.$"),
        ([[1.0, 2.0]], r"initial_state must be a non-empty 1-D vector; got shape \(1, 2\)\.$"),
    ],
)
def test_initial_state_is_checked_like_the_state_setters(
    paper_design, owner, initial_state, message
):
    system = make_system("two_state")
    with pytest.raises(ModelError, match=rf"^{owner}: {message}"):
        INITIAL_STATE_BLOCKS[owner](system, paper_design, initial_state)


@pytest.mark.parametrize("owner", ["ControlAffinePlant", "ThreeGainObserver"])
def test_a_valid_initial_state_is_the_default_state_and_is_kept_as_given(owner):
    system = make_system("two_state")
    block = INITIAL_STATE_BLOCKS[owner](system, None, [0.5, -0.25])
    assert block.initial_state == [0.5, -0.25]
    context = block.CreateDefaultContext()
    np.testing.assert_array_equal(
        context.get_continuous_state_vector().CopyToVector(), [0.5, -0.25]
    )


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"nu": -5.0}, r"^nu must be > 0; got -5\.0\.$"),
        ({"nu": np.inf}, r"^nu must be finite; got inf\.$"),
        ({"r": [0.0]}, r"^r must have entries > 0; got \[0\.0\]\.$"),
        ({"r": [1.0, 1.0]}, r"^r must have length 1; got 2\.$"),
        ({"input_bound": 0.0}, r"^input_bound must be > 0; got 0\.0\.$"),
        ({"input_bound": np.nan}, r"^input_bound must be finite; got nan\.$"),
    ],
)
def test_bellman_extrapolator_rejects_what_its_setter_would(arguments, message):
    """Not a block that builds and then outputs NaN: nu, r and lbar are checked up front."""
    system = make_system("two_state")
    features = point_features(
        system, PolynomialBasis(2), grid_points([-1, -1], [1, 1], [3, 3]), np.eye(2)
    )
    given = {"r": [1.0], "input_bound": 3.0, "nu": 0.7} | arguments
    with pytest.raises(ModelError, match=message):
        BellmanExtrapolator(features, **given)


def test_lqr_controller_keeps_its_arguments_and_reports_its_lqr_result():
    """The gain is a derived result (``lqr_result()``), not an attribute beside the arguments."""
    import dataclasses

    import scipy.linalg

    from ofrl_drake.baselines import linearize_at_origin

    lin = linearize_at_origin(make_system("two_state"))
    Q, R = 5.0 * np.eye(2), np.array([[2.0]])
    block = SaturatedLqrController(lin, Q, R, 3)
    assert block.linearization is lin and block.Q is Q and block.R is R
    assert block.input_bound == 3 and isinstance(block.input_bound, int)
    S = scipy.linalg.solve_continuous_are(lin.A(), lin.B(), Q, R)
    result = block.lqr_result()
    np.testing.assert_allclose(result.S, S, rtol=1e-8)
    np.testing.assert_allclose(result.K, np.linalg.solve(R, lin.B().T @ S), rtol=1e-8)
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.K = np.zeros((1, 2))
    context = block.CreateDefaultContext()
    x = np.array([0.01, -0.02])
    block.get_estimated_state_input_port().FixValue(context, x)
    np.testing.assert_array_equal(block.get_u_output_port().Eval(context), -result.K @ x)
    assert block.K is result.K  # read-only, as before the result object


@pytest.mark.parametrize("R", [2.0, [2.0], np.array([2.0]), [[2.0]]])
def test_lqr_controller_takes_r_of_one_input_as_a_number_a_vector_or_a_matrix(R):
    from ofrl_drake.baselines import linearize_at_origin

    lin = linearize_at_origin(make_system("two_state"))
    block = SaturatedLqrController(lin, np.eye(2), R, 3.0)
    reference = SaturatedLqrController(lin, np.eye(2), np.array([[2.0]]), 3.0)
    np.testing.assert_array_equal(block.lqr_result().K, reference.lqr_result().K)


@pytest.mark.parametrize(
    ("Q", "R", "input_bound", "message"),
    [
        (np.eye(3), np.eye(1), 3.0, r"Q must have shape \(2, 2\); got \(3, 3\)\.$"),
        (-np.eye(2), np.eye(1), 3.0, r"Q must be positive semidefinite"),
        ([[1.0, 2.0], [0.0, 1.0]], np.eye(1), 3.0, r"Q must be symmetric"),
        (np.eye(2), np.eye(2), 3.0, r"R must have shape \(1, 1\); got \(2, 2\)\.$"),
        (np.eye(2), -np.eye(1), 3.0, r"R must be positive definite"),
        (np.eye(2), [[np.nan]], 3.0, r"R must be finite; got \[\[nan\]\]\.$"),
        (np.eye(2), np.eye(1), -3.0, r"input_bound must be > 0; got -3\.0\.$"),
        (np.eye(2), np.eye(1), np.nan, r"input_bound must be finite; got nan\.$"),
    ],
)
def test_lqr_controller_rejects_bad_weights_and_bound(Q, R, input_bound, message):
    """Not a Drake abort from deep inside, nor a gain for a negative-definite Q."""
    from ofrl_drake.baselines import linearize_at_origin

    lin = linearize_at_origin(make_system("two_state"))
    with pytest.raises(ModelError, match=rf"^SaturatedLqrController: {message}"):
        SaturatedLqrController(lin, Q, R, input_bound)


def test_measured_plant_without_a_state_output_says_so():
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    inner = builder.AddSystem(ControlAffinePlant(make_system("two_state")))
    builder.ExportInput(inner.GetInputPort("u"), "u")
    builder.ExportOutput(inner.GetOutputPort("y"), "y")
    plant = MeasuredPlant(builder.Build(), period=0.1)
    assert plant.get_u_input_port().get_name() == "u"
    assert plant.get_y_output_port().get_name() == "y"
    with pytest.raises(
        ModelError,
        match=r"^MeasuredPlant: the plant Diagram has no output port 'state', so its state "
        r"cannot be read; give it one\.$",
    ):
        plant.get_state_output_port()


# --------------------------------------------- shared set-up of the blocks
def test_pack_gains_and_unpack_gains_are_inverse_with_leading_axes():
    from ofrl_drake.observer import pack_gains, unpack_gains

    system = make_system("coupled_two_state")  # n = 4, q = 2: the row-major order shows
    n, q = system.n, system.q
    gains = [random_gains(system, seed=seed) for seed in range(3)]
    packed = np.array([pack_gains(g.L, g.H, g.K) for g in gains])
    assert packed.shape == (3, 3 * n * q)
    np.testing.assert_array_equal(packed[0, : n * q], gains[0].L.ravel())
    L, H, K = unpack_gains(packed, n, q)  # a log: one row per sample
    assert L.shape == H.shape == K.shape == (3, n, q)
    for i, g in enumerate(gains):
        np.testing.assert_array_equal(L[i], g.L)
        np.testing.assert_array_equal(H[i], g.H)
        np.testing.assert_array_equal(K[i], g.K)
    one = unpack_gains(packed[1], n, q)  # one vector
    for got, want in zip(one, (gains[1].L, gains[1].H, gains[1].K), strict=True):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize(
    ("packed", "message"),
    [
        (
            np.zeros(7),
            r"^observer_gains must have 3 n q = 6 entries on its last axis .*got shape \(7,\)",
        ),
        (np.zeros((4, 5)), r"^observer_gains must have 3 n q = 6 .*got shape \(4, 5\)\.$"),
        (np.float64(1.0), r"^observer_gains must have 3 n q = 6 .*got shape \(\)\.$"),
        (["a"] * 6, r"^observer_gains must be numeric; got \['a'"),
    ],
)
def test_unpack_gains_names_a_wrong_layout(packed, message):
    from ofrl_drake.observer import unpack_gains

    with pytest.raises(ModelError, match=message):
        unpack_gains(packed, 2, 1)


def test_set_state_vector_checks_then_writes_the_whole_continuous_state():
    from ofrl_drake.drake_typing import set_state_vector

    plant = ControlAffinePlant(make_system("two_state"))
    context = plant.CreateDefaultContext()
    set_state_vector(context, [0.5, -1], 2, "ControlAffinePlant: x")
    np.testing.assert_array_equal(context.get_continuous_state_vector().CopyToVector(), [0.5, -1])
    with pytest.raises(ModelError, match=r"^ControlAffinePlant: x must have length 2; got 3\.$"):
        set_state_vector(context, [1.0, 2.0, 3.0], 2, "ControlAffinePlant: x")
    np.testing.assert_array_equal(context.get_continuous_state_vector().CopyToVector(), [0.5, -1])


@pytest.mark.parametrize(
    ("setter", "message"),
    [
        (lambda s, c: ControlAffinePlant(s).set_state(c, [np.nan, 0.0]), "ControlAffinePlant: x"),
        (
            lambda s, c: ThreeGainObserver(s, random_gains(s)).set_estimated_state(c, [1.0]),
            "ThreeGainObserver: xhat",
        ),
    ],
)
def test_state_setters_name_their_block(setter, message):
    system = make_system("two_state")
    context = ControlAffinePlant(system).CreateDefaultContext()
    with pytest.raises(ModelError, match=rf"^{message} must "):
        setter(system, context)


def test_check_cost_arguments_returns_the_checked_values_and_names_the_block():
    from ofrl_drake.cost import check_cost_arguments

    Q, r, lbar = check_cost_arguments("RunningCost", [[1, 0], [0, 2]], [1], np.float32(3.0))
    np.testing.assert_array_equal(Q, [[1.0, 0.0], [0.0, 2.0]])
    np.testing.assert_array_equal(r, [1.0])
    assert lbar == 3.0 and type(lbar) is float
    with pytest.raises(ModelError, match=r"^SymbolicRunningCost: input_bound must be > 0; got 0"):
        check_cost_arguments("SymbolicRunningCost", np.eye(2), [1.0], 0.0)


def test_require_observer_arguments_checks_system_gains_and_design(paper_design):
    from ofrl_drake.observer import require_observer_arguments

    system = make_system("two_state")
    gains = ObserverGains.from_design(system, paper_design)
    assert require_observer_arguments("Obs", system, gains, paper_design) is gains
    with pytest.raises(ModelError, match=r"^Obs: system must be a ControlAffineSystem"):
        require_observer_arguments("Obs", "two_state", gains)
    with pytest.raises(ModelError, match=r"^Obs: gains must be an ObserverGains; got dict"):
        require_observer_arguments("Obs", system, {})
    other = random_gains(system)
    with pytest.raises(ModelError, match=r"^gains\.L differs from design\.L"):
        require_observer_arguments("Obs", system, other, paper_design)
