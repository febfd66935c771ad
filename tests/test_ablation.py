"""Ablation sweeps: against the optimum, on Dask, with failures, resumed after a kill."""

import dataclasses
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump, yaml_load

from ofrl_drake.ablation import CSV_COLUMNS, ablate, read_rows
from ofrl_drake.ablation_grid import (
    AblationError,
    Variant,
    default_variants,
    initial_state_label,
    initial_states_by_label,
    sample_initial_states,
)
from ofrl_drake.ablation_metrics import (
    optimality_ratio,
    rms_estimation_error,
    settling_time,
    time_outside_box,
)
from ofrl_drake.ablation_tasks import _run, _scenario_for, run_variant
from ofrl_drake.cli import main
from ofrl_drake.diagram import build_closed_loop
from ofrl_drake.slots import VARIANT_FACTORIES
from ofrl_drake.variants import design_for

from .conftest import PAPER_SCENARIO, ROOT, edited_two_state

#: J and J* are compared over 10 s instead of 30 s: every variant is within
#: 1e-6 of its final cost by then (|x(10)| < 1e-4), and both use the same horizon.
HORIZON = 10.0

DEFAULT_NAMES = [
    "baseline",
    "observer=linear_luenberger",
    "observer=drake_luenberger",
    "observer=kalman",
    "observer=true_state",
    "controller=lqr",
    "controller=frozen_critic",
    "points=uniform",
    "points=around_estimate",
    "gamma=constant",
]
SMALL_VARIANTS = "baseline: {}\nlqr: {controller: lqr}\nfull_state: {observer: true_state}\n"


def _key(row):
    return row["variant"], row["initial_state"]


def _same(a, b):
    """Rows equal in every column but wall_time (NaN equal to NaN)."""
    for c in CSV_COLUMNS:
        if c == "wall_time":
            continue
        x, y = a[c], b[c]
        if isinstance(x, float) and math.isnan(x):
            assert isinstance(y, float) and math.isnan(y), (c, a, b)
        else:
            assert x == y, (c, a, b)


@pytest.fixture(scope="module")
def every_variant(paper_scenario):
    return ablate(paper_scenario, duration=HORIZON, progress=False)


@pytest.fixture(scope="module")
def short_files(tmp_path_factory):
    """A 2 s copy of the paper scenario and a three-variant file."""
    d = tmp_path_factory.mktemp("short")
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    data["simulation"]["duration"] = 2.0
    scenario = d / "short.yaml"
    scenario.write_text(yaml_dump(data))
    variants = d / "variants.yaml"
    variants.write_text(SMALL_VARIANTS)
    return scenario, variants


# ------------------------------------------------------------ against J*
def test_default_variants_are_the_baseline_and_every_single_swap(paper_scenario):
    variants = default_variants(paper_scenario)
    assert [v.name for v in variants] == DEFAULT_NAMES
    assert variants[0].choices == {}
    assert all(len(v.choices) == 1 for v in variants[1:])


def test_every_variant_costs_at_least_the_optimum(every_variant):
    rows = every_variant
    assert [r["variant"] for r in rows] == DEFAULT_NAMES
    assert {r["initial_state"] for r in rows} == {"[-1.0, 1.0]"}
    optimal = {r["optimal_cost"] for r in rows}
    assert len(optimal) == 1
    (j_star,) = optimal
    assert j_star == pytest.approx(3.7511, rel=1e-4)
    for r in rows:
        assert r["status"] == "ok", r
        assert j_star <= 1.01 * r["cost"], r
        assert r["optimality_ratio"] == pytest.approx(r["cost"] / j_star, rel=1e-15)
        assert r["final_state_norm"] < 1e-3, r
        assert 0 < r["settling_time"] < HORIZON, r
        assert r["min_learning_condition"] > 0, r


def test_full_state_costs_no_more_than_output_feedback(every_variant):
    cost = {r["variant"]: r["cost"] for r in every_variant}
    assert cost["observer=true_state"] <= 1.05 * cost["baseline"]


def test_rows_are_consistent_with_the_variant(every_variant):
    row = {r["variant"]: r for r in every_variant}
    assert row["observer=true_state"]["rms_estimation_error"] == 0.0
    assert row["observer=true_state"]["time_outside_box"] == 0.0
    # xhat(0) = (2, 1.5) is on the box edge and leaves it briefly under output feedback.
    assert row["baseline"]["time_outside_box"] > 0.0
    assert row["baseline"]["rms_estimation_error"] > 0.1


def test_policy_costs_measure_what_learning_buys(every_variant):
    """The policy in force at 0 and T, fed the true state: learning improves it, freezing not."""
    row = {r["variant"]: r for r in every_variant}
    base, frozen = row["baseline"], row["controller=frozen_critic"]
    assert base["initial_policy_cost"] == frozen["initial_policy_cost"]  # same W0
    assert frozen["final_policy_cost"] == frozen["initial_policy_cost"]
    assert base["final_policy_cost"] < 0.9 * base["initial_policy_cost"]
    assert base["final_policy_ratio"] == pytest.approx(
        base["final_policy_cost"] / base["optimal_cost"], rel=1e-15
    )
    assert base["final_policy_ratio"] >= 1.0 - 1e-6  # no policy beats J*
    for name in ("controller=lqr",):  # does not act on the critic
        assert math.isnan(row[name]["initial_policy_cost"])
        assert math.isnan(row[name]["final_policy_ratio"])


# -------------------------------------------------------------- metrics
def test_metrics_on_known_trajectories():
    t = np.linspace(0.0, 4.0, 5)
    x = np.array([[1.0, 0.0], [0.02, 0.0], [0.005, 0.0], [0.011, 0.0], [0.001, 0.0]])
    assert settling_time(t, x) == 4.0
    assert settling_time(t, x[[0, 1, 2, 4, 4]]) == 2.0
    assert settling_time(t, np.zeros((5, 2))) == 0.0
    assert settling_time(t, np.ones((5, 2))) == math.inf
    xhat = x + np.array([1.0, 0.0])
    assert rms_estimation_error(t, x, xhat) == pytest.approx(1.0, rel=1e-15)
    box = (np.array([-0.5, -0.5]), np.array([0.5, 0.5]))
    # x(0) = 1 and xhat(k) = x(k) + 1 lie outside at every sample: [0, 4).
    assert time_outside_box(t, x, xhat, *box) == 4.0
    assert time_outside_box(t, x * 0, x * 0, *box) == 0.0
    assert time_outside_box(t, x, x, *box) == 1.0
    assert optimality_ratio(2.0, 4.0) == 0.5
    assert math.isnan(optimality_ratio(2.0, math.nan))
    assert math.isnan(optimality_ratio(2.0, 0.0))


def test_rms_estimation_error_integrates_a_varying_error_over_uneven_samples():
    # e = x - xhat at t = 1, 2, 4: |e|^2 = 5, 1, 0. Trapezoid over [1, 2] and [2, 4]:
    # (5 + 1) / 2 * 1 + (1 + 0) / 2 * 2 = 4, over T = 3 s: RMS = sqrt(4 / 3).
    # (The mean of |e|^2 gives sqrt(2), the largest sqrt(5), the left-point rule
    # sqrt(7 / 3), dividing by t[-1] instead of T gives 1.)
    t = np.array([1.0, 2.0, 4.0])
    e = np.array([[1.0, 2.0], [0.0, -1.0], [0.0, 0.0]])
    x = np.array([[1.0, 2.5], [0.3, -1.0], [0.0, 0.2]])
    assert rms_estimation_error(t, x, x - e) == pytest.approx(math.sqrt(4.0 / 3.0), rel=1e-12)


def test_csv_columns_are_exactly_the_issue_s():
    assert CSV_COLUMNS == (
        "variant",
        "initial_state",
        "cost",
        "optimal_cost",
        "optimality_ratio",
        "final_state_norm",
        "settling_time",
        "rms_estimation_error",
        "min_learning_condition",
        "time_outside_box",
        "initial_policy_cost",
        "final_policy_cost",
        "initial_policy_ratio",
        "final_policy_ratio",
        "regulated",
        "wall_time",
        "status",
    )


# ------------------------------------------------ one build per variant
def test_a_sweep_builds_and_designs_once_per_variant(paper_scenario, tmp_path, monkeypatch):
    import ofrl_drake.design as design

    calls = []
    original = design.design_observer

    def counted(*args, **kwargs):
        calls.append(args[1])
        return original(*args, **kwargs)

    monkeypatch.setattr(design, "design_observer", counted)
    variants = [
        Variant("baseline"),
        Variant("lqr", {"controller": "lqr"}),
        Variant("full_state", {"observer": "true_state"}),
    ]
    states = [[-1.0, 1.0], [-1.5, 0.5], [0.5, -0.5]]
    rows = ablate(paper_scenario, variants, states, out=tmp_path, duration=1.0, progress=False)
    assert len(rows) == 9 and {r["status"] for r in rows} == {"ok"}
    # baseline and lqr design their three-gain observer once each; true_state has none.
    assert len(calls) == 2
    # Serially, the table is written variant by variant, in the order ablate() returns.
    assert [_key(r) for r in read_rows(tmp_path / "ablation.csv")] == [_key(r) for r in rows]


def test_one_build_runs_every_state_as_a_build_per_state(paper_scenario):
    """run_variant_states re-runs one loop; run_variant builds one per state: same bits."""
    from ofrl_drake.ablation_tasks import run_variant_states

    states = [[-1.0, 1.0], [0.5, -0.5]]
    for variant in (Variant("baseline"), Variant("kalman", {"observer": "kalman"})):
        together = run_variant_states(paper_scenario, variant, states, 1.0)
        for outcome, x0 in zip(together, states, strict=True):
            alone = run_variant(paper_scenario, variant, x0, 1.0)
            assert outcome.status == alone.status == "ok"
            assert outcome.initial_state == alone.initial_state == initial_state_label(x0)
            assert outcome.metrics == alone.metrics  # every metric, policy costs included
            assert outcome.logs.keys() == alone.logs.keys()
            for key in outcome.logs:
                assert np.array_equal(outcome.logs[key], alone.logs[key]), key
    broken = run_variant_states(paper_scenario, Variant("x", {"observer": "nonsense"}), states)
    assert [o.status for o in broken] == [
        "ScenarioError: variant.observer: unknown choice 'nonsense'; choose one of "
        "['drake_luenberger', 'kalman', 'linear_luenberger', 'three_gain', 'true_state']."
    ] * 2


# ------------------------------------------------------- initial states
def test_sampled_initial_states(paper_scenario):
    states = sample_initial_states(paper_scenario, 5, seed=3)
    assert states.shape == (6, 2)
    np.testing.assert_array_equal(states[0], paper_scenario.x0)
    np.testing.assert_array_equal(states, sample_initial_states(paper_scenario, 5, seed=3))
    assert not np.array_equal(states, sample_initial_states(paper_scenario, 5, seed=4))
    offset = np.asarray(paper_scenario.xhat0) - np.asarray(paper_scenario.x0)
    lo, hi = paper_scenario.observer.box.lower, paper_scenario.observer.box.upper
    for x0 in states:
        for z in (x0, x0 + offset):
            assert np.all(z >= lo) and np.all(z <= hi), z
    np.testing.assert_array_equal(states, np.round(states, 6))
    assert initial_state_label(states[0]) == "[-1.0, 1.0]"
    wide = dataclasses.replace(paper_scenario, xhat0=[3.5, 1.5])
    with pytest.raises(AblationError, match=r"as wide as the observer box in axis 0"):
        sample_initial_states(wide, 2, seed=0)
    with pytest.raises(AblationError, match=r"must be an integer >= 0"):
        sample_initial_states(paper_scenario, -1, seed=0)


def test_ablate_rejects_bad_input(paper_scenario, tmp_path):
    with pytest.raises(AblationError, match=r"distinct names"):
        ablate(paper_scenario, [Variant("a"), Variant("a")])
    with pytest.raises(AblationError, match=r"expected finite rows of 2 numbers"):
        ablate(paper_scenario, [Variant("a")], [[0.0, 0.0, 0.0]])
    with pytest.raises(AblationError, match=r"repeated states"):
        ablate(paper_scenario, [Variant("a")], [[0.1, 0.2], [0.1, 0.2]])
    (tmp_path / "ablation.csv").write_text(",".join(CSV_COLUMNS) + "\n")
    (tmp_path / "ablation.json").write_text("{}\n")  # an earlier sweep's plan
    with pytest.raises(AblationError, match=r"ablation.csv exists; pass --resume"):
        ablate(paper_scenario, [Variant("a")], out=tmp_path)


SLOTS = r"slots are \['controller', 'gamma', 'observer', 'points'\]"
OBSERVERS = r"choose one of \['drake_luenberger', 'kalman', 'linear_luenberger', 'three_gain'"


@pytest.mark.parametrize(
    ("variants", "match"),
    [
        ({"kal": {"obsrver": "kalman"}}, r"^variants\.kal\.obsrver: unknown slot; " + SLOTS),
        ([Variant("k", {"obs": "kalman"})], r"^variants\.k\.obs: unknown slot; " + SLOTS),
        (
            {"k": {"observer": "kalmn"}},
            r"variants\.k\.observer: unknown choice 'kalmn'; " + OBSERVERS,
        ),
        ([Variant("k", {"observer": ["kalman"]})], r"unknown choice \['kalman'\]; " + OBSERVERS),
        (
            ["baseline"],
            r"^variants\[0\]: expected a Variant\(name, \{slot: choice\}\); got 'baseline'",
        ),
        ("baseline", r"^variants: expected a list of Variant or a mapping .*; got 'baseline'"),
        ({"b": "kalman"}, r"^variants\.b: expected a mapping of slot: choice; got 'kalman'"),
        ([Variant(3, {})], r"^variants\[0\]: a variant's name must be a non-empty string; got 3"),
        (
            {"base|line": {}},
            r"^variants: the variant name 'base\|line' holds '\|', which would break the tables",
        ),
        ([Variant("lqr\nnew", {})], r"^variants\[0\]: the variant name 'lqr\\nnew' holds '\\n'"),
        (
            {"held": {"controller": "constant"}},
            r"^variants\.held: variant\.constant_input: expected 1 entries; got 0",
        ),
    ],
)
def test_ablate_refuses_a_bad_variant_before_any_run(paper_scenario, tmp_path, variants, match):
    """Checked as a --variants file is, the slot or choices listed; nothing is run or written."""
    out = tmp_path / "sweep"
    with pytest.raises(AblationError, match=match):
        ablate(paper_scenario, variants, out=out, progress=False)
    assert not out.exists()


@pytest.mark.parametrize(
    ("variants", "match"),
    [
        (
            {"a/b": {}, "a_b": {"controller": "lqr"}},
            r"^variants: 'a/b' and 'a_b' would share the files runs/a_b__<initial state>\.npz "
            r"\(characters other than letters, digits and _ \. = - become _ in a file name\); "
            r"rename one of them\.$",
        ),
        (
            [Variant("a b"), Variant("a, b", {"controller": "lqr"})],
            r"^variants: 'a b' and 'a, b' would share the files runs/a_b__<initial state>\.npz",
        ),
        (
            {"LQR": {"controller": "lqr"}, "lqr": {}},
            r"^variants: 'LQR' and 'lqr' would share the files runs/lqr__<initial state>\.npz "
            r"\(the file systems of macOS and Windows do not tell upper from lower case\); "
            r"rename one of them\.$",
        ),
        (
            {"v" * 228: {}},
            r"^variants: the name 'v{40}'\.\.\. has 228 characters as a file name in runs/; "
            r"shorten it to at most 227\.$",
        ),
    ],
    ids=["slash", "spaces_and_commas", "case", "too_long"],
)
def test_ablate_refuses_names_whose_run_files_clash_before_any_run(
    paper_scenario, tmp_path, variants, match
):
    """One file per (variant, initial state) in runs/: the figures and J*'s warm start read it."""
    out = tmp_path / "sweep"
    with pytest.raises(AblationError, match=match):
        ablate(paper_scenario, variants, out=out, duration=2.0, progress=False)
    assert not out.exists()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "a: {}\na: {controller: lqr}\n",
            r"key 'a' appears twice in one mapping \(lines 1 and 2\)",
        ),
        (
            "a: {controller: lqr, controller: learned}\n",
            r"key 'controller' appears twice in one mapping \(lines 1 and 1\)",
        ),
    ],
    ids=["variant", "slot"],
)
def test_a_variants_file_that_repeats_a_key_is_refused(tmp_path, text, match):
    """Drake's loader would keep the last silently: only the second `a` would run."""
    from ofrl_drake.ablation_grid import load_variants

    path = tmp_path / "variants.yaml"
    path.write_text(text)
    with pytest.raises(AblationError, match=rf"^{re.escape(str(path))}: {match}; keep one\.$"):
        load_variants(path)


@pytest.mark.parametrize(("key", "kind"), [("1", "int"), ("true", "bool"), ("null", "null")])
def test_a_variants_file_whose_name_is_not_a_string_says_so(tmp_path, key, kind):
    """Before: 'not valid YAML: 'int' object has no attribute 'startswith'' (Drake's loader)."""
    from ofrl_drake.ablation_grid import load_variants

    path = tmp_path / "variants.yaml"
    path.write_text(f"baseline: {{}}\n{key}: {{controller: lqr}}\n")
    with pytest.raises(
        AblationError,
        match=rf"variants\.yaml: line 2: the variant name '{key}' reads as a YAML {kind}, not a "
        rf"string; quote it \('{key}': \.\.\.\)\.$",
    ):
        load_variants(path)
    path.write_text(f"baseline: {{}}\n'{key}': {{controller: lqr}}\n")
    assert [v.name for v in load_variants(path)] == ["baseline", key]


def test_a_variants_file_nested_too_deep_is_refused_as_a_variants_file(tmp_path):
    from ofrl_drake.ablation_grid import load_variants

    path = tmp_path / "variants.yaml"
    path.write_text("baseline: " + "[" * 30 + "1" + "]" * 30 + "\n")
    with pytest.raises(
        AblationError,
        match=r"variants\.yaml: line 1: lists and mappings nested more than 20 levels deep; "
        r"no variants file needs that",
    ):
        load_variants(path)


def test_a_variants_file_that_is_not_utf8_is_refused(tmp_path):
    from ofrl_drake.ablation_grid import load_variants

    path = tmp_path / "variants.yaml"
    path.write_bytes(b"baseline: {}\n\xe9t\xe9: {controller: lqr}\n")
    with pytest.raises(
        AblationError, match=r"variants\.yaml: not UTF-8 text \(.*\); save it as UTF-8"
    ):
        load_variants(path)


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"duration": 0}, r"^duration must be > 0; got 0\.0"),
        ({"duration": math.nan}, r"^duration must be finite; got nan"),
        ({"solver": "ipop"}, r"solver must be one of \('snopt', 'ipopt'\); got 'ipop'"),
        ({"mesh": "x"}, r"mesh must be a Mesh\(initial_step, growth, max_step\) or None .*got 'x'"),
        (  # the horizon's fault, not the first variant's
            {"duration": 0.01},
            r"^scenario over duration = 0\.01 s: simulation\.log_period: 0\.02 s is longer",
        ),
    ],
)
def test_ablate_refuses_a_bad_horizon_mesh_or_solver_before_any_run(
    paper_scenario, tmp_path, options, match
):
    out = tmp_path / "sweep"
    with pytest.raises(AblationError, match=match):
        ablate(paper_scenario, [Variant("baseline")], out=out, progress=False, **options)
    assert not out.exists()


def test_ablate_names_a_path_given_as_the_scenario(tmp_path):
    from ofrl_drake import ScenarioError

    with pytest.raises(ScenarioError, match=r"^ablate: scenario must be a Scenario; got the path"):
        ablate("diagrams/two_state_paper.yaml", out=tmp_path / "sweep", progress=False)


def test_ablate_never_writes_into_a_folder_it_did_not_create(paper_scenario, tmp_path):
    foreign = tmp_path / "mine"
    (foreign / "figures").mkdir(parents=True)
    (foreign / "figures" / "trajectories.png").write_bytes(b"my figure")
    with pytest.raises(AblationError, match=r"mine is not empty and was not written by ofrl-drake"):
        ablate(paper_scenario, [Variant("a")], [[0.1, 0.2]], out=foreign)
    assert (foreign / "figures" / "trajectories.png").read_bytes() == b"my figure"
    assert sorted(p.name for p in foreign.rglob("*")) == ["figures", "trajectories.png"]
    a_file = tmp_path / "afile"
    a_file.write_text("x")
    with pytest.raises(AblationError, match=r"afile exists and is not a folder"):
        ablate(paper_scenario, [Variant("a")], [[0.1, 0.2]], out=a_file)


# ---------------------------------------------------------- robustness
def test_a_failing_variant_is_recorded_and_the_others_finish(paper_scenario, tmp_path, monkeypatch):
    def broken(parts):
        raise RuntimeError("observer exploded\non purpose")

    monkeypatch.setitem(VARIANT_FACTORIES["observer"], "broken", broken)
    variants = [Variant("baseline"), Variant("broken", {"observer": "broken"})]
    rows = ablate(paper_scenario, variants, [[-1.0, 1.0], [-1.5, 0.5]], out=tmp_path, duration=2.0)
    status = {_key(r): r["status"] for r in rows}
    assert len(rows) == 4
    for label in ("[-1.0, 1.0]", "[-1.5, 0.5]"):
        assert status[("baseline", label)] == "ok"
        assert status[("broken", label)] == "RuntimeError: observer exploded on purpose"
    broken_row = next(r for r in rows if r["variant"] == "broken")
    assert math.isnan(broken_row["cost"]) and math.isnan(broken_row["optimality_ratio"])
    assert broken_row["optimal_cost"] > 0  # J* is computed all the same
    on_disk = read_rows(tmp_path / "ablation.csv")
    assert sorted(map(_key, on_disk)) == sorted(map(_key, rows))


def test_a_run_keeps_the_scenario_s_constant_input(paper_scenario):
    """The run's scenario takes the variant's slot choices and keeps the rest of ``variant``."""
    variant = dataclasses.replace(
        paper_scenario.variant, controller="constant", constant_input=[0.5]
    )
    scenario = dataclasses.replace(paper_scenario, variant=variant)
    outcome = run_variant(scenario, Variant("baseline"), [-1.0, 1.0], duration=0.2)
    assert outcome.status == "ok", outcome.status
    np.testing.assert_array_equal(outcome.logs["u"][:, 0], 0.5)


def test_a_run_the_guard_stops_is_recorded_with_its_status(paper_scenario):
    # The design fits no budget of 1 ms, so it is made without one and the loop
    # built with it: the guard, not the design, stops the run.
    baseline = Variant("baseline")
    simulation = dataclasses.replace(paper_scenario.simulation, max_wall_time=1e-3)
    scenario = dataclasses.replace(paper_scenario, simulation=simulation)
    run = _scenario_for(scenario, baseline, [-1.0, 1.0], None)
    loop = build_closed_loop(run, design=design_for(paper_scenario))
    outcome = _run(loop, None, run, baseline, build_share=0.0)
    assert outcome.status.startswith("timeout: wall time ")
    assert "exceeded max_wall_time = 0.001 s" in outcome.status
    # A truncated run is not comparable with J*: no metrics, no warm start.
    assert all(math.isnan(v) for v in outcome.metrics.values())
    assert outcome.logs["t"].size >= 1
    assert outcome.warm_start() is None


def test_the_policy_evaluations_share_the_runs_budget(paper_scenario, monkeypatch):
    # The policy costs at 0 and T are two more simulations over the horizon after the run;
    # --max-wall did not bound them. Here the run's budget is spent before they begin.
    import types

    from ofrl_drake import ablation_tasks
    from ofrl_drake.learning_curve import PolicyEvaluator

    baseline = Variant("baseline")
    simulation = dataclasses.replace(paper_scenario.simulation, max_wall_time=60.0)
    run = _scenario_for(
        dataclasses.replace(paper_scenario, simulation=simulation), baseline, [-1.0, 1.0], 1.0
    )
    loop = build_closed_loop(run, design=design_for(paper_scenario))
    whole = _run(loop, PolicyEvaluator(loop), run, baseline, build_share=0.0)
    assert whole.status == "ok" and math.isfinite(whole.metrics["final_policy_cost"])
    clock = types.SimpleNamespace(
        monotonic=lambda: time.monotonic() - 61.0, perf_counter=time.perf_counter
    )
    monkeypatch.setattr(ablation_tasks, "time", clock)  # the deadline: a second ago
    late = _run(loop, PolicyEvaluator(loop), run, baseline, build_share=0.0)
    assert late.status.startswith("timeout: the policy evaluation passed its deadline at t = ")
    assert late.status.endswith("(max_wall_time = 60 s)")
    assert math.isnan(late.metrics["initial_policy_cost"])
    # The run itself is whole: its own metrics are those of the run without a deadline.
    for name, value in whole.metrics.items():
        if not name.endswith("policy_cost"):
            assert late.metrics[name] == value, name


def test_a_design_out_of_wall_time_is_a_timeout_row(paper_scenario):
    simulation = dataclasses.replace(paper_scenario.simulation, max_wall_time=1e-3)
    scenario = dataclasses.replace(paper_scenario, simulation=simulation)
    outcome = run_variant(scenario, Variant("baseline"), [-1.0, 1.0])
    # The budget runs out in the bounds or, on a loaded machine, already in the symbolic
    # Jacobians before them (as in test_guard): either phase names --max-wall.
    assert re.match(
        r"timeout: (the observer design's Jacobian bounds took .* of max_wall_time "
        r"\(--max-wall\) = 0\.001 s|the symbolic Jacobians of f and g were not done by the "
        r"deadline \(max_wall_time, --max-wall\))",
        outcome.status,
    ), outcome.status
    assert all(math.isnan(v) for v in outcome.metrics.values())
    assert outcome.warm_start() is None


def test_resume_completes_a_table_with_a_torn_last_line(paper_scenario, tmp_path):
    variants = [Variant("baseline"), Variant("lqr", {"controller": "lqr"})]
    states = [[-1.0, 1.0], [-1.5, 0.5]]
    full = ablate(paper_scenario, variants, states, out=tmp_path / "a", duration=2.0)
    lines = (tmp_path / "a" / "ablation.csv").read_text().splitlines(keepends=True)
    assert len(lines) == 5
    # A sweep killed while writing its third row: the folder as it was then.
    part = tmp_path / "b"
    shutil.copytree(tmp_path / "a", part)
    (part / "ablation.csv").write_text("".join(lines[:3]) + lines[3][:25])
    rows = ablate(paper_scenario, variants, states, out=part, resume=True, duration=2.0)
    text = (part / "ablation.csv").read_text()
    assert text.startswith("".join(lines[:3]))
    on_disk = read_rows(part / "ablation.csv")
    assert len(on_disk) == 4 and len(set(map(_key, on_disk))) == 4
    for a, b in zip(sorted(rows, key=_key), sorted(full, key=_key), strict=True):
        _same(a, b)
    # The same table, row for row in the same order, as the uninterrupted sweep's.
    for a, b in zip(on_disk, read_rows(tmp_path / "a" / "ablation.csv"), strict=True):
        _same(a, b)
    # The finished rows were kept, not re-run (repr: NaN columns compare equal).
    assert repr(on_disk[:2]) == repr(read_rows(tmp_path / "a" / "ablation.csv")[:2])


def test_resume_refuses_another_scenario(paper_scenario, tmp_path):
    ablate(paper_scenario, [Variant("baseline")], out=tmp_path, duration=1.0)
    other = dataclasses.replace(paper_scenario, input_bound=2.0)
    with pytest.raises(
        AblationError,
        match=r"--resume: the scenario differs in input_bound \(3.0 in the folder, 2.0 now\)",
    ):
        ablate(other, [Variant("baseline")], out=tmp_path, resume=True, duration=1.0)
    with pytest.raises(AblationError, match=r"--resume: the folder's sweep used --seed None"):
        ablate(paper_scenario, [Variant("baseline")], out=tmp_path, resume=True, seed=3)
    with pytest.raises(AblationError, match=r"--resume: the folder's sweep runs 1 initial states"):
        ablate(paper_scenario, [Variant("baseline")], [[0.5, 0.5]], out=tmp_path, resume=True)
    with pytest.raises(AblationError, match=r"--resume: the variants differ \(new \['lqr'\]\)"):
        ablate(
            paper_scenario,
            [Variant("baseline"), Variant("lqr", {"controller": "lqr"})],
            out=tmp_path,
            resume=True,
        )
    with pytest.raises(AblationError, match=r"has a horizon of 1.0 s, this one 2.0 s"):
        ablate(paper_scenario, [Variant("baseline")], out=tmp_path, resume=True, duration=2.0)


def test_resume_refuses_another_way_of_solving_j_star(paper_scenario, tmp_path):
    """Before: the plan had no mesh or solver, and a resume mixed two J* of one state."""
    from ofrl_drake.optimal import Mesh

    coarse = Mesh(refinements=0)
    variants = [Variant("baseline")]
    ablate(paper_scenario, variants, out=tmp_path, duration=0.5, mesh=coarse, progress=False)
    plan = json.loads((tmp_path / "ablation.json").read_text())
    assert plan["optimal"] == {"mesh": dataclasses.asdict(coarse), "solver": "snopt"}
    with pytest.raises(
        AblationError,
        match=r"^--resume: the folder's sweep had J\* solved by snopt on Mesh\(initial_step=0\.05, "
        r"growth=1\.03, max_step=0\.5, rtol=0\.001, refinements=0\), this one solved by snopt on "
        r"Mesh\(.*refinements=3\): rows would be scored against different J\*; resume with the "
        r"sweep's own arguments, or choose another --out\.$",
    ):
        ablate(paper_scenario, variants, out=tmp_path, resume=True, duration=0.5)
    rows = ablate(paper_scenario, variants, out=tmp_path, resume=True, duration=0.5, mesh=coarse)
    assert [row["status"] for row in rows] == ["ok"]
    # A folder of an earlier ofrl_drake, whose J* was not checked on a finer grid.
    del plan["optimal"]
    (tmp_path / "ablation.json").write_text(json.dumps(plan))
    with pytest.raises(
        AblationError,
        match=r"^--resume: the folder's sweep was written by an ofrl_drake that did not record "
        r"how J\* is had \(before J\* was checked on a finer grid\), so its rows' J\* may differ "
        r"from this sweep's; start the sweep again in another --out\.$",
    ):
        ablate(paper_scenario, variants, out=tmp_path, resume=True, duration=0.5, mesh=coarse)


def test_resume_refuses_a_plant_whose_code_changed(paper_scenario, tmp_path):
    """Before: the scenario's text was the same, so the sweep resumed with another plant."""
    from ofrl_drake.examples import EXAMPLES, register, two_state

    scenario = dataclasses.replace(paper_scenario, system="user_two_state")
    try:
        register("user_two_state", two_state)
        ablate(scenario, [Variant("baseline")], out=tmp_path, duration=0.5)
        register("user_two_state", edited_two_state(f_scale=0.9))
        with pytest.raises(
            AblationError,
            match=r"--resume: the model dynamics differ from the folder's sweep: f, g or C "
            r"give other values at the same states \(was the plant's code edited\?\)",
        ):
            ablate(scenario, [Variant("baseline")], out=tmp_path, resume=True, duration=0.5)
        register("user_two_state", two_state)  # the code as it was: the sweep resumes
        rows = ablate(scenario, [Variant("baseline")], out=tmp_path, resume=True, duration=0.5)
    finally:
        EXAMPLES.pop("user_two_state")
    assert [row["status"] for row in rows] == ["ok"]


# -------------------------------------------------------- Dask and CLI
def test_dask_cluster_gives_the_serial_rows_and_the_report(short_files, tmp_path, capsys):
    import matplotlib.pyplot as plt
    from distributed import LocalCluster

    from ofrl_drake import load_scenario
    from ofrl_drake.ablation_grid import load_variants

    scenario_file, variants_file = short_files
    out = tmp_path / "dask"
    plt.close("all")
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        code = main(
            [
                "ablate",
                str(scenario_file),
                "--out",
                str(out),
                "--variants",
                str(variants_file),
                "--initial-states",
                "1",
                "--scheduler",
                cluster.scheduler_address,
            ]
        )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert f"wrote {out}: 6 runs (6 ok)" in captured.out, captured.out
    assert plt.get_fignums() == []  # the report's figures are closed once written
    scenario = load_scenario(scenario_file)
    serial = ablate(
        scenario,
        load_variants(variants_file),
        sample_initial_states(scenario, 1, seed=0),
        progress=False,
    )
    dask_rows = read_rows(out / "ablation.csv")
    assert len(dask_rows) == len(serial) == 6
    for a, b in zip(sorted(dask_rows, key=_key), sorted(serial, key=_key), strict=True):
        _same(a, b)
    md = (out / "ablation.md").read_text()
    assert "| variant | runs | ok | J | J/J* |" in md
    for name in ("baseline", "lqr", "full_state"):
        assert f"| {name} | 2 | 2 | " in md
    from PIL import Image

    for figure in ("optimality_ratio.png", "trajectories.png"):
        with Image.open(out / "figures" / figure) as image:
            assert min(image.info["dpi"]) >= 149.9, figure


def _ablate_command(scenario_file, variants_file, out, *, initial_states, workers):
    """``python -m ofrl_drake ablate ...`` as a subprocess argument list."""
    return [
        sys.executable,
        "-m",
        "ofrl_drake",
        "ablate",
        str(scenario_file),
        "--out",
        str(out),
        "--variants",
        str(variants_file),
        "--initial-states",
        str(initial_states),
        "--workers",
        str(workers),
    ]


def test_cli_with_an_embedded_local_cluster(short_files, tmp_path):
    """`--workers 2` (docs/ablations.md): the CLI starts and stops its own LocalCluster."""
    scenario_file, variants_file = short_files
    out = tmp_path / "local"
    proc = subprocess.run(
        _ablate_command(scenario_file, variants_file, out, initial_states=1, workers=2),
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert f"wrote {out}: 6 runs (6 ok)" in proc.stdout
    rows = read_rows(out / "ablation.csv")
    assert len(rows) == 6 and {r["status"] for r in rows} == {"ok"}


def test_resume_after_killing_the_command(short_files, tmp_path):
    scenario_file, variants_file = short_files
    out = tmp_path / "killed"
    command = _ablate_command(scenario_file, variants_file, out, initial_states=2, workers=0)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(command, cwd=ROOT, env=env, stderr=subprocess.PIPE)
    table = out / "ablation.csv"
    try:
        while proc.poll() is None:
            if table.exists() and table.read_text().count("\n") >= 3:  # header + 2 rows
                break
            time.sleep(0.02)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        stderr = proc.communicate()[1].decode()
    assert proc.returncode == -signal.SIGKILL, stderr
    before = read_rows(table)
    assert 2 <= len(before) < 9
    assert main(["ablate", *command[4:], "--resume"]) == 0
    after = read_rows(table)
    assert len(after) == 9 and len(set(map(_key, after))) == 9
    assert repr(after[: len(before)]) == repr(before)  # NaN columns compare equal


def test_cli_errors_are_one_line(short_files, tmp_path, capsys):
    scenario_file, variants_file = short_files
    bad = tmp_path / "bad.yaml"
    bad.write_text("x: {estimator: kalman}\n")
    args = ["ablate", str(scenario_file), "--out", str(tmp_path / "o"), "--workers", "0"]
    assert main([*args, "--variants", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert "variants.x.estimator: unknown slot" in err
    bad.write_text("x: {observer: particle_filter}\n")
    assert main([*args, "--variants", str(bad)]) == 2
    assert "variants.x.observer: unknown choice 'particle_filter'" in capsys.readouterr().err
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "ablation.csv").write_text(",".join(CSV_COLUMNS) + "\n")
    assert main([*args, "--variants", str(variants_file)]) == 2
    assert "ablation.json is missing; it records the sweep" in capsys.readouterr().err
    (tmp_path / "o" / "ablation.json").write_text("{}\n")  # now it is an earlier sweep
    assert main([*args, "--variants", str(variants_file)]) == 2
    assert "ablation.csv exists; pass --resume" in capsys.readouterr().err
    assert main([*args, "--variants", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml: no such variants file" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("states", "match"),
    [
        ([[np.nan, 2.0]], r"^initial states must be finite; got \[\[nan, 2\.0\]\]"),
        ([[1.0, 2.0, 3.0]], r"^initial states: expected finite rows of 2 numbers; got shape"),
        ([[1.0], [1.0, 2.0]], r"^initial states must be numeric; got"),
        ([[0.1, 0.2], [0.1, 0.2]], r"^initial states: repeated states"),
    ],
)
def test_initial_states_name_the_bad_value(states, match):
    from ofrl_drake import load_scenario

    with pytest.raises(AblationError, match=match):
        initial_states_by_label(load_scenario(PAPER_SCENARIO), states)


@pytest.mark.parametrize("count", [2.0, -1, "3", True])
def test_a_count_of_initial_states_is_a_whole_number(count):
    from ofrl_drake import load_scenario

    with pytest.raises(AblationError, match=r"^count \(--initial-states\) must be an integer >= 0"):
        sample_initial_states(load_scenario(PAPER_SCENARIO), count, 0)


# ------------------------------------------------------------ trajectories.png
def _saved_runs(tmp_path, runs, label="[1.0, 0.0]"):
    """``runs/`` holding ``{variant: (t, x)}`` as ``ablate`` saves them."""
    from ofrl_drake.ablation import _run_name

    folder = tmp_path / "runs"
    folder.mkdir()
    for name, (t, x) in runs.items():
        np.savez(folder / _run_name(name, label), t=t, x=x)
    return folder, label


#: 30 s sampled every 10 ms, as a paper run's log.
T = np.linspace(0.0, 30.0, 3001)


def _clean_and_floored():
    """A run that decays to 1e-13 (no floor) and one that ends on a sawtooth at 1e-6."""
    clean = np.exp(-T)
    saw = 1e-6 * (0.1 + 0.9 * ((T * 2.0) % 1.0))  # an error-controlled integrator's floor
    floored = np.maximum(np.exp(-T), saw)
    zero = np.zeros_like(T)
    return {
        "clean": (T, np.column_stack([clean, zero])),
        "floored": (T, np.column_stack([floored, zero])),
    }


def _log_lines(ax, color):
    from matplotlib.colors import to_hex

    return [line for line in ax.get_lines() if to_hex(line.get_color()) == to_hex(color)]


def test_trajectories_shade_no_floor_a_clean_run_decays_through(tmp_path):
    # The band "integrator error floor" was the largest floor of all runs, across the
    # whole axes: the linear observers and the true state, which decay cleanly to 1e-16,
    # crossed it and read as integration error.
    from ofrl_drake.ablation_report import plot_trajectories
    from ofrl_drake.plotting import numerical_floor

    runs = _clean_and_floored()
    folder, label = _saved_runs(tmp_path, runs)
    fig = plot_trajectories(folder, ["clean", "floored"], label, accuracy=1e-4)
    log = fig.axes[-1]
    clean = np.linalg.norm(runs["clean"][1], axis=1)
    to_data = log.transData.inverted()
    for artist in [*log.patches, *log.collections]:  # any shading on the log panel
        (_, y0), (_, y1) = to_data.transform(artist.get_window_extent().get_points())
        inside = (clean >= min(y0, y1) * (1 - 1e-9)) & (clean <= max(y0, y1) * (1 + 1e-9))
        assert not np.any(inside), (artist, y0, y1)
    # The clean run: one solid line, down to its last value (nothing clipped).
    (line,) = _log_lines(log, "C0")
    assert line.get_alpha() in (None, 1.0)
    np.testing.assert_array_equal(line.get_ydata(), clean)
    # The floored run: solid until it first reaches its own floor, faded from there.
    solid, faded = _log_lines(log, "C1")
    assert solid.get_alpha() in (None, 1.0) and 0.0 < faded.get_alpha() <= 0.5
    floored = np.linalg.norm(runs["floored"][1], axis=1)
    floor = numerical_floor(T, floored)  # the largest sawtooth value over the last quarter
    assert floor == pytest.approx(1e-6, rel=0.05)
    assert solid.get_ydata()[-1] <= floor and np.all(solid.get_ydata()[:-1] > floor)
    assert faded.get_xdata()[0] == solid.get_xdata()[-1] == pytest.approx(13.8, abs=0.05)
    assert faded.get_xdata()[-1] == 30.0
    np.testing.assert_array_equal(faded.get_ydata(), floored[T >= faded.get_xdata()[0]])
    labels = fig.legends[0].get_texts()
    assert any("integrator" in t.get_text() and "$10^{-4}$" in t.get_text() for t in labels)


def test_trajectories_name_each_panel_s_time_window(tmp_path):
    # The state panels showed t = 0 to 8 s and the log panel 0 to 30 s; neither said so.
    from ofrl_drake.ablation_report import plot_trajectories

    folder, label = _saved_runs(tmp_path, _clean_and_floored())
    fig = plot_trajectories(folder, ["clean", "floored"], label)
    state, *_, log = fig.axes
    end = state.get_xlim()[1]
    assert 4.0 < end < 30.0  # zoomed: 1.5 x the settling time
    assert f"state panels t = 0 to {end:.4g} s (the transient)" in state.get_title()
    assert "t = 0 to 30 s (the whole horizon)" in log.get_title()
    assert log.get_xlim() == (0.0, 30.0)
    # No faded lines and no floor entry when no run sits on a floor.
    fig = plot_trajectories(folder, ["clean"], label)
    assert not any("integrator" in t.get_text() for t in fig.legends[0].get_texts())


def test_trajectories_do_not_clip_exact_zeros_to_an_invented_floor(tmp_path):
    # ||x|| was np.maximum(||x||, 1e-16): exact zeros were drawn at 1e-16 and the
    # axis went down to it whatever the data.
    x = np.column_stack([np.exp(-T / 3.0), np.zeros_like(T)])
    x[-100:] = 0.0  # the run ends exactly at the origin
    folder, label = _saved_runs(tmp_path, {"zeroes": (T, x)})
    from ofrl_drake.ablation_report import plot_trajectories

    log = plot_trajectories(folder, ["zeroes"], label).axes[-1]
    (line,) = log.get_lines()
    drawn = line.get_ydata()
    assert np.all(np.isnan(drawn[-100:])) and np.all(drawn[:-100] > 0)
    smallest = float(np.exp(-T[-101] / 3.0))  # 5.0e-5
    assert smallest / 10 <= log.get_ylim()[0] <= smallest
    assert "exact zeros not drawn (zeroes)" in log.get_title()


def test_a_retry_that_fails_before_its_logs_leaves_no_run_of_the_first_attempt(
    paper_scenario, tmp_path, monkeypatch
):
    # Before: the first attempt diverged and saved its trajectory; the retry failed before
    # it had logs, the row said so, but runs/ kept the first attempt's trajectory and
    # figures/trajectories.png drew it.
    from ofrl_drake import ablation, ablation_report
    from ofrl_drake.ablation import load_run
    from ofrl_drake.ablation_tasks import METRICS, RunOutcome

    real = ablation.run_variant_states

    def diverged(scenario, variant, states, duration=None, dynamics=None):
        outcomes = real(scenario, variant, states, duration, dynamics)
        return [dataclasses.replace(o, status="diverged: non-finite state") for o in outcomes]

    def out_of_time(scenario, variant, states, duration=None, dynamics=None):
        nan = dict.fromkeys(METRICS, math.nan)
        status = "WallTimeExceeded: the observer design ran out of max_wall_time"
        return [
            RunOutcome(variant.name, initial_state_label(x), nan, status, 0.0, False)
            for x in states
        ]

    out = tmp_path / "ab"
    monkeypatch.setattr(ablation, "run_variant_states", diverged)
    (row,) = ablate(paper_scenario, [Variant("baseline")], out=out, duration=0.5, progress=False)
    label = row["initial_state"]
    assert str(load_run(out / "runs", "baseline", label)["status"]).startswith("diverged")
    monkeypatch.setattr(ablation, "run_variant_states", out_of_time)
    (row,) = ablate(
        paper_scenario,
        [Variant("baseline")],
        out=out,
        duration=0.5,
        progress=False,
        resume=True,
        retry_failed=True,
    )
    assert row["status"].startswith("WallTimeExceeded")
    assert load_run(out / "runs", "baseline", label) is None
    # The figure draws only the runs of rows in the table, not a file left in runs/.
    np.savez(out / "runs" / ablation._run_name("gone", label), t=[0.0, 1.0], x=[[1.0, 1.0]] * 2)
    drawn = []

    def plot(runs_dir, variants, *args):
        drawn.append(list(variants))
        return real_plot(runs_dir, variants, *args)

    real_plot = ablation_report.plot_trajectories
    monkeypatch.setattr(ablation_report, "plot_trajectories", plot)
    ablation_report.write_report(
        out, [row], ["baseline", "gone"], scenario_name="s", x0_label=label, duration=0.5
    )
    assert drawn == [["baseline"]]
