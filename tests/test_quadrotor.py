"""diagrams/quadrotor.yaml: Drake's QuadrotorPlant hovering, from the command line.

What issue 25 asks of the quadrotor: ``drake_system:
pydrake.examples:QuadrotorPlant`` (n = 12, 4 inputs, positions and attitude
measured) is accepted, gets a sound certificate with certified bounds on a box
around hover within 5 minutes, and its closed loop converges. Layers: the
scenario as written (its W0 is the LQR value, no solver); the certified
Jacobian bounds on a smaller box hold every sample (quick); the CLI design is
decay-certified with certified bounds and not falsified (slow, about 100 s;
tests/test_verification.py runs verify_observer on it too), and the run
converges (slow, about 2 minutes).
"""

import json

import numpy as np
import pytest

from ofrl_drake.jacobian_bounds import jacobian_bounds
from ofrl_drake.plants import resolve_system
from ofrl_drake.scenario import load_scenario
from tests.cli_helpers import run_cli

from .conftest import ROOT

QUADROTOR = ROOT / "diagrams" / "quadrotor.yaml"


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(QUADROTOR)


def test_the_quadrotor_plant_is_accepted_hovering(scenario):
    from pydrake.examples import QuadrotorPlant

    system = resolve_system(scenario)
    assert (system.n, system.m, system.output_matrix.shape) == (12, 4, (6, 12))
    np.testing.assert_array_equal(system.output_matrix, np.eye(12)[:6])  # positions, attitude
    plant = QuadrotorPlant()
    np.testing.assert_allclose(scenario.equilibrium.u, [plant.m() * plant.g() / 4] * 4)
    # x* = 0, u* = m g / 4 per rotor is an equilibrium: hover.
    np.testing.assert_allclose(system.f(np.zeros(12)), 0.0, atol=1e-12)


def test_w0_is_the_lqr_value_of_the_linearization(scenario):
    from pydrake.examples import QuadrotorPlant
    from pydrake.systems.controllers import LinearQuadraticRegulator
    from pydrake.systems.primitives import Linearize

    plant = QuadrotorPlant()
    context = plant.CreateDefaultContext()
    context.SetContinuousState(scenario.equilibrium.x)
    u_port = resolve_system(scenario).source.input_port  # the port the model took as u
    plant.GetInputPort(u_port).FixValue(context, scenario.equilibrium.u)
    lin = Linearize(plant, context)
    _, P = LinearQuadraticRegulator(
        lin.A(), lin.B(), np.asarray(scenario.cost.Q), np.diag(scenario.cost.R)
    )
    W = [P[i, j] * (1 if i == j else 2) for i in range(12) for j in range(i, 12)]
    np.testing.assert_allclose(scenario.critic.W0, W, rtol=1e-4, atol=1e-4)


def test_certified_bounds_on_a_small_box_hold_every_sample(scenario):
    # The shipped box takes about 30 s; a quarter of its angles and rates, seconds.
    system = resolve_system(scenario)
    half = np.array([0.5, 0.5, 0.5, 0.025, 0.025, 0.025, 1.0, 1.0, 1.0, 0.125, 0.125, 0.125])
    box = (-half, half)
    certified = jacobian_bounds(system, box, "certified", tol=0.02, rtol=0.1)
    sampled = jacobian_bounds(system, box, "sampled", n_random=20_000, seed=7)
    assert certified.excess.converged
    assert certified.contains(sampled)
    # The attitude rows do not depend on the yaw, though their expressions name it.
    assert np.abs(certified.Mf1[9:, 5]).max() <= 0.02 + 1e-12
    assert np.abs(certified.Mf2[9:, 5]).max() <= 0.02 + 1e-12


@pytest.mark.slow
def test_the_quadrotor_is_certified_from_the_cli(tmp_path):
    # About 100 s (measured 96 s: bounds 29 s, LMI 15 s, falsifier 47 s). What
    # verify-observer checks, test_verification.py checks on every shipped
    # scenario, this one included (verify_observer on design_for's design).
    design = tmp_path / "design.json"
    # No --max-wall: a wall-time budget makes the verdict depend on the machine's
    # speed (measured 131 s on a 2-core VM: a slower CI can run past 300 s)
    # and would cut the bounds' refinement short. The subprocess timeout, over 20
    # times the measured time, only turns a hang into a failure.
    proc = run_cli("design-observer", QUADROTOR, "--out", design, timeout=3000)
    assert proc.returncode == 0, proc.stderr
    assert "decay-certified and not falsified" in proc.stdout
    d = json.loads(design.read_text())
    assert d["formulation"] == "structured_row" and d["is_decay_certified"] is True
    assert d["jacobian_method"] == "certified" and d["bounds_are_guaranteed"] is True
    assert len(d["tau"]) == 81  # one LMI per input vertex, 3^4
    assert d["verification"]["falsified"] is False


@pytest.mark.slow
def test_the_quadrotor_converges_to_hover(tmp_path):
    # About 2 minutes: the design again, the falsifier, 10 s of closed loop.
    out = tmp_path / "run"
    proc = run_cli("run", QUADROTOR, "--out", out, "--checkpoints", 0, "--quiet")
    assert proc.returncode == 0, proc.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "ok" and s["regulated"]
    assert s["final_state_norm"] < 1e-3  # |x(T) - x*|
    assert s["final_estimation_error_norm"] < 1e-3
    assert s["validity"]["valid"]  # x and xhat stayed in the certified box
