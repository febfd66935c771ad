"""The shipped Drake-plant scenarios: pendulum_upright.yaml and cart_pole.yaml.

Each runs through the command line and meets the numbers docs/own_plant.md states:
by T, |x - x*| and |e| are below 1e-3, |u - u*| stays within the bound, and the
observer is designed with the sound polytopic formulation and decay-certified.
A test scenario of Drake's AcrobotPlant (a Drake System whose symbolic input
matrix names u in vanishing terms) builds, designs and runs briefly.
"""

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest
from pydrake.systems.controllers import LinearQuadraticRegulator
from pydrake.systems.primitives import Linearize

from ofrl_drake import load_scenario
from ofrl_drake.ablation import ablate
from ofrl_drake.ablation_grid import Variant
from ofrl_drake.animation import FRAMES_PER_SECOND, frame_samples
from ofrl_drake.plants import resolve_system

from .conftest import ROOT
from .test_animation import CART_POLE_SDF, set_animation

PENDULUM = ROOT / "diagrams" / "pendulum_upright.yaml"
CART_POLE = ROOT / "diagrams" / "cart_pole.yaml"


def _run(scenario, out):
    proc = subprocess.run(
        [sys.executable, "-m", "ofrl_drake", "run", str(scenario), "--out", str(out), "--quiet"],
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert proc.returncode == 0, proc.stderr
    return proc


def _check_numbers(out, scenario):
    data = np.load(out / "trajectories.npz")
    summary = json.loads((out / "summary.json").read_text())
    x_eq, u_eq = data["x_equilibrium"], data["u_equilibrium"]
    np.testing.assert_array_equal(x_eq, scenario.equilibrium.x)
    assert np.linalg.norm(data["x"][-1] - x_eq) < 1e-3
    assert np.linalg.norm(data["x"][-1] - data["xhat"][-1]) < 1e-3
    assert summary["final_state_norm"] < 1e-3
    assert summary["final_estimation_error_norm"] < 1e-3
    assert np.max(np.abs(data["u"] - u_eq)) <= scenario.input_bound
    design = summary["observer_design"]
    assert design["formulation"] == "polytopic"
    assert design["is_decay_certified"] is True
    assert summary["validity"]["valid"] is True  # x and xhat stayed in the certified box
    return data, summary


def _lqr_weights(system_linearization, Q, R):
    _, P = LinearQuadraticRegulator(system_linearization.A(), system_linearization.B(), Q, R)
    n = P.shape[0]
    return [
        P[i, j] * (1.0 if i == j else 2.0)
        for i, j in itertools.combinations_with_replacement(range(n), 2)
    ]


# ------------------------------------------------------------ the pendulum
def test_pendulum_upright_scenario_starts_as_described():
    scenario = load_scenario(PENDULUM)
    assert scenario.plant.drake_system == "pydrake.examples:PendulumPlant"
    assert scenario.plant.C == [[1.0, 0.0]]  # the angle only
    assert scenario.equilibrium.x == [np.pi, 0.0]
    assert scenario.xhat0[1] == 0.0  # velocity estimate zero


def test_pendulum_w0_is_the_lqr_value_of_the_linearization():
    from pydrake.examples import PendulumPlant

    scenario = load_scenario(PENDULUM)
    plant = PendulumPlant()
    context = plant.CreateDefaultContext()
    context.SetContinuousState(scenario.equilibrium.x)
    plant.get_input_port().FixValue(context, scenario.equilibrium.u)
    W = _lqr_weights(
        Linearize(plant, context), np.asarray(scenario.cost.Q), np.diag(scenario.cost.R)
    )
    np.testing.assert_allclose(scenario.critic.W0, W, rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_pendulum_upright_balances(tmp_path):
    scenario = load_scenario(PENDULUM)
    _run(PENDULUM, tmp_path / "out")
    _check_numbers(tmp_path / "out", scenario)
    assert not (tmp_path / "out" / "animation.html").exists()  # not a multibody model


# ------------------------------------------------------------ the cart-pole
def test_cart_pole_scenario_starts_as_described():
    scenario = load_scenario(CART_POLE)
    system = resolve_system(scenario)
    assert (system.n, system.m, system.q) == (4, 1, 2)
    np.testing.assert_array_equal(system.output_matrix, [[1, 0, 0, 0], [0, 1, 0, 0]])
    np.testing.assert_array_equal(scenario.equilibrium.x, [0.0, np.pi, 0.0, 0.0])
    assert abs(scenario.x0[1]) >= 0.15  # pole tilt
    assert scenario.xhat0[2:] == [0.0, 0.0]  # velocity estimates zero
    assert scenario.observer.formulation == "polytopic"


def test_cart_pole_w0_is_the_lqr_value_of_the_linearization():
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    scenario = load_scenario(CART_POLE)
    plant = MultibodyPlant(0.0)
    Parser(plant).AddModels(url=CART_POLE_SDF)
    plant.Finalize()
    context = plant.CreateDefaultContext()
    plant.SetPositionsAndVelocities(context, scenario.equilibrium.x)
    plant.get_actuation_input_port().FixValue(context, scenario.equilibrium.u)
    linearization = Linearize(
        plant,
        context,
        input_port_index=plant.get_actuation_input_port().get_index(),
        output_port_index=plant.get_state_output_port().get_index(),
    )
    W = _lqr_weights(linearization, np.asarray(scenario.cost.Q), np.diag(scenario.cost.R))
    np.testing.assert_allclose(scenario.critic.W0, W, rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_cart_pole_balances_and_writes_its_animation(tmp_path):
    scenario = load_scenario(CART_POLE)
    out = tmp_path / "out"
    proc = _run(CART_POLE, out)
    assert "|x(T) - x*| = " in proc.stdout
    data, _ = _check_numbers(out, scenario)
    # The run starts as described, in the plant's own coordinates.
    np.testing.assert_allclose(data["x"][0], np.add(scenario.x0, [0, np.pi, 0, 0]), atol=1e-15)

    html = (out / "animation.html").read_text()
    assert html.lstrip().lower().startswith("<!doctype html>")
    animation = set_animation(html)
    tracks = {a["path"].rsplit("/", 1)[-1]: a["clip"] for a in animation["animations"]}
    assert {"Cart", "Pole"} <= set(tracks)
    cart = next(t for t in tracks["Cart"]["tracks"] if t["name"] == ".position")
    # One key frame per recorded sample (the logs, thinned to the frame rate) ...
    fps = tracks["Cart"]["fps"]
    assert fps == FRAMES_PER_SECOND
    times = np.array([k["time"] for k in cart["keys"]]) / fps
    assert times[-1] == pytest.approx(scenario.simulation.duration, abs=1.5 / fps)
    assert len(times) >= scenario.simulation.duration * 40
    # ... at the cart's logged position (the first entry of the translation).
    frames = frame_samples(data["t"])
    assert len(times) == len(frames)
    positions = np.array([k["value"][0] for k in cart["keys"]])
    np.testing.assert_allclose(positions, data["x"][frames, 0], rtol=0, atol=1e-9)
    assert np.ptp(positions) > 0.1  # the cart moved


@pytest.mark.slow
def test_ablate_on_the_cart_pole_scores_against_j_star(tmp_path):
    scenario = load_scenario(CART_POLE)
    rows = ablate(
        scenario,
        [Variant("baseline"), Variant("lqr", {"controller": "lqr"})],
        out=tmp_path / "ablation",
        duration=6.0,
        progress=False,
    )
    assert {r["status"] for r in rows} == {"ok"}
    for row in rows:
        assert np.isfinite(row["optimal_cost"]) and row["optimal_cost"] > 0
        assert row["optimality_ratio"] >= 1.0 - 1e-3


def test_a_model_file_beside_the_scenario_is_found_from_any_folder(tmp_path, monkeypatch):
    import shutil

    from pydrake.common import FindResourceOrThrow

    folder = tmp_path / "experiment"
    folder.mkdir()
    shutil.copy(FindResourceOrThrow("drake/examples/multibody/cart_pole/cart_pole.sdf"), folder)
    text = CART_POLE.read_text().replace(
        "multibody: package://drake/examples/multibody/cart_pole/cart_pole.sdf",
        "multibody: cart_pole.sdf",
    )
    assert "multibody: cart_pole.sdf" in text
    (folder / "scenario.yaml").write_text(text)
    monkeypatch.chdir(tmp_path)
    scenario = load_scenario(folder / "scenario.yaml")
    assert scenario.plant.multibody == str((folder / "cart_pole.sdf").resolve())
    assert resolve_system(scenario).n == 4


# ------------------------------------------------------------ the acrobot
# Drake's AcrobotPlant as a Drake System (not its URDF), upright, both angles
# measured. d xdot / d u of its symbolic dynamics names u in terms that vanish,
# so this exercises the affinity check's false positive. A smoke scenario: 0.2 s
# of a transient that takes about 2 s (a saturated LQR-like policy), with small
# manual critic gains (gains: auto gives Gamma0 ~ 1e9 here and a stiff run).
ACROBOT_SCENARIO = """\
name: acrobot_upright
plant:
  drake_system: pydrake.examples:AcrobotPlant
  C: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]   # both joint angles
equilibrium:
  x: [3.141592653589793, 0.0, 0.0, 0.0]            # both links upright
  u: [0.0]
x0: [0.05, -0.05, 0.0, 0.0]
xhat0: [0.05, -0.05, 0.1, -0.1]                    # velocity estimates off by 0.1
input_bound: 20.0
cost:
  Q: [[10.0, 0, 0, 0], [0, 10.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
  R: [1.0]
critic:
  law: policy_iteration
  gains: manual
  kc: 0.1
  nu: 1.0
  beta: 0.1
  Gamma0: [[1, 0, 0, 0, 0, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0, 0, 0, 0, 0],
           [0, 0, 1, 0, 0, 0, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0, 0, 0, 0, 0],
           [0, 0, 0, 0, 1, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 1, 0, 0, 0, 0],
           [0, 0, 0, 0, 0, 0, 1, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 1, 0, 0],
           [0, 0, 0, 0, 0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0, 0, 0, 0, 1]]
  basis_degrees: [2]
  # The LQR value of the linearization at x* with the Q and R above (recomputed below).
  W0: [16620.6066, 14940.3747, 14480.2474, 7143.1623, 3374.4364, 6512.8055, 3217.0832,
       3154.7304, 3113.0121, 768.3331]
points:
  kind: uniform
  lower: [-0.1, -0.1, -0.2, -0.2]
  upper: [0.1, 0.1, 0.2, 0.2]
  number: 100
  seed: 0
observer:
  alpha: 1.0
  formulation: polytopic
  box:
    lower: [-0.6, -0.6, -3.0, -3.0]
    upper: [0.6, 0.6, 3.0, 3.0]
  jacobian_method: sampled   # certified bounds on this plant: not covered here
  solver: clarabel
simulation:
  duration: 0.2
  integrator: runge_kutta3
  accuracy: 1.0e-4
  max_step: 0.01
  log_period: 0.01
"""


@pytest.fixture
def acrobot_scenario(tmp_path):
    path = tmp_path / "acrobot.yaml"
    path.write_text(ACROBOT_SCENARIO)
    return path


def test_acrobot_drake_system_builds_its_model(acrobot_scenario):
    from pydrake.examples import AcrobotPlant

    scenario = load_scenario(acrobot_scenario)
    system = resolve_system(scenario)
    assert (system.n, system.m, system.q) == (4, 1, 2)
    assert system.name == "AcrobotPlant"
    np.testing.assert_array_equal(system.x_eq, [np.pi, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(system.f(np.zeros(4)), 0.0, atol=1e-13)
    # f + g u in the shifted coordinates is the plant's own xdot at x* + z.
    plant = AcrobotPlant()
    context = plant.CreateDefaultContext()
    rng = np.random.default_rng(4)
    x_eq, u_eq = system.equilibrium
    for _ in range(10):
        z, v = rng.uniform(-1.0, 1.0, 4), rng.uniform(-5.0, 5.0, 1)
        context.SetContinuousState(z + x_eq)
        plant.get_input_port().FixValue(context, v + u_eq)
        xdot = plant.EvalTimeDerivatives(context).CopyToVector()
        np.testing.assert_allclose(system.f(z) + system.g(z) @ v, xdot, rtol=1e-9, atol=1e-12)


def test_acrobot_w0_is_the_lqr_value_of_the_linearization(acrobot_scenario):
    from pydrake.examples import AcrobotPlant

    scenario = load_scenario(acrobot_scenario)
    plant = AcrobotPlant()
    context = plant.CreateDefaultContext()
    context.SetContinuousState(scenario.equilibrium.x)
    plant.get_input_port().FixValue(context, scenario.equilibrium.u)
    W = _lqr_weights(
        Linearize(plant, context), np.asarray(scenario.cost.Q), np.diag(scenario.cost.R)
    )
    np.testing.assert_allclose(scenario.critic.W0, W, rtol=1e-6, atol=1e-4)


@pytest.mark.slow
def test_acrobot_designs_a_sampled_observer_and_runs_from_the_command_line(
    acrobot_scenario, tmp_path
):
    scenario = load_scenario(acrobot_scenario)
    out = tmp_path / "out"
    proc = _run(acrobot_scenario, out)
    assert "|x(T) - x*| = " in proc.stdout
    design = json.loads((out / "observer_design.json").read_text())
    assert design["jacobian_method"] == "sampled" and design["formulation"] == "polytopic"
    assert design["is_decay_certified"] is True
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "ok" and summary["final_time"] == pytest.approx(0.2)
    assert summary["validity"]["valid"] is True  # x and xhat stayed in the sampled box
    data = np.load(out / "trajectories.npz")
    assert np.all(np.isfinite(data["x"])) and np.all(np.isfinite(data["xhat"]))
    np.testing.assert_allclose(data["x"][0], np.add(scenario.x0, data["x_equilibrium"]), atol=1e-15)
    assert np.max(np.abs(data["u"] - data["u_equilibrium"])) <= scenario.input_bound
    # The observer closes the initial velocity error of 0.14 within the 0.2 s.
    assert np.linalg.norm(data["x"][-1] - data["xhat"][-1]) < 0.01
