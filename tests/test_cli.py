"""The ofrl-drake command line: outputs, exit codes, and no partial files."""

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import types

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump, yaml_load

from tests.cli_helpers import (
    assert_one_line,
    run_cli,
    run_sweep_against_unreachable_scheduler,
)

from .conftest import PAPER_SCENARIO


def _short_scenario(tmp_path, duration=2.0, **edits):
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    data["simulation"]["duration"] = duration
    for key, value in edits.items():
        data[key] = value
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml_dump(data))
    return path


def test_run_writes_every_output(tmp_path):
    out = tmp_path / "out"
    proc = run_cli("run", _short_scenario(tmp_path), "--out", out)
    assert proc.returncode == 0, proc.stderr
    data = np.load(out / "trajectories.npz")
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
    np.testing.assert_array_equal(data["W_policy"], data["W"])  # the paper's law: W_pi = W
    summary = json.loads((out / "summary.json").read_text())
    assert summary["final_time"] == pytest.approx(2.0)
    figures = {p.name for p in (out / "figures").iterdir()}
    for name in (
        "state_1.png",
        "state_2.png",
        "estimation_error.png",
        "critic_weights.png",
        "control_input.png",
        "learning_condition.png",
        "learning_curve.png",
        "learning_health.png",
    ):
        assert name in figures
    # The learning curve: 11 checkpoints 0, T/10, ..., T, each evaluated with the true state.
    curve = summary["learning_curve"]
    assert [e["t"] for e in curve] == pytest.approx(np.linspace(0.0, 2.0, 11), abs=1e-9)
    assert all(e["status"] == "ok" and e["policy_cost"] > 0 for e in curve)
    health = summary["learning_health"]
    assert health["policy_updates_accepted"] == health["policy_updates_rejected"] == 0
    assert health["min_learning_condition"] == pytest.approx(
        float(np.min(data["learning_condition"])), rel=1e-12
    )
    series = np.load(out / "learning_health.npz")
    assert {"t", "learning_condition", "gamma_norm", "gamma_condition"} <= set(series.files)
    assert series["value_eigenvalues"].shape == (data["t"].size, 2)
    assert series["spectral_abscissa"].shape == data["t"].shape
    from matplotlib.image import imread

    height = imread(out / "figures" / "state_1.png").shape[0]
    assert height >= 3.4 * 150  # figure height in inches times at least 150 dpi
    if shutil.which("dot"):
        assert (out / "diagram.svg").read_text().lstrip().startswith(("<?xml", "<svg"))
    else:
        assert (out / "diagram.dot").is_file()
        assert "diagram.dot" in proc.stdout
    design = json.loads((out / "observer_design.json").read_text())
    assert {"P", "L", "H", "K", "certificate"} <= set(design)
    # The paper design is shown falsified, in both files and on stdout.
    assert design["verification"]["falsified"] is True
    assert summary["observer_design"]["verification"] == design["verification"]
    assert "observer: claims alpha = 2 (r <= -4); falsified: r = +" in proc.stdout
    assert not list(tmp_path.glob(".out.*"))  # no temporary folder left behind


def test_bad_scenario_exits_2_with_one_line_and_no_output(tmp_path):
    out = tmp_path / "out"
    proc = run_cli("run", _short_scenario(tmp_path, input_bound=-3.0), "--out", out)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "input_bound: must be > 0; got -3.0" in lines[0]
    assert "Traceback" not in proc.stderr
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [tmp_path / "scenario.yaml"]


def test_missing_scenario_exits_2(tmp_path):
    proc = run_cli("run", tmp_path / "nope.yaml", "--out", tmp_path / "out")
    assert proc.returncode == 2
    assert "no such scenario file" in proc.stderr
    assert not (tmp_path / "out").exists()


def _scenario_with(tmp_path, **observer):
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    data["observer"].update(observer)
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml_dump(data))
    return path


def test_design_observer_writes_the_certificate(tmp_path):
    out = tmp_path / "design.json"
    proc = run_cli("design-observer", PAPER_SCENARIO, "--out", out)
    assert proc.returncode == 0, proc.stderr
    design = json.loads(out.read_text())
    for key in (
        "P",
        "L",
        "H",
        "K",
        "alpha",
        "input_bound",
        "box",
        "jacobian_bounds",
        "certificate",
        "solver",
        "solve_time",
    ):
        assert key in design, key
    assert set(design["box"]) >= {"lower", "upper"}
    assert set(design["jacobian_bounds"]) >= {"Mf1", "Mf2", "Mg1", "Mg2"}
    assert [c["input"] for c in design["certificate"]] == [[-3.0], [0.0], [3.0]]
    assert all(c["max_eigenvalue"] < 0 for c in design["certificate"])
    # The certificate re-checks in numpy from the numbers in the file alone.
    from ofrl_drake.lmi import certificate

    arrays = {k: np.asarray(design[k]) for k in ("P", "L", "H", "K")}
    bounds = {k: np.asarray(v) for k, v in design["jacobian_bounds"].items()}
    recheck = certificate(
        arrays["P"],
        arrays["L"],
        arrays["H"],
        arrays["K"],
        np.array([[0.0, 1.0]]),
        bounds,
        design["input_bound"],
        design["alpha"],
        sector="sign_correct",
    )
    np.testing.assert_allclose(
        [v for _, v in recheck],
        [c["max_eigenvalue"] for c in design["certificate"]],
        rtol=1e-6,
        atol=1e-9,
    )


def test_infeasible_design_exits_2_with_one_line(tmp_path):
    out = tmp_path / "design.json"
    proc = run_cli("design-observer", _scenario_with(tmp_path, alpha=500.0), "--out", out)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "alpha" in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scenario.yaml"]


def test_solver_info_lines_stay_off_stderr(tmp_path):
    # SCS stops inaccurate on the paper's LMI, which pydrake logs at INFO
    # ("SCS returns code 2"); the command's own error is the only line.
    out = tmp_path / "design.json"
    proc = run_cli("design-observer", _scenario_with(tmp_path, solver="scs"), "--out", out)
    assert proc.returncode == 2
    assert "INFO" not in proc.stderr and "drake" not in proc.stderr.split(":")[0]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "SCS: solved inaccurate" in lines[0], proc.stderr


def test_run_refuses_to_replace_a_folder_it_did_not_write(tmp_path):
    out = tmp_path / "precious"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    proc = run_cli("run", _short_scenario(tmp_path, duration=0.5), "--out", out)
    assert proc.returncode == 2
    assert "is not empty and was not written by ofrl-drake run" in proc.stderr
    assert (out / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["precious", "scenario.yaml"]


def test_run_replaces_its_own_earlier_output(tmp_path):
    out = tmp_path / "out"
    scenario = _short_scenario(tmp_path, duration=0.5)
    assert run_cli("run", scenario, "--out", out).returncode == 0
    (out / "stale.txt").write_text("from an older run")
    proc = run_cli("run", scenario, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert not (out / "stale.txt").exists() and (out / "summary.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "scenario.yaml"]


def test_run_without_a_certified_box_says_what_was_checked(tmp_path):
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    variant = dict(data.get("variant") or {})
    variant["observer"] = "true_state"
    proc = run_cli(
        "run", _short_scenario(tmp_path, duration=0.2, variant=variant), "--out", tmp_path / "o"
    )
    assert proc.returncode == 0, proc.stderr
    assert (
        "note: no observer design (observer block FullStateObserver): box checks not "
        "applicable; only |u_k| <= lambda_bar was checked." in proc.stderr
    )
    validity = json.loads((tmp_path / "o" / "summary.json").read_text())["validity"]
    assert validity["box_check"] == "not_applicable" and validity["box_checked"] is False


def test_bad_out_paths_exit_2_with_one_line(tmp_path):
    (tmp_path / "afile").write_text("x")
    proc = run_cli("run", PAPER_SCENARIO, "--out", tmp_path / "afile" / "sub")
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "afile is a file, so" in proc.stderr
    proc = run_cli("design-observer", PAPER_SCENARIO, "--out", tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "is a folder; name a file inside it" in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_run_without_dot_writes_the_source_and_says_so(tmp_path):
    """CI installs graphviz; this hides it to exercise the fallback."""
    empty_bin = tmp_path / "bin"
    empty_bin.mkdir()
    out = tmp_path / "o"
    proc = subprocess.run(
        [sys.executable, "-m", "ofrl_drake", "run", _short_scenario(tmp_path, 0.2), "--out", out],
        capture_output=True,
        text=True,
        timeout=900,
        env={**os.environ, "PATH": str(empty_bin)},
    )
    assert proc.returncode == 0, proc.stderr
    assert not (out / "diagram.svg").exists()
    assert (out / "diagram.dot").read_text().lstrip().startswith("digraph")
    assert [line for line in proc.stdout.splitlines() if "diagram.dot" in line], proc.stdout


# ------------------------------------------------ exit codes, provenance
def test_version_prints_the_package_version_without_loading_drake():
    from ofrl_drake import __version__

    proc = run_cli("--version")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"ofrl-drake {__version__}"
    # The command starts without Drake, so a SIGINT during its imports is handled.
    probe = subprocess.run(
        [sys.executable, "-c", "import sys, ofrl_drake.cli; print('pydrake' in sys.modules)"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert probe.stdout.strip() == "False", probe.stderr


def _cannot_write_in(folder):
    """True if ``folder`` exists and refuses a new entry (sysfs does, even to root)."""
    if not os.path.isdir(folder):
        return False
    try:
        os.rmdir(tempfile.mkdtemp(dir=folder))
    except OSError:
        return True
    return False


@pytest.mark.skipif(not _cannot_write_in("/sys"), reason="needs a folder nobody can write into")
def test_unwritable_out_parents_exit_2_with_one_line(tmp_path):
    target = "/sys/ofrl_drake_test_out/sub"  # sysfs refuses new entries, even to root
    for command in ("run", "design-observer"):
        proc = run_cli(command, PAPER_SCENARIO, "--out", target)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.count("\n") == 1, proc.stderr
        assert proc.stderr.startswith("error: --out: cannot write in /sys"), proc.stderr
        assert "choose a folder you can write to" in proc.stderr


def test_malformed_scheduler_address_exits_2_with_one_line(tmp_path):
    proc = run_cli("ablate", PAPER_SCENARIO, "--out", tmp_path / "o", "--scheduler", "notanaddress")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith("error: --scheduler: 'notanaddress' is not a scheduler address")
    assert not (tmp_path / "o").exists()


def test_resume_with_another_seed_exits_2_naming_it(tmp_path):
    from ofrl_drake.ablation import CSV_COLUMNS

    out = tmp_path / "o"
    out.mkdir()
    (out / "ablation.json").write_text(json.dumps({"seed": 0}) + "\n")
    (out / "ablation.csv").write_text(",".join(CSV_COLUMNS) + "\n")
    args = ["ablate", PAPER_SCENARIO, "--out", out, "--workers", "0", "--resume"]
    proc = run_cli(*args, "--seed", "1")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert "--resume: the folder's sweep used --seed 0, this one --seed 1" in proc.stderr


def _maps_drake(pid):
    """True once process ``pid`` has mapped Drake's library (it is importing pydrake)."""
    try:
        with open(f"/proc/{pid}/maps") as fh:
            return "libdrake" in fh.read()
    except OSError:
        return False


def _interrupt(args, *, when):
    """Start ``python -m ofrl_drake ARGS``, send SIGINT once ``when(pid)`` holds."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ofrl_drake", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    while proc.poll() is None and not when(proc.pid):
        time.sleep(0.005)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    return proc.returncode, out, err


def _terminal_lines(raw):
    """The lines a terminal shows for the bytes ``raw`` written to it.

    A carriage return moves back to the start of the line, where the text after it
    overwrites what was there (a progress bar redrawn in place); empty lines are left out.
    """
    lines = []
    for line in raw.decode(errors="replace").replace("\r\n", "\n").split("\n"):
        screen = ""
        for part in line.split("\r"):
            screen = part + screen[len(part) :]
        if screen.strip():
            lines.append(screen.rstrip())
    return lines


def _interrupt_on_a_terminal(args, *, when):
    """Run ``python -m ofrl_drake ARGS`` with stderr on a terminal (a pty), as a user does.

    SIGINT is sent once ``when(text)`` holds for what the command wrote on the terminal so
    far: an event the command shows (its progress bar), not a time. Returns the exit code
    and the lines the terminal shows.
    """
    import pty
    import select

    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "ofrl_drake", *map(str, args)],
        stdout=subprocess.DEVNULL,
        stderr=slave,
    )
    os.close(slave)
    raw, sent = b"", False
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 1.0)
            if not ready:
                if proc.poll() is not None:
                    break
                continue
            try:
                chunk = os.read(master, 65536)
            except OSError:  # EIO: the command closed the terminal (it exited)
                break
            if not chunk:
                break
            raw += chunk
            if not sent and when(raw.decode(errors="replace")):
                proc.send_signal(signal.SIGINT)
                sent = True
        proc.wait(timeout=300)
    finally:
        os.close(master)
        if proc.poll() is None:
            proc.kill()
    assert sent, f"the event never came: {raw!r}"
    return proc.returncode, _terminal_lines(raw)


def _simulating(text):
    """True once the run's progress bar shows 1 % to 99 %: the simulation is under way."""
    return re.search(r"\]\s+([1-9]\d?)%", text) is not None


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc to see the imports")
@pytest.mark.parametrize("moment", ["importing Drake", "simulating"])
def test_sigint_at_any_moment_exits_130_with_one_line(tmp_path, moment):
    """SIGINT as soon as the process maps Drake (mid-import), or mid-simulation.

    Mid-simulation is when the progress bar, on a terminal as a user sees it, has
    reached 1 % of a 3000 s run (which takes seconds): the signal used to be sent 6 s
    after the start, which a fast machine could outrun. On the terminal, the error line
    replaces the bar cut short instead of running on from it (``0.3 serror: ...``).

    A SIGINT before Python itself has started (its ``site`` imports, before any
    of ofrl_drake runs) gets Python's own traceback; nothing here can catch it.
    """
    out = tmp_path / "o"
    scenario = _short_scenario(tmp_path, duration=3000.0)
    if moment == "importing Drake":
        code, _, err = _interrupt(["run", scenario, "--out", out, "--quiet"], when=_maps_drake)
        assert code == 130, err
        assert err.count("\n") == 1, err
        assert err.startswith("error: interrupted"), err
    else:
        code, lines = _interrupt_on_a_terminal(["run", scenario, "--out", out], when=_simulating)
        assert code == 130, lines
        assert lines == ["error: interrupted; no output written"], lines
    assert not out.exists()


def test_run_scenario_yaml_reproduces_the_run_bit_for_bit(tmp_path):
    first = tmp_path / "first"
    proc = run_cli("run", _short_scenario(tmp_path), "--out", first, "--quiet")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((first / "summary.json").read_text())
    assert summary["status"] == "ok"
    origin = summary["provenance"]
    assert set(origin["versions"]) == {"ofrl_drake", "drake", "numpy", "scipy", "python"}
    assert origin["versions"]["numpy"] == np.__version__
    assert " -m ofrl_drake run " in origin["command_line"]
    assert origin["started"].endswith("+00:00")
    again = tmp_path / "again"
    proc = run_cli("run", first / "scenario.yaml", "--out", again, "--quiet")
    assert proc.returncode == 0, proc.stderr
    with np.load(first / "trajectories.npz") as a, np.load(again / "trajectories.npz") as b:
        assert a.files == b.files
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert (again / "scenario.yaml").read_text() == (first / "scenario.yaml").read_text()


# ------------------------------------------------------------ bounded inputs
HUGE_COUNTS = [
    ("run", "--checkpoints", "MAX_CHECKPOINTS", ()),
    ("ablate", "--initial-states", "MAX_INITIAL_STATES", ("--workers", "0")),
    ("montecarlo", "--runs", "MAX_RUNS", ("--workers", "0")),
]


def test_the_python_functions_refuse_the_same_huge_counts(paper_scenario):
    # The limits were the command line's alone: montecarlo(scenario, 10**9) from Python
    # ran out of memory, sample_initial_states(scenario, 10**9, 0) took 16 GB.
    from ofrl_drake.ablation_grid import AblationError, sample_initial_states
    from ofrl_drake.errors import ScenarioError
    from ofrl_drake.learning_curve import learning_curve, learning_report
    from ofrl_drake.limits import MAX_CHECKPOINTS, MAX_INITIAL_STATES, MAX_RUNS
    from ofrl_drake.monte_carlo import MonteCarloError, montecarlo

    huge = 10**9
    with pytest.raises(
        AblationError,
        match=rf"^count \(--initial-states\): 1000000000 is more than the limit of "
        rf"{MAX_INITIAL_STATES}; split the sweep into several --out folders with other --seed "
        r"values\.$",
    ):
        sample_initial_states(paper_scenario, huge, 0)
    assert sample_initial_states(paper_scenario, MAX_INITIAL_STATES, 0).shape == (10_001, 2)
    with pytest.raises(
        MonteCarloError,
        match=rf"^runs \(--runs\): 1000000000 is more than the limit of {MAX_RUNS}; split the "
        r"sweep into several --out folders",
    ):
        montecarlo(paper_scenario, huge)
    for function, name in (
        (learning_curve, "learning_curve"),
        (learning_report, "learning_report"),
    ):
        with pytest.raises(
            ScenarioError,
            match=rf"^{name}: checkpoints .*: 1000000000 is more than the limit of "
            rf"{MAX_CHECKPOINTS}; a learning curve needs far fewer checkpoints \(default 10\)\.$",
        ):
            function(None, None, checkpoints=huge)


@pytest.mark.parametrize(
    ("command", "option", "limit", "extra"), HUGE_COUNTS, ids=[c for c, *_ in HUGE_COUNTS]
)
def test_a_huge_count_is_refused_while_parsing_naming_the_limit(
    tmp_path, capsys, command, option, limit, extra
):
    # A billion checkpoints, initial states or runs took gigabytes (or a MemoryError, with a
    # folder holding only montecarlo.json) before anything was written.
    from ofrl_drake import cli, limits

    most = getattr(limits, limit)
    assert getattr(cli, limit) == most  # the command line refuses what the library does
    assert 1000 <= most < 1_000_000_000
    out = tmp_path / "o"
    args = [command, str(PAPER_SCENARIO), *extra, "--out", str(out)]
    huge = [*args, option, "1000000000"]
    pattern = (
        rf"^error: argument {option}: 1000000000 is more than the limit of {most}; .+; "
        rf"see ofrl-drake {command} --help$"
    )
    with pytest.raises(SystemExit) as stop:
        cli._parser().parse_args(huge)
    assert stop.value.code == 2
    assert re.match(pattern, capsys.readouterr().err.strip())
    # The limit itself parses (and so does an ordinary count).
    dest = option.lstrip("-").replace("-", "_")
    assert getattr(cli._parser().parse_args([*args, option, str(most)]), dest) == most
    assert getattr(cli._parser().parse_args([*args, option, "3"]), dest) == 3
    # As a user runs it: one line, exit 2, nothing written.
    proc = run_cli(*huge, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert re.match(pattern, proc.stderr.strip()), proc.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["ablate", "montecarlo"])
def test_an_unreachable_scheduler_is_given_up_after_scheduler_timeout(tmp_path, command):
    # The connection used to wait a fixed 30 s whatever --scheduler-timeout said.
    proc = run_sweep_against_unreachable_scheduler(
        command, PAPER_SCENARIO, tmp_path / "o", "0.5", timeout=300
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert re.match(
        r"^error: --scheduler: cannot connect to tcp://127\.0\.0\.1:1 within "
        r"--scheduler-timeout 0\.5 s \(.*after 0\.5 s\); start a dask scheduler there",
        proc.stderr,
    ), proc.stderr
    assert list(tmp_path.iterdir()) == []


def _no_optimal(monkeypatch):
    """J* is not solved in this test: every ``optimal_control`` call returns a stand-in, 1.0.

    (An unconverged stand-in would add montecarlo's warning line that J* is not available.)
    """
    from unittest import mock

    stand_in = types.SimpleNamespace(converged=True, cost=1.0, status="ok")
    monkeypatch.setattr("ofrl_drake.optimal.optimal_control", mock.Mock(return_value=stand_in))


# Mocks, not functions of this file: a frame of this file would read as the user's own code.
# (command, stop) -> (what fails, its exception, exit code, message)
SWEEP_STOPS = {
    ("montecarlo", "J*"): (
        "ofrl_drake.optimal.optimal_control",
        MemoryError,
        1,
        r"^internal error: MemoryError:",
    ),
    ("montecarlo", "task"): (
        "ofrl_drake.monte_carlo.run_seeds",
        RuntimeError("the worker was lost"),
        2,
        r"^error: a Monte Carlo task failed \(runs \[0, 1\]\): the worker was lost$",
    ),
    ("montecarlo", "interrupt"): (
        "ofrl_drake.monte_carlo.run_seeds",
        KeyboardInterrupt,
        130,
        r"^error: interrupted; no output written$",
    ),
    ("ablate", "error"): (
        "ofrl_drake.ablation.OptimalCostCache",
        MemoryError,
        1,
        r"^internal error: MemoryError",
    ),
    ("ablate", "interrupt"): (
        "ofrl_drake.ablation.run_variant_states",
        KeyboardInterrupt,
        130,
        r"^error: interrupted; no output written$",
    ),
}


@pytest.mark.parametrize(("command", "stop"), list(SWEEP_STOPS))
def test_a_sweep_leaves_nothing_when_it_stops_before_its_first_row(
    tmp_path, capsys, monkeypatch, command, stop
):
    # A sweep that failed (or was interrupted) before its first row left its plan
    # (montecarlo.json, ablation.json) and the table's header in --out: half-written
    # output that looked resumable.
    from unittest import mock

    from ofrl_drake.cli import main

    target, raised, code, message = SWEEP_STOPS[command, stop]
    runs = []
    if command == "montecarlo":
        _no_optimal(monkeypatch)
        runs = ["--runs", "2"]
    monkeypatch.setattr(target, mock.Mock(side_effect=raised))
    out = tmp_path / "sub" / "sweep"
    args = [command, str(PAPER_SCENARIO), *runs, "--workers", "0", "--out", str(out)]
    assert main(args) == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert re.match(message, err.strip()), err
    assert not out.exists() and list(tmp_path.iterdir()) == []  # its parent sub/ too
    # An empty folder that was there before is left as it was found: empty.
    out.mkdir(parents=True)
    assert main(args) == code
    capsys.readouterr()
    assert list(out.iterdir()) == []


def _curve_summary(out):
    summary = json.loads((out / "summary.json").read_text())
    return summary, sorted(p.name for p in (out / "figures").iterdir())


def test_max_wall_bounds_the_learning_curve_exit_3_with_the_whole_run_written(
    tmp_path, capsys, monkeypatch
):
    # --max-wall did not bound the learning curve: each of its checkpoints is one more
    # simulation over the horizon, after the run, with no budget at all. Now the curve
    # shares the budget with the simulation; when it runs out the run stops with exit 3,
    # its folder written whole (the simulation, its figures) and saying why.
    from ofrl_drake import learning_curve
    from ofrl_drake.cli import main

    out = tmp_path / "out"
    args = ["run", str(_short_scenario(tmp_path)), "--out", str(out), "--quiet"]
    assert main([*args, "--checkpoints", "2"]) == 0  # an earlier run's folder, replaced whole
    capsys.readouterr()
    # The first checkpoint's evaluation passes its deadline, while the design and the
    # simulation finish well within the budget.
    from ofrl_drake.errors import WallTimeExceeded

    def late(self, W, **kwargs):
        raise WallTimeExceeded("passed its deadline", step="policy evaluation")

    with monkeypatch.context() as patch:
        patch.setattr(learning_curve.PolicyEvaluator, "__call__", late)
        assert main([*args, "--max-wall", "600"]) == 3
    captured = capsys.readouterr()
    # The run is reported as any whole run is (its warnings, the observer, "wrote"), then why
    # it stopped, last.
    assert f"wrote {out}: |x(T)| = " in captured.out, captured.out
    assert re.match(
        r"^stopped: timeout: the learning curve did not finish within max_wall_time "
        r"\(--max-wall\) = 600 s: it stopped at checkpoint 1 of 11 \(t = 0 s\), .* into the "
        r"curve \(the run had used .* s before it\); .* 0 switches "
        rf"the learning curve off\); wrote {re.escape(str(out))} with the whole run, without "
        r"the learning curve \(out of --max-wall; summary.json -> learning_curve_stop\)$",
        captured.err.strip().splitlines()[-1],
    ), captured.err
    summary, figures = _curve_summary(out)
    assert summary["status"] == "ok" and summary["final_time"] == pytest.approx(2.0)
    assert "learning_curve" not in summary  # none of the earlier run's curve either
    assert summary["learning_curve_stop"].startswith("the learning curve did not finish")
    assert "learning_curve.png" not in figures and "state_1.png" in figures
    assert (out / "trajectories.npz").is_file() and (out / "learning_health.npz").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "scenario.yaml"]
    # A budget the run used up before the curve began: no checkpoint to blame.
    monkeypatch.setattr(
        learning_curve, "time", types.SimpleNamespace(monotonic=lambda: time.monotonic() + 9e4)
    )
    assert main([*args, "--max-wall", "600"]) == 3
    assert re.search(
        r"= 600 s: the run had used 9e\+04 s of it before the curve began .*, so no "
        r"checkpoint was evaluated; allow more wall time \(a larger --max-wall\) \(--checkpoints",
        capsys.readouterr().err.strip().splitlines()[-1],
    )


def test_max_wall_bounds_j_star_of_run_optimal(tmp_path, capsys, monkeypatch):
    # J* (--optimal) ran as long as its solves took, whatever --max-wall said. Now no solve
    # starts after the budget: here the budget is gone (by J*'s clock) before its first.
    from ofrl_drake import cli, optimal
    from ofrl_drake.cli import main

    late = types.SimpleNamespace(
        monotonic=lambda: time.monotonic() + 9e4, perf_counter=time.perf_counter
    )
    monkeypatch.setattr(optimal, "time", late)
    out = tmp_path / "out"
    args = ["run", str(_short_scenario(tmp_path)), "--out", str(out), "--quiet", "--optimal"]
    assert main([*args, "--max-wall", "600"]) == 3
    captured = capsys.readouterr()
    assert f"wrote {out}: |x(T)| = " in captured.out, captured.out
    assert re.match(
        r"^stopped: timeout: J\* \(--optimal\) did not finish within max_wall_time "
        r"\(--max-wall\) = 600 s: J\* ran out of wall time [\d.e-]+ s into its solves, before "
        r"its attempt 'default guess \(1 s\)' on a grid of 27 intervals, so no checkpoint of the "
        r"learning curve was evaluated; allow more wall time \(a larger --max-wall\) or run "
        r"without --optimal; wrote .* with the whole run, without the learning curve",
        captured.err.strip().splitlines()[-1],
    ), captured.err
    summary, figures = _curve_summary(out)
    assert summary["status"] == "ok" and "learning_curve" not in summary
    assert summary["learning_curve_stop"].startswith("J* (--optimal) did not finish")
    assert "learning_curve.png" not in figures
    # The budget spent before J* began (by the command's clock, after the simulation's
    # start): J* is not blamed for it, and without a curve none is said to be missing.
    readings = iter([0.0])
    clock = types.SimpleNamespace(
        monotonic=lambda: next(readings, 9e4) + time.monotonic(), perf_counter=time.perf_counter
    )
    monkeypatch.setattr(cli, "time", clock)
    assert main([*args, "--max-wall", "600", "--checkpoints", "0"]) == 3
    assert re.match(
        r"^stopped: timeout: J\* \(--optimal\) did not finish within max_wall_time "
        r"\(--max-wall\) = 600 s: the run had used 9e\+04 s of it before J\* began \(the "
        r"simulation and the checks after it\); allow more wall time \(a larger --max-wall\) or "
        r"run without --optimal; wrote",
        capsys.readouterr().err.strip().splitlines()[-1],
    )
    # Without a budget J* has no deadline and the curve is scored against it.
    monkeypatch.undo()
    assert main(args) == 0
    curve = json.loads((out / "summary.json").read_text())["learning_curve"]
    assert curve and all(math.isfinite(point["optimality_ratio"]) for point in curve)


def test_max_wall_bounds_the_observers_verification(tmp_path, capsys, monkeypatch):
    # The verification of the design (26 s on the quadrotor) ran whatever --max-wall said.
    # Now its search stops with the budget; the run is kept whole, and exit 3 says why.
    from ofrl_drake import verification
    from ofrl_drake.cli import main

    late = types.SimpleNamespace(
        monotonic=lambda: time.monotonic() + 9e4, perf_counter=time.perf_counter
    )
    monkeypatch.setattr(verification, "time", late)
    out = tmp_path / "out"
    args = ["run", str(_short_scenario(tmp_path)), "--out", str(out), "--quiet"]
    assert main([*args, "--checkpoints", "0", "--max-wall", "600"]) == 3
    captured = capsys.readouterr()
    assert f"wrote {out}: |x(T)| = " in captured.out and "observer:" not in captured.out
    assert re.fullmatch(
        r"stopped: timeout: the observer's verification did not finish within max_wall_time "
        r"\(--max-wall\) = 600 s: the observer's verification ran out of wall time [\d.e-]+ s "
        r"into its search, before chunk 1 of 1 of the small-error search; allow more wall time "
        rf"\(a larger --max-wall\); wrote {re.escape(str(out))} with the whole run, without the "
        r"observer's verification \(summary.json -> verification_stop\)",
        captured.err.strip().splitlines()[-1],
    ), captured.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "ok" and "verification" not in summary["observer_design"]
    assert summary["verification_stop"].startswith("the observer's verification did not")
    assert "verification" not in json.loads((out / "observer_design.json").read_text())
    # Without a budget the search has no deadline.
    assert main([*args, "--checkpoints", "0"]) == 0
    assert "observer: " in capsys.readouterr().out


def test_solver_chooses_j_stars_solver_and_a_bad_one_is_refused_before_the_work(
    tmp_path, capsys, monkeypatch
):
    # J*'s solver could be chosen only in Python; the status of a tiny J* that SNOPT cannot
    # settle suggests IPOPT. --solver chooses it; a typo is refused before any run.
    from ofrl_drake import optimal
    from ofrl_drake.cli import main
    from ofrl_drake.monte_carlo import read_montecarlo_rows

    path = _short_scenario(tmp_path, duration=1.0)
    out = tmp_path / "out"
    proc = run_cli("run", path, "--out", out, "--solver", "ipopt")
    assert proc.returncode == 2 and not out.exists()
    assert proc.stderr == "error: --solver ipopt: chooses the solver of J*; pass --optimal too.\n"
    unknown = "--solver: optimal control: solver must be one of ('snopt', 'ipopt'); got 'SNOPT'."
    commands = {
        "run": ["--optimal"],
        "ablate": ["--workers", "0"],
        "montecarlo": ["--runs", "1", "--workers", "0"],
    }
    for command, extra in commands.items():
        folder = tmp_path / command
        args = [command, str(path), *extra, "--out", str(folder)]
        assert main([*args, "--solver", "SNOPT"]) == 2 and not folder.exists()
        assert capsys.readouterr().err == f"error: {unknown}\n"
    # The solver reaches every J*: the one solved (spied on) and the one the report reads.
    real = optimal.optimal_control
    solvers = []

    def spy(*args, **kwargs):
        solvers.append(kwargs.get("solver"))
        return real(*args, **kwargs)

    monkeypatch.setattr(optimal, "optimal_control", spy)
    mc = tmp_path / "mc"
    args = ["montecarlo", str(path), "--runs", "1", "--workers", "0", "--out", str(mc)]
    assert main([*args, "--solver", "ipopt"]) == 0
    assert solvers == ["ipopt"]
    assert json.loads((mc / "montecarlo.json").read_text())["optimal"]["solver"] == "ipopt"
    (row,) = read_montecarlo_rows(mc / "montecarlo.csv")
    assert row["optimal_cost"] == pytest.approx(3.6492, rel=1e-3)  # 1 s horizon
    variants = tmp_path / "variants.yaml"
    variants.write_text("baseline: {}\n")
    ab = tmp_path / "ab"
    args = ["ablate", str(path), "--variants", str(variants), "--workers", "0", "--out", str(ab)]
    assert main([*args, "--solver", "ipopt"]) == 0, capsys.readouterr().err
    (cached,) = (ab / "optimal").glob("*.json")
    assert json.loads(cached.read_text())["solver"] == "ipopt"
    assert "(direct collocation, IPOPT)" in (ab / "ablation.md").read_text()
    out = tmp_path / "run_ipopt"
    args = ["run", str(path), "--out", str(out), "--quiet", "--optimal", "--checkpoints", "1"]
    solvers.clear()
    assert main([*args, "--solver", "ipopt"]) == 0
    assert solvers == ["ipopt"]
    optimum = json.loads((out / "summary.json").read_text())["optimal"]
    assert optimum["solver"] == "ipopt" and optimum["converged"] and optimum["intervals"] > 0


def test_a_run_that_times_out_has_no_learning_curve_left_to_run(tmp_path):
    # The simulation used the whole --max-wall: the learning curve used to run after it
    # anyway, unbounded; now the folder says it was not evaluated, and exit 3 as before.
    path = _short_scenario(tmp_path, variant={"observer": "true_state"})  # no design: 1 ms
    out = tmp_path / "out"
    proc = run_cli("run", path, "--out", out, "--quiet", "--max-wall", "0.001")
    assert_one_line(
        proc,
        3,
        r"^stopped: timeout: wall time .* exceeded max_wall_time = 0\.001 s at t = .*; wrote "
        r".* without the learning curve \(out of --max-wall; summary.json -> "
        r"learning_curve_stop\)$",
    )
    summary, figures = _curve_summary(out)
    assert summary["status"] == "timeout" and "learning_curve" not in summary
    assert re.match(
        r"^the learning curve did not finish within max_wall_time \(--max-wall\) = 0\.001 s",
        summary["learning_curve_stop"],
    )
    assert "learning_curve.png" not in figures
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "scenario.yaml"]


def test_an_error_in_the_users_plant_names_its_file_line_and_function(tmp_path):
    source = tmp_path / "rp.py"
    source.write_text(
        "import numpy as np\n"
        "from ofrl_drake import ControlAffineSystem\n"
        "\n"
        "\n"
        "def f(x):\n"
        "    return np.array([x[1], undefined_name * x[0]])  # noqa: F821\n"
        "\n"
        "\n"
        "def g(x):\n"
        "    return np.array([[0 * x[0]], [1 + 0 * x[0]]])\n"
        "\n"
        "\n"
        "def make_fraise():\n"
        "    return ControlAffineSystem(f, g, C=[[0.0, 1.0]], name='fraise')\n"
    )
    scenario = _short_scenario(tmp_path, system=f"{source}:make_fraise")
    proc = run_cli("run", scenario, "--out", tmp_path / "o")
    assert_one_line(
        proc,
        2,
        r"system: '.*rp\.py:make_fraise' raised ModelError: f\(x\) failed at the probe point "
        rf"x = \[.*\]: name 'undefined_name' is not defined \(at {re.escape(str(source))}:6, "
        r"in f\)$",
    )
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------- what is not a dask scheduler
class _FakeServer:
    """A local TCP server that accepts connections and, per ``greeting``, sends it or stays silent.

    Stands in for what a mistyped ``--scheduler`` port reaches: an HTTP server, which
    waits for a request line (silent), or an SSH server, which greets first.
    """

    def __init__(self, greeting):
        import socket
        import threading

        self.greeting = greeting
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = f"tcp://127.0.0.1:{self.listener.getsockname()[1]}"
        self.accepted = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                conn, _ = self.listener.accept()
            except OSError:  # closed
                return
            self.accepted.append(conn)
            if self.greeting:
                conn.sendall(self.greeting)

    def close(self):
        self.listener.close()
        for conn in self.accepted:
            conn.close()


@pytest.mark.parametrize(
    ("greeting", "cause"),
    [
        (b"", r"no dask scheduler answered after 2 s"),
        (
            b"SSH-2.0-OpenSSH_9.2p1 Debian-2\r\n",
            r"what answered there is not a dask scheduler: MemoryError: .*",
        ),
    ],
    ids=["silent", "greets"],
)
def test_a_server_that_is_not_a_dask_scheduler_is_given_up_in_one_line(tmp_path, greeting, cause):
    # A silent server held the command forever, past --scheduler-timeout (distributed bounds
    # the TCP connection, not the handshake); one that greets first was read as a message of
    # exabytes: "internal error: MemoryError", exit 1. The subprocess timeout, far above any
    # honest run, turns a hang into a failure; no clock in the assert.
    server = _FakeServer(greeting)
    try:
        proc = run_cli(
            "montecarlo",
            PAPER_SCENARIO,
            "--runs",
            1,
            "--out",
            tmp_path / "o",
            "--scheduler",
            server.address,
            "--scheduler-timeout",
            2,
            timeout=300,
        )
    finally:
        server.close()
    assert_one_line(
        proc,
        2,
        rf"^error: --scheduler: cannot connect to {re.escape(server.address)} within "
        rf"--scheduler-timeout 2 s \({cause}\); start a dask scheduler there, check the "
        r"address \(a dask scheduler's port, not another server's\), or raise "
        r"--scheduler-timeout\.$",
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("address", "why"),
    [
        ("tcp://127.0.0.1:0", r"port 0 is not in 1-65535"),
        ("tcp://127.0.0.1:99999", r"port 99999 is not in 1-65535"),
    ],
)
def test_a_scheduler_address_of_no_dask_scheduler_is_named_before_connecting(
    tmp_path, capsys, address, why
):
    # A port no server can have was tried for the whole --scheduler-timeout, then named as
    # a scheduler that did not answer.
    from ofrl_drake.cli import main

    out = tmp_path / "o"
    args = ["ablate", str(PAPER_SCENARIO), "--out", str(out), "--scheduler", address]
    assert main([*args, "--scheduler-timeout", "5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert re.match(
        rf"^error: --scheduler: '{re.escape(address)}' is not a scheduler address \(.*{why}.*\); "
        r"give tcp://HOST:PORT of a running dask scheduler\.$",
        err,
    ), err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------ Ctrl-C reaches the whole process group
def _workers(pid):
    """The process ids of the Dask worker processes started by process ``pid``."""
    found = []
    for child in os.listdir("/proc"):
        if not child.isdigit():
            continue
        try:
            with open(f"/proc/{child}/stat") as fh:
                parent = int(fh.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{child}/cmdline", "rb") as fh:
                command = fh.read()
        except (OSError, ValueError, IndexError):
            continue
        if parent == pid and b"spawn_main" in command:
            found.append(int(child))
    return found


def _takes_sigint(pid):
    """True if process ``pid`` acts on a SIGINT: neither blocked nor ignored."""
    with open(f"/proc/{pid}/status") as fh:
        fields = dict(line.split(":", 1) for line in fh.read().splitlines() if ":" in line)
    bit = 1 << (signal.SIGINT - 1)
    return not (int(fields["SigBlk"], 16) & bit or int(fields["SigIgn"], 16) & bit)


def _table_rows(table):
    try:
        return len(table.read_text().splitlines()) - 1
    except OSError:
        return 0


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc to see the workers")
@pytest.mark.parametrize("moment", ["workers starting", "workers running"])
def test_ctrl_c_to_the_process_group_of_a_sweep_prints_one_line(tmp_path, moment):
    # A terminal's Ctrl-C goes to the whole process group, Dask's worker processes too:
    # each printed its traceback (12 to 67 lines: "Process Dask Worker process (from
    # Nanny)", "Fatal Python error: init_import_site") beside the command's line.
    out = tmp_path / "o"
    table = out / "montecarlo.csv"
    args = ["montecarlo", PAPER_SCENARIO, "--runs", 40, "--workers", 1, "--out", out]
    proc = subprocess.Popen(
        [sys.executable, "-m", "ofrl_drake", *map(str, args)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    if moment == "workers starting":  # the worker's process exists: it is starting up

        def ready():
            return bool(_workers(proc.pid))

    else:  # a row is written, so the worker is running the next runs

        def ready():
            return _table_rows(table) >= 1

    try:
        while proc.poll() is None and not ready():
            time.sleep(0.01)
        # Whether a worker printed its traceback is a race (with its being closed); that it
        # cannot take the signal is not.
        workers = _workers(proc.pid)
        taking = [pid for pid in workers if _takes_sigint(pid)]
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert workers and not taking, (workers, taking)
    assert proc.returncode == 130, err
    assert err.count("\n") == 1, err
    if moment == "workers starting":
        assert err.startswith("error: interrupted; "), err
    else:
        assert err == (
            f"error: interrupted; finished rows are in {table}; rerun with --resume to "
            "complete the sweep\n"
        )
        assert 1 <= _table_rows(table) < 40


def _interrupt_threads():
    import threading

    return [t for t in threading.enumerate() if t.name == "ofrl-drake interrupt again"]


@pytest.mark.parametrize("when", ["mid-sweep", "as the sweep ends"])
def test_an_interrupt_swallowed_by_python_still_stops_the_command(
    tmp_path, capsys, monkeypatch, when
):
    # A KeyboardInterrupt that lands in a __del__ or a weakref callback (Dask releases many
    # objects) is "ignored" by Python: it printed "Exception ignored in: ..." with a
    # traceback, and the sweep went on to its end, exit 0. Its signal, sent again from a
    # timer, came after main() had returned when the command ended first: the caller (a
    # user's Python, pytest) was interrupted. Mid-sweep, the timer's signal interrupts the
    # wait; as the sweep ends (the timer never fires in time), the interrupt is raised then.
    import threading

    from ofrl_drake import cli

    class Doomed:
        def __del__(self):
            raise KeyboardInterrupt

    def runs(*args, **kwargs):
        Doomed()  # interrupted where Python cannot raise it
        if when == "mid-sweep":
            threading.Event().wait(600)  # until the interrupt comes again, here
        return []

    if when == "as the sweep ends":
        monkeypatch.setattr(cli, "RESIGNAL_DELAY", 3600.0)
    _no_optimal(monkeypatch)
    monkeypatch.setattr("ofrl_drake.monte_carlo.run_seeds", runs)
    out = tmp_path / "o"
    args = ["montecarlo", str(PAPER_SCENARIO), "--runs", "2", "--workers", "0", "--out", str(out)]
    assert cli.main(args) == 130
    err = capsys.readouterr().err
    kept = (
        "no output written"  # the sweep stopped before it wrote anything
        if when == "mid-sweep"
        else f"finished rows are in {out / 'montecarlo.csv'}; rerun with --resume to complete "
        "the sweep"
    )
    assert err == f"error: interrupted; {kept}\n", err
    assert _interrupt_threads() == []  # nothing left to interrupt the caller


def _montecarlo_interrupted_in_its_report(tmp_path, capsys, monkeypatch, report):
    """Run a one-row montecarlo whose report is ``report`` (it raises KeyboardInterrupt):
    exit 130, one line naming the finished rows. Returns the output folder."""

    from ofrl_drake.cli import main

    _no_optimal(monkeypatch)
    monkeypatch.setattr("ofrl_drake.monte_carlo.write_montecarlo_report", report)
    out = tmp_path / "o"
    scenario = _short_scenario(tmp_path, duration=0.2)
    args = ["montecarlo", str(scenario), "--runs", "1", "--workers", "0", "--out", str(out)]
    assert main(args) == 130
    err = capsys.readouterr().err
    assert err == (
        f"error: interrupted; finished rows are in {out / 'montecarlo.csv'}; rerun with "
        "--resume to complete the sweep\n"
    ), err
    return out


def test_an_interrupt_while_a_sweep_writes_its_report_keeps_the_rows(tmp_path, capsys, monkeypatch):
    # The sweep's rows were all written; an interrupt in its report (figures, J*) said
    # "no output written", beside a folder holding every row.
    from unittest import mock

    out = _montecarlo_interrupted_in_its_report(
        tmp_path, capsys, monkeypatch, mock.Mock(side_effect=KeyboardInterrupt)
    )
    assert _table_rows(out / "montecarlo.csv") == 1


# ------------------------------------------------------------------ --out is not the input
@pytest.mark.parametrize("command", ["design-observer", "verify-observer"])
@pytest.mark.parametrize("spelling", ["same path", "hard link"])
def test_out_that_is_the_scenario_file_is_refused(tmp_path, capsys, command, spelling):
    # design-observer same.yaml --out same.yaml exited 0, the scenario replaced with JSON.
    from ofrl_drake.cli import main

    scenario = tmp_path / "same.yaml"
    scenario.write_text(PAPER_SCENARIO.read_text())
    out = scenario
    if spelling == "hard link":
        out = tmp_path / "design.json"
        os.link(scenario, out)
    assert main([command, str(scenario), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"error: --out: {out} is the scenario file {scenario}; the JSON would replace the "
        "scenario. Name another file for the output.\n"
    ), err
    assert scenario.read_text() == PAPER_SCENARIO.read_text()


def test_verify_observer_checks_its_out_before_the_work(tmp_path, capsys, monkeypatch):
    # verify-observer designed and verified (seconds to minutes), then found that --out
    # could not be written; design-observer checked first.
    from unittest import mock

    from ofrl_drake.cli import main

    design = mock.Mock(side_effect=AssertionError("the design ran"))
    monkeypatch.setattr("ofrl_drake.variants.design_for", design)
    (tmp_path / "afile").write_text("x")
    for out in (tmp_path / "afile" / "report.json", tmp_path):
        assert main(["verify-observer", str(PAPER_SCENARIO), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("error: --out: "), err
    design.assert_not_called()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


# ---------------------------------------------------------------- stderr on success
def test_a_name_the_font_cannot_draw_gives_one_note_line(tmp_path, capsys):
    # matplotlib warned once per character and drawing pass, with its source line: about 83
    # stderr lines for name: "倒立振子".
    from ofrl_drake.cli import main

    scenario = _short_scenario(tmp_path, duration=0.2, name="倒立振子")
    args = ["run", str(scenario), "--out", str(tmp_path / "o"), "--quiet", "--checkpoints", "0"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "Glyph" not in err and "savefig" not in err, err
    glyphs = [line for line in err.splitlines() if "glyph" in line]
    assert glyphs == [
        "note: the figures' font (DejaVu Sans) has no glyph for '倒立振子', drawn as empty "
        "boxes; use other characters in the scenario's name (and variant names), or set "
        "matplotlib's font.family to a font that has them."
    ], err
    assert (tmp_path / "o" / "figures" / "state_1.png").is_file()


def test_save_png_warns_once_per_figure_naming_the_missing_characters(tmp_path):
    import matplotlib.pyplot as plt

    from ofrl_drake.plotting import MissingGlyphWarning, save_png

    fig = plt.figure()
    fig.text(0.1, 0.5, "倒立振子 and 倒立")
    with pytest.warns(MissingGlyphWarning) as caught:
        save_png(fig, tmp_path / "f.png", 50)
    glyphs = [w for w in caught if "glyph" in str(w.message).lower()]
    assert len(glyphs) == 1, [str(w.message) for w in caught]
    assert glyphs[0].message.characters == "倒立振子"
    assert re.match(
        r"^f\.png: the font \(DejaVu Sans\) has no glyph for '倒立振子'", str(glyphs[0].message)
    )
    assert (tmp_path / "f.png").is_file()


@pytest.mark.parametrize(
    ("x0", "shown"), [([1e300, 1e300], "[1e+300, 1e+300]"), ([1e308, 1.0], "[1e+308, 1.0]")]
)
def test_a_state_that_overflows_is_reported_by_the_runs_status_alone(tmp_path, x0, shown):
    # x0 = [1e300, 1e300]: numpy's "RuntimeWarning: overflow encountered in dot" and its
    # source line, beside the run's own line saying it diverged. x0 = [1e308, 1]: "internal
    # error: ValueError: Axis limits cannot be NaN or Inf" from the figures, nothing written.
    scenario = _short_scenario(tmp_path, duration=0.2, x0=x0)
    proc = run_cli("run", scenario, "--out", tmp_path / "o", "--quiet", "--checkpoints", 0)
    assert proc.returncode == 3, proc.stderr
    assert "RuntimeWarning" not in proc.stderr, proc.stderr
    assert "overflow encountered" not in proc.stderr, proc.stderr
    lines = proc.stderr.splitlines()
    assert lines[0].startswith(f"warning: x0 = {shown} outside the observer box")
    assert lines[1].startswith(f"stopped: diverged: x_1 = {x0[0]:g} left the abort box"), lines
    assert len(lines) == 2, proc.stderr
    assert (tmp_path / "o" / "figures" / "overview.png").is_file()


def test_a_python_warning_is_one_line_without_its_source_line(tmp_path):
    # A plant whose f does not take a batch of states warns (model.py); Python printed the
    # warning and the user's source line under it, two lines before the one-line error.
    source = tmp_path / "scalar_plant.py"
    source.write_text(
        "import math\n"
        "import numpy as np\n"
        "from ofrl_drake import ControlAffineSystem\n"
        "\n"
        "\n"
        "def f(x):\n"
        "    return np.array([x[1], -math.sin(x[0])])\n"
        "\n"
        "\n"
        "def g(x):\n"
        "    return np.array([[0.0], [1.0]])\n"
        "\n"
        "\n"
        "def make_plant():\n"
        "    return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name='scalar_only')\n"
    )
    scenario = _short_scenario(tmp_path, system=f"{source}:make_plant")
    proc = run_cli("run", scenario, "--out", tmp_path / "o")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 2, proc.stderr
    assert lines[0] == (
        "warning: scalar_only: f and g do not accept a batch of states of shape (n, N); "
        "falling back to a Python loop over points. Write constants as 0 * x[0] so they "
        "broadcast."
    ), proc.stderr
    assert lines[1].startswith("error: scalar_only: f and g must accept pydrake.symbolic"), lines


# --------------------------------------------------- what main leaves behind in its caller
def test_an_unanswered_scheduler_leaves_no_thread_and_no_client(tmp_path):
    # The thread connecting to a silent server went on connecting after the error (for
    # ever: "ofrl-drake connect" and distributed's "IO loop" alive 20 s later); a scheduler
    # answering late would then have left a client registered as dask's default.
    import threading

    import distributed

    from ofrl_drake.cli import _connect
    from ofrl_drake.errors import OfrlError

    before = set(threading.enumerate())
    server = _FakeServer(b"")
    try:
        with pytest.raises(
            OfrlError, match=rf"cannot connect to {re.escape(server.address)} .*no dask scheduler"
        ):
            _connect(server.address, 0.5, OfrlError)
    finally:
        server.close()
    left = [t.name for t in set(threading.enumerate()) - before if t.is_alive()]
    left = [name for name in left if not name.startswith("Thread-")]  # the fake server's
    assert left == [], left
    assert list(distributed.client._global_clients.values()) == []
    with pytest.raises(ValueError):
        distributed.client.default_client()


def test_a_dask_workers_warning_is_one_line(capfd):
    # A warning raised in a Dask worker process kept Python's format there, on the
    # command's stderr: its file and line ("ofrl_drake/diagram.py:466:
    # InitialPolicyWarning: ...") and the source line, once per task.
    import warnings
    from unittest import mock

    from distributed import Client, LocalCluster

    from ofrl_drake.cli import _WarningLines
    from ofrl_drake.sweep import Engine

    def task(k):  # pickled by value: runs in the worker process
        import warnings

        warnings.warn("critic.W0: the start   is not admissible", UserWarning, stacklevel=1)
        return k

    cluster = LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
    )
    with (
        cluster,
        Client(cluster) as client,
        mock.patch.object(warnings, "showwarning", _WarningLines()),
    ):
        engine = Engine(client)
        for k in (1, 2):
            engine.submit(task, k)
        assert sorted(value for _, value, _ in engine.completed()) == [1, 2]
    err = capfd.readouterr().err
    assert err == "warning: critic.W0: the start is not admissible\n", err


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="needs signal masks")
def test_an_ignored_sigint_is_not_taken_by_the_command():
    # A script's background job (cmd &) starts with SIGINT ignored; the command recorded a
    # SIGINT while importing or starting workers and raised it: exit 130 on a signal it was
    # told to ignore.
    from ofrl_drake.atomic import sigint_held
    from ofrl_drake.cli import _sigint_kept_from_children

    was = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
        for block in (sigint_held, _sigint_kept_from_children):
            with block():
                assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN, block
                assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == mask, block
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0)  # the signal, were it handled, is handled by now
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN, block
    finally:
        signal.signal(signal.SIGINT, was)


def test_an_interrupted_sweep_prints_one_line_not_the_glyph_note(tmp_path, capsys, monkeypatch):
    # The note on the figures' missing glyphs came after "error: interrupted; ...": two
    # lines for a command that stopped.
    from pathlib import Path

    from ofrl_drake.plotting import MissingGlyphWarning

    def report(*args, **kwargs):
        import warnings

        warnings.warn(MissingGlyphWarning("倒立", "DejaVu Sans", Path("f.png")), stacklevel=1)
        raise KeyboardInterrupt

    _montecarlo_interrupted_in_its_report(tmp_path, capsys, monkeypatch, report)


@pytest.mark.parametrize("command", ["bad input", "sweep"])
def test_main_leaves_sigterm_and_the_warning_and_unraisable_hooks_as_they_were(
    tmp_path, capsys, monkeypatch, command
):
    # SIGTERM stayed set to raise Terminated after main() returned, in the caller's Python.
    import warnings
    from unittest import mock

    from ofrl_drake.cli import main

    def on_sigterm(signum, frame):  # the caller's own handler
        pass

    _no_optimal(monkeypatch)
    monkeypatch.setattr("ofrl_drake.monte_carlo.write_montecarlo_report", mock.Mock())
    if command == "bad input":
        args = ["design-observer", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "d")]
    else:
        scenario = _short_scenario(tmp_path, duration=0.2)
        args = ["montecarlo", str(scenario), "--runs", "1", "--workers", "0"]
        args += ["--out", str(tmp_path / "o")]
    was = signal.signal(signal.SIGTERM, on_sigterm)
    hook, show = sys.unraisablehook, warnings.showwarning
    try:
        assert main(args) == (2 if command == "bad input" else 0), capsys.readouterr().err
        assert signal.getsignal(signal.SIGTERM) is on_sigterm
        assert sys.unraisablehook is hook
        assert warnings.showwarning is show
    finally:
        signal.signal(signal.SIGTERM, was)
