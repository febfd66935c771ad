"""Fault injection: bad outputs, signals, concurrent writers, hostile YAML, bad values.

Each case is a failure class found by trying the tool as a new user would
(issue 22): every one ends with one line, the documented exit code, the key or
path named, and nothing partial left behind.
"""

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump, yaml_load

from ofrl_drake.atomic import atomic_write_text, output_lock
from ofrl_drake.errors import OutputError
from tests.cli_helpers import (
    assert_one_line,
    run_cli,
    run_sweep_against_unreachable_scheduler,
)

from .conftest import PAPER_SCENARIO, ROOT

PENDULUM = ROOT / "diagrams" / "pendulum_upright.yaml"


def _short(tmp_path, source=PAPER_SCENARIO, **simulation):
    data = yaml_load(filename=str(source))
    data["simulation"].update({"duration": 1.0, **simulation})
    path = tmp_path / "short.yaml"
    path.write_text(yaml_dump(data))
    return path


# ------------------------------------------------------------------ outputs
def test_out_refuses_a_fifo_a_symlink_and_a_device(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    proc = run_cli("design-observer", PAPER_SCENARIO, "--out", fifo)
    assert_one_line(proc, 2, r"--out: .*pipe is not a regular file \(a device, FIFO or socket\)")
    assert fifo.is_fifo()  # untouched
    target = tmp_path / "real.json"
    target.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    proc = run_cli("design-observer", PAPER_SCENARIO, "--out", link)
    assert_one_line(proc, 2, r"--out: .*link\.json is a symbolic link")
    assert link.is_symlink() and target.read_text() == "{}"
    proc = run_cli("verify-observer", PAPER_SCENARIO, "--samples", 10, "--out", "/dev/null")
    assert_one_line(proc, 2, r"--out: /dev/null is not a regular file")
    assert not os.path.isfile("/dev/null")  # still the device
    os.symlink(tmp_path, tmp_path / "dir_link")
    proc = run_cli("run", PAPER_SCENARIO, "--out", tmp_path / "dir_link")
    assert_one_line(proc, 2, r"--out: .*dir_link is a symbolic link")


def test_out_refuses_the_empty_path_and_the_current_folder(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    proc = run_cli("run", PAPER_SCENARIO, "--out", "", cwd=tmp_path)
    assert_one_line(proc, 2, r"--out: the path is empty")
    proc = run_cli("run", PAPER_SCENARIO, "--out", ".", cwd=tmp_path)
    assert_one_line(proc, 2, r"--out: .* is the current folder or holds it")
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_a_full_disk_is_named_and_leaves_nothing(tmp_path, monkeypatch):
    real_fdopen = os.fdopen

    def full(fd, mode="r", *args, **kwargs):
        fh = real_fdopen(fd, mode, *args, **kwargs)

        class Full:
            def __enter__(self):
                return self

            def __exit__(self, *exc):
                fh.close()
                return False

            def write(self, data):
                raise OSError(errno.ENOSPC, "No space left on device")

        return Full()

    monkeypatch.setattr(os, "fdopen", full)
    with pytest.raises(OutputError, match=r"--out: no space left on device writing .*out\.json"):
        atomic_write_text(tmp_path / "out.json", "{}")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- signals
def test_sigterm_exits_143_with_nothing_partial(tmp_path):
    out = tmp_path / "o"
    long = _short(tmp_path, duration=3000.0)
    proc = subprocess.Popen(
        [sys.executable, "-m", "ofrl_drake", "run", str(long), "--out", str(out), "--quiet"],
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(8.0)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    assert stderr.strip().splitlines()[-1] == "error: terminated (SIGTERM); no output written"
    assert not out.exists()
    assert not list(tmp_path.glob(".o.partial-*"))


def test_a_partial_folder_of_a_dead_run_is_removed_by_the_next_run(tmp_path):
    out = tmp_path / "o"
    stale = tmp_path / ".o.partial-4194303.abc"  # above any pid: its process is gone
    stale.mkdir()
    (stale / "summary.json").write_text('{"status": "ok"}')
    proc = run_cli("run", _short(tmp_path), "--out", out, "--quiet", "--checkpoints", "0")
    assert proc.returncode == 0, proc.stderr
    assert not stale.exists()
    assert (out / "summary.json").is_file()


# ------------------------------------------------------------- concurrency
def test_a_second_writer_of_the_same_output_is_refused(tmp_path):
    out = tmp_path / "o"
    with output_lock(out):
        proc = run_cli("run", _short(tmp_path), "--out", out, "--quiet")
        assert_one_line(proc, 2, r"--out: another ofrl-drake command is writing .*o now")
        proc = run_cli("ablate", _short(tmp_path), "--workers", 0, "--out", out)
        assert_one_line(proc, 2, r"--out: another ofrl-drake command is writing")
    assert not out.exists()


# ------------------------------------------------------------ hostile YAML
def test_duplicate_keys_are_refused_with_both_lines(tmp_path):
    text = PAPER_SCENARIO.read_text().replace(
        "name: two_state_paper\n", "name: two_state_paper\nname: other\n", 1
    )
    path = tmp_path / "dup.yaml"
    path.write_text(text)
    proc = run_cli("run", path, "--out", tmp_path / "o")
    assert_one_line(proc, 2, r"key 'name' appears twice in one mapping \(lines \d+ and \d+\)")


def _alias_bomb(tmp_path):
    """A YAML file of nine nested aliases, 9^9 values once expanded ("billion laughs")."""
    rows = ['a: &a ["x","x","x","x","x","x","x","x","x"]']
    for prev, name in zip("abcdefgh", "bcdefghi", strict=True):
        rows.append(f"{name}: &{name} [{','.join([f'*{prev}'] * 9)}]")
    rows.append("name: *i")
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(rows) + "\n")
    return path


def test_an_alias_bomb_is_refused_at_once(tmp_path):
    path = _alias_bomb(tmp_path)
    proc = run_cli("run", path, "--out", tmp_path / "o")
    assert_one_line(proc, 2, r"expands to more than 100000 values")


def test_an_alias_bomb_is_refused_before_any_loader_expands_it(tmp_path, monkeypatch):
    # Expanding it took 123 s and 11.5 GB: the walk over the composed nodes
    # refuses it, and the expanding loaders (PyYAML's, Drake's) are never called.
    import ofrl_drake.scenario as scenario_module

    def expand(*args, **kwargs):
        raise AssertionError("an expanding YAML loader was called")

    monkeypatch.setattr(scenario_module, "_raw_yaml", expand)
    monkeypatch.setattr(scenario_module, "yaml_load_typed", expand)
    path = _alias_bomb(tmp_path)
    with pytest.raises(scenario_module.ScenarioError, match=r"expands to more than 100000 values"):
        scenario_module.load_scenario(path)


def test_a_long_list_without_aliases_is_named_by_its_line_not_blamed_on_aliases(tmp_path):
    from ofrl_drake import ScenarioError, load_scenario

    text = PAPER_SCENARIO.read_text()
    identity = ",".join(
        "[" + ",".join("1" if i == j else "0" for j in range(400)) + "]" for i in range(400)
    )
    text = re.sub(r"(?m)^  Gamma0: .*$", f"  Gamma0: [{identity}]", text, count=1)
    path = tmp_path / "gamma.yaml"
    path.write_text(text)  # 320 kB: under the size limit
    line = 1 + text.splitlines().index(next(x for x in text.splitlines() if "Gamma0: [[" in x))
    with pytest.raises(
        ScenarioError,
        match=rf"holds more than 100000 values.*the longest list \(400 entries\) starts at "
        rf"line {line}; shorten it",
    ):
        load_scenario(path)


def test_a_huge_file_is_refused_before_parsing(tmp_path):
    path = tmp_path / "huge.yaml"
    path.write_text("name: " + "x" * 2_000_000 + "\n")
    proc = run_cli("run", path, "--out", tmp_path / "o")
    assert_one_line(proc, 2, r"the file is 2\.0 MB; a scenario file is at most 1 MB")


# -------------------------------------------------------------- bad values
def test_an_input_bound_that_would_overflow_is_named(tmp_path):
    data = yaml_load(filename=str(PAPER_SCENARIO))
    data["input_bound"] = 1e308
    path = tmp_path / "huge_u.yaml"
    path.write_text(yaml_dump(data))
    proc = run_cli("design-observer", path, "--out", tmp_path / "d.json")
    assert_one_line(
        proc, 2, r"input_bound: 1e\+308 is beyond what the input sector .* at most 1e\+12"
    )


def test_a_log_period_beyond_the_horizon_is_refused(tmp_path):
    proc = run_cli("run", _short(tmp_path, log_period=5.0), "--out", tmp_path / "o")
    assert_one_line(proc, 2, r"simulation\.log_period: 5\.0 s is longer than the horizon")


def test_cenic_is_not_offered(tmp_path):
    proc = run_cli("run", _short(tmp_path, integrator="cenic"), "--out", tmp_path / "o")
    assert_one_line(proc, 2, r"simulation\.integrator: unknown scheme 'cenic'; choose one of \[")
    assert "'cenic'" not in proc.stderr.split("choose one of")[1]


# --------------------------------------------------------------- regulated
def test_summary_says_whether_the_run_regulated_and_run_warns_when_not(tmp_path):
    out = tmp_path / "short"
    proc = run_cli("run", _short(tmp_path, source=PENDULUM, duration=0.3), "--out", out, "--quiet")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "ok" and summary["regulated"] is False
    details = summary["regulation"]
    assert details["tolerance"] == pytest.approx([0.03, 0.15])  # 5% of half-widths 0.6, 3
    assert details["final_error"][0] > 0.03 or details["final_error"][1] > 0.15
    assert "warning: the run did not regulate: |x_" in proc.stderr
    assert "simulation.regulation_tolerance" in proc.stderr
    full = tmp_path / "full"
    proc = run_cli("run", PENDULUM, "--out", full, "--quiet", "--checkpoints", "0")
    summary = json.loads((full / "summary.json").read_text())
    assert summary["regulated"] is True and "did not regulate" not in proc.stderr
    assert np.all(np.asarray(summary["regulation"]["final_error"]) < 1e-6)


# ------------------------------------------------------------------ resume
def test_resume_retry_failed_reruns_failed_rows_and_a_missing_plan_is_explained(tmp_path):
    from ofrl_drake.ablation import CSV_COLUMNS, read_rows

    scenario = _short(tmp_path)
    variants = tmp_path / "variants.yaml"
    variants.write_text("baseline: {}\n")
    out = tmp_path / "sweep"
    args = ["ablate", scenario, "--variants", variants, "--workers", 0, "--out", out]
    assert run_cli(*args).returncode == 0
    table = out / "ablation.csv"
    (row,) = read_rows(table)
    assert row["status"] == "ok" and row["regulated"] in ("true", "false")
    failed = table.read_text().replace(",ok\n", ",timeout: injected\n")
    table.write_text(failed)
    proc = run_cli(*args, "--resume")
    assert proc.returncode == 0 and read_rows(table)[0]["status"].startswith("timeout")
    proc = run_cli(*args, "--resume", "--retry-failed")
    assert proc.returncode == 0, proc.stderr
    rows = read_rows(table)
    assert len(rows) == 1 and rows[0]["status"] == "ok"
    assert tuple(table.read_text().splitlines()[0].split(",")) == CSV_COLUMNS
    proc = run_cli(*args[:-2], "--out", out, "--retry-failed")
    assert_one_line(proc, 2, r"--retry-failed: reruns failed rows of a sweep; pass --resume too")
    (out / "ablation.json").unlink()
    proc = run_cli(*args, "--resume")
    assert_one_line(
        proc, 2, r"ablation\.json is missing; it records the sweep .* Restore it, or move"
    )


# ------------------------------------------------------------------- sizes
@pytest.mark.parametrize(
    ("points", "message"),
    [
        (
            {"kind": "uniform", "number": 10**12},
            r"points\.number: 1e\+12 points would need about .* GiB .* at most about \d+ points",
        ),
        (
            {"kind": "grid", "counts": [10**6, 10**6]},
            r"points\.counts: 1e\+12 points would need about",
        ),
        ({"seed": -5}, r"points\.seed: must be an integer >= 0; got -5"),
    ],
)
def test_point_sets_are_checked_before_any_allocation(tmp_path, points, message):
    data = yaml_load(filename=str(PAPER_SCENARIO))
    data["points"].update(points)
    path = tmp_path / "big.yaml"
    path.write_text(yaml_dump(data))
    proc = run_cli("run", path, "--out", tmp_path / "o")
    assert_one_line(proc, 2, message)
    # The refusal is the scenario's validation: loading builds no point.
    from ofrl_drake import ScenarioError, load_scenario

    with pytest.raises(ScenarioError, match=message):
        load_scenario(path)


def test_a_long_name_and_too_many_samples_are_refused(tmp_path):
    data = yaml_load(filename=str(PAPER_SCENARIO))
    data["name"] = "n" * 20_000
    path = tmp_path / "long.yaml"
    path.write_text(yaml_dump(data))
    assert_one_line(run_cli("run", path, "--out", tmp_path / "o"), 2, r"name: 20000 characters")
    proc = run_cli("verify-observer", PAPER_SCENARIO, "--samples", 10**9)
    assert_one_line(proc, 2, r"samples: 1000000000 would need about .* GiB .* at most 10000000")


# --------------------------------------------------------------- sweeps
def test_a_cut_short_plan_and_a_failing_table_write_are_named(tmp_path, monkeypatch):
    from ofrl_drake.errors import OfrlError
    from ofrl_drake.sweep_store import RowWriter

    scenario = _short(tmp_path)
    variants = tmp_path / "variants.yaml"
    variants.write_text("baseline: {}\n")
    out = tmp_path / "sweep"
    args = ["ablate", scenario, "--variants", variants, "--workers", 0, "--out", out]
    assert run_cli(*args).returncode == 0
    plan = out / "ablation.json"
    plan.write_text(plan.read_text()[:40])
    assert_one_line(
        run_cli(*args, "--resume"), 2, r"ablation\.json is not valid JSON \(cut short\?\)"
    )
    writer = RowWriter(tmp_path / "t.csv", ("a",), ())
    writer._fh.close()
    writer._fh = open("/dev/full", "w")  # every write: no space left on device
    with pytest.raises(OfrlError, match=r"no space left on device writing .*t\.csv; the rows"):
        writer.write({"a": 1.0})


def test_a_scheduler_without_workers_is_waited_for_a_stated_time(tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, dashboard_address=None, processes=True) as cluster:
        # No clock in the assert (a slow machine is not a failure): the message states
        # the 3 s waited, and the subprocess timeout, far above any honest run, turns a
        # wait that never ends into a failure (subprocess.TimeoutExpired).
        proc = run_cli(
            "ablate",
            _short(tmp_path),
            "--out",
            tmp_path / "o",
            "--scheduler",
            cluster.scheduler_address,
            "--scheduler-timeout",
            3,
            timeout=600,
        )
        assert_one_line(proc, 2, r"--scheduler: no worker joined tcp://.* within 3 s; start one")


# ------------------------------------------------------------ first run
def test_the_first_runs_warnings_point_to_the_docs(tmp_path):
    proc = run_cli("run", _short(tmp_path), "--out", tmp_path / "o", "--quiet", "--checkpoints", 0)
    assert proc.returncode == 0, proc.stderr
    assert "falsified: r = +" in proc.stdout
    assert "What the observer certificate does, and does not, prove" in proc.stdout
    assert "left the certified region" in proc.stderr and "docs/theory.md" in proc.stderr
    assert "s in all" in proc.stdout  # the command's own wall time


# -------------------------------------------------------------- bounds
def test_bad_jacobian_bounds_name_the_entry_and_the_cause():
    """One message used to cover three causes; now each is named with its entry."""
    from ofrl_drake.lmi import LmiError, box_corners

    with pytest.raises(
        LmiError, match=r"entry \[1, 0\]: lower = nan, upper = 1; a bound is NaN: f"
    ):
        box_corners([[0.0, 0.0], [np.nan, 0.0]], [[1.0, 0.0], [1.0, 0.0]])
    with pytest.raises(
        LmiError, match=r"entry \[0, 1\]: lower = -inf, upper = inf; a bound is inf"
    ):
        box_corners([[0.0, -np.inf]], [[1.0, np.inf]])
    with pytest.raises(
        LmiError, match=r"entry \[0\]: lower = 2, upper = 1; the lower bound exceeds"
    ):
        box_corners([2.0], [1.0])


# ------------------------------------------------------------ user code
USER_PLANT = """
import numpy as np
from ofrl_drake import ControlAffineSystem


def f(x):
    if np.any(np.asarray(x[0], dtype=float) > 0.9):
        raise ZeroDivisionError("my model breaks beyond 0.9")
    return np.array([-x[0] + x[1], -x[0] - 0.5 * x[1]])


def g(x):
    return np.array([[0 * x[0]], [1 + 0 * x[0]]])


def make_plant():
    return ControlAffineSystem(f, g, C=[[0.0, 1.0]], name="my_plant")
"""


def _user_plant_scenario(tmp_path, module, source):
    """A 1 s paper scenario whose system is ``module.make_plant`` written from ``source``.

    The true state is fed back: the user's f need not trace, so no observer is designed.
    """
    (tmp_path / f"{module}.py").write_text(source)
    data = yaml_load(filename=str(PAPER_SCENARIO))
    data.update(
        system=f"{module}:make_plant",
        x0=[1.0, 0.0],
        xhat0=[1.0, 0.0],
        variant={"observer": "true_state"},
    )
    data["simulation"]["duration"] = 1.0
    path = tmp_path / "s.yaml"
    path.write_text(yaml_dump(data))
    return path


def test_an_error_inside_the_users_f_names_the_users_file_not_ofrl_drake(tmp_path):
    path = _user_plant_scenario(tmp_path, "my_plant", USER_PLANT)
    proc = run_cli("run", path, "--out", tmp_path / "o", "--checkpoints", 0)
    assert_one_line(
        proc,
        2,
        r"your code raised ZeroDivisionError: my model breaks beyond 0\.9 \(at .*my_plant\.py:8, "
        r"in f\); fix it there",
    )
    assert not (tmp_path / "o").exists()


LOG_PLANT = """
import numpy as np
from ofrl_drake import ControlAffineSystem


def f(x):
    return np.array([x[1], -x[0] + np.log(x[0] + 0.2)])  # undefined for x_1 <= -0.2


def g(x):
    return np.array([[0 * x[0]], [1 + 0 * x[0]]])


def make_plant():
    return ControlAffineSystem(f, g, C=[[0.0, 1.0]], name="log_plant")
"""


def test_a_users_f_that_leaves_its_domain_stops_the_run_and_says_so(tmp_path):
    # log of a negative number inside a traced f is raised by Drake's symbolic math mid-run:
    # the run stops as diverged (exit 3) naming the model and the cause, not as an internal
    # error. The extrapolation points stay inside the domain (points where f is not finite
    # are refused when the loop is built); the state, moving left at 2 /s, leaves it.
    path = _user_plant_scenario(tmp_path, "log_plant", LOG_PLANT)
    data = yaml_load(filename=str(path))
    data.update(x0=[0.0, -2.0], xhat0=[0.0, -2.0])
    data["points"].update(lower=[-0.15, -1.0], upper=[1.0, 1.0])
    path.write_text(yaml_dump(data))
    proc = run_cli("run", path, "--out", tmp_path / "o", "--checkpoints", 0)
    assert proc.returncode == 3, proc.stderr
    assert "internal error" not in proc.stderr
    assert re.search(
        r"stopped: diverged: the model's f or g was evaluated outside its domain \(log\(-?[0-9.e-]+"
        r"\) : numerical argument out of domain.*for the model 'log_plant'",
        proc.stderr,
    ), proc.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["status"] == "diverged"
    assert "outside its domain" in summary["stop"]["reason"]


def test_a_users_f_that_is_not_finite_at_the_extrapolation_points_is_refused_at_build(tmp_path):
    # Before: the critic's sums went NaN at the 40 points with x_1 <= -0.2 and the run ended
    # with a domain error that said nothing of the points.
    path = _user_plant_scenario(tmp_path, "log_plant", LOG_PLANT)
    proc = run_cli("run", path, "--out", tmp_path / "o", "--checkpoints", 0)
    assert_one_line(
        proc,
        2,
        r"the model's f is not finite at extrapolation point 0 x = \[-1\.0, -1\.0\] .*"
        r"40 of 100 points\) for the model 'log_plant'.*shrink the extrapolation points",
    )
    assert not (tmp_path / "o").exists()


def test_simulate_takes_a_path_and_names_a_wrong_type():
    import ofrl_drake as od

    with pytest.raises(TypeError, match=r"scenario must be a Scenario or the path .*got int"):
        od.simulate(42)
    with pytest.raises(od.ScenarioError, match=r"no_such_scenario\.yaml"):
        od.simulate("no_such_scenario.yaml")
    result = od.simulate(str(PAPER_SCENARIO))  # a path is loaded, as by the CLI
    assert result.scenario_name == od.load_scenario(PAPER_SCENARIO).name


# ------------------------------------------------------- argument checks
@pytest.mark.parametrize(
    ("command", "value"),
    [("ablate", "0"), ("ablate", "nan"), ("ablate", "-5"), ("ablate", "inf"), ("montecarlo", "0")],
)
def test_a_scheduler_timeout_that_never_expires_is_refused_before_connecting(
    tmp_path, command, value
):
    # Dask waits forever for timeout=0 and never times out on NaN: refused while parsing,
    # so no scheduler is contacted (nothing listens on port 1).
    proc = run_sweep_against_unreachable_scheduler(
        command, PAPER_SCENARIO, tmp_path / "o", value, timeout=120
    )
    assert_one_line(
        proc,
        2,
        rf"^error: argument --scheduler-timeout: must be a finite number of seconds > 0 .*"
        rf"e\.g\. 60; got '{re.escape(value)}'; see ofrl-drake {command} --help$",
    )
    assert list(tmp_path.iterdir()) == []


def test_ablate_refuses_a_negative_seed_as_montecarlo_does(tmp_path):
    proc = run_cli(
        "ablate",
        PAPER_SCENARIO,
        "--seed",
        -1,
        "--initial-states",
        1,
        "--workers",
        0,
        "--out",
        tmp_path / "o",
    )
    assert_one_line(proc, 2, r"^error: seed \(--seed\) must be an integer >= 0; got -1\.$")
    assert list(tmp_path.iterdir()) == []
    from ofrl_drake import load_scenario
    from ofrl_drake.ablation_grid import AblationError, sample_initial_states

    with pytest.raises(AblationError, match=r"^seed \(--seed\) must be an integer >= 0; got -1\."):
        sample_initial_states(load_scenario(PAPER_SCENARIO), 0, -1)


def _raised_below_the_caller(call, *args):
    """The exception ``call(*args)`` raises, its traceback starting below this frame.

    As in ``main``, whose own frame (in ofrl_drake) is never the user's.
    """
    try:
        call(*args)
    except Exception as err:
        return err.with_traceback(err.__traceback__.tb_next)
    raise AssertionError("nothing was raised")


def test_a_frame_of_compiled_library_code_is_not_the_users(tmp_path, monkeypatch):
    from ofrl_drake.cli import _user_code_frame

    # numpy's Cython frames name numpy/random/bit_generator.pyx, a path relative to the
    # build: resolved against the current folder it looked like the user's own file.
    monkeypatch.chdir(tmp_path)
    err = _raised_below_the_caller(np.random.default_rng, -1)
    assert isinstance(err, ValueError)
    assert _user_code_frame(err) is None
    # Even if such a relative file happens to exist below the current folder.
    (tmp_path / "numpy" / "random").mkdir(parents=True)
    (tmp_path / "numpy" / "random" / "bit_generator.pyx").write_text("")
    assert _user_code_frame(err) is None
    # A real file of the user's is still named, at its innermost frame.
    import importlib.util

    source = tmp_path / "users_module.py"
    source.write_text("def boom():\n    raise ZeroDivisionError('mine')\n")
    spec = importlib.util.spec_from_file_location("users_module", source)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    frame = _user_code_frame(_raised_below_the_caller(module.boom))
    assert frame is not None
    assert (frame.filename, frame.lineno, frame.name) == (str(source), 2, "boom")


@pytest.mark.parametrize(("command", "extra"), [("ablate", ()), ("montecarlo", ("--runs", 1))])
@pytest.mark.parametrize("out", [".", ".."])
def test_sweeps_refuse_the_current_folder_as_run_does(tmp_path, command, extra, out):
    work = tmp_path / "work"
    work.mkdir()
    proc = run_cli(command, PAPER_SCENARIO, *extra, "--workers", 0, "--out", out, cwd=work)
    assert_one_line(proc, 2, r"^error: --out: .* is the current folder or holds it; name an output")
    assert list(work.iterdir()) == []
    assert list(tmp_path.iterdir()) == [work]


@pytest.mark.parametrize(
    "args",
    [
        ("run", PAPER_SCENARIO, "--out", "r1", "--checkpoints", "x"),
        ("run", PAPER_SCENARIO),
    ],
    ids=["bad-int", "missing-out"],
)
def test_argument_errors_are_one_line_naming_the_help(tmp_path, args):
    proc = run_cli(*args, cwd=tmp_path, timeout=120)
    assert_one_line(
        proc,
        2,
        r"^error: (argument --checkpoints: invalid int value: 'x'|"
        r"the following arguments are required: --out); see ofrl-drake run --help$",
    )
    assert "usage:" not in proc.stderr and proc.stdout == ""
    assert list(tmp_path.iterdir()) == []


def test_help_and_a_missing_command_still_work():
    for args in (("--help",), ("run", "--help")):
        proc = run_cli(*args, timeout=120)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.startswith("usage: ofrl-drake") and proc.stderr == ""
    proc = run_cli(timeout=120)
    assert_one_line(
        proc, 2, r"^error: the following arguments are required: command; see ofrl-drake"
    )
    proc = run_cli("nope", timeout=120)
    assert_one_line(proc, 2, r"^error: argument command: invalid choice: 'nope' .*; see ofrl-drake")
