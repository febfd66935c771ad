"""Slot choices: every variant builds and simulates, and each baseline block is right."""

import dataclasses

import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import solve_ivp

from ofrl_drake import ScenarioError, build_closed_loop, load_scenario, simulate
from ofrl_drake.baselines import (
    linearize_at_origin,
    luenberger_gain,
    luenberger_poles,
    point_offsets,
    symbolic_plant,
)
from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import extrapolate, point_features
from ofrl_drake.diagram import LOGGED
from ofrl_drake.errors import ModelError
from ofrl_drake.examples import make_system
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.scenario import VariantConfig
from ofrl_drake.systems import BellmanExtrapolator, ThreeGainObserver
from ofrl_drake.systems.baselines import (
    FullStateObserver,
    LinearizedLuenbergerObserver,
    MovingBellmanExtrapolator,
    SaturatedLqrController,
)
from ofrl_drake.variants import NEEDS_PARAMETERS, VARIANT_FACTORIES

from .conftest import PAPER_SCENARIO

#: Choices that build from the scenario alone (``controller=constant`` needs its input
#: value and is tested in tests/test_counterexample.py).
CHOICES = [
    (slot, choice)
    for slot, options in VARIANT_FACTORIES.items()
    for choice in options
    if (slot, choice) not in NEEDS_PARAMETERS
]
SHORT = 3.0


def _short(scenario, duration=SHORT, **choices):
    return dataclasses.replace(
        scenario,
        simulation=dataclasses.replace(scenario.simulation, duration=duration),
        variant=dataclasses.replace(scenario.variant, **choices),
    )


def _sub_context(loop, name, context):
    block = loop.blocks[name]
    return block, block.GetMyContextFromRoot(context)


@pytest.fixture(scope="module")
def baseline_short(paper_scenario):
    return simulate(_short(paper_scenario), progress=False)


def test_every_documented_choice_is_registered():
    assert {slot: sorted(options) for slot, options in VARIANT_FACTORIES.items()} == {
        "observer": [
            "drake_luenberger",
            "kalman",
            "linear_luenberger",
            "three_gain",
            "true_state",
        ],
        "controller": ["constant", "frozen_critic", "learned", "lqr"],
        "points": ["around_estimate", "grid", "uniform"],
        "gamma": ["constant", "least_squares"],
    }


@pytest.mark.parametrize(("slot", "choice"), CHOICES)
def test_every_choice_builds_and_simulates_with_the_same_logs(paper_scenario, slot, choice):
    scenario = _short(paper_scenario, **{slot: choice})
    loop = build_closed_loop(scenario)
    assert set(loop.loggers) >= set(LOGGED) - {"learning_condition"}
    r = simulate(scenario, loop=loop, progress=False)
    T = r.t.size
    assert r.t[-1] == pytest.approx(SHORT, abs=1e-9)
    assert r.x.shape == r.xhat.shape == (T, 2)
    assert r.W.shape == (T, 3) and r.Gamma.shape == (T, 3, 3) and r.u.shape == (T, 1)
    assert r.learning_condition.shape == r.cost.shape == (T,)
    for key in ("x", "xhat", "W", "Gamma", "u", "learning_condition", "cost"):
        assert np.all(np.isfinite(getattr(r, key))), key
    assert np.all(np.abs(r.u) <= paper_scenario.input_bound)
    # Every variant steers the paper's x0 = (-1, 1) towards the origin. The Kalman filter
    # keeps one pole at -1, the zero of x1' = -x1 + x2 seen from y = x2 with no process noise
    # on x1 (its estimate error decays as e^-t), so it gets a looser bound.
    factor = 0.2 if choice == "kalman" else 0.1
    assert np.linalg.norm(r.x[-1]) < factor * np.linalg.norm(r.x[0])


def test_true_state_feeds_the_state_through(paper_scenario):
    r = simulate(_short(paper_scenario, observer="true_state"), progress=False)
    np.testing.assert_array_equal(r.xhat, r.x)


def test_constant_controller_block():
    from ofrl_drake.systems import ConstantController

    block = ConstantController([1.5, -0.25])
    assert block.num_input_ports() == 0 and block.num_continuous_states() == 0
    assert block.get_u_output_port().get_name() == "u"
    context = block.CreateDefaultContext()
    np.testing.assert_array_equal(block.get_u_output_port().Eval(context), [1.5, -0.25])
    with pytest.raises(ModelError, match=r"value must be a non-empty finite vector; got \[nan\]"):
        ConstantController([float("nan")])


def test_full_state_observer_block():
    block = FullStateObserver(2)
    assert block.num_continuous_states() == 0
    assert block.get_state_input_port().get_name() == "state"
    assert block.get_estimated_state_output_port().get_name() == "estimated_state"
    context = block.CreateDefaultContext()
    block.get_state_input_port().FixValue(context, [0.3, -1.7])
    np.testing.assert_array_equal(
        block.get_estimated_state_output_port().Eval(context), [0.3, -1.7]
    )


def test_linearization_of_the_paper_plant():
    lin = linearize_at_origin(make_system("two_state"))
    # df/dx at 0: row 1 of f is -x1 + x2; row 2 is -x1 - x2 (1 - 9)/2 at x1 = 0.
    np.testing.assert_allclose(lin.A(), [[-1.0, 1.0], [-1.0, 4.0]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(lin.B(), [[0.0], [3.0]], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(lin.C(), [[0.0, 1.0]])
    np.testing.assert_array_equal(lin.D(), [[0.0]])


def test_linearization_needs_an_equilibrium_at_the_origin():
    shifted = ControlAffineSystem(
        lambda x: np.array([1.0 - x[0]]), lambda x: np.array([[1 + 0 * x[0]]]), [[1.0]]
    )
    with pytest.raises(ScenarioError, match=r"origin is not an equilibrium"):
        linearize_at_origin(shifted)


def test_symbolic_plant_matches_the_model():
    system = make_system("two_state")
    plant = symbolic_plant(system)
    context = plant.CreateDefaultContext()
    x, u = np.array([0.4, -1.3]), np.array([0.9])
    context.SetContinuousState(x)
    plant.get_input_port().FixValue(context, u)
    xdot = plant.EvalTimeDerivatives(context).CopyToVector()
    np.testing.assert_allclose(xdot, system.dynamics(x, u), rtol=1e-14, atol=1e-14)


def test_luenberger_gain_places_the_poles():
    lin = linearize_at_origin(make_system("two_state"))
    poles = luenberger_poles(2.0, 2)
    np.testing.assert_array_equal(poles, [-4.0, -6.0])
    L = luenberger_gain(lin.A(), lin.C(), poles)
    eig = np.sort(np.linalg.eigvals(lin.A() - L @ lin.C()).real)
    np.testing.assert_allclose(eig, [-6.0, -4.0], rtol=1e-10)


def test_luenberger_gain_rejects_an_unobservable_pair():
    with pytest.raises(ScenarioError, match=r"not observable"):
        luenberger_gain(np.diag([-1.0, 2.0]), np.array([[1.0, 0.0]]), [-1.0, -2.0])
    with pytest.raises(ModelError, match=r"alpha must be a positive number"):
        luenberger_poles(0.0, 2)


def test_drake_luenberger_block_starts_at_xhat0_and_runs_the_linear_observer():
    lin = linearize_at_origin(make_system("two_state"))
    L = luenberger_gain(lin.A(), lin.C(), [-4.0, -6.0])
    xhat0 = np.array([2.0, 1.5])
    block = LinearizedLuenbergerObserver(lin, L, initial_state=xhat0)
    assert block.get_y_input_port().get_name() == "y"
    assert block.get_u_input_port().get_name() == "u"
    context = block.CreateDefaultContext()
    y, u = np.array([0.7]), np.array([-1.2])
    block.get_y_input_port().FixValue(context, y)
    block.get_u_input_port().FixValue(context, u)
    out = block.get_estimated_state_output_port()
    np.testing.assert_allclose(out.Eval(context), xhat0, rtol=0, atol=1e-15)
    # The derivative of the (shifted) state is xhat' = A xhat + B u + L (y - C xhat).
    xdot = block.EvalTimeDerivatives(context).CopyToVector()
    expected = lin.A() @ xhat0 + lin.B() @ u + L @ (y - lin.C() @ xhat0)
    np.testing.assert_allclose(xdot, expected, rtol=1e-13, atol=1e-13)
    # Moving the observer's state moves the estimate by the same amount.
    shift = np.array([0.25, -0.5])
    context.SetContinuousState(shift)
    np.testing.assert_allclose(out.Eval(context), xhat0 + shift, rtol=0, atol=1e-15)


def test_lqr_block_gain_and_saturation():
    lin = linearize_at_origin(make_system("two_state"))
    Q, R = 5.0 * np.eye(2), np.array([[1.0]])
    block = SaturatedLqrController(lin, Q, R, 3.0)
    S = scipy.linalg.solve_continuous_are(lin.A(), lin.B(), Q, R)
    K = np.linalg.solve(R, lin.B().T @ S)
    np.testing.assert_allclose(block.K, K, rtol=1e-8)
    context = block.CreateDefaultContext()
    port = block.get_estimated_state_input_port()
    small = np.array([0.01, -0.02])
    port.FixValue(context, small)
    np.testing.assert_allclose(block.get_u_output_port().Eval(context), -K @ small, rtol=1e-8)
    for sign in (1.0, -1.0):
        port.FixValue(context, sign * np.array([5.0, 5.0]))
        assert block.get_u_output_port().Eval(context)[0] == -sign * 3.0


def test_lqr_variant_keeps_learning_w_and_gamma(paper_scenario, baseline_short):
    """W and Gamma depend only on the points (docs/paper_notes.md), so swapping the controller
    leaves them as in the baseline, up to the integrator's error control."""
    r = simulate(_short(paper_scenario, controller="lqr"), progress=False)
    for time in (0.5, 1.5, 3.0):
        np.testing.assert_allclose(r.at("W", time), baseline_short.at("W", time), rtol=0, atol=1e-5)
        np.testing.assert_allclose(
            r.at("Gamma", time), baseline_short.at("Gamma", time), rtol=1e-6, atol=1e-4
        )
    assert not np.allclose(r.u, baseline_short.u, atol=1e-3)


def test_frozen_critic_and_constant_gamma_hold_their_state(paper_scenario):
    r = simulate(_short(paper_scenario, 1.0, controller="frozen_critic"), progress=False)
    np.testing.assert_array_equal(r.W, np.tile(paper_scenario.critic.W0, (r.t.size, 1)))
    r = simulate(_short(paper_scenario, 1.0, gamma="constant"), progress=False)
    np.testing.assert_array_equal(
        r.Gamma, np.tile(np.asarray(paper_scenario.critic.Gamma0), (r.t.size, 1, 1))
    )


def test_linear_luenberger_has_no_injection_gains_and_a_certificate(paper_scenario):
    loop = build_closed_loop(_short(paper_scenario, observer="linear_luenberger"))
    observer = loop.observer
    assert isinstance(observer, ThreeGainObserver)
    np.testing.assert_array_equal(observer.gains.H, np.zeros((2, 1)))
    np.testing.assert_array_equal(observer.gains.K, np.zeros((2, 1)))
    assert np.linalg.norm(observer.gains.L) > 0
    from ofrl_drake.variants import linear_observer_design

    design = linear_observer_design(paper_scenario, make_system("two_state"))
    assert design.is_certified
    assert max(ev for _, ev in design.certificate()) < 0
    np.testing.assert_array_equal(observer.gains.L, design.L)


def test_uniform_points_override_a_grid_scenario(paper_scenario):
    assert paper_scenario.points.kind == "grid"
    loop = build_closed_loop(_short(paper_scenario, points="uniform"))
    p = paper_scenario.points
    np.testing.assert_array_equal(
        loop.bellman.features.points, uniform_points(p.lower, p.upper, p.number, p.seed)
    )
    grid = build_closed_loop(_short(paper_scenario, points="grid"))
    np.testing.assert_array_equal(
        grid.bellman.features.points, grid_points(p.lower, p.upper, p.counts)
    )


def test_grid_choice_needs_counts(paper_scenario):
    uniform = dataclasses.replace(
        paper_scenario,
        points=dataclasses.replace(paper_scenario.points, kind="uniform", counts=[]),
    )
    with pytest.raises(ScenarioError, match=r"variant.points: 'grid' needs points.counts"):
        build_closed_loop(_short(uniform, points="grid"))


def test_around_estimate_points_move_with_xhat(paper_scenario):
    loop = build_closed_loop(_short(paper_scenario, points="around_estimate"))
    bellman = loop.bellman
    assert isinstance(bellman, MovingBellmanExtrapolator)
    context = loop.diagram.CreateDefaultContext()
    sub = bellman.GetMyContextFromRoot(context)
    system, basis = make_system("two_state"), PolynomialBasis(2)
    Q, r = np.asarray(paper_scenario.cost.Q), np.asarray(paper_scenario.cost.R)
    p = paper_scenario.points
    offsets = point_offsets(grid_points(p.lower, p.upper, p.counts), p.lower, p.upper)
    xhat0 = np.asarray(paper_scenario.xhat0)
    expected = extrapolate(
        point_features(system, basis, xhat0[:, None] + offsets, Q),
        np.asarray(paper_scenario.critic.W0),
        r,
        paper_scenario.input_bound,
        paper_scenario.critic.nu,
    )
    np.testing.assert_allclose(
        bellman.get_critic_sum_output_port().Eval(sub), expected.critic_sum, rtol=1e-13
    )


def test_moving_bellman_block_equals_the_fixed_one_at_shifted_points():
    system, basis = make_system("two_state"), PolynomialBasis(2)
    Q, r, W = 5.0 * np.eye(2), np.array([1.0]), np.array([0.4, 0.2, 0.8])
    offsets = grid_points([-1, -1], [1, 1], [4, 5])
    block = MovingBellmanExtrapolator(system, basis, offsets, Q, r, 3.0, 0.7)
    assert block.get_estimated_state_input_port().get_name() == "estimated_state"
    context = block.CreateDefaultContext()
    block.get_weights_input_port().FixValue(context, W)
    block.get_policy_weights_input_port().FixValue(context, W)
    for xhat in (np.zeros(2), np.array([0.6, -1.1])):
        block.get_estimated_state_input_port().FixValue(context, xhat)
        fixed = BellmanExtrapolator(
            point_features(system, basis, offsets + xhat[:, None], Q), r, 3.0, 0.7
        )
        fctx = fixed.CreateDefaultContext()
        fixed.get_weights_input_port().FixValue(fctx, W)
        fixed.get_policy_weights_input_port().FixValue(fctx, W)
        for name in ("critic_sum", "gain_sum", "learning_condition"):
            np.testing.assert_allclose(
                block.GetOutputPort(name).Eval(context),
                fixed.GetOutputPort(name).Eval(fctx),
                rtol=1e-13,
                atol=1e-15,
            )
    with pytest.raises(ModelError, match=r"offsets must have shape \(n, N\) = \(2, N\)"):
        MovingBellmanExtrapolator(system, basis, np.zeros((3, 4)), Q, r, 3.0, 0.7)


def test_the_variant_section_of_a_scenario_file(tmp_path):
    text = PAPER_SCENARIO.read_text()
    path = tmp_path / "variant.yaml"
    path.write_text(text + "variant:\n  observer: true_state\n  controller: lqr\n")
    scenario = load_scenario(path)
    assert scenario.variant == VariantConfig(
        observer="true_state", controller="lqr", points="", gamma="least_squares"
    )
    loop = build_closed_loop(scenario)
    assert isinstance(loop.observer, FullStateObserver)
    assert isinstance(loop.controller, SaturatedLqrController)
    path.write_text(text + "variant:\n  observer: particle_filter\n")
    with pytest.raises(ScenarioError, match=r"variant.observer: unknown choice 'particle_filter'"):
        load_scenario(path)


def test_drake_luenberger_variant_simulates_the_linear_observer(paper_scenario):
    """The logged estimate follows xhat' = A xhat + B u + L (y - C xhat) (scipy check)."""
    scenario = _short(paper_scenario, 1.0, observer="drake_luenberger")
    r = simulate(scenario, progress=False)
    lin = linearize_at_origin(make_system("two_state"))
    A, B, C = lin.A(), lin.B(), lin.C()
    L = luenberger_gain(A, C, luenberger_poles(paper_scenario.observer.alpha, 2))

    def rhs(t, xhat):
        u = np.array([np.interp(t, r.t, r.u[:, 0])])
        y = C @ np.array([np.interp(t, r.t, r.x[:, i]) for i in range(2)])
        return A @ xhat + B @ u + L @ (y - C @ xhat)

    sol = solve_ivp(rhs, (0, 1.0), paper_scenario.xhat0, rtol=1e-10, atol=1e-12, max_step=0.01)
    # Linear interpolation of the 10 ms logs of u and y limits the agreement.
    np.testing.assert_allclose(sol.y[:, -1], r.xhat[-1], rtol=0, atol=2e-3)
