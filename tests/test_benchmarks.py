"""Smoke test of the benchmark runner: a tiny run, then the output format; and the
stronger baseline held to the fused one and to ``simulate()``.

No timing is asserted; only that every section reports finite numbers under
the documented keys, and that the baselines integrate the same loop.
"""

import json
import math

import numpy as np
import pytest

from benchmarks.__main__ import BEGIN, END, SECTIONS, main, write_markdown
from benchmarks.cases import fused_loop, initial_state, precomputed_loop, with_duration
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
    _check_run(row["precomputed"])
    _check_run(row["fused"])
    assert set(row["ours"]["advance"]) == TIMING_KEYS
    for key in ("ratio", "ratio_of_pairs", "ratio_fused", "ratio_of_pairs_fused"):
        assert _finite(row[key]) and row[key] > 0, key


@pytest.fixture(scope="module", params=["two_state_paper", "coupled_two_state"])
def baselines(request):
    from ofrl_drake import load_scenario
    from ofrl_drake.variants import design_for
    from tests.conftest import ROOT

    scenario = load_scenario(ROOT / "diagrams" / f"{request.param}.yaml")
    design = design_for(scenario)
    return scenario, design, precomputed_loop(scenario, design), fused_loop(scenario, design)


def test_stronger_baseline_is_the_fused_right_hand_side(baselines):
    """At random states (weights and Gamma far from a run's), to round-off."""
    scenario, _, strong, fused = baselines
    z0 = initial_state(scenario, fused)
    rng = np.random.default_rng(3)
    for _ in range(20):
        z = z0 + 0.5 * rng.normal(size=z0.size)
        expected = fused.rhs(0.0, z)
        np.testing.assert_allclose(strong.rhs(0.0, z), expected, rtol=1e-12, atol=1e-12)


def test_stronger_baseline_follows_simulate(paper_scenario, paper_design):
    """LSODA (rtol 1e-9) on the stronger baseline and simulate() (Runge-Kutta 3 at
    accuracy 1e-4) over the first 3 s of the paper scenario, at every logged time:
    x within 1e-4 (measured 5e-6), xhat within 1e-4 (2e-5), W within 1e-7 (1.3e-8),
    Gamma within 1e-6 (5e-8, entries up to 84) and J within 1e-4 (1e-5)."""
    from ofrl_drake import simulate
    from ofrl_drake.bellman import pack_symmetric

    scenario = with_duration(paper_scenario, 3.0)
    result = simulate(scenario, design=paper_design, progress=False)
    loop = precomputed_loop(scenario, paper_design)
    sol = loop.solve(initial_state(scenario, loop), 3.0, t_eval=result.t)
    assert sol.success
    n, L = loop.n, loop.size
    x, xhat, W, Gamma, J = np.split(sol.y.T, np.cumsum([n, n, L, L * L]), axis=1)
    np.testing.assert_allclose(x, result.x, rtol=0, atol=1e-4)
    np.testing.assert_allclose(xhat, result.xhat, rtol=0, atol=1e-4)
    np.testing.assert_allclose(W, result.W, rtol=0, atol=1e-7)
    np.testing.assert_allclose(
        pack_symmetric(Gamma.reshape(-1, L, L)), pack_symmetric(result.Gamma), rtol=0, atol=1e-6
    )
    np.testing.assert_allclose(J[:, 0], result.cost, rtol=0, atol=1e-4)


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
        "profile",
        "bellman",
        "points",
        "basis",
        "state_dimension",
        "scaling",
        "blocks",
        "integrators",
        "sweep",
        "lmi_design",
        "targets",
    ):
        assert key in results, key
    assert results["settings"]["duration"] == pytest.approx(0.3)
    assert results["settings"]["repeats"] == 1
    assert results["settings"]["baseline"]["kinds"] == ["precomputed", "fused"]
    assert results["machine"]["cpu_count"] >= 1
    for when in ("start", "end"):
        probe = results["speed_probe"][when]
        assert _finite(probe["numpy_matmul_3x3_us"]) and probe["numpy_matmul_3x3_us"] > 0
        assert _finite(probe["python_call_us"]) and probe["python_call_us"] > 0
        assert len(probe["load_average"]) == 3


def test_paper_section_compares_with_both_baselines(results):
    paper = results["paper"]
    _check_pair(paper)
    assert _finite(paper["ratio_simulation_only"])
    assert _finite(paper["ratio_simulation_only_fused"])
    assert set(paper["design"]) == TIMING_KEYS
    for kind in ("precomputed", "fused"):
        assert paper[kind]["integrator"] == "scipy LSODA"
        assert paper[kind]["W_max_error"] < 1e-6
    # All three runners integrate the same equations to the same W.
    assert paper["ours"]["W_max_error"] < 1e-5
    np.testing.assert_allclose(
        paper["ratio"], paper["ours"]["median"] / paper["precomputed"]["median"]
    )


def test_paper_floor_replaces_only_the_simulation(results):
    paper = results["paper"]
    floor = paper["floor"]
    assert set(floor["advance"]) == TIMING_KEYS
    assert set(floor["whole"]) == TIMING_KEYS
    # Logged only at 0 and the horizon, the bare loop integrates the same equations.
    assert floor["num_derivative_evaluations"] > 0
    ours, advance = paper["ours"]["runs"], paper["ours"]["advance"]["runs"]
    np.testing.assert_allclose(
        floor["whole"]["runs"],
        np.array(ours) - np.array(advance) + np.array(floor["advance"]["runs"]),
        rtol=1e-12,
    )
    np.testing.assert_allclose(
        paper["ratio_floor"], floor["whole"]["median"] / paper["precomputed"]["median"]
    )


def test_overhead_section_reports_microseconds(results):
    o = results["overhead"]
    for key in (
        "diagram_us",
        "precomputed_us",
        "fused_us",
        "overhead_us",
        "overhead_us_fused",
        "max_derivative_difference",
    ):
        assert _finite(o[key]), key
    assert o["diagram_us"] > 0 and o["precomputed_us"] > 0 and o["fused_us"] > 0
    np.testing.assert_allclose(o["overhead_us"], o["diagram_us"] - o["precomputed_us"])
    np.testing.assert_allclose(o["overhead_us_fused"], o["diagram_us"] - o["fused_us"])
    # Both baselines are the same right-hand side as the diagram.
    assert o["max_derivative_difference"] < 1e-9


def test_profile_section_splits_an_evaluation_by_block(results):
    p = results["profile"]
    slots = [b["slot"] for b in p["blocks"]]
    assert slots == [
        "plant",
        "observer",
        "controller",
        "critic",
        "policy",
        "gamma",
        "bellman",
        "running_cost",
    ]
    assert {b["slot"]: b["num_states"] for b in p["blocks"]}["gamma"] == 6  # packed, L = 3
    for key in ("diagram_us", "set_state_us", "advance_us_per_evaluation"):
        assert _finite(p[key]) and p[key] > 0, key
    assert _finite(p["outside_evaluation_us"]) and _finite(p["blocks_work_us"])
    assert p["num_states"] == 2 + 2 + 1 + 3 + 6 + 1  # plant, observer, controller, W, Gamma, J
    assert "| bellman | BellmanExtrapolator |" in format_report(results)


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


def test_cart_pole_scaling_rows(results):
    s = results["scaling"]
    assert [r["N"] for r in s["points"]] == [100, 1000]
    assert [(r["degrees"], r["L"]) for r in s["basis"]] == [([2], 10), ([2, 4], 45)]
    assert [(r["n"], r["scenario"]) for r in s["state_dimension"]] == [
        (2, "pendulum_upright"),
        (4, "cart_pole"),
        (6, "planar_quadrotor"),
    ]
    for rows in s.values():
        assert rows[0]["seconds_per_simulated_second_growth"] == 1.0
        for r in rows:
            assert r["status"] == "ok"
            for key in (
                "seconds_per_simulated_second",
                "evaluations_per_simulated_second",
                "us_per_evaluation",
                "seconds_per_simulated_second_growth",
                "evaluations_growth",
                "us_per_evaluation_growth",
            ):
                assert _finite(r[key]) and r[key] > 0, key
            np.testing.assert_allclose(
                r["seconds_per_simulated_second"], r["median"] / r["duration"]
            )
    assert "| 6 (planar_quadrotor, L = 21, N = 200) |" in format_report(results)


def test_sweep_section_times_one_against_more_initial_states(results):
    s = results["sweep"]
    assert s["counts"] == [1, 2] and s["workers"] == 1
    for mode in ("solved", "cached"):
        for k, case in s[mode]["cases"].items():
            assert case["statuses"] == ["ok"], (mode, k)
            assert _finite(case["runs_per_second"]) and case["runs_per_second"] > 0
            np.testing.assert_allclose(case["runs_per_second"], int(k) / case["median"])
        for key in ("extra_state_seconds", "extra_state_over_simulation"):
            assert _finite(s[mode][key]), key
    assert "One extra initial state costs" in format_report(results)


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
        "sweep_extra_state_over_simulation",
    } <= set(t)
    assert any(name.startswith("lmi_drake_over_cvxpy") for name in t)
    for check in t.values():
        assert _finite(check["value"]) and _finite(check["limit"])
        assert isinstance(check["met"], bool)
    # Against the stronger baseline, with the fused one beside it.
    assert t["paper_ratio"]["value"] == results["paper"]["ratio"]
    assert t["paper_ratio"]["fused"] == results["paper"]["ratio_fused"]
    assert t["coupled_ratio"]["fused"] > 0


def test_runner_prints_and_writes_markdown_tables(tmp_path, capsys):
    md = tmp_path / "tables.md"
    args = ["--quick", "--duration", "0.1", "--repeats", "1", "--only", "overhead"]
    assert main([*args, "--markdown", str(md)]) == 0
    out = capsys.readouterr().out
    assert "| target | value (stronger baseline) | fused baseline | limit | met |" in out
    assert "overhead_us" in out
    assert "One derivative evaluation" in out
    assert "Load average (1, 5, 15 min) at the start" in out
    assert md.read_text().strip() == out.strip()


def test_markdown_goes_between_the_markers_of_an_existing_file(tmp_path):
    page = tmp_path / "RESULTS.md"
    page.write_text(f"# Title\n\nprose\n\n{BEGIN}\nold tables\n{END}\n\nmore prose\n")
    write_markdown(page, "| new | tables |")
    assert page.read_text() == (
        f"# Title\n\nprose\n\n{BEGIN}\n\n| new | tables |\n\n{END}\n\nmore prose\n"
    )
    plain = tmp_path / "plain.md"
    write_markdown(plain, "| t |")
    assert plain.read_text() == "| t |\n"


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
