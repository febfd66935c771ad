"""The sweep engine and the sweep's folder, shared by ablate and montecarlo (no Drake run)."""

import dataclasses
import io
import json
import math
import re
import sys

import numpy as np
import pytest

from ofrl_drake.errors import OfrlError
from ofrl_drake.sweep import Engine, execute, split_consecutive, worker_threads
from ofrl_drake.sweep_store import (
    SweepFiles,
    SweepStore,
    describe_difference,
    first_difference,
    load_arrays,
)

from .conftest import edited_two_state


class _SweepError(OfrlError):
    pass


FILES = SweepFiles(
    table="t.csv",
    plan="t.json",
    columns=("name", "value", "status"),
    text=("name", "status"),
    command="test",
    kind="example table",
    error=_SweepError,
)


def _never_different(old, new):
    return None


def _seed_differs(old, new):
    return None if old["seed"] == new["seed"] else f"seed {old['seed']} != {new['seed']}"


# ------------------------------------------------------------------ engine
def _twice(x):
    return 2 * x


def _fails(x):
    raise ValueError(f"no {x}")


def test_the_serial_engine_runs_in_order_and_passes_results_on():
    engine = Engine()
    first = engine.submit(_twice, 3)
    second = engine.submit(_twice, engine.ref(first))
    broken = engine.submit(_fails, 1)
    done = list(engine.completed())
    assert [(h, v) for h, v, _ in done] == [(first, 6), (second, 12), (broken, None)]
    assert isinstance(done[2][2], ValueError) and str(done[2][2]) == "no 1"


def test_execute_counts_rows_not_tasks(monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    seen = []

    def submit(engine):
        return {engine.submit(_twice, k): k for k in range(3)}

    def finish(task, value, err):  # task 0 completes no row, task 2 completes two
        seen.append((task, value, err))
        return [None] * task

    execute(submit, finish, client=None, total=4, done=1, progress=True)
    assert seen == [(0, 0, None), (1, 2, None), (2, 4, None)]
    labels = [f.split("] ")[1].split("  ")[0] for f in stream.getvalue().split("\r")[1:]]
    assert labels == ["1/4 runs", "2/4 runs", "3/4 runs", "4/4 runs"]


def test_execute_stops_when_the_sweep_raises_and_ends_the_bar_line(monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)

    def finish(task, value, err):
        raise _SweepError("stop here")

    with pytest.raises(_SweepError, match="stop here"):
        execute(
            lambda e: {e.submit(_twice, 1): 0}, finish, client=None, total=1, done=0, progress=True
        )
    assert stream.getvalue().endswith("\n")


# ------------------------------------------------------------------- store
def test_a_new_folder_gets_its_plan_and_a_streamed_table(tmp_path):
    store = SweepStore(FILES, tmp_path / "out")
    assert store.open({"seed": 1}, resume=False, mismatch=_never_different) == []
    assert json.loads((tmp_path / "out" / "t.json").read_text()) == {"seed": 1}
    store.start()
    store.write({"name": "a", "value": math.nan, "status": "ok"})
    store.write({"name": "b, c", "value": 0.1, "status": "timeout: 3 s"})
    store.save_run("a.npz", {"t": np.arange(3.0)})
    store.close()
    text = (tmp_path / "out" / "t.csv").read_text()
    assert text == 'name,value,status\na,nan,ok\n"b, c",0.1,timeout: 3 s\n'
    rows = FILES.read(tmp_path / "out" / "t.csv")
    assert rows[1] == {"name": "b, c", "value": 0.1, "status": "timeout: 3 s"}
    np.testing.assert_array_equal(load_arrays(tmp_path / "out" / "runs" / "a.npz")["t"], [0, 1, 2])
    assert load_arrays(tmp_path / "out" / "runs" / "b.npz") is None


def _filled(tmp_path):
    out = tmp_path / "out"
    store = SweepStore(FILES, out)
    store.open({"seed": 1}, resume=False, mismatch=_seed_differs)
    store.start()
    store.write({"name": "a", "value": 1.0, "status": "ok"})
    store.write({"name": "b", "value": 2.0, "status": "diverged: x left"})
    store.close()
    return out


def test_resume_keeps_rows_drops_a_torn_line_and_retries_failed_ones(tmp_path):
    out = _filled(tmp_path)
    table = out / "t.csv"
    table.write_text(table.read_text() + "c,3.")  # killed while writing
    with pytest.raises(_SweepError, match=r"t\.csv exists; pass --resume to complete it"):
        SweepStore(FILES, out).open({"seed": 1}, resume=False, mismatch=_seed_differs)
    rows = SweepStore(FILES, out).open({"seed": 1}, resume=True, mismatch=_seed_differs)
    assert [r["name"] for r in rows] == ["a", "b"]
    assert table.read_text().endswith("diverged: x left\n")
    store = SweepStore(FILES, out)
    rows = store.open({"seed": 1}, resume=True, mismatch=_seed_differs, retry_failed=True)
    assert [r["name"] for r in rows] == ["a"]
    assert table.read_text() == "name,value,status\na,1.0,ok\n"


def test_resume_refuses_another_sweep_a_cut_short_plan_and_a_missing_one(tmp_path):
    out = _filled(tmp_path)
    with pytest.raises(
        _SweepError, match=r"^--resume: seed 1 != 2; resume with the sweep's own arguments"
    ):
        SweepStore(FILES, out).open({"seed": 2}, resume=True, mismatch=_seed_differs)
    (out / "t.json").write_text('{"se')
    with pytest.raises(_SweepError, match=r"t\.json is not valid JSON \(cut short\?\)"):
        SweepStore(FILES, out).open({"seed": 1}, resume=True, mismatch=_seed_differs)
    (out / "t.json").unlink()
    with pytest.raises(_SweepError, match=r"t\.json is missing; it records the sweep that t\.csv"):
        SweepStore(FILES, out).open({"seed": 1}, resume=True, mismatch=_seed_differs)


def test_a_folder_of_another_command_is_refused(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(_SweepError, match=r"not written by ofrl-drake test \(no t\.json\)"):
        SweepStore(FILES, tmp_path / "mine").open({}, resume=False, mismatch=_never_different)
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]


def _tree(folder):
    """Every path under ``folder`` (relative, sorted) with each file's bytes."""
    return {
        str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None
        for p in sorted(folder.rglob("*"))
    }


@pytest.mark.parametrize("stop", [_SweepError("disk full"), KeyboardInterrupt()])
def test_a_sweep_stopped_before_its_first_row_leaves_its_folder_as_it_was_found(tmp_path, stop):
    # Before: a failed or interrupted first run left a folder holding only the plan and
    # the table's header (ablation.json, an empty ablation.csv), which looked resumable.
    files = dataclasses.replace(FILES, folders=("runs", "cache"))

    def stopped(out, plan=None, resume=False, rows=0):
        store = SweepStore(files, out)
        with pytest.raises(type(stop)):
            with store.recording(plan or {"seed": 1}, resume=resume, mismatch=_seed_differs):
                store.save_run("a.npz", {"t": np.arange(3.0)})
                (out / "cache").mkdir(exist_ok=True)
                (out / "cache" / "j.json").write_text("{}")
                for k in range(rows):
                    store.write({"name": f"r{k}", "value": 1.0, "status": "ok"})
                raise stop
        return store

    # A folder the sweep created goes, with everything in it, and the parents it created.
    new = tmp_path / "new"
    assert stopped(new).written == 0
    assert not new.exists() and list(tmp_path.iterdir()) == []
    stopped(tmp_path / "a" / "b" / "new")
    assert list(tmp_path.iterdir()) == []
    # A folder that was there stays, with its files (empty, or a sweep being resumed).
    empty = tmp_path / "empty"
    empty.mkdir()
    stopped(empty)
    assert list(empty.iterdir()) == []
    resumed = _filled(tmp_path)
    (resumed / "runs").mkdir()
    (resumed / "runs" / "old.npz").write_bytes(b"old run")
    before = _tree(resumed)
    stopped(resumed, resume=True)
    assert _tree(resumed) == before  # the new runs/a.npz and cache/ are gone, the rest kept
    # A refused resume removes nothing either.
    with pytest.raises(_SweepError, match=r"seed 1 != 2"):
        with SweepStore(files, resumed).recording({"seed": 2}, resume=True, mismatch=_seed_differs):
            pass
    assert _tree(resumed) == before
    # After a first row, nothing is removed: the folder can be resumed.
    kept = tmp_path / "kept"
    assert stopped(kept, rows=1).written == 1
    assert sorted(_tree(kept)) == ["cache", "cache/j.json", "runs", "runs/a.npz", "t.csv", "t.json"]
    assert FILES.read(kept / "t.csv") == [{"name": "r0", "value": 1.0, "status": "ok"}]


def test_a_second_interrupt_does_not_cut_the_clean_up_short(tmp_path, monkeypatch):
    """A terminal's Ctrl-C (or `timeout`) can reach the command twice; before, the second
    one landed in the clean-up of the first and left the plan alone in a new folder."""
    import os
    import signal

    from ofrl_drake import sweep_store

    remove = sweep_store._remove

    def interrupted_remove(path):
        os.kill(os.getpid(), signal.SIGINT)  # delivered at the next line of Python
        remove(path)

    monkeypatch.setattr(sweep_store, "_remove", interrupted_remove)
    new = tmp_path / "new"
    with pytest.raises(KeyboardInterrupt):
        with SweepStore(FILES, new).recording({"seed": 1}, resume=False, mismatch=_seed_differs):
            raise KeyboardInterrupt
    assert not new.exists() and list(tmp_path.iterdir()) == []


def test_a_sweep_that_ends_keeps_its_folder_even_without_a_new_row(tmp_path):
    out = _filled(tmp_path)
    before = _tree(out)
    store = SweepStore(FILES, out)
    with store.recording({"seed": 1}, resume=True, mismatch=_seed_differs) as rows:
        assert [r["name"] for r in rows] == ["a", "b"]  # all done: nothing to write
    assert store.written == 0 and _tree(out) == before
    new = tmp_path / "new"
    with SweepStore(FILES, new).recording({"seed": 1}, resume=False, mismatch=_seed_differs):
        pass  # a sweep of no row that ended: its plan and header stay
    assert sorted(_tree(new)) == ["t.csv", "t.json"]


def test_a_table_of_another_kind_is_named(tmp_path):
    (tmp_path / "t.csv").write_text("a,b\n1,2\n")
    with pytest.raises(
        _SweepError,
        match=r"t\.csv: not a valid example table: expected the header \('name', 'value', "
        r"'status'\); got the header \('a', 'b'\)\. Move it away, or choose another --out",
    ):
        FILES.read(tmp_path / "t.csv")


def test_a_table_of_another_kind_reads_with_its_article(tmp_path):
    from ofrl_drake.monte_carlo import FILES as MONTE_CARLO
    from ofrl_drake.monte_carlo import MonteCarloError

    (tmp_path / "montecarlo.csv").write_text("a,b\n")
    with pytest.raises(MonteCarloError, match=r"not a valid Monte Carlo table: expected"):
        MONTE_CARLO.read(tmp_path / "montecarlo.csv")


@pytest.mark.parametrize(
    ("line", "match"),
    [
        (b"c,\xff\xfe,ok\n", r"line 4 is not UTF-8 text \(byte 0xff at offset 52\)"),
        (b"c," + b"9" * 200_000 + b",ok\n", r"line 4 cannot be read as CSV \(field larger than"),
        (b"c,3,ok,x\n", r"line 4 is malformed: \['c', '3', 'ok', 'x'\]"),
    ],
    ids=["not_utf8", "huge_field", "extra_field"],
)
def test_resume_of_a_corrupt_table_names_the_line_and_the_fix(tmp_path, line, match):
    out = _filled(tmp_path)
    table = out / "t.csv"
    table.write_bytes(table.read_bytes() + line)
    with pytest.raises(
        _SweepError,
        match=rf"^{re.escape(str(table))}: {match}.*; the file is corrupt: delete that line "
        r"\(--resume then runs its row again\), or choose another --out\.$",
    ):
        SweepStore(FILES, out).open({"seed": 1}, resume=True, mismatch=_seed_differs)


def test_a_table_with_a_damaged_header_says_to_move_it_away(tmp_path):
    (tmp_path / "t.csv").write_bytes(b"name,\xe9value,status\n")
    with pytest.raises(
        _SweepError,
        match=r"t\.csv: line 1 is not UTF-8 text \(byte 0xe9 at offset 5\); the file is "
        r"corrupt: the header is damaged: move the file away, or choose another --out\.$",
    ):
        FILES.read(tmp_path / "t.csv")


def test_first_difference_names_the_key_path():
    assert first_difference({"a": {"b": 1, "c": 2}}, {"a": {"b": 1, "c": 3}}) == "a.c"
    assert first_difference({"a": 1}, {"a": 1, "z": 0}) == "z"
    assert first_difference({"a": [1]}, {"a": [1]}) is None


def test_describe_difference_names_the_folder_s_value_and_the_command_s():
    assert describe_difference({"runs": 3, "seed": 0}, {"runs": 2, "seed": 0}) == (
        "runs (3 in the folder, 2 now)"
    )
    missing = describe_difference({"a": {"b": "x"}}, {"a": {}})
    assert missing == "a.b ('x' in the folder, absent now)"
    assert describe_difference({"a": [1]}, {"a": [1]}) is None


@pytest.mark.parametrize(
    ("count", "parts", "lengths"),
    [(5, 2, [3, 2]), (5, 1, [5]), (3, 8, [1, 1, 1]), (0, 3, []), (7, 3, [3, 2, 2])],
)
def test_split_consecutive_keeps_order_and_balances(count, parts, lengths):
    items = list(range(count))
    chunks = split_consecutive(items, parts)
    assert [len(c) for c in chunks] == lengths
    assert [i for c in chunks for i in c] == items


def test_worker_threads_without_a_cluster_or_with_one_that_cannot_tell():
    class Client:
        def nthreads(self):
            return {"a": 2, "b": 3}

    class Broken:
        def nthreads(self):
            raise OSError("scheduler gone")

    assert worker_threads(None) == 1
    assert worker_threads(Client()) == 5
    assert worker_threads(Broken()) == 1


# -------------------------------------------------------------- montecarlo
@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"mass_spread": "0.1"}, r"^mass_spread \(--mass-spread\) must be in \[0, 1\); got '0\.1'"),
        ({"mass_spread": None}, r"^mass_spread \(--mass-spread\) must be in \[0, 1\); got None"),
        ({"optimal_cost": "1"}, r"^optimal_cost: must be J\* .*a number >= 0 .*; got '1'"),
        ({"optimal_cost": -1.0}, r"^optimal_cost: .*; got -1\.0"),
        ({"optimal_cost": math.inf}, r"^optimal_cost: .*; got inf"),
    ],
)
def test_montecarlo_refuses_a_bad_spread_or_optimal_cost_before_any_run(
    paper_scenario, tmp_path, options, match
):
    from ofrl_drake.monte_carlo import MonteCarloError, montecarlo

    out = tmp_path / "mc"
    with pytest.raises(MonteCarloError, match=match):
        montecarlo(paper_scenario, 1, out=out, progress=False, **{"optimal_cost": 1.0, **options})
    assert not out.exists()


@pytest.mark.parametrize(
    ("seed", "runs", "match"),
    [
        (
            99999999999999999999,
            1,
            r"^the last run's measurement seed, seed \+ runs - 1 = 99999999999999999999 \+ 1 - 1 "
            r"\(--seed, --runs\), must be at most 2\*\*32 - 1 = 4294967295 .*; got "
            r"99999999999999999999\. With runs = 1, give a seed of at most 4294967295\.$",
        ),
        (
            2**32 - 1,
            2,
            r"= 4294967295 \+ 2 - 1 .*; got 4294967296\. With runs = 2, give a seed of at most "
            r"4294967294\.$",
        ),
    ],
    ids=["seed_too_large", "last_seed_too_large"],
)
def test_montecarlo_refuses_seeds_drake_cannot_keep_before_any_run(
    paper_scenario, tmp_path, seed, runs, match
):
    """Run k uses measurement seed seed + k; Drake keeps 32 bits of a seed."""
    from ofrl_drake.monte_carlo import MonteCarloError, montecarlo

    out = tmp_path / "mc"
    with pytest.raises(MonteCarloError, match=match):
        montecarlo(paper_scenario, runs, seed, out=out, progress=False, optimal_cost=1.0)
    assert not out.exists()


def test_montecarlo_resume_names_the_folder_s_value_and_the_command_s(paper_scenario, tmp_path):
    from ofrl_drake.monte_carlo import MonteCarloError, montecarlo

    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=0.2)
    )
    out = tmp_path / "mc"
    montecarlo(short, 1, seed=3, out=out, progress=False, optimal_cost=1.0)
    with pytest.raises(
        MonteCarloError,
        match=r"^--resume: the folder's sweep differs in runs \(1 in the folder, 2 now\); resume "
        r"with the sweep's own arguments",
    ):
        montecarlo(short, 2, seed=3, out=out, resume=True, progress=False, optimal_cost=1.0)
    longer = dataclasses.replace(
        short, simulation=dataclasses.replace(short.simulation, duration=0.3)
    )
    with pytest.raises(
        MonteCarloError,
        match=r"differs in scenario_values\.simulation\.duration \(0\.2 in the folder, 0\.3 now\)",
    ):
        montecarlo(longer, 1, seed=3, out=out, resume=True, progress=False, optimal_cost=1.0)


def test_montecarlo_resume_refuses_a_plant_whose_code_changed(paper_scenario, tmp_path):
    """Before: the scenario's text was the same, so the sweep resumed with another plant."""
    from ofrl_drake.examples import EXAMPLES, register, two_state
    from ofrl_drake.monte_carlo import MonteCarloError, montecarlo

    scenario = dataclasses.replace(
        paper_scenario,
        system="user_two_state_mc",
        simulation=dataclasses.replace(paper_scenario.simulation, duration=0.2),
    )
    out = tmp_path / "mc"
    try:
        register("user_two_state_mc", two_state)
        montecarlo(scenario, 1, seed=3, out=out, progress=False, optimal_cost=1.0)
        register("user_two_state_mc", edited_two_state(g_scale=0.5))
        with pytest.raises(
            MonteCarloError,
            match=r"^--resume: the model dynamics differ from the folder's sweep: f, g or C",
        ):
            montecarlo(scenario, 1, seed=3, out=out, resume=True, progress=False, optimal_cost=1.0)
    finally:
        EXAMPLES.pop("user_two_state_mc")


def test_montecarlo_names_a_path_given_as_the_scenario(tmp_path):
    from ofrl_drake import ScenarioError
    from ofrl_drake.monte_carlo import montecarlo

    with pytest.raises(ScenarioError, match=r"^montecarlo: scenario must be a Scenario; got the"):
        montecarlo("diagrams/two_state_paper.yaml", 1, out=tmp_path / "mc", progress=False)


def test_a_stopped_sweep_never_removes_what_it_did_not_create(tmp_path):
    def stop_before_first_row(out, **kwargs):
        store = SweepStore(FILES, out)
        with pytest.raises(KeyboardInterrupt):
            with store.recording({"seed": 1}, mismatch=_seed_differs, **kwargs):
                raise KeyboardInterrupt

    # A finished sweep reached through a spelling with ".." over an absent folder
    # looked absent, and was removed whole.
    done = _filled(tmp_path)
    before = _tree(done)
    stop_before_first_row(tmp_path / "absent" / ".." / "out", resume=True)
    assert _tree(done) == before and not (tmp_path / "absent").exists()
    # --retry-failed drops the failed rows from the table before it runs them again; stopped
    # before a new row, the table is put back as it was found.
    stop_before_first_row(done, resume=True, retry_failed=True)
    assert _tree(done) == before
    assert [r["status"] for r in FILES.read(done / "t.csv")] == ["ok", "diverged: x left"]
    # A table created by this store but holding rows it did not write (another process
    # sweeping into the same folder) keeps the folder whole.
    shared = tmp_path / "shared"
    store = SweepStore(FILES, shared)
    with pytest.raises(KeyboardInterrupt):
        with store.recording({"seed": 1}, resume=False, mismatch=_seed_differs):
            with open(shared / "t.csv", "a") as fh:
                fh.write("other,3.0,ok\n")
            raise KeyboardInterrupt
    assert [r["name"] for r in FILES.read(shared / "t.csv")] == ["other"]


def test_a_run_s_file_belongs_to_its_row_of_the_table(tmp_path):
    # Before: a folder holding the plan but no table (the table deleted to start over)
    # kept its runs/, and the figures drew those runs as the new sweep's.
    out = _filled(tmp_path)
    (out / "runs").mkdir()
    np.savez(out / "runs" / "a.npz", t=np.arange(3.0))
    np.savez(out / "runs" / "b.npz", t=np.arange(3.0))
    (out / "t.csv").unlink()
    before = _tree(out)
    # A sweep that stops before its first row leaves the folder as it was found.
    with pytest.raises(KeyboardInterrupt):
        with SweepStore(FILES, out).recording({"seed": 1}, resume=False, mismatch=_seed_differs):
            raise KeyboardInterrupt
    assert _tree(out) == before
    # With its first row, the files of no row go; the one written with the row stays.
    store = SweepStore(FILES, out)
    with store.recording({"seed": 1}, resume=False, mismatch=_seed_differs):
        store.save_run("a.npz", {"t": np.arange(5.0)})
        store.write({"name": "a", "value": 1.0, "status": "ok"})
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["a.npz"]
    np.testing.assert_array_equal(load_arrays(out / "runs" / "a.npz")["t"], np.arange(5.0))
    # A row done again without logs removes its earlier attempt's file (none there: fine).
    store = SweepStore(FILES, out)
    with store.recording({"seed": 1}, resume=True, mismatch=_seed_differs):
        store.remove_run("a.npz")
        store.remove_run("never.npz")
        store.write({"name": "b", "value": 2.0, "status": "WallTimeExceeded: design"})
    assert list((out / "runs").iterdir()) == []


def test_montecarlo_whose_runs_all_fail_draws_no_envelope_of_older_runs(
    paper_scenario, tmp_path, monkeypatch
):
    # Before: montecarlo.csv deleted from a finished sweep, every run failing, a rerun
    # without --resume reported "0 ok" and wrote figures/envelope.png from the old runs.
    from ofrl_drake import monte_carlo
    from ofrl_drake.monte_carlo import montecarlo, write_montecarlo_report

    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=0.2)
    )
    out = tmp_path / "mc"
    rows = montecarlo(short, 2, seed=3, out=out, progress=False, optimal_cost=1.0)
    with pytest.warns(monte_carlo.IdenticalRunsWarning):  # no noise in the paper's scenario
        write_montecarlo_report(out, rows, "short")
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["seed_3.npz", "seed_4.npz"]
    assert (out / "figures" / "envelope.png").is_file()
    (out / "montecarlo.csv").unlink()

    def failing(scenario, seed, ks, mass_spread, dynamics=None):
        error = monte_carlo.MonteCarloError("the build failed")
        return [monte_carlo._failed(seed + k, {}, error, 0.0) for k in ks]

    monkeypatch.setattr(monte_carlo, "run_seeds", failing)
    rows = montecarlo(short, 2, seed=3, out=out, progress=False, optimal_cost=1.0)
    assert [r["status"] for r in rows] == ["MonteCarloError: the build failed"] * 2
    assert list((out / "runs").iterdir()) == []
    write_montecarlo_report(out, rows, "short")
    assert not (out / "figures" / "envelope.png").exists()
