"""The closed loop on the paper's scenario and the MIMO example."""

import numpy as np
import pytest
from pydrake.systems.primitives import ConstantVectorSource
from scipy.integrate import solve_ivp

from ofrl_drake import ScenarioError, SimulationResult, SwapError, build_closed_loop, simulate
from ofrl_drake.diagram import INITIAL_VALUES, LOGGED, ClosedLoop, initial_value_setter
from ofrl_drake.slots import SLOTS
from ofrl_drake.systems import CriticWeights, PolicyPassThrough
from ofrl_drake.systems.baselines import FullStateObserver


def _critic_gamma_reference(scenario, t_eval):
    """W and Gamma from (W_c) and (gamma), integrated by scipy, written from the paper.

    The learning laws sum over the extrapolation points only, so W and Gamma do
    not depend on the plant or the observer (docs/paper_notes.md).
    """
    lbar, kc, nu, beta = (
        scenario.input_bound,
        scenario.critic.kc,
        scenario.critic.nu,
        scenario.critic.beta,
    )
    g1 = np.linspace(-1, 1, 10)
    X1, X2 = (a.ravel() for a in np.meshgrid(g1, g1, indexing="ij"))
    N = X1.size
    c = np.cos(2 * X1) + 2
    f1, f2 = -X1 + X2, -X1 - 0.5 * X2 * (1 - c**2)
    # grad sigma for sigma = [x1^2, x1 x2, x2^2]: rows are d sigma_l / d(x1, x2).
    dsig_dx1 = np.array([2 * X1, X2, 0 * X1])
    dsig_dx2 = np.array([0 * X1, X1, 2 * X2])
    Qx = 5 * (X1**2 + X2**2)

    def rhs(_, z):
        W, G = z[:3], z[3:].reshape(3, 3)
        gradV2 = W @ dsig_dx2  # dV/dx2 at each point; g has only a second row
        D = c * gradV2 / (2 * lbar)
        u = -lbar * np.tanh(D)
        omega = dsig_dx1 * f1 + dsig_dx2 * (f2 + c * u)
        U = 2 * lbar * (u * np.arctanh(u / lbar) + lbar / 2 * np.log(1 - u**2 / lbar**2))
        delta = W @ omega + Qx + U
        rho = 1 + nu * np.sum(omega**2, axis=0)
        dW = -(kc / N) * G @ (omega @ (delta / rho))
        dG = beta * G - (kc / N) * G @ ((omega / rho**2) @ omega.T) @ G
        return np.concatenate([dW, dG.ravel()])

    z0 = np.concatenate([scenario.critic.W0, np.ravel(scenario.critic.Gamma0)])
    sol = solve_ivp(
        rhs, (0, t_eval[-1]), z0, method="DOP853", rtol=1e-12, atol=1e-12, t_eval=t_eval
    )
    assert sol.success
    return sol.y[:3].T, sol.y[3:].T.reshape(-1, 3, 3)


def test_paper_scenario_converges(paper_result):
    r = paper_result
    assert r.t[-1] == pytest.approx(30.0, abs=1e-9)
    assert np.linalg.norm(r.x[-1]) < 1e-3
    assert np.linalg.norm(r.x[-1] - r.xhat[-1]) < 1e-3
    assert np.all(np.abs(r.u) <= 3.0)


def test_paper_weights_match_independent_scipy_integration(paper_scenario, paper_result):
    times = np.array([1.0, 5.0, 10.0, 30.0])
    W_ref, Gamma_ref = _critic_gamma_reference(paper_scenario, times)
    for k, t in enumerate(times):
        np.testing.assert_allclose(paper_result.at("W", t), W_ref[k], rtol=0, atol=1e-5)
        np.testing.assert_allclose(paper_result.at("Gamma", t), Gamma_ref[k], rtol=1e-5, atol=1e-4)


def test_paper_learning_condition_and_cost(paper_result):
    r = paper_result
    assert np.min(r.learning_condition) > 0.0
    assert np.all(np.diff(r.cost) >= -1e-12)  # J is an integral of a nonnegative rate
    assert r.cost[0] == pytest.approx(0.0, abs=1e-12)
    G = r.Gamma[-1]
    np.testing.assert_allclose(G, G.T, rtol=0, atol=1e-10)
    assert np.all(np.linalg.eigvalsh(G) > 0)


def test_learning_condition_computed_after_the_run_equals_the_port(
    paper_scenario, paper_design, paper_result
):
    loop = build_closed_loop(paper_scenario, design=paper_design)
    bellman = loop.blocks["bellman"]
    context = bellman.CreateDefaultContext()
    for k in (0, 1, len(paper_result.t) // 2, len(paper_result.t) - 1):
        bellman.get_weights_input_port().FixValue(context, paper_result.W[k])
        bellman.get_policy_weights_input_port().FixValue(context, paper_result.W[k])
        port = bellman.get_learning_condition_output_port().Eval(context)[0]
        assert paper_result.learning_condition[k] == port  # the same kernels, bit for bit


def test_result_shapes_and_summary(paper_result, tmp_path):
    r = paper_result
    T = r.t.size
    assert r.x.shape == r.xhat.shape == (T, 2)
    assert r.W.shape == (T, 3) and r.Gamma.shape == (T, 3, 3)
    assert r.u.shape == (T, 1) and r.learning_condition.shape == r.cost.shape == (T,)
    r.save(tmp_path)
    data = np.load(tmp_path / "trajectories.npz")
    assert set(data.files) == {
        "t",
        "x",
        "xhat",
        "W",
        "W_policy",
        "Gamma",
        "u",
        "learning_condition",
        "cost",
    }
    import json

    summary = json.loads((tmp_path / "summary.json").read_text())
    for key in (
        "final_state",
        "final_estimation_error",
        "final_weights",
        "final_gamma_eigenvalues",
        "min_learning_condition",
        "final_cost",
        "wall_time",
        "integrator",
        "validity",
    ):
        assert key in summary, key
    assert summary["integrator"]["num_derivative_evaluations"] > 0
    assert summary["final_cost"] == pytest.approx(r.cost[-1])


def test_mimo_scenario_regulates_with_a_near_optimal_learned_policy(mimo_scenario):
    """The shipped two-input scenario over its horizon: regulated, and what it learned is good.

    The learned policy, frozen and fed the true state, costs at most 1.02 J* from
    x0 (docs/learning.md measures 1.0021); without a working controller the
    plant diverges in under 2 s.
    """
    from ofrl_drake.learning_curve import PolicyEvaluator
    from ofrl_drake.optimal import optimal_control

    r = simulate(mimo_scenario, progress=False)
    assert isinstance(r, SimulationResult)
    T = r.t.size
    assert (
        r.x.shape == (T, 4)
        and r.u.shape == (T, 2)
        and r.W.shape == (T, 10)
        and r.Gamma.shape == (T, 10, 10)
    )
    assert r.status == "ok" and r.regulated is True
    assert r.t[-1] == pytest.approx(mimo_scenario.simulation.duration)
    assert np.all(np.abs(r.u) <= mimo_scenario.input_bound + 1e-12)
    assert np.linalg.norm(r.x[-1]) < 1e-6 and np.linalg.norm(r.e[-1]) < 1e-6
    J_star = optimal_control(mimo_scenario)
    assert J_star.converged, J_star.status
    learned = PolicyEvaluator(build_closed_loop(mimo_scenario))(r.W_policy[-1])
    assert learned.status == "ok"
    assert learned.cost <= 1.02 * J_star.cost, learned.cost / J_star.cost


def test_build_returns_named_handles(paper_scenario, paper_design):
    loop = build_closed_loop(paper_scenario, design=paper_design)
    for slot in SLOTS:  # one typed property per slot, no attribute lookup by name
        assert isinstance(vars(ClosedLoop)[slot], property), slot
        assert getattr(loop, slot) is loop.blocks[slot] and loop.blocks[slot].get_name() == slot
    with pytest.raises(AttributeError, match=r"'ClosedLoop' object has no attribute 'nonsense'"):
        loop.nonsense  # noqa: B018
    # The learning condition is computed from the logged W after the run.
    assert set(loop.loggers) == set(LOGGED) - {"learning_condition"}
    assert "observer" in loop.diagram.GetGraphvizString()


@pytest.mark.parametrize("blocks", ["symbolic", "python"])
def test_every_initial_value_has_the_setter_its_table_names(paper_scenario, paper_design, blocks):
    import dataclasses

    scenario = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(paper_scenario.simulation, blocks=blocks),
        critic=dataclasses.replace(paper_scenario.critic, law="policy_iteration"),  # a gate
    )
    loop = build_closed_loop(scenario, design=paper_design)
    for slot, (name, _) in INITIAL_VALUES.items():
        setter = initial_value_setter(slot, loop.blocks[slot])
        assert setter is not None and setter.__name__ == name, (slot, type(loop.blocks[slot]))
    # No initial value for the running cost; none settable for stateless blocks.
    assert initial_value_setter("running_cost", loop.running_cost) is None
    assert initial_value_setter("observer", FullStateObserver(2)) is None
    assert initial_value_setter("policy", PolicyPassThrough(3)) is None


def test_swap_frozen_critic(paper_scenario, paper_design):
    import dataclasses

    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=2.0)
    )
    frozen = CriticWeights(paper_scenario.critic.W0, kc=0.0)
    r = simulate(short, design=paper_design, critic=frozen, progress=False)
    np.testing.assert_allclose(
        r.W, np.tile(paper_scenario.critic.W0, (r.t.size, 1)), rtol=0, atol=0
    )


def test_swap_with_a_factory(paper_scenario, paper_design):
    loop = build_closed_loop(
        paper_scenario,
        design=paper_design,
        critic=lambda parts: CriticWeights(np.zeros(parts.basis.size), 0.01),
    )
    context = loop.diagram.CreateDefaultContext()
    np.testing.assert_array_equal(
        loop.critic.get_weights_output_port().Eval(loop.critic.GetMyContextFromRoot(context)),
        np.zeros(3),
    )


def test_bad_swaps_raise(paper_scenario, paper_design):
    with pytest.raises(SwapError, match=r"nonsense: unknown slot"):
        build_closed_loop(paper_scenario, design=paper_design, nonsense=CriticWeights([0.0], 0.1))
    with pytest.raises(
        SwapError,
        match=r"critic: input port 'critic_sum' has size 2, but bellman's output "
        r"'critic_sum' has size 3",
    ):
        build_closed_loop(
            paper_scenario, design=paper_design, critic=CriticWeights([0.0, 0.0], 0.1)
        )
    with pytest.raises(SwapError, match=r"must be a Drake System or a factory"):
        build_closed_loop(paper_scenario, design=paper_design, critic=42)


def _sampled(scenario):
    """``scenario`` with a sampled measurement and a digital (sample-and-hold) controller."""
    import dataclasses

    from ofrl_drake.scenario import ActuationConfig, MeasurementConfig

    return dataclasses.replace(
        scenario,
        measurement=MeasurementConfig(period=0.01),
        actuation=ActuationConfig(period=0.01),
    )


def _unactuated_plant():
    """A plant with the outputs ``y`` and ``state`` but no input ``u``."""
    from pydrake.systems.framework import LeafSystem

    plant = LeafSystem()
    plant.DeclareVectorOutputPort("y", 1, lambda context, out: out.SetFromVector([0.0]))
    plant.DeclareVectorOutputPort("state", 2, lambda context, out: out.SetFromVector([0.0, 0.0]))
    return plant


@pytest.mark.parametrize(
    ("slot", "make", "message"),
    [
        (
            "plant",
            lambda: ConstantVectorSource(np.zeros(2)),
            r"^plant: the block must have an output port named 'y'; ConstantVectorSource "
            r"has none \(its output ports: \['y0'\]\)",
        ),
        (
            "plant",
            _unactuated_plant,
            r"^plant: the block must have an input port named 'u', which the scenario's "
            r"measurement and actuation feed; LeafSystem has none \(its input ports: \[\]\)",
        ),
        (
            "controller",
            lambda: ConstantVectorSource(np.zeros(1)),
            r"^controller: the block must have an output port named 'u'; ConstantVectorSource "
            r"has none \(its output ports: \['y0'\]\)",
        ),
        (
            "controller",
            lambda: CriticWeights([0.0, 0.0, 0.0], 0.1),
            r"^controller: the block must have an output port named 'u'; CriticWeights has "
            r"none \(its output ports: \['weights'\]\)",
        ),
    ],
)
def test_swaps_into_a_sampled_loop_are_checked_before_they_are_wrapped(
    paper_scenario, paper_design, slot, make, message
):
    """A sampled measurement wraps the plant, a digital controller the controller
    (:mod:`ofrl_drake.systems.world`): a missing port is a SwapError, not Drake's RuntimeError."""
    block = make()
    with pytest.raises(SwapError, match=message):
        build_closed_loop(_sampled(paper_scenario), design=paper_design, **{slot: block})
    assert block.GetSystemPathname() == "::" + block.GetSystemName()  # not built into anything


def test_a_factory_must_take_the_parts_and_return_a_system(paper_scenario, paper_design):
    with pytest.raises(
        SwapError,
        match=r"^critic: the factory .*<lambda> returned int, not a Drake System; a factory "
        r"f\(parts\) must return the block",
    ):
        build_closed_loop(paper_scenario, design=paper_design, critic=lambda parts: 3)
    with pytest.raises(
        SwapError,
        match=r"^critic: the factory .*<lambda> cannot be called with one argument; a factory "
        r"is f\(parts\) -> System",
    ):
        build_closed_loop(paper_scenario, design=paper_design, critic=lambda: None)


@pytest.mark.parametrize(
    ("scenario", "got"),
    [
        (
            "x.yaml",
            r"got the path 'x\.yaml'\. Load it first with "
            r"ofrl_drake\.load_scenario\('x\.yaml'\)",
        ),
        (None, r"got NoneType\. Load one with ofrl_drake\.load_scenario\(path\)"),
        ({"name": "paper"}, r"got dict\. Load one with ofrl_drake\.load_scenario\(path\)"),
    ],
)
def test_build_refuses_what_is_not_a_scenario(scenario, got):
    with pytest.raises(
        ScenarioError, match=r"^build_closed_loop: scenario must be a Scenario; " + got
    ):
        build_closed_loop(scenario, observer="kalman")  # a choice by name replaces a field


def test_build_refuses_a_design_that_is_not_one_or_is_certified_for_smaller_inputs(
    paper_scenario,
):
    from ofrl_drake.design import DesignError, design_observer
    from ofrl_drake.examples import make_system

    with pytest.raises(DesignError, match=r"^design: expected an ObserverDesign; got str\."):
        build_closed_loop(paper_scenario, design="x")
    small = design_observer(make_system("two_state"), ([-1.0, -1.0], [1.0, 1.0]), 0.1, 0.1)
    # The controller saturates at the scenario's bound, 3: |u| would reach past 0.1.
    with pytest.raises(
        DesignError,
        match=r"^design: certified for \|u_k\| <= input_bound = 0\.1, but the scenario's "
        r"controller saturates at input_bound = 3, .*design for an input bound of at least 3",
    ):
        simulate(paper_scenario, design=small, progress=False)


@pytest.mark.parametrize(
    ("period", "message"),
    [
        (-1, r"^log_period must be > 0; got -1\.0\. Or omit log_period"),
        (0, r"^log_period must be > 0; got 0\.0\."),
        (float("nan"), r"^log_period must be finite; got nan\."),
        (float("inf"), r"^log_period must be finite; got inf\."),
        ("0.1", r"^log_period must be a number; got '0\.1'\."),
        (
            100.0,
            r"^log_period: 100\.0 is refused, as in the scenario: simulation\.log_period: "
            r"100\.0 s is longer than the horizon simulation\.duration = 30\.0 s",
        ),
    ],
)
def test_log_period_is_checked_as_the_scenario_s(paper_scenario, paper_design, period, message):
    # Before: Drake aborted the interpreter on -1 and nan, and logged one sample for inf.
    with pytest.raises(ScenarioError, match=message):
        build_closed_loop(paper_scenario, design=paper_design, log_period=period)


def test_log_period_may_be_a_numpy_number(paper_scenario, paper_design):
    import dataclasses

    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=2.0)
    )
    loop = build_closed_loop(short, design=paper_design, log_period=np.float32(0.5))
    r = simulate(short, loop=loop, progress=False)
    np.testing.assert_allclose(r.t, [0.0, 0.5, 1.0, 1.5, 2.0], atol=1e-12)


def test_sound_scenario_is_decay_certified_and_stays_in_the_box():
    from ofrl_drake import load_scenario

    from .conftest import ROOT

    scenario = load_scenario(ROOT / "diagrams" / "two_state_sound.yaml")
    r = simulate(scenario, progress=False)
    assert r.design["formulation"] == "polytopic"
    assert r.design["is_decay_certified"]
    assert all(c["max_eigenvalue"] < 0 for c in r.design["decay_certificate"])
    assert r.validity.valid and r.validity.fraction_outside == 0.0
    assert np.linalg.norm(r.x[-1]) < 1e-3 and np.linalg.norm(r.e[-1]) < 1e-3
    # The certified rate holds along the run: e^T P e decays at least like exp(-2 alpha t).
    P = np.asarray(r.design["P"])
    V = np.einsum("ti,ij,tj->t", r.e, P, r.e)
    alpha = scenario.observer.alpha
    assert np.all(V <= V[0] * np.exp(-2 * alpha * r.t) * (1 + 1e-6) + 1e-14)


def test_paper_design_satisfies_lmi2_but_not_the_decay_certificate(paper_design):
    assert paper_design.formulation == "paper"
    assert paper_design.is_certified
    assert not paper_design.is_decay_certified


def test_build_refuses_a_design_made_for_another_measurement(paper_scenario):
    # Before: accepted; the run diverged while summary.json reported the design's
    # certificate (for C = [1 0]) as if it applied to the loop measuring x2.
    from ofrl_drake.design import DesignError, design_observer
    from ofrl_drake.examples import make_system
    from ofrl_drake.model import ControlAffineSystem

    paper = make_system("two_state")
    other = ControlAffineSystem(paper.f, paper.g, C=[[1.0, 0.0]], name="two_state_x1")
    design = design_observer(other, ([-2.0, -2.0], [2.0, 2.0]), 3.0, 0.5)
    with pytest.raises(
        DesignError,
        match=r"^design: made for a plant with n = 2 states, m = 1 inputs and C = "
        r"\[\[1\.0, 0\.0\]\], but the scenario's model 'two_state' has n = 2, m = 1 and "
        r"C = \[\[0\.0, 1\.0\]\], so its certificate would not apply",
    ):
        build_closed_loop(paper_scenario, design=design)
