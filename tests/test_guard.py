"""The run guard: divergence and time-outs end a run with a status; progress changes nothing."""

import dataclasses
import io
import json
import re
import sys

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump, yaml_load
from pydrake.systems.framework import BasicVector, LeafSystem

from ofrl_drake import simulate
from ofrl_drake.errors import ScenarioError
from ofrl_drake.guard import STATUS_DIVERGED, STATUS_OK, STATUS_TIMEOUT, RunGuard
from ofrl_drake.scenario import ABORT_BOX_FACTOR, BoxConfig, abort_box, validate_scenario
from ofrl_drake.simulation import TRAJECTORY_KEYS
from tests.cli_helpers import run_cli

from .conftest import PAPER_SCENARIO, ROOT


def _with_simulation(scenario, **changes):
    return dataclasses.replace(
        scenario, simulation=dataclasses.replace(scenario.simulation, **changes)
    )


def test_default_abort_box_is_the_stated_multiple_of_the_observer_box(paper_scenario):
    lower, upper = abort_box(paper_scenario)
    assert ABORT_BOX_FACTOR == 10.0
    np.testing.assert_array_equal(lower, [-20.0, -20.0])
    np.testing.assert_array_equal(upper, [20.0, 20.0])
    shifted = dataclasses.replace(
        paper_scenario,
        observer=dataclasses.replace(
            paper_scenario.observer, box=BoxConfig([0.0, 1.0], [2.0, 2.0])
        ),
    )
    lower, upper = abort_box(shifted)
    np.testing.assert_allclose(lower, [1.0 - 10.0, 1.5 - 5.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(upper, [1.0 + 10.0, 1.5 + 5.0], rtol=0, atol=1e-15)
    given = _with_simulation(paper_scenario, abort_box=BoxConfig([-3.0, -4.0], [5.0, 6.0]))
    np.testing.assert_array_equal(abort_box(given)[0], [-3.0, -4.0])


def test_bad_guard_keys_are_named(paper_scenario):
    bad = _with_simulation(paper_scenario, abort_box=BoxConfig([-1.0], [1.0]))
    with pytest.raises(ScenarioError, match=r"simulation.abort_box.lower: expected 2 entries"):
        validate_scenario(bad)
    bad = _with_simulation(paper_scenario, abort_box=BoxConfig([1.0, -1.0], [0.0, 1.0]))
    with pytest.raises(ScenarioError, match=r"simulation.abort_box.upper: must exceed"):
        validate_scenario(bad)
    bad = _with_simulation(paper_scenario, max_wall_time=0.0)
    with pytest.raises(ScenarioError, match=r"simulation.max_wall_time: must be > 0; got 0.0"):
        validate_scenario(bad)


def test_progress_on_and_off_give_identical_arrays(paper_scenario, paper_design, monkeypatch):
    scenario = _with_simulation(paper_scenario, duration=5.0)
    quiet = simulate(scenario, design=paper_design, progress=False)
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    shown = simulate(scenario, design=paper_design, progress=True)
    assert "100%" in stream.getvalue()  # the bar was drawn
    for key in TRAJECTORY_KEYS:
        np.testing.assert_array_equal(getattr(shown, key), getattr(quiet, key), err_msg=key)
    assert shown.integrator["num_steps"] == quiet.integrator["num_steps"]
    assert shown.status == quiet.status == STATUS_OK


def test_a_stop_about_an_equilibrium_names_the_coordinates_of_the_box():
    """Before: 'x_1 = 0.205 left the abort box' beside stop.x[0] = 3.35 (the plant's own
    angle, near pi) in the same summary: the box and the reason are relative to x*."""
    from ofrl_drake import load_scenario

    from .conftest import ROOT

    pendulum = load_scenario(ROOT / "diagrams" / "pendulum_upright.yaml")
    box = BoxConfig([-0.205, -3.0], [0.205, 3.0])  # x0 = (0.2, 0.3): the angle leaves it
    result = simulate(_with_simulation(pendulum, abort_box=box, duration=1.0), progress=False)
    assert result.status == STATUS_DIVERGED
    assert re.match(
        r"x_1 - x\*_1 = 0\.205\d* left the abort box \[-0\.205, 0\.205\]", result.stop.reason
    )
    stop = result.summary()["stop"]
    assert stop["reason"] == result.stop.reason
    assert stop["x"][0] == pytest.approx(np.pi + result.stop.x[0], abs=1e-12)  # the plant's own


def test_leaving_the_abort_box_stops_the_run_with_its_logs(paper_scenario, paper_design):
    box = BoxConfig([-2.5, -2.5], [2.5, 2.5])
    scenario = dataclasses.replace(
        _with_simulation(paper_scenario, abort_box=box, duration=5.0), xhat0=[2.4, 1.5]
    )
    result = simulate(scenario, design=paper_design, progress=False)
    assert result.status == STATUS_DIVERGED
    stop = result.stop
    assert 0.0 < stop.time < 1.0
    assert "left the abort box [-2.5, 2.5]" in stop.reason
    # The logs end at the stop, with the state that tripped the guard.
    assert result.t[-1] == stop.time
    np.testing.assert_array_equal(result.x[-1], stop.x)
    np.testing.assert_array_equal(result.xhat[-1], stop.xhat)
    last = np.concatenate([result.x[-1], result.xhat[-1]])
    assert np.any(np.abs(last) > 2.5)
    before = np.concatenate([result.x[:-1], result.xhat[:-1]], axis=1)
    assert np.all(np.abs(before) <= 2.5)
    summary = json.loads(json.dumps(result.summary()))
    assert summary["status"] == "diverged"
    assert summary["stop"]["time"] == stop.time
    assert summary["final_time"] == stop.time


def test_a_tiny_wall_time_budget_gives_timeout(paper_scenario, paper_design):
    scenario = _with_simulation(paper_scenario, max_wall_time=1e-3)
    result = simulate(scenario, design=paper_design, progress=False)
    assert result.status == STATUS_TIMEOUT
    assert "exceeded max_wall_time = 0.001 s" in result.stop.reason
    assert result.stop.time < scenario.simulation.duration
    assert result.t[-1] == result.stop.time and result.t.size >= 1
    assert result.summary()["status"] == "timeout"


def test_the_guard_reports_a_non_finite_state(paper_scenario, paper_design):
    from pydrake.systems.analysis import Simulator

    from ofrl_drake import build_closed_loop

    loop = build_closed_loop(paper_scenario, design=paper_design)
    guard = RunGuard(loop.diagram, loop.plant, loop.observer, abort_box(paper_scenario), None)
    simulator = Simulator(loop.diagram)
    context = simulator.get_mutable_context()
    assert guard.check(context) == (STATUS_OK, "")
    state = context.get_mutable_continuous_state_vector()
    values = state.CopyToVector()
    values[1] = np.nan
    state.SetFromVector(values)
    status, reason = guard.check(context)
    assert status == STATUS_DIVERGED
    assert reason == "continuous state 1 is nan at t = 0 s"
    assert guard(context).severity() == guard(context).Severity.kReachedTermination
    assert guard.stopped


def test_a_far_initial_state_ends_diverged_with_exit_3_and_a_complete_folder(tmp_path):
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    data["x0"] = [100.0, 100.0]
    path = tmp_path / "far.yaml"
    path.write_text(yaml_dump(data))
    out = tmp_path / "out"
    proc = run_cli("run", path, "--out", out, "--quiet", cwd=ROOT)
    assert proc.returncode == 3, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 2, proc.stderr
    assert lines[0].startswith("warning: x0 = [100.0, 100.0] outside the observer box")
    assert "outside the abort box too" in lines[0]
    assert lines[1].startswith("stopped: diverged: x_1 = 100 left the abort box [-20, 20]")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "diverged"
    assert summary["stop"]["x"] == [100.0, 100.0]
    for name in ("trajectories.npz", "scenario.yaml", "observer_design.json"):
        assert (out / name).is_file(), name
    assert (out / "figures" / "state_1.png").is_file()
    assert (out / "figures" / "estimation_error_log.png").is_file()


def test_max_wall_on_the_command_line_gives_timeout_and_exit_3(tmp_path):
    # With the true state fed back there is no observer design to fit in 1 ms:
    # the run itself is what --max-wall stops.
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    data["variant"] = {**data.get("variant", {}), "observer": "true_state"}
    path = tmp_path / "true_state.yaml"
    path.write_text(yaml_dump(data))
    out = tmp_path / "out"
    proc = run_cli("run", path, "--out", out, "--quiet", "--max-wall", "0.001", cwd=ROOT)
    assert proc.returncode == 3, proc.stderr
    assert proc.stderr.startswith("stopped: timeout: wall time")
    assert proc.stderr.count("\n") == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "timeout"
    scenario = yaml_load(data=(out / "scenario.yaml").read_text())
    assert scenario["simulation"]["max_wall_time"] == 0.001


@pytest.mark.parametrize("command", ["run", "design-observer", "verify-observer"])
def test_max_wall_bounds_the_observer_design_too(tmp_path, command):
    out = tmp_path / "out.json"
    args = [] if command == "verify-observer" else ["--out", out]
    proc = run_cli(command, PAPER_SCENARIO, *args, "--max-wall", "0.001", cwd=ROOT)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    # The budget runs out in the bounds or, on a loaded machine, already in the symbolic
    # Jacobians before them: either phase names --max-wall and stops the design.
    assert re.match(
        r"error: (the observer design's Jacobian bounds took .* of max_wall_time \(--max-wall\) "
        r"= 0\.001 s, leaving nothing for the LMI|the symbolic Jacobians of f and g were not done "
        r"by the deadline \(max_wall_time, --max-wall\))",
        lines[0],
    ), lines[0]
    assert not out.exists() and list(tmp_path.iterdir()) == []


class _FiniteTimeBlowUp(LeafSystem):
    """A plant slot block with ``x' = x^3``: from x = 1 it reaches infinity at t = 0.5."""

    def __init__(self):
        super().__init__()
        self.DeclareVectorInputPort("u", 1)
        state = self.DeclareContinuousState(BasicVector([1.0, 1.0]))
        self.DeclareStateOutputPort("state", state)
        self.DeclareVectorOutputPort("y", 1, self._y, {self.xc_ticket()})

    def _y(self, context, output):
        output.SetAtIndex(0, context.get_continuous_state_vector().GetAtIndex(1))

    def DoCalcTimeDerivatives(self, context, derivatives):
        x = context.get_continuous_state_vector().CopyToVector()
        derivatives.get_mutable_vector().SetFromVector(x**3)


def test_an_integrator_that_gives_up_ends_the_run_as_diverged(paper_scenario, paper_design):
    scenario = _with_simulation(
        paper_scenario, abort_box=BoxConfig([-1e300, -1e300], [1e300, 1e300]), duration=1.0
    )
    plant = _FiniteTimeBlowUp()
    result = simulate(scenario, design=paper_design, plant=plant, progress=False)
    assert result.status == STATUS_DIVERGED
    assert result.stop.reason.startswith(
        "the integrator gave up: Error control wants to select step smaller than minimum"
    )
    assert 0.4 < result.stop.time < 0.5 + 1e-3
    assert result.t[-1] == result.stop.time


def test_a_stop_report_reads_back_what_to_dict_wrote():
    from ofrl_drake.guard import StopReport

    stop = StopReport(STATUS_DIVERGED, "x_1 left", 1.5, [float("nan"), 2.0], [0.5, 1.0], 0.25)
    back = StopReport.from_dict(json.loads(json.dumps(stop.to_dict())), 2)
    assert back.status == STATUS_DIVERGED and back.x[1] == 2.0 and np.isnan(back.x[0])
    assert (back.reason, back.time, back.xhat, back.wall_time) == (
        "x_1 left",
        1.5,
        [0.5, 1.0],
        0.25,
    )
    with pytest.raises(ValueError, match=r"status 'finished' is not one of \['ok', 'diverged'"):
        StopReport.from_dict({**stop.to_dict(), "status": "finished"})
    with pytest.raises(ValueError, match=r"expected a list of 3 numbers"):
        StopReport.from_dict(stop.to_dict(), 3)
    with pytest.raises(TypeError, match=r"expected a number, got str"):
        StopReport.from_dict({**stop.to_dict(), "time": "1.5"})


class _NaNPastAThreshold(_FiniteTimeBlowUp):
    """A plant slot block with ``x' = x`` until x passes 1.5, and NaN past it.

    Drake's error control shrinks the step at x = 1.5 (t = ln 1.5) below what
    time can resolve, so without the guard's stall check the run never ends.
    """

    def DoCalcTimeDerivatives(self, context, derivatives):
        x = context.get_continuous_state_vector().CopyToVector()
        derivatives.get_mutable_vector().SetFromVector(np.where(x > 1.5, np.nan, x))


def test_a_nan_derivative_that_stalls_the_integrator_ends_the_run_as_diverged(
    paper_scenario, paper_design
):
    from ofrl_drake.guard import STALL_STEPS

    scenario = _with_simulation(
        paper_scenario, abort_box=BoxConfig([-1e3, -1e3], [1e3, 1e3]), duration=2.0
    )
    result = simulate(scenario, design=paper_design, plant=_NaNPastAThreshold(), progress=False)
    assert result.status == STATUS_DIVERGED
    assert result.stop.reason.startswith(
        f"the integrator stalled at t = 0.405465 s: {STALL_STEPS} steps in a row each "
        "advanced time by less than 1.0e-14 s; a time derivative is probably NaN"
    )
    np.testing.assert_allclose(result.stop.time, np.log(1.5), rtol=1e-6)
    assert result.t[-1] == result.stop.time
    assert np.isfinite(result.x).all()


def test_steps_that_advance_time_never_count_as_a_stall(paper_scenario, paper_design):
    from pydrake.systems.analysis import Simulator

    from ofrl_drake import build_closed_loop
    from ofrl_drake.guard import STALL_STEPS

    loop = build_closed_loop(paper_scenario, design=paper_design)
    guard = RunGuard(loop.diagram, loop.plant, loop.observer, abort_box(paper_scenario), None)
    context = Simulator(loop.diagram).get_mutable_context()
    # Steps just above Drake's smallest working step go on; shorter ones, in a row, stop it.
    for k in range(3 * STALL_STEPS):
        context.SetTime(1.0 + k * 1.1e-14)
        assert guard.check(context) == (STATUS_OK, "")
    for _ in range(STALL_STEPS - 1):
        assert guard.check(context) == (STATUS_OK, "")
    status, reason = guard.check(context)
    assert status == STATUS_DIVERGED and reason.startswith("the integrator stalled at t = 1 s")
    context.SetTime(2.0)  # a step that advances time starts the count again
    assert guard.check(context) == (STATUS_OK, "")


class _NaNRateInAHalfPlane(_FiniteTimeBlowUp):
    """A plant slot block with ``x1' = x2, x2' = 1``, and x2' NaN once x1 > 1.5.

    Drake's error control accepts the step into NaN here (only x2 is NaN).
    """

    def DoCalcTimeDerivatives(self, context, derivatives):
        x = context.get_continuous_state_vector().CopyToVector()
        rate = np.nan if x[0] > 1.5 else 1.0
        derivatives.get_mutable_vector().SetFromVector(np.array([x[1], rate]))


def test_a_run_that_turns_nan_writes_strict_json_and_loads_back(
    paper_scenario, paper_design, tmp_path
):
    from ofrl_drake import SimulationResult

    scenario = _with_simulation(
        paper_scenario, abort_box=BoxConfig([-1e3, -1e3], [1e3, 1e3]), duration=3.0
    )
    result = simulate(scenario, design=paper_design, plant=_NaNRateInAHalfPlane(), progress=False)
    assert result.status == STATUS_DIVERGED
    assert result.stop.reason.startswith("continuous state 1 is nan at t = 0.41")
    assert np.isnan(result.summary()["final_state_norm"])
    result.save(tmp_path / "run")
    text = (tmp_path / "run" / "summary.json").read_text()

    def refuse(token):
        raise AssertionError(f"summary.json holds {token}, which strict JSON parsers refuse")

    # Before: "final_state": [1.50014, NaN], and NaN norms.
    summary = json.loads(text, parse_constant=refuse)
    assert summary["final_state"][1] is None and summary["final_state_norm"] is None
    assert summary["stop"]["x"][1] is None
    back = SimulationResult.load(tmp_path / "run")
    assert back.status == STATUS_DIVERGED and np.isnan(back.stop.x[1])
    np.testing.assert_array_equal(back.x, result.x)  # NaN where the run had NaN
    back.save(tmp_path / "again")
    assert (tmp_path / "again" / "summary.json").read_text() == text


class _NaNFromTheStart(_FiniteTimeBlowUp):
    """A plant slot block whose ``x2'`` is NaN at every state, the initial one included."""

    def DoCalcTimeDerivatives(self, context, derivatives):
        x = context.get_continuous_state_vector().CopyToVector()
        derivatives.get_mutable_vector().SetFromVector(np.array([x[1], np.nan]))


class _SlowRates(_FiniteTimeBlowUp):
    """A plant slot block that takes 0.2 s of wall time per derivative evaluation."""

    def DoCalcTimeDerivatives(self, context, derivatives):
        import time

        time.sleep(0.2)
        derivatives.get_mutable_vector().SetFromVector(np.zeros(2))


def _simulate_in_a_child(plant: str, **simulation) -> dict:
    """``simulate`` of the paper's scenario with the plant slot block ``plant`` of this
    module, in a child process with a timeout: a hang fails the test instead of the suite."""
    import subprocess

    code = f"""
import json, dataclasses
from ofrl_drake import load_scenario, simulate
from ofrl_drake.scenario import BoxConfig
from ofrl_drake.variants import design_for
from tests.test_guard import {plant}, _with_simulation
scenario = load_scenario({str(PAPER_SCENARIO)!r})
design = design_for(scenario)
scenario = _with_simulation(
    scenario, abort_box=BoxConfig([-1e3, -1e3], [1e3, 1e3]), **{simulation!r}
)
result = simulate(scenario, design=design, plant={plant}(), progress=False)
print(json.dumps({{"stop": result.stop.to_dict(), "t": result.t.tolist(),
                  "finite": bool(all(map(lambda v: v == v, result.x.ravel())))}}))
"""
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


def test_a_step_that_never_ends_is_stopped_as_diverged():
    # Before: Drake's error control shrank the first step tenfold forever (a NaN error
    # estimate has no floor), the monitor was never called, and AdvanceTo never returned.
    # Python blocks: a C++ block fed the NaN stage states would raise instead.
    run = _simulate_in_a_child(
        "_NaNFromTheStart", duration=1.0, max_wall_time=60.0, blocks="python"
    )
    stop = run["stop"]
    assert stop["status"] == STATUS_DIVERGED
    assert re.match(
        r"the integrator made no step in \d+ derivative evaluations at t = 0 s: a time "
        r"derivative is NaN or infinite at this state",
        stop["reason"],
    ), stop["reason"]
    # The last finished step's time and states, not a stage of the one that never ended.
    assert (stop["time"], stop["x"]) == (0.0, [1.0, 1.0])
    assert run["t"] == [0.0] and run["finite"]


def test_max_wall_time_stops_a_run_within_a_step():
    # Before: the wall-time budget was checked only after a step ended.
    run = _simulate_in_a_child("_SlowRates", duration=1.0, max_wall_time=0.5)
    stop = run["stop"]
    assert stop["status"] == STATUS_TIMEOUT
    assert re.match(
        r"wall time \S+ s exceeded max_wall_time = 0\.5 s at t = \S+ s, within a step",
        stop["reason"],
    ), stop["reason"]
    assert stop["wall_time"] < 5.0


def test_the_watchdog_raises_in_the_thread_it_watches_once_evaluations_pass_the_limit():
    import time

    from ofrl_drake.guard import IntegratorStalled, StallWatchdog

    class _Stuck:  # a guard whose monitor is never called, an integrator that keeps evaluating
        steps = 0
        max_wall_time = None
        evaluations = 0
        last_time = 2.5

        def get_num_derivative_evaluations(self):
            self.evaluations += 1000
            return self.evaluations

    stuck = _Stuck()
    watchdog = StallWatchdog(stuck, stuck, limit=10_000, period=0.01)
    start = time.monotonic()
    with pytest.raises(IntegratorStalled):
        with watchdog:
            while time.monotonic() - start < 30:  # lines of Python, as a block's calc runs
                time.sleep(0.001)
    assert time.monotonic() - start < 5
    status, reason = watchdog.fired
    assert status == STATUS_DIVERGED
    assert re.match(
        r"the integrator made no step in 1[01]\d{3} derivative evaluations at "
        r"t = 2\.5 s",
        reason,
    ), reason
    assert not watchdog._thread.is_alive()
