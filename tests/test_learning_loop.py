"""Does the critic learn? The policy-iteration law in the closed loop, on shipped and new plants.

The yardstick of issue 20: from a stabilising critic as poor as three times the
LQR value of the linearization, the policy learned by the horizon T, frozen and
fed the true state, costs at most max(1.02 J*, J_LQR + 0.01 J*) from x0, and
less than the initial policy; the run over 5 T ends ok and regulated, with
Gamma bounded and every policy in force stabilising its linearized loop.
"""

import dataclasses
import math
import re
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.learning_table import with_critic, with_policy_iteration
from ofrl_drake import build_closed_loop, load_scenario, simulate
from ofrl_drake.errors import InitialPolicyWarning, ScenarioError, TargetWarning
from ofrl_drake.examples import EXAMPLES, register
from ofrl_drake.learning import value_matrix
from ofrl_drake.learning_curve import (
    PolicyEvaluator,
    evaluate_policy,
    learning_health,
    lqr_weights,
)
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.optimal import optimal_control
from ofrl_drake.scenario import (
    BoxConfig,
    CostConfig,
    CriticConfig,
    ObserverConfig,
    PointsConfig,
    Scenario,
    SimulationConfig,
)

from .conftest import ROOT

PENDULUM = ROOT / "diagrams" / "pendulum_upright.yaml"
CART_POLE = ROOT / "diagrams" / "cart_pole.yaml"
PAPER = ROOT / "diagrams" / "two_state_paper.yaml"


def _lqr(scenario):
    """The LQR weights of ``scenario``'s linearization (its own W0 does not matter here)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InitialPolicyWarning)  # W0 = 0 is not admissible
        loop = build_closed_loop(scenario)
    return lqr_weights(loop)


# ------------------------------------------------------------ user plants
def _damped_pendulum(rate_unit: float = 1.0) -> ControlAffineSystem:
    """An inverted pendulum with viscous damping, its rate in units of ``rate_unit`` rad/s."""
    s = rate_unit

    def f(x):
        return np.array([x[1] / s, s * (9.81 * np.sin(x[0]) - 0.5 * x[1] / s)])

    def g(x):
        return np.array([[0 * x[0]], [s * 2.0 + 0 * x[0]]])

    return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name=f"damped_pendulum_{s:g}")


def _cart_spring(scale: float = 1.0) -> ControlAffineSystem:
    """A cart on a hardening spring with a pendulum-like unstable coupling (n = 4, q = 2)."""

    def f(x):
        return np.array(
            [
                x[2],
                x[3],
                -x[0] - 0.5 * x[0] ** 3 + 0.4 * np.sin(x[1]) - 0.2 * x[2],
                3.0 * np.sin(x[1]) - 0.5 * x[0] - 0.1 * x[3],
            ]
        )

    def g(x):
        return np.array(
            [[0 * x[0]], [0 * x[0]], [1.0 + 0 * x[0]], [-np.cos(x[1]) * scale + 0 * x[0]]]
        )

    return ControlAffineSystem(f, g, C=[[1.0, 0, 0, 0], [0, 1.0, 0, 0]], name="cart_spring")


def _user_scenario(system_name: str, n: int, *, units=None, duration=10.0) -> Scenario:
    """A scenario a user might write: quadratic critic, derived gains, output feedback."""
    t = np.ones(n) if units is None else np.asarray(units, float)
    half = np.array([0.3, 0.2, 0.3, 0.5]) if n == 4 else np.array([0.4, 1.0])
    box = np.array([1.0, 0.6, 1.5, 2.0]) if n == 4 else np.array([0.8, 3.0])
    x0 = np.array([0.2, 0.1, 0.0, 0.0][:n]) if n == 4 else np.array([0.3, 0.0])
    Q = np.eye(n) / np.outer(t, t)
    return Scenario(
        system=system_name,
        x0=(t * x0).tolist(),
        xhat0=(t * x0 * np.array([1, 1, 0, 0][:n] if n == 4 else [1, 0])).tolist(),
        input_bound=10.0,
        cost=CostConfig(Q=Q.tolist(), R=[1.0]),
        critic=CriticConfig(basis_degrees=[2], W0=[0.0] * (n * (n + 1) // 2)),
        points=PointsConfig(
            kind="uniform", lower=(-t * half).tolist(), upper=(t * half).tolist(), number=200
        ),
        observer=ObserverConfig(
            alpha=1.0,
            box=BoxConfig(lower=(-t * box).tolist(), upper=(t * box).tolist()),
            jacobian_method="sampled",
        ),
        simulation=SimulationConfig(
            duration=duration, integrator="runge_kutta3", accuracy=1e-6, max_step=0.05
        ),
        name=system_name,
    )


@pytest.fixture(scope="module", autouse=True)
def _registered_user_plants():
    added = {
        "damped_pendulum": _damped_pendulum,
        "damped_pendulum_x20": lambda: _damped_pendulum(20.0),
        "cart_spring": _cart_spring,
    }
    for name, factory in added.items():
        register(name, factory)
    yield
    for name in added:
        EXAMPLES.pop(name, None)


def _with_lqr_start(scenario, multiple):
    W_lqr = _lqr(scenario)
    return with_critic(scenario, W0=(multiple * W_lqr).tolist()), W_lqr


def _targets(scenario, W_lqr, W_learned, W_initial):
    evaluate = PolicyEvaluator(build_closed_loop(scenario))  # one diagram, three policies
    J_star = optimal_control(scenario)
    assert J_star.converged, J_star.status
    J_lqr = evaluate(W_lqr).cost
    J_initial = evaluate(W_initial).cost
    J_learned = evaluate(W_learned).cost
    return J_star.cost, J_lqr, J_initial, J_learned


@pytest.mark.parametrize("blocks", ["symbolic", "python"])
def test_one_policy_evaluator_runs_as_a_diagram_built_per_policy(blocks):
    """W and x0 written into the context of each run: the numbers of a diagram built for it."""
    scenario = load_scenario(PENDULUM)
    scenario = dataclasses.replace(
        scenario, simulation=dataclasses.replace(scenario.simulation, blocks=blocks, duration=2.0)
    )
    loop = build_closed_loop(scenario)
    evaluate = PolicyEvaluator(loop)
    W0 = np.asarray(scenario.critic.W0)
    runs = [(W0, None), (3.0 * W0, [0.2, -0.3]), (W0, None)]
    for W, x0 in runs:
        reused = evaluate(W, x0=x0)
        fresh = evaluate_policy(loop, W, x0=x0)  # a diagram of its own
        assert reused == fresh and reused.status == "ok"
    assert evaluate(W0).cost != evaluate(3.0 * W0).cost
    assert evaluate(W0, duration=1.0).cost < evaluate(W0).cost


CASES = {
    "pendulum_upright": lambda: load_scenario(PENDULUM),
    "cart_pole": lambda: load_scenario(CART_POLE),
    "two_state_paper": lambda: with_policy_iteration(load_scenario(PAPER)),
    "damped_pendulum": lambda: _user_scenario("damped_pendulum", 2),
    "cart_spring": lambda: _user_scenario("cart_spring", 4, duration=20.0),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_the_critic_learns_from_three_times_the_lqr_value(name):
    base = CASES[name]()
    scenario, W_lqr = _with_lqr_start(base, 3.0)
    result = simulate(scenario, progress=False)
    assert result.status == "ok"
    J_star, J_lqr, J_initial, J_learned = _targets(
        scenario, W_lqr, result.W_policy[-1], np.asarray(scenario.critic.W0)
    )
    target = max(1.02 * J_star, J_lqr + 0.01 * J_star)
    assert J_learned <= target, (J_learned / J_star, target / J_star, J_initial / J_star)
    assert J_learned < J_initial
    # Five horizons with the gains derived for T: ok and regulated.
    resolved = build_closed_loop(scenario).resolved_scenario()
    long = dataclasses.replace(
        resolved,
        simulation=dataclasses.replace(
            resolved.simulation, duration=5 * resolved.simulation.duration
        ),
    )
    long_result = simulate(long, progress=False)
    assert long_result.status == "ok"
    assert np.linalg.norm(long_result.x[-1]) < 1e-5


@pytest.mark.slow
@pytest.mark.parametrize("multiple", [1.0, 3.0])
def test_cart_pole_runs_five_horizons_regulated_with_a_bounded_gain(multiple):
    base = load_scenario(CART_POLE)
    start = with_critic(base, W0=(multiple * np.asarray(base.critic.W0)).tolist())
    loop = build_closed_loop(start)
    resolved = loop.resolved_scenario()  # the gains derived for the horizon T
    T = resolved.simulation.duration
    long = dataclasses.replace(
        resolved, simulation=dataclasses.replace(resolved.simulation, duration=5 * T)
    )
    long_loop = build_closed_loop(long)
    result = simulate(long, loop=long_loop, progress=False)
    assert result.status == "ok"
    assert result.t[-1] == pytest.approx(5 * T)
    assert np.linalg.norm(result.x[-1]) < 1e-6  # regulated
    assert np.linalg.norm(result.e[-1]) < 1e-6
    # Bounded-gain forgetting: tr(Gamma0^-1 Gamma) / L <= k0 at every sample.
    G0inv = np.linalg.inv(np.asarray(long.critic.Gamma0))
    L = G0inv.shape[0]
    ratio = np.einsum("ij,tji->t", G0inv, result.Gamma) / L
    assert np.max(ratio) <= long.critic.gamma_bound * (1 + 1e-9)
    assert np.all(np.isfinite(result.Gamma))
    # Every policy in force: positive definite value, stable linearized loop.
    health = learning_health(long_loop, result)
    assert np.max(health.spectral_abscissa) < 0.0
    P = value_matrix(long_loop.parts.basis, result.W_policy)
    assert np.min(np.linalg.eigvalsh(P)) > 0.0


def test_the_paper_law_is_kept_as_printed(paper_result):
    """``critic.law: paper``: the controller acts on the critic's own weights, no gate."""
    np.testing.assert_array_equal(paper_result.W_policy, paper_result.W)
    assert "policy_updates" not in paper_result.extra


def test_a_rejected_update_keeps_the_policy_in_force():
    """A critic whose value is indefinite is never put in force; every rejection is logged."""
    from ofrl_drake.systems import CriticWeights

    scenario = load_scenario(PENDULUM)
    W0 = np.asarray(scenario.critic.W0)
    bad = W0 * np.array([1.0, 1.0, -1.0])  # P22 < 0: indefinite
    loop = build_closed_loop(scenario, critic=CriticWeights(bad, kc=0.0))
    result = simulate(scenario, loop=loop, progress=False)
    assert result.status == "ok"
    np.testing.assert_array_equal(result.W_policy, np.tile(W0, (result.t.size, 1)))
    health = learning_health(loop, result)
    assert health.accepted_times == []
    assert health.rejected_times == pytest.approx(np.arange(1.0, 10.0), abs=0.011)
    assert result.extra["policy_updates"][-1].tolist() == [0.0, 9.0]
    assert np.linalg.norm(result.x[-1]) < 1e-6  # the policy in force still regulates


@settings(
    max_examples=4,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(st.floats(0.05, 20.0))
def test_a_plant_and_its_rescaled_twin_learn_the_same_policy(unit):
    """The damped pendulum with its rate in units of ``unit`` rad/s: same policy, rescaled."""
    twin = f"damped_pendulum_in_units_of_{unit!r}"
    register(twin, lambda: _damped_pendulum(unit))
    try:
        runs = []
        for name, units in (("damped_pendulum", None), (twin, [1.0, unit])):
            scenario = _user_scenario(name, 2, units=units, duration=5.0)
            scenario = dataclasses.replace(
                scenario,
                variant=dataclasses.replace(scenario.variant, observer="true_state"),
            )
            W_lqr = _lqr(scenario)
            scenario = with_critic(scenario, W0=(3.0 * W_lqr).tolist())
            runs.append(simulate(scenario, progress=False))
    finally:
        EXAMPLES.pop(twin, None)
    Dw = np.array([1.0, unit, unit**2])  # sigma(T x) = Dw sigma(x) for T = diag(1, unit)
    base, twin = runs
    np.testing.assert_allclose(twin.W_policy[-1] * Dw, base.W_policy[-1], rtol=1e-5)
    np.testing.assert_allclose(twin.x[:, 1] / unit, base.x[:, 1], rtol=1e-4, atol=1e-6)


def test_run_writes_the_derived_gains_and_its_scenario_yaml_reproduces_the_run(tmp_path):
    """``gains: auto``: scenario.yaml records them under ``gains: manual``, bit for bit."""
    import json
    import subprocess
    import sys

    from pydrake.common.yaml import yaml_load

    def run(scenario, out):
        command = [sys.executable, "-m", "ofrl_drake", "run", str(scenario), "--out", str(out)]
        proc = subprocess.run(
            [*command, "--quiet", "--checkpoints", "2"],
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert proc.returncode == 0, proc.stderr
        return np.load(out / "trajectories.npz"), json.loads((out / "summary.json").read_text())

    first, summary = run(PENDULUM, tmp_path / "a")
    written = yaml_load(filename=str(tmp_path / "a" / "scenario.yaml"))["critic"]
    assert written["law"] == "policy_iteration" and written["gains"] == "manual"
    assert written["kc"] == 1.0 and written["policy_period"] == pytest.approx(1.0)
    assert written["gamma_bound"] == 10.0
    assert len(written["Gamma0"]) == 3
    again, _ = run(tmp_path / "a" / "scenario.yaml", tmp_path / "b")
    for key in first.files:
        np.testing.assert_array_equal(again[key], first[key], err_msg=key)
    assert [e["t"] for e in summary["learning_curve"]] == pytest.approx([0.0, 5.0, 10.0])
    assert summary["learning_health"]["policy_updates_accepted"] == 0  # LQR is in force
    assert summary["learning_health"]["policy_updates_rejected"] == 9


@pytest.mark.parametrize("checkpoints", [0, -1, 1.5, "3", True, None])
def test_a_learning_curve_needs_a_whole_number_of_checkpoints(checkpoints):
    # Before: a bare ValueError (0, -1), or a TypeError/AttributeError from deep inside.
    from ofrl_drake.errors import ScenarioError
    from ofrl_drake.learning_curve import learning_curve

    with pytest.raises(
        ScenarioError,
        match=r"learning_curve: checkpoints \(the intervals between checkpoints; "
        rf"learning_report\(checkpoints=0\) switches the curve off\) must be an integer "
        rf">= 1; got {checkpoints!r}",
    ):
        learning_curve(None, None, checkpoints=checkpoints)


@pytest.mark.parametrize("checkpoints", [-1, 2.0, "3"])
def test_a_learning_report_needs_checkpoints_of_zero_or_more(checkpoints):
    # Before: -1 switched the curve off silently; 2.0 and "3" failed deep inside.
    from ofrl_drake.errors import ScenarioError
    from ofrl_drake.learning_curve import learning_report

    with pytest.raises(
        ScenarioError,
        match=r"learning_report: checkpoints \(0 switches the learning curve off\) must be "
        rf"an integer >= 0; got {checkpoints!r}",
    ):
        learning_report(None, None, checkpoints=checkpoints)


def test_an_optimal_task_names_a_warm_start_of_the_wrong_kind():
    # Before: a TypeError, where every other bad argument is the project's error.
    from ofrl_drake.ablation_grid import AblationError
    from ofrl_drake.ablation_tasks import solve_optimal_task

    with pytest.raises(
        AblationError,
        match=r"solve_optimal_task: warm must be a RunOutcome, the runs of a run_variant_states "
        r"task, an optimal.Trajectory or None; got str 'last run'\. Pass the run",
    ):
        solve_optimal_task(load_scenario(PAPER), [0.1, 0.2], "last run")


# ------------------------------------------------------------ wall time
@pytest.fixture(scope="module")
def short_paper_run():
    """The paper's loop over 2 s (its observer: the true state, no design) and its run."""
    scenario = load_scenario(PAPER)
    scenario = dataclasses.replace(
        scenario,
        simulation=dataclasses.replace(scenario.simulation, duration=2.0),
        variant=dataclasses.replace(scenario.variant, observer="true_state"),
    )
    loop = build_closed_loop(scenario)
    return loop, simulate(scenario, loop=loop, progress=False)


def test_each_checkpoint_evaluates_the_policy_in_force_at_its_time(short_paper_run):
    """A checkpoint's cost is that of ``W_policy`` at its sample, and its ratio that cost / J*."""
    from ofrl_drake.learning_curve import learning_curve

    loop, result = short_paper_run
    J_star = optimal_control(loop.parts.scenario)
    assert J_star.converged, J_star.status
    curve = learning_curve(loop, result, checkpoints=2, optimal_cost=J_star.cost)
    assert [entry["t"] for entry in curve] == pytest.approx([0.0, 1.0, 2.0])
    evaluate = PolicyEvaluator(loop)
    for entry in (curve[0], curve[-1]):
        (i,) = np.flatnonzero(result.t == entry["t"])  # the logged sample of the checkpoint
        expected = evaluate(result.W_policy[i]).cost
        assert entry["status"] == "ok"
        assert entry["policy_cost"] == pytest.approx(expected, rel=1e-12)
        assert entry["optimality_ratio"] == pytest.approx(expected / J_star.cost, rel=1e-12)
    # The paper's law moves W over the run, so the policies and their costs differ.
    assert not np.allclose(result.W_policy[0], result.W_policy[-1])
    costs = [entry["policy_cost"] for entry in curve]
    assert len(set(costs)) == len(costs), costs


def test_a_j_star_of_zero_gives_no_ratio(short_paper_run):
    """x0 at the target has J* = 0; before, the curve divided by it (ZeroDivisionError:
    run --optimal wrote nothing)."""
    from ofrl_drake.learning_curve import learning_curve

    loop, result = short_paper_run
    curve = learning_curve(loop, result, checkpoints=1, optimal_cost=0.0)
    assert [entry["optimality_ratio"] for entry in curve] == [None, None]
    assert all(entry["policy_cost"] > 0 for entry in curve)


def test_a_checkpoint_at_a_gate_decision_takes_the_policy_it_decided():
    """Drake logs before the gate's update at t = 1 s: the sample at 1 s still holds the
    previous policy. Before, the curve evaluated that one, one improvement late
    (its entry at t = 1 s equalled the one at t = 0 from a 3x LQR start)."""
    from ofrl_drake.learning_curve import learning_curve, learning_health

    base = load_scenario(PENDULUM)
    base = dataclasses.replace(base, simulation=dataclasses.replace(base.simulation, duration=2.0))
    scenario, _ = _with_lqr_start(base, 3.0)
    loop = build_closed_loop(scenario)
    assert loop.resolved_scenario().critic.policy_period == pytest.approx(0.2)
    result = simulate(scenario, loop=loop, progress=False)
    log_period = scenario.simulation.log_period
    assert 1.0 + log_period == pytest.approx(learning_health(loop, result).accepted_times[4])
    at, after = np.searchsorted(result.t, [1.0 - 1e-9, 1.0 + 1e-9])
    assert result.t[after] == pytest.approx(1.0 + log_period)
    assert not np.array_equal(result.W_policy[at], result.W_policy[after])  # decided at 1 s
    curve = learning_curve(loop, result, checkpoints=2)
    assert [entry["t"] for entry in curve] == pytest.approx([0.0, 1.0, 2.0])
    evaluate = PolicyEvaluator(loop)
    assert curve[1]["policy_cost"] == pytest.approx(
        evaluate(result.W_policy[after]).cost, rel=1e-12
    )
    assert curve[1]["policy_cost"] < 0.99 * curve[0]["policy_cost"]


def test_a_learning_report_out_of_wall_time_names_where_it_stopped_the_budget_and_the_fix(
    short_paper_run, monkeypatch
):
    # Before: the learning curve had no budget at all, so run --max-wall did not bound it.
    import time

    from ofrl_drake.errors import WallTimeExceeded
    from ofrl_drake.learning_curve import learning_report

    loop, result = short_paper_run
    with pytest.raises(
        WallTimeExceeded,
        match=r"^the learning curve did not finish within max_wall_time \(--max-wall\) = 1 s: "
        r"the run had used 10 s of it before the curve began \(the simulation and the checks "
        r"after it\), so no checkpoint was evaluated; allow more wall time \(a larger "
        r"--max-wall\) \(--checkpoints 0 switches the learning curve off\)\.$",
    ) as raised:
        # a budget of 1 s that began 10 s ago: used up before the curve, whatever the machine
        learning_report(loop, result, max_wall_time=1.0, started=time.monotonic() - 10.0)
    assert raised.value.step == "learning curve"
    # A checkpoint that passes the deadline: the curve names it.
    from ofrl_drake import learning_curve

    def late(self, W, **kwargs):
        raise WallTimeExceeded("passed its deadline", step="policy evaluation")

    with monkeypatch.context() as patch:
        patch.setattr(learning_curve.PolicyEvaluator, "__call__", late)
        with pytest.raises(
            WallTimeExceeded,
            match=r"^the learning curve did not finish within max_wall_time \(--max-wall\) = "
            r"60 s: it stopped at checkpoint 1 of 3 \(t = 0 s\), [0-9.e+-]+ s into the curve "
            r"\(the run had used [0-9.e+-]+ s before it\); allow more wall time \(a larger "
            r"--max-wall\) or evaluate fewer checkpoints \(--checkpoints 0 switches the learning "
            r"curve off\)\.$",
        ):
            learning_report(loop, result, checkpoints=2, max_wall_time=60.0)


def test_a_policy_evaluation_stops_at_its_deadline_and_a_budget_changes_no_number(
    short_paper_run,
):
    import time

    from ofrl_drake.errors import WallTimeExceeded
    from ofrl_drake.learning_curve import learning_report

    loop, result = short_paper_run
    evaluate = PolicyEvaluator(loop)
    W = result.W_policy[-1]
    # The monitor sees the deadline passed right after Initialize, before any step.
    with pytest.raises(
        WallTimeExceeded, match=r"^the policy evaluation passed its deadline at t = 0 s of 2 s"
    ):
        evaluate(W, deadline=time.monotonic() - 1.0)
    # A budget that does not run out takes the same steps: the same numbers, bit for bit.
    assert evaluate(W, deadline=time.monotonic() + 600.0) == evaluate(W)
    free = learning_report(loop, result, checkpoints=4)
    bounded = learning_report(loop, result, checkpoints=4, max_wall_time=600.0)
    assert bounded.curve == free.curve and bounded.curve_stop is None
    assert bounded.lqr_policy_cost == free.lqr_policy_cost


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"max_wall_time": 0.0}, r"max_wall_time \(seconds, --max-wall\) must be > 0; got 0\.0"),
        ({"max_wall_time": -1}, r"max_wall_time \(seconds, --max-wall\) must be > 0; got -1\.0"),
        ({"max_wall_time": math.nan}, r"max_wall_time \(seconds, --max-wall\) must be finite"),
        ({"max_wall_time": math.inf}, r"max_wall_time \(seconds, --max-wall\) must be finite"),
        (
            {"max_wall_time": "5"},
            r"max_wall_time \(seconds, --max-wall\) must be a number; got '5'",
        ),
        (
            {"max_wall_time": 5, "started": -1.0},
            r"started \(a time\.monotonic\(\) reading\) must be >= 0; got -1\.0",
        ),
        ({"started": 3.0}, r"started \(3\.0\) is when max_wall_time starts counting; give"),
    ],
)
def test_a_learning_report_names_a_bad_budget(options, match):
    from ofrl_drake.errors import ScenarioError
    from ofrl_drake.learning_curve import learning_report

    with pytest.raises(ScenarioError, match=r"^learning_report: " + match):
        learning_report(None, None, checkpoints=0, **options)


def test_derived_gains_follow_the_scenario_policy_period():
    """Before: beta stayed 5 / (T/10) when critic.policy_period was given with gains: auto."""
    scenario = with_critic(with_policy_iteration(load_scenario(PENDULUM)), policy_period=0.25)
    gains = build_closed_loop(scenario).parts.critic.gains
    assert gains.policy_period == 0.25
    assert gains.beta == pytest.approx(5.0 / 0.25, rel=1e-12)


def test_every_gate_decision_is_counted_when_several_share_a_log_sample():
    """policy_period < log_period: the summary's counts are the gate's own, one time each."""
    scenario = with_critic(with_policy_iteration(load_scenario(PENDULUM)), policy_period=0.005)
    scenario = dataclasses.replace(
        scenario, simulation=dataclasses.replace(scenario.simulation, duration=0.5)
    )
    loop = build_closed_loop(scenario)
    result = simulate(scenario, loop=loop, progress=False)
    health = learning_health(loop, result).summary()
    accepted, rejected = result.extra["policy_updates"][-1]
    # Before: one per log sample that saw the count rise (about 25 of the ~100 here).
    assert accepted + rejected >= 90
    assert health["policy_updates_accepted"] == accepted
    assert health["policy_updates_rejected"] == rejected
    assert len(health["accepted_times"]) == accepted
    assert health["accepted_times"] == sorted(health["accepted_times"])
    assert set(health["accepted_times"]) <= set(result.t.tolist())


def test_the_gate_keeps_its_policy_when_the_value_is_negative_at_the_points():
    """A quartic term can make V negative on the points with a positive-definite P."""
    from pydrake.systems.analysis import Simulator

    from ofrl_drake.learning import value_weights
    from ofrl_drake.points import grid_points
    from ofrl_drake.systems import PolicyGate

    from .test_learning import A, B, R, _lqr_value, _quartic_dip

    # The double integrator's LQR value (a smaller local cost) minus 50 x1^4 (V < 0).
    basis, candidate = _quartic_dip(-50.0)
    in_force = value_weights(basis, 3.0 * _lqr_value(np.eye(2)))
    points = grid_points([-1, -1], [1, 1], [5, 5])
    gate = PolicyGate(in_force, 1.0, A, B, np.eye(2), R, basis, points)
    context = gate.CreateDefaultContext()
    gate.get_weights_input_port().FixValue(context, candidate)
    simulator = Simulator(gate, context)
    simulator.AdvanceTo(2.5)  # two decisions
    np.testing.assert_array_equal(gate.get_policy_updates_output_port().Eval(context), [0, 2])
    np.testing.assert_array_equal(gate.get_policy_weights_output_port().Eval(context), in_force)
    # Without the minus sign the same candidate is put in force (and kept: the second
    # decision finds the same local cost).
    candidate = _quartic_dip(50.0)[1]
    context = gate.CreateDefaultContext()
    gate.get_weights_input_port().FixValue(context, candidate)
    Simulator(gate, context).AdvanceTo(2.5)
    np.testing.assert_array_equal(gate.get_policy_updates_output_port().Eval(context), [2, 0])
    np.testing.assert_array_equal(gate.get_policy_weights_output_port().Eval(context), candidate)


def test_exact_policy_iteration_learns_on_the_pendulum_as_the_loop_does():
    """benchmarks.learning_basis: the gate's decisions with each evaluation solved exactly."""
    from benchmarks.learning_basis import iterate

    loop = build_closed_loop(load_scenario(PENDULUM))
    W_lqr = lqr_weights(loop)
    start = evaluate_policy(loop, 3.0 * W_lqr).cost
    out = iterate(loop, 3.0 * W_lqr)
    learned = evaluate_policy(loop, out["W"]).cost
    lqr = evaluate_policy(loop, W_lqr).cost
    # docs/learning.md, the loop from 3 x LQR: 1.4928 to 1.0101 J*, the LQR policy 1.0004 J*;
    # exactly evaluated, the iteration ends within 1% of the LQR policy too (0.66%).
    assert out["accepted"] == 9 and out["last_min_eig"] > 0 and out["last_min_value"] > 0
    assert learned < 0.7 * start
    assert lqr <= learned <= 1.01 * lqr
    # Without the local-cost condition nothing changes on this plant.
    np.testing.assert_allclose(iterate(loop, 3.0 * W_lqr, local_cost=False)["W"], out["W"])


def test_a_target_that_is_no_equilibrium_is_named_under_either_law():
    """f(0) != 0: the greedy policy is zero at the origin, so no law can rest there.

    policy_iteration suggested critic.law: paper as the fix, which then ran to |x(T)| = 3.3
    with no word about the target."""

    def offset():
        return ControlAffineSystem(
            lambda x: np.array([x[1], -x[0] - 0.3 * x[1] + 1.0]),
            lambda x: np.array([[0.0 * x[0]], [1.0 + 0.0 * x[0]]]),
            C=[[1.0, 0.0]],
            name="offset",
        )

    register("offset_plant", offset)
    try:
        scenario = _user_scenario("offset_plant", 2, duration=1.0)
        message = (
            r"the origin is not an equilibrium of f \(f\(0\) = \[0\.0, 1\.0\]\): the policy is "
            r"zero there, .*give the target as an equilibrium, equilibrium: \{x: x\*, u: u\*\} "
            r"with f\(x\*\) \+ g\(x\*\) u\* = 0"
        )
        with pytest.raises(ScenarioError, match=message) as err:
            build_closed_loop(scenario)
        assert "critic.law: paper" not in str(err.value)
        paper = with_critic(scenario, law="paper")
        with pytest.warns(TargetWarning, match=message):
            build_closed_loop(paper)
    finally:
        EXAMPLES.pop("offset_plant")


def _domain_plant() -> ControlAffineSystem:
    """A pendulum whose f is defined only for |x1| < 1.5 (sqrt of 2.25 - x1^2)."""

    def f(x):
        return np.array([x[1], np.sin(x[0]) + np.sqrt(2.25 - x[0] ** 2) - 1.5])

    def g(x):
        return np.array([[0.0 * x[0]], [1.0 + 0.0 * x[0]]])

    return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name="domain_pendulum")


def _evaluate_zero_policy(name, factory, x0, blocks="auto"):
    """The policy W = 0 of a user plant registered as ``name``, from ``x0``, for 2 s."""
    register(name, factory)
    try:
        scenario = _user_scenario(name, 2, duration=2.0)
        scenario = dataclasses.replace(
            scenario,
            x0=[0.2, 0.0],
            xhat0=[0.2, 0.0],
            simulation=dataclasses.replace(scenario.simulation, blocks=blocks),
        )
        with pytest.warns(InitialPolicyWarning):  # W0 = 0; the evaluator is given its own W
            loop = build_closed_loop(scenario)
        return PolicyEvaluator(loop)(np.zeros(loop.parts.basis.size), x0=np.array(x0))
    finally:
        EXAMPLES.pop(name)


def test_a_policy_evaluation_leaving_the_domain_of_f_is_diverged_not_an_internal_error():
    """Before: the evaluator caught only RuntimeError, so Drake's ValueError ended the CLI."""
    run = _evaluate_zero_policy("domain_pendulum", _domain_plant, [1.4, 3.0])
    assert math.isnan(run.cost)
    assert re.match(r"^diverged: the model's f or g was evaluated outside its domain", run.status)


def _nan_plant(everywhere: bool) -> ControlAffineSystem:
    """A double integrator whose f is NaN past x1 = 1: both entries, or x2's alone.

    Drake traces the model inside x1 < 1 (for the bounds); numbers past it are NaN.
    """

    def f(x):
        x = np.asarray(x)
        if x.dtype == object:
            return np.array([x[1], 0.0 * x[0]])
        past = x[0] > 1.0
        return np.array([np.where(past & everywhere, np.nan, x[1]), np.where(past, np.nan, 0.0)])

    def g(x):
        return np.array([[0.0 * x[0]], [1.0 + 0.0 * x[0]]])

    return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name="nan_plant")


@pytest.mark.parametrize(
    ("everywhere", "status"),
    [
        # Before: Drake's error control shrank the step to 1e-17 s at x1 = 1 and
        # the evaluation never ended.
        (True, r"^diverged: the integrator stalled at t = 0\.0333333 s: 100 steps in a row"),
        # Before: "left the abort box", of a state inside the box but NaN.
        (False, r"^diverged: the state turned NaN or infinite at t = 0\.03"),
    ],
)
def test_a_policy_evaluation_on_a_nan_model_ends_diverged_naming_why(everywhere, status):
    run = _evaluate_zero_policy(
        f"nan_plant_{everywhere}", lambda: _nan_plant(everywhere), [0.9, 3.0], blocks="python"
    )
    assert math.isnan(run.cost)
    assert re.match(status, run.status), run.status


def test_a_w0_negative_at_the_points_warns_naming_only_that():
    from ofrl_drake.basis import PolynomialBasis
    from ofrl_drake.learning import value_weights

    scenario = with_policy_iteration(load_scenario(PENDULUM))
    basis = PolynomialBasis(2, (2, 4))
    W0 = value_weights(basis, value_matrix(PolynomialBasis(2), scenario.critic.W0))
    W0[[tuple(e) for e in basis.exponents].index((4, 0))] = -1e6
    dipped = with_critic(scenario, basis_degrees=[2, 4], W0=W0.tolist())
    with pytest.warns(InitialPolicyWarning) as record:
        build_closed_loop(dipped)
    (warning,) = [w for w in record if w.category is InitialPolicyWarning]
    text = str(warning.message)
    (value,) = re.findall(
        r"not accept: the smallest of its values W0\^T sigma\(x_i\) at the extrapolation "
        r"points is (\S+) \(must be > 0\); the loop",
        text,
    )
    assert float(value) < -1e3
    assert "eigenvalue" not in text and "abscissa" not in text  # its P and K pass


def test_policy_iteration_from_an_inadmissible_policy_warns_naming_w0():
    """Kleinman's iteration needs a stabilizing start: a W0 that is not one is named."""
    scenario = with_policy_iteration(load_scenario(PENDULUM))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the shipped W0 warns nothing
        build_closed_loop(scenario)
    indefinite = with_critic(scenario, W0=[15.2321, 5.3705, -0.6065])
    with pytest.warns(
        InitialPolicyWarning, match=r"^critic\.W0: policy iteration starts from"
    ) as record:
        build_closed_loop(indefinite)
    (warning,) = [w for w in record if w.category is InitialPolicyWarning]
    # Only conditions that fail are named, each with its number; at the caller's line.
    named = re.findall(r"is (\S+) \(must be ([<>]) 0\)", str(warning.message))
    assert named, warning.message
    assert all(float(v) <= 0 if sign == ">" else float(v) >= 0 for v, sign in named), named
    assert warning.filename == __file__
    # The paper's law has no gate and no such test.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_closed_loop(
            with_critic(indefinite, law="paper", policy_period=None, gamma_bound=None)
        )
