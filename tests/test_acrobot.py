"""diagrams/acrobot.yaml: Drake's Acrobot.urdf balanced upright, from the command line.

What issue 25 asks of the acrobot: the observer is decay-certified with
certified (multibody-structure) bounds and ||L|| <= 1e3, verify-observer finds
no counterexample, and the run converges to |x - x*|, |e| < 1e-3.
"""

import json

import numpy as np
import pytest

from ofrl_drake.scenario import load_scenario
from tests.cli_helpers import run_cli

from .conftest import ROOT

ACROBOT = ROOT / "diagrams" / "acrobot.yaml"


def test_w0_is_the_lqr_value_of_the_urdfs_linearization():
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant
    from pydrake.systems.controllers import LinearQuadraticRegulator
    from pydrake.systems.primitives import Linearize

    scenario = load_scenario(ACROBOT)
    plant = MultibodyPlant(0.0)
    Parser(plant).AddModels(url=scenario.plant.multibody)
    plant.Finalize()
    context = plant.CreateDefaultContext()
    plant.SetPositionsAndVelocities(context, scenario.equilibrium.x)
    plant.get_actuation_input_port().FixValue(context, scenario.equilibrium.u)
    lin = Linearize(
        plant,
        context,
        input_port_index=plant.get_actuation_input_port().get_index(),
        output_port_index=plant.get_state_output_port().get_index(),
    )
    _, P = LinearQuadraticRegulator(
        lin.A(), lin.B(), np.asarray(scenario.cost.Q), np.diag(scenario.cost.R)
    )
    W = [P[i, j] * (1 if i == j else 2) for i in range(4) for j in range(i, 4)]
    np.testing.assert_allclose(scenario.critic.W0, W, rtol=1e-6)


@pytest.mark.slow
def test_the_acrobot_is_certified_verified_and_balanced(tmp_path):
    design = tmp_path / "design.json"
    proc = run_cli("design-observer", ACROBOT, "--out", design)
    assert proc.returncode == 0, proc.stderr
    d = json.loads(design.read_text())
    assert d["is_decay_certified"] and d["bounds_are_guaranteed"]
    assert d["jacobian_method"] == "certified"
    assert d["gain_norm"] <= 1e3

    proc = run_cli("verify-observer", ACROBOT, "--samples", 20000)
    assert proc.returncode == 0, proc.stdout + proc.stderr

    out = tmp_path / "run"
    proc = run_cli("run", ACROBOT, "--out", out, "--checkpoints", 0, "--quiet")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "ok"
    assert summary["final_state_norm"] < 1e-3  # |x(T) - x*|
    assert summary["final_estimation_error_norm"] < 1e-3
    assert summary["observer_design"]["is_decay_certified"]
    assert summary["units"] == {"state": ["rad", "rad", "rad/s", "rad/s"], "input": ["N·m"]}
    assert (out / "animation.html").exists()
