"""The optimal-control yardstick J*: the problem it solves, its accuracy, its cache."""

import dataclasses
import json
import math
import re

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ofrl_drake import ModelError, OfrlError, ScenarioError
from ofrl_drake.cost import stage_cost
from ofrl_drake.examples import make_system
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.optimal import (
    Mesh,
    OptimalControlResult,
    OptimalCostCache,
    Trajectory,
    cost_augmented_plant,
    optimal_control,
    problem_key,
    saturation_cost,
    solve_optimal_control,
)

from .conftest import edited_two_state

Q = 5.0 * np.eye(2)
R = np.array([1.0])


EDGE = 2.0**-3.5  # where the series gives way to the closed form
S_VALUES = [
    1e-12,
    1e-8,
    1e-5,
    1e-3,
    0.05,
    EDGE * (1 - 1e-9),
    EDGE * (1 + 1e-9),
    0.1,
    0.3,
    0.9,
    0.999,
]


@pytest.mark.parametrize("s", S_VALUES + [-v for v in S_VALUES])
def test_the_saturation_cost_is_accurate_for_small_and_large_inputs(s):
    """Before: ln(1 - s^2) lost s^2's digits, so U(u) at lbar = 1e6 was a staircase
    (0.99999992 at lbar = 1e5, 1.0000221 at 1e6, for U = 1) and SNOPT gave up."""
    from pydrake.symbolic import Variable

    v = Variable("s")
    expression = saturation_cost(v)
    # numpy's arctanh and log1p are accurate near 0; only a factor 2 cancels.
    exact = s * np.arctanh(s) + 0.5 * np.log1p(-s * s)
    assert expression.Evaluate({v: s}) == pytest.approx(exact, rel=2e-14)
    # Its derivative is atanh(s), on either side of the series' edge (the closed form's
    # 1 - s costs digits near s = 1, as atanh's own formula does).
    assert expression.Differentiate(v).Evaluate({v: s}) == pytest.approx(np.arctanh(s), rel=1e-11)


def test_j_star_with_a_bound_that_never_binds_is_solved():
    """The pendulum with lbar = 1e6 to 1e8: its input stays below 10 N, so U(u) = r u^2
    to 1e-10 and J* is that of the quadratic cost (0.98077, measured). Before: SNOPT
    'not converged' (info 41) from 1e6 on."""
    from ofrl_drake import load_scenario

    from .conftest import ROOT

    pendulum = load_scenario(ROOT / "diagrams" / "pendulum_upright.yaml")
    costs = []
    for bound in (1e6, 1e8):
        result = optimal_control(dataclasses.replace(pendulum, input_bound=bound))
        assert result.converged, result.status
        costs.append(result.cost)
    assert costs[0] == pytest.approx(costs[1], rel=1e-8)
    assert costs[0] == pytest.approx(0.9807696, rel=1e-6)


LBAR = 3.0


@pytest.fixture(scope="module")
def two_state():
    return make_system("two_state")


@pytest.fixture(scope="module")
def paper_optimum(two_state):
    """J* from the paper's x0 over 5 s (the cost after 5 s is below 1e-6 of it)."""
    return solve_optimal_control(two_state, [-1.0, 1.0], Q, R, LBAR, 5.0)


@pytest.mark.parametrize("u", [-2.9999, -1.3, 0.0, 0.4, 2.99])
def test_cost_state_derivative_is_the_stage_cost(two_state, u):
    """J' of the collocated system equals Q(x) + U(u) of ofrl_drake.cost."""
    plant = cost_augmented_plant(two_state, Q, R, LBAR)
    context = plant.CreateDefaultContext()
    x = np.array([0.7, -1.4])
    context.SetContinuousState(np.concatenate([x, [0.0]]))
    plant.get_input_port().FixValue(context, [u])
    deriv = plant.EvalTimeDerivatives(context).CopyToVector()
    np.testing.assert_allclose(deriv[:2], two_state.dynamics(x, np.array([u])), rtol=1e-14)
    np.testing.assert_allclose(deriv[2], stage_cost(x, np.array([u]), Q, R, LBAR), rtol=1e-12)


def test_paper_optimum_converges_within_the_bound(paper_optimum):
    r = paper_optimum
    assert r.converged and r.status == "ok" and r.solver == "snopt"
    assert r.cost == pytest.approx(3.7511, rel=1e-4)
    traj = r.trajectory
    assert np.all(np.abs(traj.u) <= LBAR * (1 - 1e-6) * (1 + 1e-12))
    assert traj.t[0] == 0.0 and traj.t[-1] == pytest.approx(5.0, abs=1e-12)
    np.testing.assert_array_equal(traj.x[0], [-1.0, 1.0])
    assert traj.cost[0] == 0.0 and traj.cost[-1] == r.cost
    assert np.all(np.diff(traj.cost) >= 0)


def test_optimal_input_replayed_open_loop_follows_the_optimal_state(two_state, paper_optimum):
    """Integrate x' = f + g u with the collocated (first-order-hold) input by scipy."""
    traj = paper_optimum.trajectory

    def rhs(t, x):
        return two_state.dynamics(x, np.array([np.interp(t, traj.t, traj.u[:, 0])]))

    sol = solve_ivp(rhs, (0.0, 1.0), [-1.0, 1.0], rtol=1e-11, atol=1e-12, max_step=0.01)
    x1 = np.array([np.interp(1.0, traj.t, traj.x[:, i]) for i in range(2)])
    # The plant is open-loop unstable (eigenvalue 3.8), which amplifies the
    # collocation error of the replay.
    np.testing.assert_allclose(sol.y[:, -1], x1, rtol=0, atol=1e-3)


def test_mesh_refinement_and_horizon_leave_j_star_unchanged(two_state, paper_optimum):
    fine = solve_optimal_control(
        two_state, [-1.0, 1.0], Q, R, LBAR, 5.0, mesh=Mesh(0.02, 1.02, 0.2)
    )
    longer = solve_optimal_control(two_state, [-1.0, 1.0], Q, R, LBAR, 10.0)
    assert fine.converged and longer.converged
    assert fine.trajectory.t.size > 1.5 * paper_optimum.trajectory.t.size
    assert fine.cost == pytest.approx(paper_optimum.cost, rel=1e-5)
    assert longer.cost == pytest.approx(paper_optimum.cost, rel=1e-5)


def test_j_star_is_below_the_paper_closed_loop(paper_scenario, paper_optimum):
    from ofrl_drake import simulate

    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=5.0)
    )
    r = simulate(short, progress=False)
    assert paper_optimum.cost <= r.cost[-1]
    assert r.cost[-1] / paper_optimum.cost == pytest.approx(1.1454, abs=2e-3)


def test_warm_start_reaches_the_same_optimum(two_state, paper_optimum):
    warm = dataclasses.replace(paper_optimum.trajectory, u=paper_optimum.trajectory.u * 0.5)
    r = solve_optimal_control(two_state, [-1.0, 1.0], Q, R, LBAR, 5.0, warm_start=warm)
    assert r.converged and r.warm_started
    assert r.cost == pytest.approx(paper_optimum.cost, rel=1e-6)


def test_scenario_level_call_uses_the_scenario_problem(paper_scenario, paper_optimum):
    short = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=5.0)
    )
    r = optimal_control(short)
    assert r.x0 == (-1.0, 1.0) and r.duration == 5.0
    assert r.cost == pytest.approx(paper_optimum.cost, rel=1e-9)


def test_infeasible_problem_reports_status_and_nan():
    """x' = x^2 + u escapes to infinity before T from x0 = 10 for every |u| <= 1."""
    escape = ControlAffineSystem(
        lambda x: np.array([x[0] ** 2]), lambda x: np.array([[1 + 0 * x[0]]]), [[1.0]]
    )
    r = solve_optimal_control(escape, [10.0], np.eye(1), [1.0], 1.0, 5.0)
    assert not r.converged and math.isnan(r.cost) and r.trajectory is None
    assert r.status.startswith("not converged (default guess (1 s): snopt kInfeasible")
    assert r.status.count("default guess") == 3
    assert r.to_dict()["cost"] is None


def test_bad_arguments_raise(two_state):
    with pytest.raises(OfrlError, match=r"x0 must be 2 finite numbers"):
        solve_optimal_control(two_state, [1.0], Q, R, LBAR, 5.0)
    with pytest.raises(OfrlError, match=r"solver must be one of \('snopt', 'ipopt'\)"):
        solve_optimal_control(two_state, [1.0, 0.0], Q, R, LBAR, 5.0, solver="gurobi")
    with pytest.raises(OfrlError, match=r"input_margin must be in \(0, 1\)"):
        solve_optimal_control(two_state, [1.0, 0.0], Q, R, LBAR, 5.0, input_margin=0.0)
    with pytest.raises(OfrlError, match=r"mesh: need initial_step > 0"):
        Mesh(initial_step=0.0)
    with pytest.raises(OfrlError, match=r"the horizon must be a positive number"):
        Mesh().steps(-1.0)


def _with_cost(scenario, **changes):
    return dataclasses.replace(scenario, cost=dataclasses.replace(scenario.cost, **changes))


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"R": [1.0, 1.0]}, r"^cost\.R: expected 1 entries; got 2"),
        ({"R": [0.0]}, r"^cost\.R: entries must be > 0; got \[0\.0\]"),
        ({"Q": [[math.nan, 0.0], [0.0, 1.0]]}, r"^cost\.Q: entries must be finite"),
        ({"Q": [[1.0]]}, r"^cost\.Q: expected a 2x2 matrix; got 1x1"),
        ({"input_bound": math.nan}, r"^input_bound: must be > 0; got nan"),
    ],
)
def test_optimal_control_validates_the_scenario(paper_scenario, change, match):
    """A bad scenario is named, not solved ("ok" with R = [1, 1]) nor a Drake error."""
    if "input_bound" in change:
        bad = dataclasses.replace(paper_scenario, **change)
    else:
        bad = _with_cost(paper_scenario, **change)
    with pytest.raises(ScenarioError, match=match):
        optimal_control(bad)


def test_optimal_control_refuses_a_bad_mesh_warm_start_or_solver(paper_scenario, tmp_path):
    with pytest.raises(OfrlError, match=r"mesh must be a Mesh\(initial_step, .*; got 'x'"):
        optimal_control(paper_scenario, mesh="x")
    with pytest.raises(OfrlError, match=r"warm_start must be a Trajectory .* or None; got 'x'"):
        optimal_control(paper_scenario, warm_start="x")
    t = np.linspace(0.0, 1.0, 5)
    wrong = Trajectory(t=t, x=np.zeros((5, 3)), u=np.zeros((5, 1)), cost=np.zeros(5))
    with pytest.raises(OfrlError, match=r"warm_start must have .* x \(T, 2\).*got .* x \(5, 3\)"):
        optimal_control(paper_scenario, warm_start=wrong)
    with pytest.raises(OfrlError, match=r"solver must be one of .*; got \['snopt'\]"):
        optimal_control(paper_scenario, solver=["snopt"])
    with pytest.raises(
        OfrlError,
        match=r"need initial_step > 0, .*all numbers, and refinements an integer from 0 to 6; "
        r"got .*'0\.05'",
    ):
        Mesh("0.05")
    with pytest.raises(OfrlError, match=r"mesh must be a Mesh.*; got 'x'"):
        problem_key(paper_scenario, np.array([-1.0, 1.0]), mesh="x")
    with pytest.raises(OfrlError, match=r"solver must be one of .*; got 'ipop'"):
        OptimalCostCache(tmp_path, solver="ipop")


def test_solve_optimal_control_checks_the_problem_data(two_state):
    with pytest.raises(ModelError, match=r"optimal control: Q must be finite; got \[\[nan"):
        solve_optimal_control(two_state, [1.0, 0.0], [[math.nan, 0.0], [0.0, 1.0]], R, LBAR, 5.0)
    with pytest.raises(ModelError, match=r"optimal control: r must have entries > 0; got \[0\.0\]"):
        solve_optimal_control(two_state, [1.0, 0.0], Q, [0.0], LBAR, 5.0)
    with pytest.raises(ModelError, match=r"optimal control: input_bound must be finite; got nan"):
        solve_optimal_control(two_state, [1.0, 0.0], Q, R, math.nan, 5.0)
    with pytest.raises(OfrlError, match=r"x0 must be 2 finite numbers; got 'ab'"):
        solve_optimal_control(two_state, "ab", Q, R, LBAR, 5.0)


def test_mesh_covers_the_horizon_exactly():
    steps = Mesh().steps(30.0)
    assert steps.sum() == pytest.approx(30.0, rel=1e-14)
    assert steps.size == 108
    assert np.all(np.diff(steps) >= -1e-15)
    assert steps[0] == pytest.approx(0.05, rel=0.01) and steps.max() <= 0.5 * (1 + 1e-2)


def test_cache_round_trip_and_keys(tmp_path, paper_scenario, paper_optimum):
    cache = OptimalCostCache(tmp_path / "optimal")
    x0 = np.array([-1.0, 1.0])
    assert cache.get(paper_scenario, x0) is None
    cache.put(paper_scenario, paper_optimum)
    got = cache.get(paper_scenario, x0)
    assert got.cost == paper_optimum.cost and got.status == "ok" and got.converged
    np.testing.assert_array_equal(got.trajectory.x, paper_optimum.trajectory.x)
    stored = json.loads(cache.path(paper_scenario, x0).read_text())
    assert stored["x0"] == [-1.0, 1.0] and stored["scenario"] == "two_state_paper"
    # The key changes with x0 and with the problem, not with unrelated settings.
    key = problem_key(paper_scenario, x0)
    assert problem_key(paper_scenario, np.array([-1.0, 1.0 + 1e-12])) != key
    longer = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, duration=31.0)
    )
    assert problem_key(longer, x0) != key
    assert problem_key(paper_scenario, x0, mesh=Mesh(0.02)) != key
    renamed = dataclasses.replace(
        paper_scenario, critic=dataclasses.replace(paper_scenario.critic, kc=0.02)
    )
    assert problem_key(renamed, x0) == key
    # The plant's code is part of the key: a name registered again with other
    # dynamics is another problem (the name is part of the key too).
    from ofrl_drake.examples import EXAMPLES, register, two_state

    edited = dataclasses.replace(paper_scenario, system="edited_two_state")
    try:
        register("edited_two_state", two_state)
        same_code = problem_key(edited, x0)
        register("edited_two_state", edited_two_state(g_scale=0.5))
        assert problem_key(edited, x0) not in (key, same_code)
    finally:
        EXAMPLES.pop("edited_two_state")
    assert same_code != key  # the name is part of the key too
    # A failure is not cached; a damaged file reads as missing.
    failed = OptimalControlResult((0.5, 0.5), math.nan, False, "not converged", 30.0, "snopt", 1.0)
    cache.put(paper_scenario, failed)
    assert cache.get(paper_scenario, np.array([0.5, 0.5])) is None
    cache.path(paper_scenario, x0).write_text("{ not json")
    assert cache.get(paper_scenario, x0) is None


def _user_plant(name, f):
    """A two-state user plant ``x1' = x2, x2' = f(x) + u``, C = [1 0]."""
    return lambda: ControlAffineSystem(
        lambda x: np.array([x[1], f(x)]),
        lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[1.0, 0.0]],
        name=name,
    )


def _warm_start_at_x1(x1):
    """A 2 s warm start that stays at ``x = (x1, 0)``."""
    t = np.linspace(0.0, 2.0, 20)
    return Trajectory(t=t, x=np.c_[x1 + 0 * t, 0 * t], u=np.zeros((20, 1)), cost=np.zeros(20))


def _user_scenario(paper_scenario, name, x0):
    return dataclasses.replace(
        paper_scenario,
        system=name,
        x0=x0,
        xhat0=x0,
        simulation=dataclasses.replace(paper_scenario.simulation, duration=2.0),
    )


def _optimum_near_the_edge_of_a_domain(paper_scenario, x0, **options):
    """J* of f = -x1 - x2 + 0.1 sqrt(1 - x1), warm-started at x1 = 1.5 (outside its domain)."""
    from ofrl_drake.examples import EXAMPLES, register

    register(
        "user_nan_region",
        _user_plant("user_nan_region", lambda x: -x[0] - x[1] + 0.1 * np.sqrt(1.0 - x[0])),
    )
    try:
        scenario = _user_scenario(paper_scenario, "user_nan_region", x0)
        warm = _warm_start_at_x1(1.5)
        return optimal_control(scenario, warm_start=warm, mesh=Mesh(0.1, 1.0, 0.1), **options)
    finally:
        EXAMPLES.pop("user_nan_region")


@pytest.mark.parametrize("solver", ["snopt", "ipopt"])
def test_iterates_outside_the_domain_of_f_are_a_failed_solve(paper_scenario, solver):
    """From x0 = (0.9, 1) every attempt leaves x1 < 1.

    SNOPT wraps Drake's domain error in a RuntimeError, IPOPT passes on the
    ValueError; both are reported as a not-converged J*, with the warm start
    (outside the domain from its first point) as one of the failed attempts.
    """
    r = _optimum_near_the_edge_of_a_domain(paper_scenario, [0.9, 1.0], solver=solver)
    assert not r.converged and math.isnan(r.cost) and r.trajectory is None
    assert "\n" not in r.status
    assert re.match(
        rf"not converged \(warm start: {solver} stopped, f or g evaluated outside its domain "
        r"\(sqrt\(-[0-9.e-]+\) : numerical argument out of domain",
        r.status,
    )
    assert r.status.count("outside its domain") == 4
    assert "'user_nan_region' are defined" in r.status


def test_a_warm_start_outside_the_domain_falls_back_to_the_default_guesses(paper_scenario):
    r = _optimum_near_the_edge_of_a_domain(paper_scenario, [0.2, 0.0])
    assert r.converged and r.status == "ok" and not r.warm_started


@pytest.mark.filterwarnings("ignore:user_branchy. f and g do not accept a batch")
def test_a_plant_drake_cannot_trace_is_refused_before_the_solve(paper_scenario):
    """An ``if`` on the state is fine for ``run`` with the true state, not for J*."""
    from ofrl_drake.examples import EXAMPLES, register

    register(
        "user_branchy", _user_plant("user_branchy", lambda x: -x[0] - (x[1] if x[1] > 0 else 0))
    )
    try:
        scenario = _user_scenario(paper_scenario, "user_branchy", [0.5, 0.0])
        with pytest.raises(
            ModelError,
            match=r"J\* .*needs f and g that Drake can trace.*model 'user_branchy'.*__bool__"
            r".*no branches on the state; without them J\* is not available\.$",
        ):
            optimal_control(scenario, mesh=Mesh(0.1, 1.0, 0.1))
    finally:
        EXAMPLES.pop("user_branchy")


def _fast_oscillator():
    """``x'' = -400 x - 0.1 x' + u``: 20 rad/s, too fast for the default grid alone."""
    return ControlAffineSystem(
        lambda x: np.array([x[1], -400.0 * x[0] - 0.1 * x[1]]),
        lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[1.0, 0.0]],
        name="fast_oscillator",
    )


def _fast_optimum(x0, duration, **options):
    return solve_optimal_control(_fast_oscillator(), x0, np.eye(2), [1.0], 1.0, duration, **options)


def test_mesh_refined_halves_every_step():
    mesh = Mesh(rtol=1e-4, refinements=2)
    finer = mesh.refined()
    assert finer == Mesh(0.025, math.sqrt(1.03), 0.25, rtol=1e-4, refinements=2)
    assert finer.steps(30.0).size == 2 * mesh.steps(30.0).size == 216
    assert finer.steps(30.0).sum() == pytest.approx(30.0, rel=1e-14)


@pytest.mark.parametrize(
    "bad",
    [
        {"rtol": 0.0},
        {"rtol": math.nan},
        {"refinements": -1},
        {"refinements": 7},
        {"refinements": 1.0},
        {"refinements": True},
    ],
)
def test_mesh_refuses_a_bad_check(bad):
    with pytest.raises(OfrlError, match=r"rtol > 0, .* refinements an integer from 0 to 6; got"):
        Mesh(**bad)


def test_a_grid_too_coarse_for_the_plant_is_refined_until_j_star_settles():
    """The default grid alone overstates J* by 2 % at 20 rad/s; the check corrects it.

    The reference is the grid of 373 intervals, steps an eighth of the default's.
    """
    x0, T = [0.0, 1.0], 5.0
    reference = _fast_optimum(x0, T, mesh=Mesh(refinements=0).refined().refined().refined())
    unchecked = _fast_optimum(x0, T, mesh=Mesh(refinements=0))
    checked = _fast_optimum(x0, T)
    assert reference.converged and reference.intervals == 373
    assert unchecked.converged and unchecked.intervals == 47 and math.isnan(unchecked.mesh_change)
    assert unchecked.cost > 1.015 * reference.cost
    assert checked.converged and checked.status == "ok"
    assert checked.intervals == 187 and checked.trajectory.t.size == 188
    assert checked.mesh_change <= 1e-3
    error = abs(checked.cost - reference.cost) / reference.cost
    assert error <= min(1e-4, checked.mesh_change)
    assert checked.trajectory.cost[-1] == checked.cost


def test_j_star_that_does_not_settle_is_not_converged():
    r = _fast_optimum([0.0, 1.0], 5.0, mesh=Mesh(refinements=1))
    assert not r.converged and math.isnan(r.cost) and r.trajectory is None and r.intervals == 0
    assert r.mesh_change == pytest.approx(0.0196, abs=5e-4)
    assert re.fullmatch(
        r"not converged \(J\* did not settle to rtol 0\.001 in 1 refinement, each grid twice as "
        r"fine as the last: 0\.93\d+ on 47, 0\.91\d+ on 94 intervals; pass a finer Mesh, more "
        r"refinements or a larger rtol \(mesh= in Python; the command line uses the default\)\)",
        r.status,
    )
    assert r.to_dict()["cost"] is None and r.to_dict()["mesh_change"] == r.mesh_change


def test_a_check_that_fails_to_converge_leaves_j_star_unconverged(monkeypatch):
    """The grid's J* converged but the finer one did not: no unchecked J* is passed off."""
    from ofrl_drake import optimal

    solve = optimal._Problem.solve
    calls = []

    def second_fails(self, mesh, attempts):
        calls.append(mesh)
        if len(calls) == 1:
            return solve(self, mesh, attempts)
        return optimal._Failed(["stand-in: snopt failed"], domain_failed=False)

    monkeypatch.setattr(optimal._Problem, "solve", second_fails)
    r = _fast_optimum([0.0, 1.0], 5.0)
    assert len(calls) == 2 and calls[1] == Mesh().refined()
    assert not r.converged and math.isnan(r.cost) and r.trajectory is None
    assert re.fullmatch(
        r"not converged \(J\* = 0\.93\d+ on 47 intervals, but the check on a grid twice as fine "
        r"did not converge: stand-in: snopt failed; pass a finer Mesh, or Mesh\(refinements=0\) "
        r"to accept an unchecked J\*\)",
        r.status,
    )


def test_a_warm_start_from_a_saturated_optimum_is_used():
    """An input started on its bound is not stepped past it (where U is undefined).

    SNOPT's default gradient check did, and the warm start failed with a domain
    error; here every solve from x0 = (1, 0) saturates the input.
    """
    mesh = Mesh(refinements=0)
    optimum = _fast_optimum([1.0, 0.0], 10.0, mesh=mesh)
    assert optimum.converged
    assert np.sum(np.abs(optimum.trajectory.u) >= 1 - 2e-6) > 10
    again = _fast_optimum([1.0, 0.0], 10.0, mesh=mesh, warm_start=optimum.trajectory)
    assert again.converged and again.warm_started and again.status == "ok"
    assert again.cost == pytest.approx(optimum.cost, rel=1e-6)


def test_result_dict_round_trips_the_check():
    r = _fast_optimum([0.0, 1.0], 5.0)
    back = OptimalControlResult.from_dict(json.loads(json.dumps(r.to_dict())))
    assert back == r and back.intervals == 187 and back.mesh_change == r.mesh_change
    old = {k: v for k, v in r.to_dict().items() if k not in ("intervals", "mesh_change")}
    older = OptimalControlResult.from_dict(old)  # a file written before the check
    assert older.intervals == 0 and math.isnan(older.mesh_change)


def _clock(monkeypatch, step):
    """``optimal``'s ``time.monotonic`` advancing by ``step`` seconds a call, from now."""
    import time
    import types

    from ofrl_drake import optimal

    now = time.monotonic()
    ticks = iter(range(1, 10**6))
    fake = types.SimpleNamespace(
        monotonic=lambda: now + step * next(ticks), perf_counter=time.perf_counter
    )
    monkeypatch.setattr(optimal, "time", fake)
    return now


def test_no_solve_starts_after_the_deadline(monkeypatch):
    """J* stops between its solves once its deadline passed (here: after the first grid)."""
    from ofrl_drake import WallTimeExceeded

    now = _clock(monkeypatch, 10.0)  # J* starts at +10 s, the first solve at +20 s
    with pytest.raises(
        WallTimeExceeded,
        match=r"^J\* ran out of wall time 20 s into its solves, before its attempt 'from the grid "
        r"of 47 intervals' on a grid of 94 intervals$",
    ) as err:
        _fast_optimum([0.0, 1.0], 5.0, deadline=now + 25.0)
    assert err.value.step == "J*"
    with pytest.raises(WallTimeExceeded, match=r"before its attempt 'default guess \(1 s\)' on"):
        _fast_optimum([0.0, 1.0], 5.0, deadline=now)


def test_a_bad_deadline_is_refused(two_state):
    with pytest.raises(OfrlError, match=r"deadline must be a time\.monotonic\(\) reading or None"):
        solve_optimal_control(two_state, [-1.0, 1.0], Q, R, LBAR, 5.0, deadline="soon")


def test_a_solver_optimum_without_a_cost_is_named_as_such(monkeypatch, two_state):
    """The status said "kSolutionFound" for a J* of -1.9e-13, refused as a cost."""
    from ofrl_drake import optimal

    class NegativeCost(optimal.DirectCollocation):
        def GetStateSamples(self, result):
            states = np.array(super().GetStateSamples(result))
            states[-1, -1] = -1.9e-13
            return states

    monkeypatch.setattr(optimal, "DirectCollocation", NegativeCost)
    r = solve_optimal_control(two_state, [-1.0, 1.0], Q, R, LBAR, 5.0, mesh=Mesh(refinements=0))
    assert not r.converged and math.isnan(r.cost)
    assert r.status.startswith(
        "not converged (default guess (1 s): snopt kSolutionFound (info 1), but its J* = "
        "-1.9e-13 is not a number >= 0; default guess (0.5 s): "
    )


def test_a_tiny_j_star_that_does_not_settle_names_the_solver_tolerance(paper_scenario):
    """From x0 = (1e-4, 0) (J* = 2.3e-8) the grids' J* differ by half: not the grid's fault."""
    r = optimal_control(paper_scenario, [1e-4, 0.0], mesh=Mesh(refinements=1))
    assert not r.converged
    assert r.status.endswith(
        "; a J* below 0.0001 may be limited by snopt's tolerances instead, which no grid "
        "improves: try solver='ipopt' (--solver ipopt), or start farther from the equilibrium)"
    )
    ipopt = optimal_control(paper_scenario, [1e-4, 0.0], mesh=Mesh(refinements=1), solver="ipopt")
    assert ipopt.converged and ipopt.cost == pytest.approx(2.33e-8, rel=0.01)
    fast = _fast_optimum([0.0, 1.0], 5.0, mesh=Mesh(refinements=1))  # J* = 0.91: no such hint
    assert not fast.converged and "absolute tolerance" not in fast.status
