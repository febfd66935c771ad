"""Real-world conditions: a wrong model, noisy sampled sensors, a held input, Monte Carlo."""

import dataclasses
import json
import math

import numpy as np
import pytest
from matplotlib.collections import PolyCollection
from pydrake.common import RandomGenerator
from pydrake.common.yaml import yaml_dump, yaml_load
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput
from scipy import stats

from ofrl_drake import PolynomialBasis, build_closed_loop, load_scenario, simulate
from ofrl_drake.errors import ModelError
from ofrl_drake.examples import make_system
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.monte_carlo import (
    MonteCarloError,
    envelope_samples,
    montecarlo,
    montecarlo_table,
    read_montecarlo_rows,
    run_seeds,
    write_montecarlo_report,
)
from ofrl_drake.scenario import MeasurementConfig, TruthConfig
from ofrl_drake.systems import ControlAffinePlant, SaturatedController
from ofrl_drake.systems.world import MeasuredPlant, SampledController
from ofrl_drake.variants import kalman
from tests.cli_helpers import run_cli

from .conftest import ROOT

REAL = ROOT / "diagrams" / "cart_pole_real_world.yaml"
CART_POLE = ROOT / "diagrams" / "cart_pole.yaml"


@pytest.fixture(scope="module")
def real():
    return load_scenario(REAL)


@pytest.fixture(scope="module")
def real_result(real):
    return simulate(real, progress=False)


# ---------------------------------------------------------------- done when
def test_the_real_world_cart_pole_balances(real, real_result):
    """Heavier pole, lighter cart, 2 mm / 2 mrad of noise at 100 Hz, a 10 ms hold."""
    assert real.truth.body_mass_scale == {"Pole": 1.3, "Cart": 0.8}
    assert real.measurement.noise_std == [0.002, 0.002] and real.measurement.period == 0.01
    assert real.actuation.period == 0.01
    r = real_result
    assert r.status == "ok"
    cart, angle = r.x[-1, 0], r.x[-1, 1]  # relative to upright
    assert abs(angle) < 0.02 and abs(cart) < 0.1
    assert r.provenance["seeds"] == {"measurement": 0}
    error = r.summary()["model_error"]
    assert "does not cover" in error["note"]
    assert max(error["max_f_error"]) > 0.1  # the truth is not the model
    assert max(abs(v) for v in error["equilibrium_residual"]) < 1e-12  # upright still is one


def test_a_seed_reproduces_its_run_and_another_seed_changes_it(real, real_result):
    again = simulate(real, progress=False)
    for key in ("x", "xhat", "u", "W", "cost"):
        np.testing.assert_array_equal(getattr(again, key), getattr(real_result, key))
    other = dataclasses.replace(real, measurement=dataclasses.replace(real.measurement, seed=1))
    changed = simulate(other, progress=False)
    assert not np.array_equal(changed.x, real_result.x)
    assert changed.provenance["seeds"] == {"measurement": 1}


def test_a_montecarlo_of_six_runs_succeeds_in_five(real, tmp_path):
    rows = montecarlo(real, 6, seed=0, out=tmp_path, optimal_cost=35.6263)
    assert [r["seed"] for r in rows] == [str(k) for k in range(6)]
    good = sum(r["status"] == "ok" and r["regulated"] == "true" for r in rows)
    assert good >= 5, rows
    write_montecarlo_report(tmp_path, rows, real.name)
    assert "| 6 |" in (tmp_path / "montecarlo.md").read_text()
    assert "identical" not in (tmp_path / "montecarlo.md").read_text()
    assert (tmp_path / "figures" / "envelope.png").stat().st_size > 10_000
    with np.load(tmp_path / "runs" / "seed_0.npz") as run:  # the envelope's units
        assert run["state_units"].tolist() == ["m", "rad", "m/s", "rad/s"]


# ----------------------------------------------------------------- sensors
def _measured_origin(noise_std, period, seed, duration=20.0):
    """The paper's plant held at its equilibrium x = 0: the measured y is the noise alone."""
    system = make_system("two_state")
    builder = DiagramBuilder()
    plant = builder.AddSystem(
        MeasuredPlant(ControlAffinePlant(system), noise_std=noise_std, period=period)
    )
    zero = builder.AddSystem(ConstantVectorSource([0.0]))
    builder.Connect(zero.get_output_port(), plant.GetInputPort("u"))
    log = LogVectorOutput(plant.GetOutputPort("y"), builder, period)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.SetRandomContext(context, RandomGenerator(seed))
    plant.start_holds(plant.GetMyMutableContextFromRoot(context))
    simulator.AdvanceTo(duration)
    data = log.FindLog(simulator.get_context())
    return data.sample_times(), data.data()[0]


def test_noise_statistics_match_noise_std():
    std = 0.05
    _, y = _measured_origin([std], 0.01, seed=3)
    samples = np.unique(y)  # each held value once: the noise draws
    N = samples.size
    assert N > 1500
    # Mean: within 4 standard errors. Variance: inside the chi-square 99.99% interval.
    assert abs(samples.mean()) < 4 * std / np.sqrt(N)
    low, high = stats.chi2.ppf([5e-5, 1 - 5e-5], N - 1) / (N - 1)
    assert low * std**2 < samples.var(ddof=1) < high * std**2


def _interval(times, period):
    """The hold interval of each logged time: ``(k h, (k + 1) h]``, and 0 for ``t = 0``.

    A log at ``t = k h`` is published before the hold's update at that time, so it
    still shows the value of the interval that ends there.
    """
    return np.maximum(np.ceil(times / period - 1e-9).astype(int) - 1, 0)


def test_y_is_piecewise_constant_on_the_sampling_grid():
    """Logged four times per period: constant inside each interval, C x at its start."""
    system = make_system("two_state")
    builder = DiagramBuilder()
    plant = builder.AddSystem(
        MeasuredPlant(ControlAffinePlant(system, initial_state=[0.5, -0.5]), period=0.01)
    )
    zero = builder.AddSystem(ConstantVectorSource([0.0]))
    builder.Connect(zero.get_output_port(), plant.GetInputPort("u"))
    y_log = LogVectorOutput(plant.GetOutputPort("y"), builder, 0.0025)
    x_log = LogVectorOutput(plant.GetOutputPort("state"), builder, 0.0025)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant.start_holds(plant.GetMyMutableContextFromRoot(context))
    simulator.AdvanceTo(0.5)
    ctx = simulator.get_context()
    times = y_log.FindLog(ctx).sample_times()
    held = y_log.FindLog(ctx).data()[0]
    state = x_log.FindLog(ctx).data()
    k = _interval(times, 0.01)
    for interval in np.unique(k):
        inside = held[k == interval]
        assert np.all(inside == inside[0]), interval
        # the held value is C x at the interval's start, t = k period
        start = np.argmin(np.abs(times - 0.01 * interval))
        assert inside[0] == pytest.approx(state[1, start], abs=1e-12)
    assert np.ptp(state[1]) > 0.1  # while the true output moves


def test_u_is_held_by_the_sampled_controller(real):
    short = dataclasses.replace(
        real,
        simulation=dataclasses.replace(real.simulation, duration=0.3, log_period=0.0025),
    )
    r = simulate(short, progress=False)
    k = _interval(r.t, 0.01)
    for interval in np.unique(k):
        inside = r.u[k == interval, 0]
        assert np.all(inside == inside[0]), interval
    assert np.ptp(r.u) > 1.0  # the command does change between samples


# ------------------------------------------------------------------ truths
def test_a_truth_with_unit_mass_scale_runs_the_model(tmp_path):
    """``truth: {body_mass_scale: {Pole: 1.0}}`` runs Drake's MultibodyPlant: same loop."""
    base = load_scenario(CART_POLE)
    base = dataclasses.replace(
        base, simulation=dataclasses.replace(base.simulation, duration=5.0, accuracy=1e-7)
    )
    truth = dataclasses.replace(base, truth=TruthConfig(body_mass_scale={"Pole": 1.0}))
    loop = build_closed_loop(truth)
    # The plant block runs the model's own MultibodyPlant (a clone), the pole's mass scaled.
    model_plant = loop.parts.truth.multibody_plant
    assert isinstance(loop.plant.plant, MultibodyPlant) and loop.plant.plant is not model_plant
    assert loop.plant.plant.num_positions() == model_plant.num_positions()
    assert loop.plant.body_mass_scale == {"Pole": 1.0}
    a, b = simulate(base, progress=False), simulate(truth, loop=loop, progress=False)
    # Drake's plant against the model's f and g: the same loop to the integrator's accuracy.
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-5)
    # A scale of 1.0 against no scale on the same multibody truth: the same run to round-off.
    unscaled = simulate(dataclasses.replace(base, truth=TruthConfig()), progress=False)
    np.testing.assert_allclose(b.x, unscaled.x, rtol=0, atol=1e-12)
    error = b.summary()["model_error"]
    assert max(error["max_f_error"]) < 1e-10 and np.max(error["max_g_error"]) < 1e-10


class _PlantSource:
    """A model source of another class than MultibodySource that still has a plant."""

    def __init__(self, plant):
        self.multibody_plant = plant


def _multibody_truth(loop):
    # MeasuredPlant around DrakePlant around the MultibodyPlant, by Drake's names.
    plant = loop.plant.GetSubsystemByName("plant").GetSubsystemByName("multibody_plant")
    assert isinstance(plant, MultibodyPlant)
    return plant


def test_a_mass_set_in_parameters_is_the_mass_simulated(real):
    """Before: a body named in body_mass_scale got the scaled mass whatever the
    parameters= context held (a pole of 5 kg ran as 1.3 kg, bit for bit); and a
    context prepared by set_initial_values, as by hand for a Simulator, ran the
    model's masses."""
    short = dataclasses.replace(real, simulation=dataclasses.replace(real.simulation, duration=0.3))
    loop = build_closed_loop(short)
    plant = _multibody_truth(loop)
    pole = plant.GetBodyByName("Pole")
    context = loop.diagram.CreateDefaultContext()
    assert pole.get_mass(plant.GetMyContextFromRoot(context)) == pole.default_mass() == 1.0
    loop.set_initial_values(context, short)  # a Simulator by hand: the truth's masses
    assert pole.get_mass(plant.GetMyContextFromRoot(context)) == pytest.approx(1.3, rel=1e-15)
    loop.set_initial_values(context, short)  # not scaled twice
    assert pole.get_mass(plant.GetMyContextFromRoot(context)) == pytest.approx(1.3, rel=1e-15)

    parameters = loop.diagram.CreateDefaultContext()
    pole.SetMass(plant.GetMyMutableContextFromRoot(parameters), 5.0)
    heavy = simulate(short, loop=loop, parameters=parameters, progress=False)
    scaled = dataclasses.replace(
        short, truth=dataclasses.replace(short.truth, body_mass_scale={"Pole": 5.0, "Cart": 0.8})
    )
    expected = simulate(scaled, progress=False)
    np.testing.assert_array_equal(heavy.x, expected.x)
    # An untouched parameters context keeps the scenario's truth.
    plain = simulate(
        short, loop=loop, parameters=loop.diagram.CreateDefaultContext(), progress=False
    )
    np.testing.assert_array_equal(plain.x, simulate(short, progress=False).x)
    assert not np.array_equal(plain.x, heavy.x)


def test_the_model_error_of_a_mass_scaled_truth_asks_the_truth_for_its_plant():
    # Before: only a MultibodySource counted, so this truth's masses were silently unscaled.
    from ofrl_drake.model_error import model_mismatch

    url = "package://drake/examples/multibody/cart_pole/cart_pole.sdf"
    upright = ([0.0, np.pi, 0.0, 0.0], [0.0])
    base = ControlAffineSystem.from_multibody(url)
    model = base.shifted(*upright)
    truth = ControlAffineSystem(
        base.f, base.g, base.C, source=_PlantSource(base.source.plant)
    ).shifted(*upright)
    box = ([-0.2] * 4, [0.2] * 4)
    same = model_mismatch(model, truth, box, body_mass_scale={"Pole": 1.0}, samples=20)
    heavy = model_mismatch(model, truth, box, body_mass_scale={"Pole": 1.5}, samples=20)
    assert max(same.max_f_error) < 1e-10 and max(same.equilibrium_residual) < 1e-10
    assert max(heavy.max_f_error) > 1e-2


def test_kalman_observer_regulates_the_real_world_cart_pole(real):
    scenario = dataclasses.replace(
        real, variant=dataclasses.replace(real.variant, observer="kalman")
    )
    r = simulate(scenario, progress=False)
    assert r.status == "ok"
    assert abs(r.x[-1, 1]) < 0.02 and abs(r.x[-1, 0]) < 0.1
    # The loop's observer is the one the kalman variant builds: Drake's steady-state gain.
    loop = build_closed_loop(scenario)
    np.testing.assert_array_equal(loop.observer.gain, kalman(loop.parts).gain)


def test_without_real_world_keys_nothing_changes(paper_result, paper_scenario):
    """No truth, measurement or actuation: no seeds, no model error, the same blocks."""
    assert "seeds" not in paper_result.provenance
    assert "model_error" not in paper_result.summary()
    quiet = dataclasses.replace(paper_scenario, measurement=MeasurementConfig())
    loop = build_closed_loop(quiet)
    assert not isinstance(loop.plant, MeasuredPlant)


# ----------------------------------------------------------------- montecarlo
@pytest.mark.parametrize("mass_spread", [0.0, 0.2], ids=["seeds", "seeds_and_masses"])
def test_a_task_of_several_seeds_gives_each_run_as_a_task_of_its_own(real, mass_spread):
    """One task designs once (and, without a mass spread, builds the loop once) for its runs.

    Run 1 after run 0 on the same loop or design equals run 1 alone, bit for bit.
    """
    short = dataclasses.replace(real, simulation=dataclasses.replace(real.simulation, duration=0.5))
    together = run_seeds(short, 3, (0, 1), mass_spread)
    alone = run_seeds(short, 3, (1,), mass_spread)[0]
    assert [r["row"]["seed"] for r in together] == ["3", "4"]
    assert together[1]["row"]["status"] == "ok"
    for key in ("perturbation", "final_state_norm", "rms_estimation_error", "cost"):
        assert together[1]["row"][key] == alone["row"][key], key
    np.testing.assert_array_equal(together[1]["logs"]["x"], alone["logs"]["x"])
    assert together[0]["row"]["cost"] != together[1]["row"]["cost"]  # another seed
    perturbed = json.loads(together[1]["row"]["perturbation"])
    assert (perturbed != {}) == (mass_spread > 0)


def test_montecarlo_statuses_resume_and_refusals(real, tmp_path):
    short = dataclasses.replace(
        real, simulation=dataclasses.replace(real.simulation, duration=1.0, max_wall_time=1e-4)
    )
    rows = montecarlo(short, 2, seed=5, out=tmp_path, optimal_cost=1.0)
    assert [r["seed"] for r in rows] == ["5", "6"]
    assert all(r["status"].startswith("timeout") and r["regulated"] == "false" for r in rows)
    on_disk = read_montecarlo_rows(tmp_path / "montecarlo.csv")
    assert [r["seed"] for r in on_disk] == ["5", "6"]
    # A torn last line is dropped; --resume runs only what is missing.
    text = (tmp_path / "montecarlo.csv").read_text()
    (tmp_path / "montecarlo.csv").write_text(text[: text.rindex("\n", 0, -1) + 1] + "6,{}")
    again = montecarlo(short, 2, seed=5, out=tmp_path, resume=True, optimal_cost=1.0)
    assert [r["seed"] for r in again] == ["5", "6"]
    assert len(read_montecarlo_rows(tmp_path / "montecarlo.csv")) == 2
    with pytest.raises(MonteCarloError, match=r"exists; pass --resume"):
        montecarlo(short, 2, seed=5, out=tmp_path, optimal_cost=1.0)
    with pytest.raises(
        MonteCarloError, match=r"^--resume: the folder's sweep differs in seed \(5 in the folder, 6"
    ):
        montecarlo(short, 2, seed=6, out=tmp_path, resume=True, optimal_cost=1.0)
    with pytest.raises(
        MonteCarloError, match=r"^mass_spread \(--mass-spread\) must be in \[0, 1\); got 1.5"
    ):
        montecarlo(short, 2, mass_spread=1.5)
    with pytest.raises(MonteCarloError, match=r"^runs \(--runs\) must be an integer >= 1; got 0"):
        montecarlo(short, 0)


def test_montecarlo_resume_refuses_another_j_star(paper_scenario, tmp_path):
    """Before: a resume with another optimal_cost (or J* solved another way) mixed two J*."""
    short = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(paper_scenario.simulation, duration=0.5),
    )
    montecarlo(short, 2, out=tmp_path, optimal_cost=1.0, progress=False)
    plan = json.loads((tmp_path / "montecarlo.json").read_text())
    assert plan["optimal"] == {"optimal_cost": 1.0}
    with pytest.raises(
        MonteCarloError,
        match=r"^--resume: the folder's sweep had J\* given as 1\.0, this one given as 2\.0: rows "
        r"would be scored against different J\*; resume with the sweep's own arguments, or "
        r"choose another --out\.$",
    ):
        montecarlo(short, 2, out=tmp_path, resume=True, optimal_cost=2.0, progress=False)
    with pytest.raises(
        MonteCarloError, match=r"had J\* given as 1\.0, this one solved by snopt on Mesh\("
    ):
        montecarlo(short, 2, out=tmp_path, resume=True, progress=False)
    rows = montecarlo(short, 2, out=tmp_path, resume=True, optimal_cost=1.0, progress=False)
    assert [row["optimal_cost"] for row in rows] == [1.0, 1.0]
    del plan["optimal"]  # a folder of an ofrl_drake that did not record it
    (tmp_path / "montecarlo.json").write_text(json.dumps(plan))
    with pytest.raises(MonteCarloError, match=r"did not record how J\* is had"):
        montecarlo(short, 2, out=tmp_path, resume=True, optimal_cost=1.0, progress=False)


def test_montecarlo_resume_refuses_a_cut_short_or_missing_plan_before_any_run(real, tmp_path):
    """The folder is the ablation's store: its refusals come before J* and any run."""
    from ofrl_drake.monte_carlo import CSV_COLUMNS

    (tmp_path / "montecarlo.csv").write_text(",".join(CSV_COLUMNS) + "\n")
    (tmp_path / "montecarlo.json").write_text('{"scenario": "cart')
    with pytest.raises(MonteCarloError, match=r"montecarlo\.json is not valid JSON \(cut short"):
        montecarlo(real, 2, out=tmp_path, resume=True, optimal_cost=1.0)
    (tmp_path / "montecarlo.json").unlink()
    with pytest.raises(MonteCarloError, match=r"montecarlo\.json is missing; it records the sweep"):
        montecarlo(real, 2, out=tmp_path, resume=True, optimal_cost=1.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["montecarlo.csv"]


def test_montecarlo_perturbs_every_body_mass_by_the_spread(real):
    from ofrl_drake.monte_carlo import run_for

    run, perturbation = run_for(real, 3, 2, 0.1)
    assert set(perturbation) == {"Cart", "Pole"}
    assert 0.8 * 0.9 <= perturbation["Cart"] <= 0.8 * 1.1
    assert 1.3 * 0.9 <= perturbation["Pole"] <= 1.3 * 1.1
    assert run.measurement.seed == 5
    assert run_for(real, 3, 2, 0.1)[1] == perturbation  # drawn from the seed and the index


def test_montecarlo_command_on_dask(tmp_path):
    out = tmp_path / "mc"
    scenario = tmp_path / "short.yaml"
    data = yaml_load(filename=str(REAL))
    data["simulation"]["duration"] = 2.0
    data["truth"]["body_mass_scale"] = {"Pole": 1.3, "Cart": 0.8}
    scenario.write_text(yaml_dump(data))
    proc = run_cli("montecarlo", scenario, "--runs", 2, "--workers", 2, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "wrote" in proc.stdout and "montecarlo.md" in proc.stdout
    rows = read_montecarlo_rows(out / "montecarlo.csv")
    assert sorted(r["seed"] for r in rows) == ["0", "1"]
    plan = json.loads((out / "montecarlo.json").read_text())
    assert plan["runs"] == 2 and plan["seed"] == 0


# ------------------------------------------------------------------ errors
@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ({"measurement": {"period": -0.01}}, r"measurement\.period: must be >= 0; got -0\.01"),
        (
            {"measurement": {"noise_std": [0.1], "period": 0.01}},
            r"measurement\.noise_std: expected 2 entries; got 1",
        ),
        (
            {"measurement": {"noise_std": [0.1, 0.1]}},
            r"measurement\.period: noise is drawn once per sample",
        ),
        ({"actuation": {"period": -1.0}}, r"actuation\.period: must be >= 0; got -1\.0"),
        (
            {"truth": {"body_mass_scale": {"Pendulum": 1.2}}},
            r"truth\.body_mass_scale\.Pendulum: no body of that name .* "
            r"\['world', 'Cart', 'Pole'\]",
        ),
        (
            {"truth": {"body_mass_scale": {"Pole": -1.0}}},
            r"truth\.body_mass_scale\.Pole: must be a number > 0; got -1\.0",
        ),
        ({"truth": {"mass": 2.0}}, r"truth\.mass: unknown key in truth"),
    ],
)
def test_bad_real_world_keys_exit_2_naming_the_key(tmp_path, edit, message):
    import re

    data = yaml_load(filename=str(CART_POLE))
    data.update(edit)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml_dump(data))
    proc = run_cli("run", path, "--out", tmp_path / "o")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and re.search(message, lines[0]), lines
    assert not (tmp_path / "o").exists()


def test_montecarlo_with_a_seed_drake_cannot_keep_exits_2_before_any_run(tmp_path):
    """It exited 0 with "0% success" and a pybind11 TypeError as every run's status."""
    out = tmp_path / "mc"
    proc = run_cli("montecarlo", REAL, "--seed", 99999999999999999999, "--runs", 1, "--out", out)
    assert proc.returncode == 2, proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line == (
        "error: the last run's measurement seed, seed + runs - 1 = 99999999999999999999 + 1 - 1 "
        "(--seed, --runs), must be at most 2**32 - 1 = 4294967295 (Drake's random sources keep "
        "32 bits of a seed); got 99999999999999999999. With runs = 1, give a seed of at most "
        "4294967295."
    )
    assert not out.exists()


def test_run_writes_a_scenario_yaml_that_reproduces_the_noisy_run(tmp_path):
    """The truth, measurement and actuation keys round-trip through scenario.yaml, bit for bit."""
    import ofrl_drake as od

    assert od.montecarlo is montecarlo
    data = yaml_load(filename=str(REAL))
    data["simulation"]["duration"] = 1.0
    path = tmp_path / "short.yaml"
    path.write_text(yaml_dump(data))
    first = run_cli("run", path, "--out", tmp_path / "a", "--quiet", "--checkpoints", "0")
    assert first.returncode == 0, first.stderr
    again = run_cli(
        "run",
        tmp_path / "a" / "scenario.yaml",
        "--out",
        tmp_path / "b",
        "--quiet",
        "--checkpoints",
        "0",
    )
    assert again.returncode == 0, again.stderr
    a, b = (
        np.load(tmp_path / "a" / "trajectories.npz"),
        np.load(tmp_path / "b" / "trajectories.npz"),
    )
    for key in a.files:
        np.testing.assert_array_equal(b[key], a[key], err_msg=key)
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["provenance"]["seeds"] == {"measurement": 0}
    assert "model_error" in summary


def test_the_measured_plant_forwards_the_slot_contracts_of_its_plant():
    from ofrl_drake.contracts import ContextInitializer, HoldStarter, PlantStateSetter
    from ofrl_drake.errors import ModelError

    system = make_system("two_state")
    plant = MeasuredPlant(ControlAffinePlant(system), period=0.1)
    assert all(isinstance(plant, c) for c in (PlantStateSetter, HoldStarter, ContextInitializer))
    context = plant.CreateDefaultContext()
    plant.set_state(context, [0.3, -0.2])
    np.testing.assert_array_equal(plant.GetOutputPort("state").Eval(context), [0.3, -0.2])
    # A plant block without set_state: the wrapper says so when asked for it.
    builder = DiagramBuilder()
    inner = builder.AddSystem(ControlAffinePlant(system))
    builder.ExportInput(inner.GetInputPort("u"), "u")
    for port in ("y", "state"):
        builder.ExportOutput(inner.GetOutputPort(port), port)
    bare = builder.Build()
    assert not isinstance(bare, PlantStateSetter)
    wrapped = MeasuredPlant(bare, period=0.1)
    with pytest.raises(
        ModelError,
        match=r"^MeasuredPlant: the plant Diagram has no set_state\(context, x\), so its state "
        r"cannot be set; give it one\.$",
    ):
        wrapped.set_state(wrapped.CreateDefaultContext(), [0.3, -0.2])


X_MEASURED = [0.4, -0.3, 0.2, 0.1]


def _measured_y(plant, seed=4):
    """``y`` of ``plant`` at ``t = 0`` with its noise drawn from ``seed``, ``u = 0``."""
    context = plant.CreateDefaultContext()
    plant.SetRandomContext(context, RandomGenerator(seed))
    plant.get_u_input_port().FixValue(context, np.zeros(plant.get_u_input_port().size()))
    plant.set_state(context, X_MEASURED)
    plant.start_holds(context)
    return plant.get_y_output_port().Eval(context)


def test_the_measured_plant_takes_arrays_as_it_takes_lists():
    """``coupled_two_state`` has q = m = 2: arrays are not asked for their truth value."""
    system = make_system("coupled_two_state")
    listed = MeasuredPlant(
        ControlAffinePlant(system), noise_std=[0.1, 0.2], period=0.01, disturbance=[0.3, -0.1]
    )
    arrays = MeasuredPlant(
        ControlAffinePlant(system),
        noise_std=np.array([0.1, 0.2]),
        period=0.01,
        disturbance=np.array([0.3, -0.1]),
    )
    y = _measured_y(listed)
    assert np.all(y != system.output_matrix @ X_MEASURED)  # noisy
    np.testing.assert_array_equal(_measured_y(arrays), y)
    # Empty arrays, like None and empty lists: no noise, no disturbance.
    for nothing in (None, [], np.array([])):
        plain = MeasuredPlant(
            ControlAffinePlant(system), noise_std=nothing, period=0.01, disturbance=nothing
        )
        np.testing.assert_array_equal(_measured_y(plain), system.output_matrix @ X_MEASURED)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"noise_std": np.array([0.1, 0.1, 0.1])}, r"noise_std must have length 2; got 3\.$"),
        ({"noise_std": np.array([0.1, np.nan])}, r"noise_std must be finite; got \[0\.1, nan\]"),
        ({"noise_std": np.array([-0.1, 0.1])}, r"noise_std must be >= 0; got \[-0\.1, 0\.1\]"),
        ({"disturbance": np.array([0.1])}, r"disturbance must have length 2; got 1\.$"),
        ({"disturbance": [np.inf, 0.0]}, r"disturbance must be finite; got \[inf, 0\.0\]"),
    ],
)
def test_the_measured_plant_names_a_bad_noise_std_or_disturbance(arguments, message):
    system = make_system("coupled_two_state")
    with pytest.raises(ModelError, match=rf"^MeasuredPlant: {message}"):
        MeasuredPlant(ControlAffinePlant(system), period=0.01, **arguments)


def test_the_wrappers_accessors_return_their_named_ports():
    system = make_system("two_state")
    plant = MeasuredPlant(ControlAffinePlant(system), noise_std=[0.1], period=0.01)
    assert plant.get_u_input_port().get_name() == "u"
    assert plant.get_y_output_port().get_name() == "y"
    assert plant.get_state_output_port().get_name() == "state"
    assert plant.get_u_input_port() is plant.GetInputPort("u")
    assert plant.get_y_output_port() is plant.GetOutputPort("y")
    assert plant.get_state_output_port() is plant.GetOutputPort("state")
    basis = PolynomialBasis(2)
    controller = SampledController(SaturatedController(system, basis, np.ones(1), 3.0), 0.01)
    assert controller.get_u_output_port().get_name() == "u"
    assert controller.get_u_output_port() is controller.GetOutputPort("u")


def test_the_envelope_of_a_run_stopped_early_ends_where_it_stopped():
    # Interpolated onto the first run's grid, a run the guard stopped early was held flat
    # to the horizon, and a short first run cut every run to its length.
    short = (np.linspace(0.0, 1.0, 11), np.ones((11, 2)))
    whole = (np.linspace(0.0, 2.0, 21), np.zeros((21, 2)))
    grid, stack = envelope_samples([short, whole])
    np.testing.assert_allclose(grid, np.linspace(0.0, 2.0, 21), rtol=0, atol=1e-15)
    assert stack.shape == (2, 21, 2)
    assert np.all(stack[0, grid <= 1.0] == 1.0) and np.all(np.isnan(stack[0, grid > 1.0]))
    assert np.all(stack[1] == 0.0)


def test_a_statistic_over_fewer_runs_than_the_table_says_names_its_count():
    row = {"status": "ok", "regulated": "true", "final_state_norm": 1.0}
    row.update(rms_estimation_error=0.5, cost=2.0, optimality_ratio=float("nan"))
    rows = [dict(row), dict(row, cost=4.0), dict(row, cost=float("nan"))]
    table = montecarlo_table(rows)
    assert "| 1 ± 0 |" in table  # every run: no count
    assert "| 3 ± 1.4 (n = 2) |" in table
    assert table.rstrip().endswith("| n/a |")


# ---------------------------------------------------------------- envelope.png
def _envelope(tmp_path, monkeypatch, runs, perturbation="{}"):
    """``write_montecarlo_report`` on ``runs`` ({seed: (t, x)}): its figure, kept open."""
    from ofrl_drake import plotting

    (tmp_path / "runs").mkdir()
    rows = []
    for seed, (t, x) in runs.items():
        np.savez(tmp_path / "runs" / f"seed_{seed}.npz", t=t, x=x, state_units=["m", "rad"])
        rows.append(
            {
                "seed": str(seed),
                "perturbation": perturbation,
                "status": "ok",
                "regulated": "true",
                "final_state_norm": float(np.linalg.norm(x[-1])),
                "rms_estimation_error": 0.1,
                "cost": 1.0,
                "optimal_cost": 0.9,
                "optimality_ratio": 1.1,
            }
        )
    figures = []
    save = plotting.save_png
    monkeypatch.setattr(plotting, "save_png", lambda fig, *a: (figures.append(fig), save(fig, *a)))
    write_montecarlo_report(tmp_path, rows, "toy")
    (fig,) = figures
    fig.canvas.draw()
    return fig


def _two_runs(noise=0.05):
    t = np.linspace(0.0, 5.0, 501)
    x = np.column_stack([np.exp(-t), -np.exp(-2 * t)])
    return {0: (t, x), 1: (t, x + noise * np.sin(7 * t)[:, None])}


def test_the_envelope_names_units_and_time_and_keeps_its_legend_off_the_curves(
    tmp_path, monkeypatch
):
    # The legend sat inside the upper right of x1's panel, over the curve; the axes had
    # no units and read "t [s]" where every other figure reads "time t [s]".
    fig = _envelope(tmp_path, monkeypatch, _two_runs())
    axes = fig.axes
    assert [ax.get_ylabel() for ax in axes] == ["$x_{1}$ [m]", "$x_{2}$ [rad]"]
    assert axes[-1].get_xlabel() == r"time $t$ [s]"
    assert all(ax.get_legend() is None for ax in axes)
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == ["min-max", "median"]
    box = legend.get_window_extent()
    for ax in axes:  # outside every panel, with a pixel to spare
        assert not box.padded(1.0).overlaps(ax.get_window_extent()), ax.get_ylabel()
    assert any(isinstance(c, PolyCollection) for c in axes[0].collections)  # the band


def test_identical_runs_are_one_curve_and_said_so_once(tmp_path, monkeypatch):
    # A noise-free scenario without --mass-spread ran N identical runs: the figure drew a
    # band of width 0 and the table "± 0", with no word on why.
    from ofrl_drake.monte_carlo import IdenticalRunsWarning, identical_runs

    runs = _two_runs(noise=0.0)
    assert identical_runs(list(runs.values())) and not identical_runs([runs[0]])
    assert not identical_runs(list(_two_runs().values()))
    message = (
        r"^montecarlo toy: the 2 runs are identical, bit for bit \(no --mass-spread, and the "
        r"scenario has no measurement noise: the runs' noise seeds change nothing\); "
        r"the envelope is their one curve\. For runs that differ, give "
        r"measurement\.noise_std \(with measurement\.period > 0\) or --mass-spread\.$"
    )
    with pytest.warns(IdenticalRunsWarning, match=message) as caught:
        fig = _envelope(tmp_path, monkeypatch, runs)
    assert len(caught) == 1
    text = (tmp_path / "montecarlo.md").read_text()
    assert text.count("The 2 runs are identical, bit for bit (no --mass-spread") == 1
    assert fig.get_suptitle() == "toy: 2 identical runs"
    for ax in fig.axes:
        assert not any(isinstance(c, PolyCollection) for c in ax.collections)  # no band
        (line,) = ax.get_lines()
        assert line.get_label() == "all 2 runs (identical)"


def test_run_seeds_records_a_truth_it_cannot_build_instead_of_raising(real):
    """Before: with a mass spread, a truth that failed to build escaped the task ("never
    raises"), and the whole sweep stopped instead of recording the runs' status."""
    from ofrl_drake.monte_carlo import run_seeds

    bad = dataclasses.replace(
        real, truth=dataclasses.replace(real.truth, body_mass_scale={"no_such_body": 1.1})
    )
    rows = run_seeds(bad, 7, [0, 1], 0.1)
    assert [r["row"]["seed"] for r in rows] == ["7", "8"]
    assert all(
        r["row"]["status"].startswith("ScenarioError: truth.body_mass_scale.no_such_body: no body")
        and r["row"]["perturbation"] == "{}"
        for r in rows
    ), rows


def test_montecarlo_refuses_a_solver_for_a_given_j_star(paper_scenario):
    with pytest.raises(
        MonteCarloError,
        match=r"^solver: J\* is given as optimal_cost = 1\.0, so no solver 'ipopt' runs; pass one "
        r"or the other\.$",
    ):
        montecarlo(paper_scenario, 2, optimal_cost=1.0, solver="ipopt")


def test_montecarlo_md_says_why_an_ok_run_did_not_succeed(tmp_path):
    """Before: a run that ended ok but not regulated was listed with "ok" as its reason."""
    from ofrl_drake.monte_carlo import write_montecarlo_report

    row = {
        "seed": "0",
        "perturbation": "{}",
        "status": "ok",
        "regulated": "false",
        "final_state_norm": 0.5812,
        "rms_estimation_error": 0.1,
        "cost": 2.0,
        "optimal_cost": 1.0,
        "optimality_ratio": 2.0,
        "wall_time": 0.1,
    }
    write_montecarlo_report(tmp_path, [row], "short")
    text = (tmp_path / "montecarlo.md").read_text()
    assert "- seed 0 ({}): ok but not regulated (|x(T) - x*| = 0.581)\n" in text, text
    assert "J/J* is n/a" not in text


def test_montecarlo_md_names_the_component_that_failed_regulation(paper_scenario, tmp_path):
    """Before: an ok run that did not regulate showed the norm |x(T) - x*|, while
    regulation is judged per component, each against its own tolerance."""
    from ofrl_drake.monte_carlo import montecarlo, write_montecarlo_report

    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=0.3)
    )
    rows = montecarlo(short, 1, out=tmp_path, progress=False, optimal_cost=1.0)
    assert (rows[0]["status"], rows[0]["regulated"]) == ("ok", "false")
    with np.load(tmp_path / "runs" / "seed_0.npz") as arrays:
        error, bound = arrays["final_error"], arrays["regulation_tolerance"]
        assert bool(arrays["inside_observer_box"])
    worst = int(np.argmax(error / bound))
    assert error[worst] > bound[worst]
    write_montecarlo_report(tmp_path, rows, "short")
    text = (tmp_path / "montecarlo.md").read_text()
    line = (
        f"- seed 0 ({{}}): ok but not regulated: |x_{worst + 1}(T) - x*_{worst + 1}| = "
        f"{error[worst]:.3g} > {bound[worst]:.3g}\n"
    )
    assert line in text, text


def test_a_run_the_guard_stopped_has_no_cost_or_final_state(paper_scenario, tmp_path):
    """Before: a run stopped at t = 0.6 s kept J(0.6), |x(0.6)| and J/J*, and
    montecarlo.md averaged them with whole runs' J(T) (a cheaper-looking sweep)."""
    from ofrl_drake.monte_carlo import montecarlo, write_montecarlo_report
    from ofrl_drake.scenario import BoxConfig

    # xhat rises from 1.5 to about 3 in the first second: it leaves this box.
    box = BoxConfig(lower=[-2.0, -2.0], upper=[2.5, 2.0])
    short = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(paper_scenario.simulation, duration=3.0, abort_box=box),
    )
    rows = montecarlo(short, 1, out=tmp_path, progress=False, optimal_cost=1.0)
    assert rows[0]["status"].startswith("diverged: xhat_1 = "), rows[0]["status"]
    for key in ("final_state_norm", "rms_estimation_error", "cost", "optimality_ratio"):
        assert math.isnan(rows[0][key]), (key, rows[0][key])
    with np.load(tmp_path / "runs" / "seed_0.npz") as arrays:  # its logs are kept
        assert 0 < arrays["t"][-1] < 3.0
    write_montecarlo_report(tmp_path, rows, "short")
    table = (tmp_path / "montecarlo.md").read_text()
    assert "| 1 | 0 | 0 | 0% | n/a | n/a | n/a | n/a |" in table, table


def test_montecarlo_md_says_why_j_star_is_not_available(tmp_path):
    """Before: the rows' J/J* were n/a and only the command's warning line said why."""
    from ofrl_drake.monte_carlo import write_montecarlo_report

    row = {
        "seed": "0",
        "perturbation": "{}",
        "status": "MonteCarloError: the build failed",
        "regulated": "false",
        "final_state_norm": np.nan,
        "rms_estimation_error": np.nan,
        "cost": np.nan,
        "optimal_cost": np.nan,
        "optimality_ratio": np.nan,
        "wall_time": 0.1,
    }
    why = "not converged (SNOPT: kIterationLimit)"
    write_montecarlo_report(tmp_path, [{**row, "optimal_status": why}], "short")
    text = (tmp_path / "montecarlo.md").read_text()
    assert f"\nJ/J* is n/a: J* of the nominal problem is not available: {why}.\n" in text, text
    write_montecarlo_report(tmp_path, [row], "short")  # rows read back from montecarlo.csv
    text = (tmp_path / "montecarlo.md").read_text()
    assert (
        "\nJ/J* is n/a: J* of the nominal problem is not available (the command that ran the "
        "sweep said why).\n" in text
    ), text
