"""DrakePlant: the source multibody plant as the plant block."""

import numpy as np
import pytest
from pydrake.examples import PendulumPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput

from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.systems import ControlAffinePlant, DrakePlant, SymbolicPlant

CART_POLE = "package://drake/examples/multibody/cart_pole/cart_pole.sdf"
UPRIGHT = [0.0, np.pi, 0.0, 0.0]


def _run(block, u, duration=1.0):
    builder = DiagramBuilder()
    plant = builder.AddSystem(block)
    source = builder.AddSystem(ConstantVectorSource(u))
    builder.Connect(source.get_output_port(), plant.get_u_input_port())
    x_log = LogVectorOutput(plant.get_state_output_port(), builder, 0.05)
    y_log = LogVectorOutput(plant.get_y_output_port(), builder, 0.05)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.get_mutable_integrator().set_target_accuracy(1e-10)
    simulator.AdvanceTo(duration)
    context = simulator.get_context()
    return x_log.FindLog(context).data(), y_log.FindLog(context).data()


def test_drake_plant_ports():
    system = ControlAffineSystem.from_multibody(CART_POLE, C=[[1, 0, 0, 0], [0, 1, 0, 0]])
    block = DrakePlant(system.shifted(UPRIGHT))
    assert [block.get_input_port(i).get_name() for i in range(block.num_input_ports())] == ["u"]
    names = [block.get_output_port(i).get_name() for i in range(block.num_output_ports())]
    assert sorted(names) == ["state", "y"]
    assert block.get_u_input_port().size() == 1
    assert block.get_y_output_port().size() == 2 and block.get_state_output_port().size() == 4
    assert block.num_continuous_states() == 4
    assert block.plant is not system.source.plant  # a clone; the model's plant is untouched


def test_drake_plant_matches_the_python_plant_in_shifted_coordinates():
    system = ControlAffineSystem.from_multibody(CART_POLE, C=[[1, 0, 0, 0], [0, 1, 0, 0]])
    upright = system.shifted(UPRIGHT, [0.0])
    z0 = [0.2, 0.15, 0.0, 0.0]
    x_drake, y_drake = _run(DrakePlant(upright, initial_state=z0), [3.0])
    x_model, y_model = _run(ControlAffinePlant(upright, initial_state=z0), [3.0])
    np.testing.assert_allclose(x_drake[:, 0], z0, atol=0)
    np.testing.assert_allclose(x_drake, x_model, rtol=0, atol=1e-6)
    np.testing.assert_allclose(y_drake, y_model, rtol=0, atol=1e-6)
    # The pole falls away from the upright: the run did move.
    assert abs(x_drake[1, -1]) > 1.0


def test_drake_plant_errors():
    pendulum = ControlAffineSystem.from_drake(PendulumPlant(), C=[[1.0, 0.0]])
    with pytest.raises(ModelError, match=r"has none \(source = DrakeSystemSource\)"):
        DrakePlant(pendulum)
    system = ControlAffineSystem.from_multibody(CART_POLE)
    with pytest.raises(ModelError, match=r"cart_pole: initial_state must have length 4; got 2"):
        DrakePlant(system, initial_state=[0.0, 0.1])
    with pytest.raises(ModelError, match=r"body_mass_scale names 'Pendulum', which is not a body"):
        DrakePlant(system, body_mass_scale={"Pendulum": 2.0})


@pytest.mark.parametrize(
    ("initial_state", "match"),
    [
        ([0.0, np.nan, 0.0, 0.0], r"cart_pole: initial_state must be finite; got \[0\.0, nan,"),
        ([0.0, np.inf, 0.0, 0.0], r"cart_pole: initial_state must be finite; got \[0\.0, inf,"),
        ([[0.0, 0.1, 0.0, 0.0]], r"initial_state must be a non-empty 1-D vector; got shape"),
        (["a", 0.0, 0.0, 0.0], r"cart_pole: initial_state must be numeric; got \['a'"),
    ],
)
def test_drake_plant_refuses_a_non_finite_initial_state(initial_state, match):
    # Before: Drake's SetDefaultPositions aborted on NaN; set_state already refused it.
    system = ControlAffineSystem.from_multibody(CART_POLE).shifted(UPRIGHT)
    with pytest.raises(ModelError, match=match):
        DrakePlant(system, initial_state=initial_state)


class _PlantSource:
    """A model source of another class than MultibodySource that still has a plant."""

    def __init__(self, plant):
        self.multibody_plant = plant


def test_drake_plant_asks_the_model_for_its_plant_and_equilibrium():
    """Any source that gives a plant will do; unshifted, the plant runs at its own origin."""
    # Before: only a MultibodySource was accepted (isinstance), and a ShiftedSystem's x_eq.
    from ofrl_drake.plants import multibody_body_names

    model = ControlAffineSystem.from_multibody(CART_POLE, C=[[1, 0, 0, 0], [0, 1, 0, 0]])
    system = ControlAffineSystem(
        model.f, model.g, model.C, name="cart_pole", source=_PlantSource(model.source.plant)
    )
    assert system.multibody_plant is model.source.plant
    assert multibody_body_names(system) == multibody_body_names(model)
    assert "Pole" in multibody_body_names(system)
    z0 = [0.1, 0.2, 0.0, 0.0]
    for block, x_star in (
        (DrakePlant(system, initial_state=z0), np.zeros(4)),
        (DrakePlant(system.shifted(UPRIGHT), initial_state=z0), np.asarray(UPRIGHT)),
    ):
        context = block.CreateDefaultContext()
        block.initialize_context(context)
        plant_context = block.GetSubsystemContext(block.plant, context)
        np.testing.assert_array_equal(
            block.plant.GetPositionsAndVelocities(plant_context), x_star + z0
        )
        np.testing.assert_allclose(block.get_state_output_port().Eval(context), z0, atol=1e-15)


def _run_initialized(block, u, duration=1.0):
    """As _run, with the block's initialize_context hook applied, as simulate() does."""
    from ofrl_drake.systems.world import initialize_context

    builder = DiagramBuilder()
    plant = builder.AddSystem(block)
    source = builder.AddSystem(ConstantVectorSource(u))
    builder.Connect(source.get_output_port(), plant.get_u_input_port())
    x_log = LogVectorOutput(plant.get_state_output_port(), builder, 0.05)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.get_mutable_integrator().set_target_accuracy(1e-10)
    context = simulator.get_mutable_context()
    initialize_context(plant, plant.GetMyMutableContextFromRoot(context))
    simulator.Initialize()
    simulator.AdvanceTo(duration)
    return x_log.FindLog(simulator.get_context()).data()


def test_drake_plant_starts_from_any_state_and_scales_masses():
    """Velocities come from initialize_context; a mass scale of 1 changes nothing, 1.5 does."""
    system = ControlAffineSystem.from_multibody(CART_POLE, C=[[1, 0, 0, 0], [0, 1, 0, 0]])
    upright = system.shifted(UPRIGHT, [0.0])
    z0 = [0.1, 0.1, -0.3, 0.5]  # moving
    x_model = _run(ControlAffinePlant(upright, initial_state=z0), [3.0])[0]
    x_drake = _run_initialized(DrakePlant(upright, initial_state=z0), [3.0])
    np.testing.assert_allclose(x_drake[:, 0], z0, atol=0)
    np.testing.assert_allclose(x_drake, x_model, rtol=0, atol=1e-6)
    same = _run_initialized(
        DrakePlant(upright, initial_state=z0, body_mass_scale={"Pole": 1.0}), [3.0]
    )
    np.testing.assert_allclose(same, x_drake, rtol=0, atol=1e-12)
    heavy = _run_initialized(
        DrakePlant(upright, initial_state=z0, body_mass_scale={"Pole": 1.5}), [3.0]
    )
    assert np.max(np.abs(heavy - x_drake)) > 1e-2


def test_drake_plant_in_the_closed_loop_of_the_cart_pole_scenario():
    import dataclasses
    from pathlib import Path

    from ofrl_drake import build_closed_loop, load_scenario, simulate
    from ofrl_drake.diagram import drake_plant
    from ofrl_drake.plants import resolve_system
    from ofrl_drake.variants import design_for

    path = Path(__file__).resolve().parents[1] / "diagrams" / "cart_pole.yaml"
    base = load_scenario(path)
    scenario = dataclasses.replace(
        base,
        x0=[0.1, 0.15, 0.0, 0.0],  # at rest: a MultibodyPlant has no default velocities
        simulation=dataclasses.replace(base.simulation, duration=1.0, accuracy=1e-8),
    )
    design = design_for(scenario, resolve_system(scenario))
    drake_loop = build_closed_loop(scenario, design=design, plant=drake_plant)
    model_loop = build_closed_loop(scenario, design=design)
    assert isinstance(drake_loop.plant, DrakePlant)
    assert isinstance(model_loop.plant, SymbolicPlant)  # f and g evaluated by Drake in C++
    a = simulate(scenario, loop=drake_loop, progress=False)
    b = simulate(scenario, loop=model_loop, progress=False)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-5)
    np.testing.assert_allclose(a.u, b.u, rtol=0, atol=1e-4)
    # Logged in z = x - x*: the pole moved back from its 0.15 rad tilt towards the upright.
    assert a.x[0, 1] == pytest.approx(0.15) and abs(a.x[-1, 1]) < 0.1
