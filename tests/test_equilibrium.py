"""Scenarios with an ``equilibrium:``: the plant is shifted, results show its own coordinates."""

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump

from ofrl_drake import load_scenario
from ofrl_drake.errors import ScenarioError
from ofrl_drake.model import ShiftedSystem
from ofrl_drake.plants import resolve_system
from ofrl_drake.plotting import plot_input, plot_state

#: A damped pendulum held at a right angle, x* = (pi/2, 0), by the torque u* = 1.
HELD_PENDULUM = textwrap.dedent(
    """
    import numpy as np
    from ofrl_drake import ControlAffineSystem


    def make_plant():
        def f(x):
            return np.array([x[1], -np.sin(x[0]) - 0.1 * x[1]])

        def g(x):
            return np.array([[0 * x[0]], [1 + 0 * x[0]]])

        return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name="held_pendulum")
    """
)

X_EQ = [float(np.pi / 2), 0.0]


def _data(**edits):
    data = {
        "name": "held_pendulum",
        "system": "held_pendulum:make_plant",
        "equilibrium": {"x": X_EQ, "u": [1.0]},
        "x0": [0.3, 0.0],
        "xhat0": [0.3, 0.5],
        "input_bound": 0.5,
        "cost": {"Q": [[1.0, 0.0], [0.0, 1.0]], "R": [1.0]},
        "critic": {
            "basis_degrees": [2],
            "W0": [1.7, 2.0, 1.7],  # the LQR value x^T P x of the linearization
            "Gamma0": [[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]],
            "kc": 0.01,
            "nu": 0.7,
            "beta": 0.2,
        },
        "points": {"kind": "grid", "lower": [-0.5, -0.5], "upper": [0.5, 0.5], "counts": [5, 5]},
        "observer": {"alpha": 1.0, "box": {"lower": [-1.0, -2.0], "upper": [1.0, 2.0]}},
        "simulation": {
            "duration": 15.0,
            "integrator": "runge_kutta3",
            "accuracy": 1e-4,
            "max_step": 0.1,
            "log_period": 0.05,
        },
    }
    for key, value in edits.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    return data


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "held_pendulum.py").write_text(HELD_PENDULUM)
    return tmp_path


def _write(folder, **edits):
    path = folder / "scenario.yaml"
    path.write_text(yaml_dump(_data(**edits)))
    return path


def test_the_scenario_runs_the_shifted_system(folder):
    system = resolve_system(load_scenario(_write(folder)))
    assert isinstance(system, ShiftedSystem)
    np.testing.assert_allclose(system.x_eq, X_EQ)
    np.testing.assert_allclose(system.u_eq, [1.0])
    np.testing.assert_allclose(system.f(np.zeros(2)), 0.0, atol=1e-15)
    z = np.array([0.2, -0.1])
    # f~(z) = f(z + x*) + g(z + x*) u*
    expected = [z[1], -np.sin(z[0] + X_EQ[0]) - 0.1 * z[1] + 1.0]
    np.testing.assert_allclose(system.f(z), expected, rtol=1e-14)


BAD = [
    (
        {"equilibrium": {"x": [0.5, 0.0], "u": [1.0]}},
        r"equilibrium: held_pendulum: \(x\*, u\*\) = \(\[0.5, 0.0\], \[1.0\]\) is not an "
        r"equilibrium: f\(x\*\) \+ g\(x\*\) u\* = .*row 1",
    ),
    ({"equilibrium": {"x": [0.5], "u": [1.0]}}, r"equilibrium.x: expected 2 entries .*got 1"),
    ({"equilibrium": {"x": X_EQ, "u": [1.0, 0.0]}}, r"equilibrium.u: expected 1 entries"),
    ({"equilibrium": {"x": X_EQ, "v": [1.0]}}, r"equilibrium.v: unknown key in equilibrium"),
    ({"equilibrium": {"u": [1.0]}}, r"equilibrium.x: missing required key"),
    ({"system": None}, r"system: missing; name the plant with system: .* or with plant:"),
    (
        {"plant": {"drake_system": "pydrake.examples:PendulumPlant", "C": [[1.0, 0.0]]}},
        r"plant: the scenario names its plant twice",
    ),
    (
        {"system": None, "plant": {"C": [[1.0, 0.0]]}},
        r"plant: give exactly one of plant.multibody .* and plant.drake_system",
    ),
    ({"system": None, "plant": {"urdf": "a.urdf"}}, r"plant.urdf: unknown key in plant"),
]


@pytest.mark.parametrize(("edits", "match"), BAD)
def test_bad_equilibrium_and_plant_entries_name_the_key(folder, edits, match):
    with pytest.raises(ScenarioError, match=match):
        load_scenario(_write(folder, **edits))


def test_cli_writes_the_plant_s_own_coordinates_and_bounds_u_minus_u_star(folder, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "ofrl_drake", "run", str(_write(folder)), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "|x(T) - x*| = " in proc.stdout
    data = np.load(out / "trajectories.npz")
    np.testing.assert_array_equal(data["x_equilibrium"], X_EQ)
    np.testing.assert_array_equal(data["u_equilibrium"], [1.0])
    np.testing.assert_allclose(data["x"][0], np.add([0.3, 0.0], X_EQ), rtol=0, atol=1e-15)
    np.testing.assert_allclose(data["xhat"][0], np.add([0.3, 0.5], X_EQ), rtol=0, atol=1e-15)
    # The bound holds for u - u*, not for u: u itself stays around u* = 1 > 0.5.
    assert np.all(np.abs(data["u"] - 1.0) <= 0.5)
    assert data["u"].min() > 0.4
    summary = json.loads((out / "summary.json").read_text())
    assert summary["equilibrium"] == {"x": X_EQ, "u": [1.0]}
    final = np.asarray(summary["final_state"])
    assert summary["final_state_norm"] == pytest.approx(np.linalg.norm(final - X_EQ), abs=1e-12)
    assert summary["final_state_norm"] < 1e-4
    assert summary["validity"]["valid"]


def test_figures_label_the_plant_s_coordinates(folder):
    from ofrl_drake import simulate

    scenario = load_scenario(_write(folder, simulation={**_data()["simulation"], "duration": 1.0}))
    result = simulate(scenario, progress=False)
    np.testing.assert_allclose(result.original("x"), result.x + X_EQ)
    np.testing.assert_allclose(result.original("u"), result.u + 1.0)
    fig = plot_state(result, 0)
    ax = fig.axes[0]
    np.testing.assert_allclose(ax.lines[0].get_ydata(), result.x[:, 0] + X_EQ[0])
    assert "plant coordinates" in ax.get_title()  # the y label stays short: it must fit
    assert any("equilibrium" in line.get_label() for line in ax.lines)
    fig = plot_input(result, 0.5)
    bounds = sorted({line.get_ydata()[0] for line in fig.axes[0].lines[1:]})
    assert bounds == pytest.approx([0.5, 1.5])
    assert "plant coordinates" in fig.axes[0].get_title()
    assert any("u^*" in line.get_label() for line in fig.axes[0].lines)


def test_the_optimum_s_cache_key_tells_plants_and_equilibria_apart(folder):
    import dataclasses

    from ofrl_drake.optimal import problem_key
    from ofrl_drake.scenario import EquilibriumConfig, PlantConfig

    scenario = load_scenario(_write(folder))
    x0 = np.asarray(scenario.x0)
    other_point = dataclasses.replace(
        scenario, equilibrium=EquilibriumConfig(x=[-X_EQ[0], 0.0], u=[-1.0])
    )
    pendulum = PlantConfig(drake_system="pydrake.examples:PendulumPlant", C=[[1.0, 0.0]])
    # The pendulum (m = 1 kg, l = 0.5 m) held at the same angle needs u* = m g l sin(x1*).
    held = EquilibriumConfig(x=list(scenario.equilibrium.x), u=[9.81 * 0.5 * np.sin(X_EQ[0])])
    drake_plant = dataclasses.replace(scenario, system="", plant=pendulum, equilibrium=held)
    keys = {problem_key(s, x0) for s in (scenario, other_point, drake_plant)}
    assert len(keys) == 3
    unshifted = dataclasses.replace(scenario, equilibrium=None)
    assert problem_key(unshifted, x0) != problem_key(scenario, x0)


def test_ablate_reports_states_relative_to_the_equilibrium(folder, tmp_path):
    from ofrl_drake.ablation import read_rows
    from ofrl_drake.cli import main

    scenario = _write(folder, simulation={**_data()["simulation"], "duration": 3.0})
    variants = tmp_path / "variants.yaml"
    variants.write_text("baseline: {}\n")
    out = tmp_path / "ablation"
    args = ["ablate", str(scenario), "--out", str(out), "--variants", str(variants)]
    assert main([*args, "--workers", "0"]) == 0
    (row,) = read_rows(out / "ablation.csv")
    assert row["status"] == "ok" and row["optimality_ratio"] >= 1.0 - 1e-3
    assert row["initial_state"] == "[0.3, 0.0]"  # x0 - x*, as in the scenario
    md = (out / "ablation.md").read_text()
    assert f"relative to the equilibrium x* = {X_EQ}" in md


def test_an_equilibrium_at_the_origin_without_u_is_kept_as_given_and_recorded(folder):
    """x* = 0 with no u: the model keeps u_eq = None, and the run still records (0, 0)."""
    # Before: the shifted system replaced u_eq by zeros and had no equilibrium accessor.
    import dataclasses

    from ofrl_drake import simulate

    scenario = load_scenario(_write(folder, equilibrium={"x": [0.0, 0.0]}))
    system = resolve_system(scenario)
    assert system.is_shifted and system.x_eq == [0.0, 0.0] and system.u_eq is None
    x_eq, u_eq = system.equilibrium
    np.testing.assert_array_equal(x_eq, [0.0, 0.0])
    np.testing.assert_array_equal(u_eq, [0.0])
    short = dataclasses.replace(
        scenario, simulation=dataclasses.replace(scenario.simulation, duration=0.2)
    )
    result = simulate(short, progress=False)
    np.testing.assert_array_equal(result.x_equilibrium, [0.0, 0.0])
    np.testing.assert_array_equal(result.u_equilibrium, [0.0])
    assert result.summary()["equilibrium"] == {"x": [0.0, 0.0], "u": [0.0]}
