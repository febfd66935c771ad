"""The C++ symbolic plant, observer and controller against the Python blocks."""

import dataclasses

import numpy as np
import pytest
from pydrake.systems.primitives import Linearize

from ofrl_drake import PolynomialBasis, simulate
from ofrl_drake.diagram import build_closed_loop
from ofrl_drake.errors import ModelError, ScenarioError
from ofrl_drake.examples import make_system
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.observer import ObserverGains, observer_rhs
from ofrl_drake.systems import (
    ControlAffinePlant,
    RunningCost,
    SaturatedController,
    SymbolicController,
    SymbolicObserver,
    SymbolicPlant,
    SymbolicRunningCost,
    ThreeGainObserver,
)
from tests.block_helpers import ports, random_gains

RTOL, ATOL = 1e-13, 1e-13


def _with_blocks(scenario, kind):
    return dataclasses.replace(
        scenario, simulation=dataclasses.replace(scenario.simulation, blocks=kind)
    )


def _is_cpp(block):
    """Whether ``block`` is made of C++ systems: only those convert to ``AutoDiffXd``.

    The Python blocks (``LeafSystem`` subclasses) declare no scalar conversion.
    """
    try:
        block.ToAutoDiffXd()
    except RuntimeError as err:
        assert "does not support scalar conversion" in str(err)
        return False
    return True


def _derivatives(block, state, inputs):
    context = block.CreateDefaultContext()
    for name, value in inputs.items():
        block.GetInputPort(name).FixValue(context, value)
    if state is not None:
        context.SetContinuousState(state)
    return block.EvalTimeDerivatives(context).CopyToVector(), context


@pytest.mark.parametrize("name", ["two_state", "coupled_two_state"])
def test_ports_match_the_python_blocks(name):
    system = make_system(name)
    basis = PolynomialBasis(system.n)
    r, lbar = np.ones(system.m), 2.0
    gains = random_gains(system)
    pairs = [
        (SymbolicPlant(system), ControlAffinePlant(system)),
        (SymbolicObserver(system, gains), ThreeGainObserver(system, gains)),
        (SymbolicController(system, basis, r, lbar), SaturatedController(system, basis, r, lbar)),
        (
            SymbolicRunningCost(np.eye(system.n), r, lbar),
            RunningCost(np.eye(system.n), r, lbar),
        ),
    ]
    for symbolic, python in pairs:
        assert ports(symbolic) == ports(python)


def test_the_state_is_x_itself_zero_by_default():
    """No offset: the context holds x (xhat), which starts at zero (Drake's default)."""
    system = make_system("coupled_two_state")
    x = np.array([0.3, -1.2, 0.5, 2.0])
    plant = SymbolicPlant(system)
    context = plant.CreateDefaultContext()
    np.testing.assert_array_equal(plant.get_state_output_port().Eval(context), np.zeros(4))
    context.SetContinuousState(x)
    np.testing.assert_array_equal(plant.get_state_output_port().Eval(context), x)
    np.testing.assert_allclose(
        plant.get_y_output_port().Eval(context), system.output_matrix @ x, rtol=RTOL
    )
    observer = SymbolicObserver(system, random_gains(system))
    context = observer.CreateDefaultContext()
    np.testing.assert_array_equal(
        observer.get_estimated_state_output_port().Eval(context), np.zeros(4)
    )
    context.SetContinuousState(-x)
    np.testing.assert_array_equal(observer.get_estimated_state_output_port().Eval(context), -x)


def test_set_state_writes_the_state_the_ports_read():
    system = make_system("two_state")
    x0, x = np.array([0.3, -1.2]), np.array([1.1, 0.4])
    for plant in (SymbolicPlant(system), ControlAffinePlant(system, x0)):
        context = plant.CreateDefaultContext()
        plant.set_state(context, x)
        np.testing.assert_array_equal(plant.get_state_output_port().Eval(context), x)
        np.testing.assert_array_equal(context.get_continuous_state_vector().CopyToVector(), x)
    gains = random_gains(system)
    for observer in (
        SymbolicObserver(system, gains),
        ThreeGainObserver(system, gains, initial_state=x0),
    ):
        context = observer.CreateDefaultContext()
        observer.set_estimated_state(context, x)
        np.testing.assert_array_equal(observer.get_estimated_state_output_port().Eval(context), x)
    # The block is named, as in its other messages and the Python blocks' setters.
    with pytest.raises(ModelError, match=r"^SymbolicPlant: x must have length 2; got 3"):
        SymbolicPlant(system).set_state(context, [1.0, 2.0, 3.0])
    with pytest.raises(
        ModelError, match=r"^SymbolicObserver: xhat must be finite; got \[nan, 0.0\]"
    ):
        SymbolicObserver(system, gains).set_estimated_state(context, [np.nan, 0.0])


@pytest.mark.parametrize("name", ["two_state", "coupled_two_state"])
def test_plant_derivative_matches_f_plus_g_u(name):
    system = make_system(name)
    plant = SymbolicPlant(system)
    rng = np.random.default_rng(1)
    for _ in range(5):
        x, u = rng.uniform(-2, 2, system.n), rng.uniform(-3, 3, system.m)
        xdot, _ = _derivatives(plant, x, {"u": u})
        np.testing.assert_allclose(xdot, system.dynamics(x, u), rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("name", ["two_state", "coupled_two_state"])
def test_observer_derivative_matches_the_compiled_kernel(name):
    system = make_system(name)
    gains = random_gains(system, seed=2)
    observer = SymbolicObserver(system, gains)
    rng = np.random.default_rng(3)
    for sign in (1.0, -1.0, 0.0):  # both sides of the input sector, and u = 0
        xhat, y = rng.uniform(-2, 2, system.n), rng.uniform(-2, 2, system.q)
        u = sign * rng.uniform(0.1, 3, system.m)
        xdot, _ = _derivatives(observer, xhat, {"y": y, "u": u})
        expected = observer_rhs(system, gains, xhat, y, u)
        np.testing.assert_allclose(xdot, expected, rtol=1e-12, atol=1e-12)


def test_running_cost_rate_matches_the_compiled_stage_cost():
    Q, r, lbar = np.array([[2.0, 0.5], [0.5, 1.0]]), np.array([0.5, 2.0]), 3.0
    blocks = (SymbolicRunningCost(Q, r, lbar), RunningCost(Q, r, lbar))
    x = np.array([0.7, -1.3])
    # Zero, tiny, moderate, near and at the bound, both signs.
    for u in ([0.0, 1e-9], [1e-4, -0.5], [2.9, -2.999999], [3.0, -3.0]):
        rates = [_derivatives(block, [0.0], {"state": x, "u": u})[0] for block in blocks]
        # Absolute error of the symbolic form: about r lbar^2 1e-16 per input.
        np.testing.assert_allclose(rates[0], rates[1], rtol=1e-14, atol=1e-14)
    # Beyond the bound: the symbolic block clips, the Python one refuses.
    beyond = {"state": x, "u": [3.5, 0.0]}
    clipped = _derivatives(blocks[0], [0.0], beyond)[0]
    at_bound = _derivatives(blocks[0], [0.0], {"state": x, "u": [3.0, 0.0]})[0]
    np.testing.assert_allclose(clipped, at_bound, rtol=1e-14)
    with pytest.raises(ModelError, match=r"exceeds the input bound 3\.0"):
        _derivatives(blocks[1], [0.0], beyond)


@pytest.mark.parametrize("name", ["two_state", "coupled_two_state"])
def test_controller_output_matches_the_compiled_policy(name):
    system = make_system(name)
    basis = PolynomialBasis(system.n, (2, 4))
    r, lbar = np.linspace(0.5, 2.0, system.m), 1.5
    symbolic = SymbolicController(system, basis, r, lbar)
    python = SaturatedController(system, basis, r, lbar)
    rng = np.random.default_rng(4)
    for _ in range(5):
        inputs = {
            "estimated_state": rng.uniform(-2, 2, system.n),
            "policy_weights": rng.normal(size=basis.size),
        }
        outputs = []
        for block in (symbolic, python):
            context = block.CreateDefaultContext()
            for port, value in inputs.items():
                block.GetInputPort(port).FixValue(context, value)
            outputs.append(block.get_u_output_port().Eval(context))
        np.testing.assert_allclose(outputs[0], outputs[1], rtol=1e-12, atol=1e-12)
        assert np.all(np.abs(outputs[0]) <= lbar)


def test_closed_loop_matches_the_python_blocks(paper_scenario, paper_design):
    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=3.0)
    )
    runs = {
        kind: simulate(_with_blocks(short, kind), design=paper_design, progress=False)
        for kind in ("symbolic", "python")
    }
    loop = build_closed_loop(_with_blocks(short, "symbolic"), design=paper_design)
    assert loop.parts.symbolic
    for slot in ("plant", "observer", "controller", "running_cost"):
        assert _is_cpp(loop.blocks[slot]), slot
    assert not _is_cpp(loop.critic)  # Python in every mode (see the module)
    for key in ("x", "xhat", "W", "u", "cost"):
        np.testing.assert_allclose(
            getattr(runs["symbolic"], key), getattr(runs["python"], key), rtol=1e-9, atol=1e-10
        )
    assert runs["symbolic"].design == runs["python"].design


def test_the_controller_state_stays_zero(paper_scenario, paper_design):
    from pydrake.systems.analysis import Simulator

    loop = build_closed_loop(_with_blocks(paper_scenario, "symbolic"), design=paper_design)
    simulator = Simulator(loop.diagram)
    simulator.AdvanceTo(1.0)
    context = loop.controller.GetMyContextFromRoot(simulator.get_context())
    np.testing.assert_array_equal(context.get_continuous_state_vector().CopyToVector(), [0.0])


def test_observer_certificate_reports_the_design(paper_scenario, paper_design):
    system = make_system("two_state")
    gains = ObserverGains.from_design(system, paper_design)
    cert = SymbolicObserver(system, gains, design=paper_design).observer_certificate()
    assert cert.kind == "design"
    assert cert.design == paper_design.to_dict()
    assert SymbolicObserver(system, gains).observer_certificate().kind == "none"
    other = ObserverGains.from_arrays(
        system, 2 * gains.L, gains.H, gains.K, gains.Mf1, gains.Mg1, gains.Mg2
    )
    with pytest.raises(ModelError, match=r"gains\.L differs from design\.L"):
        SymbolicObserver(system, other, design=paper_design)


def test_plant_linearizes_through_autodiff():
    system = make_system("coupled_two_state")
    plant = SymbolicPlant(system)
    context = plant.CreateDefaultContext()
    u0 = np.zeros(system.m)
    plant.get_u_input_port().FixValue(context, u0)
    linear = Linearize(
        plant,
        context,
        input_port_index=plant.get_u_input_port().get_index(),
        output_port_index=plant.get_state_output_port().get_index(),
        equilibrium_check_tolerance=1e-12,
    )
    model = system.symbolic()
    from pydrake.symbolic import Evaluate, Jacobian

    env = dict.fromkeys(model.x, 0.0)
    np.testing.assert_allclose(
        linear.A(), Evaluate(Jacobian(model.f, model.x), env), rtol=RTOL, atol=ATOL
    )
    np.testing.assert_allclose(linear.B(), Evaluate(model.g, env), rtol=RTOL, atol=ATOL)


def _branching_system():
    def f(x):
        if x[0] > 0:  # a branch on the state: cannot be traced symbolically
            return np.array([-x[0], -x[1]])
        return np.array([-2 * x[0], -x[1]])

    with pytest.warns(UserWarning, match="falling back to a Python loop"):
        return ControlAffineSystem(f, lambda x: np.array([[0.0], [1.0]]), [[1.0, 0.0]])


def test_a_system_that_cannot_be_traced():
    system = _branching_system()
    with pytest.raises(ModelError, match=r"f or g branches on the state .*smooth form"):
        system.symbolic()
    with pytest.raises(ModelError, match=r"f or g branches on the state .*smooth form"):
        SymbolicPlant(system)


def test_blocks_setting_picks_the_blocks(paper_scenario, paper_design):
    from ofrl_drake import diagram

    python = build_closed_loop(_with_blocks(paper_scenario, "python"), design=paper_design)
    assert not python.parts.symbolic
    assert not _is_cpp(python.plant) and not _is_cpp(python.controller)
    auto = build_closed_loop(paper_scenario, design=paper_design)  # blocks: auto
    assert auto.parts.symbolic and _is_cpp(auto.plant)

    assert not diagram.symbolic_blocks(paper_scenario, _branching_system())
    with pytest.raises(ScenarioError, match=r"simulation\.blocks: symbolic needs f and g"):
        diagram.symbolic_blocks(_with_blocks(paper_scenario, "symbolic"), _branching_system())


def test_blocks_setting_picks_the_truths_block_too(paper_scenario, paper_design):
    """Before: a truth other than the model ran as a C++ block under blocks: python
    (whenever it traced), and silently as Python under blocks: symbolic when it
    did not."""
    from ofrl_drake.scenario import TruthConfig
    from ofrl_drake.variants import symbolic_blocks

    with_truth = dataclasses.replace(paper_scenario, truth=TruthConfig(system="two_state"))
    python = build_closed_loop(_with_blocks(with_truth, "python"), design=paper_design)
    assert python.parts.truth is not None
    assert not _is_cpp(python.plant) and not _is_cpp(python.controller)
    symbolic = build_closed_loop(_with_blocks(with_truth, "symbolic"), design=paper_design)
    assert _is_cpp(symbolic.plant)
    with pytest.raises(
        ScenarioError, match=r"simulation\.blocks: symbolic needs the truth's f and g"
    ):
        symbolic_blocks(
            _with_blocks(paper_scenario, "symbolic"), _branching_system(), "the truth's "
        )


def test_unknown_blocks_setting_is_refused(paper_scenario):
    from ofrl_drake.scenario import validate_scenario

    with pytest.raises(ScenarioError, match=r"simulation\.blocks: unknown kind 'cpp'"):
        validate_scenario(_with_blocks(paper_scenario, "cpp"))
