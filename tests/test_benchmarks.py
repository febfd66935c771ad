"""Smoke test of the benchmark runner: a tiny run, then the output format.

No timing is asserted; only that every section reports finite numbers under
the documented keys.
"""

import json
import math

import numpy as np
import pytest

from benchmarks.__main__ import SECTIONS, main
from benchmarks.report import format_report

TIMING_KEYS = {"median", "min", "max", "runs"}
RUN_KEYS = TIMING_KEYS | {
    "us_per_evaluation",
    "num_derivative_evaluations",
    "num_steps",
    "integrator",
    "W_final_error",
    "W_max_error",
}


def _finite(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_run(run):
    assert RUN_KEYS <= set(run), sorted(RUN_KEYS - set(run))
    for key in ("median", "min", "max", "us_per_evaluation", "W_final_error", "W_max_error"):
        assert _finite(run[key]) and run[key] >= 0, key
    assert run["min"] <= run["median"] <= run["max"]
    assert all(_finite(t) and t > 0 for t in run["runs"])
    assert run["num_derivative_evaluations"] > 0 and run["num_steps"] > 0


def _check_pair(row):
    _check_run(row["ours"])
    _check_run(row["baseline"])
    assert set(row["ours"]["advance"]) == TIMING_KEYS
    assert _finite(row["ratio"]) and row["ratio"] > 0
    assert _finite(row["ratio_of_pairs"]) and row["ratio_of_pairs"] > 0


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "results.json"
    # Every section but "compile", which times fresh processes (format checked below).
    sections = [s for s in SECTIONS if s != "compile"]
    code = main(
        ["--quick", "--duration", "0.3", "--repeats", "1", "--out", str(out), "--only", *sections]
    )
    assert code == 0
    return json.loads(out.read_text())


def test_all_sections_and_metadata_are_written(results):
    for key in (
        "machine",
        "settings",
        "section_seconds",
        "speed_probe",
        "paper",
        "overhead",
        "bellman",
        "points",
        "basis",
        "state_dimension",
        "blocks",
        "integrators",
        "lmi_design",
        "targets",
    ):
        assert key in results, key
    assert results["settings"]["duration"] == pytest.approx(0.3)
    assert results["settings"]["repeats"] == 1
    assert results["machine"]["cpu_count"] >= 1
    for when in ("start", "end"):
        assert all(_finite(v) and v > 0 for v in results["speed_probe"][when].values())


def test_paper_section_compares_with_the_baseline(results):
    paper = results["paper"]
    _check_pair(paper)
    assert _finite(paper["ratio_simulation_only"])
    assert set(paper["design"]) == TIMING_KEYS
    assert paper["baseline"]["integrator"] == "scipy LSODA"
    # Both runners integrate the same equations to the same W.
    assert paper["ours"]["W_max_error"] < 1e-5
    assert paper["baseline"]["W_max_error"] < 1e-6


def test_overhead_section_reports_microseconds(results):
    o = results["overhead"]
    for key in ("diagram_us", "fused_us", "overhead_us", "max_derivative_difference"):
        assert _finite(o[key]), key
    assert o["diagram_us"] > 0 and o["fused_us"] > 0
    np.testing.assert_allclose(o["overhead_us"], o["diagram_us"] - o["fused_us"])
    # The fused baseline is the same right-hand side as the diagram.
    assert o["max_derivative_difference"] < 1e-9


def test_bellman_section_reports_microseconds_per_call(results):
    rows = results["bellman"]
    assert [row["N"] for row in rows] == [100, 1000]
    for row in rows:
        assert _finite(row["us_per_call"]) and row["us_per_call"] > 0
        assert row["us_per_call_min"] <= row["us_per_call"]


def test_compile_summary_is_formatted():
    run = {"import_numba": 0.4, "import_ofrl_drake": 2.0, "second_simulate": 0.05}
    text = format_report(
        {
            "compile": {
                "cold": {**run, "first_simulate": 9.0},
                "warm": {**run, "first_simulate": 0.5},
                "compile_s": 8.5,
                "install_bytes": {"numba": 35 * 2**20, "llvmlite": 170 * 2**20},
                "versions": {"numba": "0.68.1", "llvmlite": "0.50.0"},
            }
        }
    )
    assert "installed 35 MB + 170 MB" in text
    assert "first-call compile 8.5 s" in text


def test_scaling_sections(results):
    assert [row["N"] for row in results["points"]] == [100, 1000]
    assert [row["L"] for row in results["basis"]] == [3, 8]
    assert [row["n"] for row in results["state_dimension"]] == [2, 4]
    for section in ("points", "basis", "state_dimension"):
        for row in results[section]:
            _check_pair(row)


def test_blocks_section_times_both_block_kinds_on_every_scenario(results):
    rows = {row["scenario"]: row for row in results["blocks"]}
    assert set(rows) == {"two_state_paper", "coupled_two_state", "pendulum_upright", "cart_pole"}
    for row in rows.values():
        assert _finite(row["design_seconds"]) and row["design_seconds"] > 0
        for kind in ("symbolic", "python"):
            run = row[kind]
            assert run["min"] <= run["median"] <= run["max"]
            assert set(run["advance"]) == TIMING_KEYS
            assert run["num_derivative_evaluations"] > 0 and run["num_steps"] > 0
            assert _finite(run["us_per_evaluation"]) and run["us_per_evaluation"] > 0
        assert _finite(row["python_over_symbolic"]) and row["python_over_symbolic"] > 0
    assert "| cart_pole | 4 | python |" in format_report(results)


def test_integrator_section(results):
    rows = results["integrators"]
    assert {row["integrator"] for row in rows} == {"runge_kutta3", "radau3"}
    for row in rows:
        _check_run(row)
        assert _finite(row["accuracy"])


def test_lmi_section(results):
    rows = results["lmi_design"]
    assert {(r["backend"], r["solver"]) for r in rows} == {
        ("drake", "clarabel"),
        ("cvxpy", "clarabel"),
    }
    for row in rows:
        assert "failed" not in row, row.get("failed")
        for key in ("median", "min", "max", "solve_time", "max_eigenvalue", "gain_norm"):
            assert _finite(row[key]), key
        assert row["certified"] is True


def test_targets_have_values_limits_and_verdicts(results):
    t = results["targets"]
    assert {
        "paper_ratio",
        "paper_W_max_error",
        "overhead_us",
        "bellman_us_N100",
        "points_ratio",
        "coupled_ratio",
    } <= set(t)
    assert any(name.startswith("lmi_drake_over_cvxpy") for name in t)
    for check in t.values():
        assert _finite(check["value"]) and _finite(check["limit"])
        assert isinstance(check["met"], bool)


def test_runner_prints_markdown_tables(tmp_path, capsys):
    assert main(["--quick", "--duration", "0.1", "--repeats", "1", "--only", "overhead"]) == 0
    out = capsys.readouterr().out
    assert "| target | value | limit | met |" in out
    assert "overhead_us" in out
    assert "One derivative evaluation" in out


def test_multilink_scaling_row_on_the_pendulum():
    from benchmarks.multilink_scaling import FORMULATIONS, format_table, row

    r = row("pendulum_upright")
    assert (r["name"], r["n"], r["m"], r["q"], r["k"]) == ("pendulum_upright", 2, 1, 1, 1)
    assert r["input_vertices"] == 3
    assert r["bounds"]["method"] == "certified" and r["bounds"]["converged"] is True
    assert _finite(r["bounds"]["seconds"]) and r["bounds"]["seconds"] >= 0
    # 3 input vertices x 2^1 corners of size n; g is constant, so one structured LMI of n + k.
    assert (r["polytopic"]["blocks"], r["polytopic"]["block_size"]) == (6, 2)
    assert (r["structured"]["blocks"], r["structured"]["block_size"]) == (1, 3)
    for formulation in FORMULATIONS:
        e = r[formulation]
        assert "not_run" not in e
        assert e["feasible"] is True and e["decay_certified"] is True, formulation
        for key in ("lmi_seconds", "solve_time", "gain_norm", "condition_number"):
            assert _finite(e[key]) and e[key] > 0, (formulation, key)
    table = format_table([r])
    assert "| pendulum_upright | 2 | 1 |" in table and "| structured | 1 x 3 |" in table
