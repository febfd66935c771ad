"""Scenario files: the paper's parameters, and every bad input named by its key."""

import dataclasses

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump, yaml_load

from ofrl_drake import ScenarioError, load_scenario
from ofrl_drake.scenario import BoxConfig, abort_box, dump_scenario

from .conftest import MIMO_SCENARIO, PAPER_SCENARIO


def test_paper_scenario_holds_every_parameter_of_notes(paper_scenario):
    s = paper_scenario
    assert s.system == "two_state"
    assert s.x0 == [-1.0, 1.0] and s.xhat0 == [2.0, 1.5]
    assert s.input_bound == 3.0
    np.testing.assert_array_equal(s.cost.Q, 5 * np.eye(2))
    assert s.cost.R == [1.0]
    assert s.critic.W0 == [0.4, 0.2, 0.8]
    np.testing.assert_array_equal(s.critic.Gamma0, 50 * np.eye(3))
    assert (s.critic.kc, s.critic.nu, s.critic.beta) == (0.01, 0.7, 0.2)
    assert s.points.kind == "grid" and s.points.counts == [10, 10]
    assert s.points.lower == [-1.0, -1.0] and s.points.upper == [1.0, 1.0]
    assert s.observer.alpha == 2.0
    assert s.observer.box.lower == [-2.0, -2.0] and s.observer.box.upper == [2.0, 2.0]
    assert s.simulation.duration == 30.0
    assert s.simulation.integrator == "runge_kutta3"


def test_mimo_scenario_loads(mimo_scenario):
    assert mimo_scenario.system == "coupled_two_state"
    assert len(mimo_scenario.critic.W0) == 10


def _write(tmp_path, edit):
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml_dump(data))
    return path


def _set(*keys, value):
    def edit(d):
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value

    return edit


def _drop(*keys):
    def edit(d):
        for k in keys[:-1]:
            d = d[k]
        del d[keys[-1]]

    return edit


BAD = [
    (_set("critic", "speed", value=1.0), r"critic\.speed: unknown key in critic"),
    (_set("bogus", value=1), r"bogus: unknown key in scenario"),
    (_drop("critic", "kc"), r"critic\.kc: missing; critic\.gains: manual needs critic\.kc"),
    (
        _set("critic", "law", value="newton"),
        r"critic\.law: must be one of \[.policy_iteration., .paper.\]",
    ),
    (_set("critic", "gains", value="auto"), r"critic\.kc: given, but critic\.gains is auto"),
    (
        _set("critic", "policy_period", value=1.0),
        r"critic\.policy_period: applies to critic\.law: policy_iteration only",
    ),
    (_drop("x0"), r"x0: missing required key"),
    (
        _set("critic", "Gamma0", value=[[1, 2, 0], [2, 1, 0], [0, 0, 1]]),
        r"critic\.Gamma0: must be symmetric positive definite; its smallest eigenvalue is -1",
    ),
    (
        _set("critic", "Gamma0", value=[[1, 2, 0], [0, 1, 0], [0, 0, 1]]),
        r"critic\.Gamma0: must be symmetric",
    ),
    (
        _set("critic", "Gamma0", value=[[1, 0], [0, 1]]),
        r"critic\.Gamma0: expected a 3x3 matrix; got 2x2",
    ),
    (_set("input_bound", value=0.0), r"input_bound: must be > 0; got 0\.0"),
    (_set("input_bound", value=-3.0), r"input_bound: must be > 0; got -3\.0"),
    (_set("critic", "kc", value=-0.01), r"critic\.kc: must be > 0; got -0\.01"),
    (_set("critic", "nu", value=0.0), r"critic\.nu: must be > 0"),
    (_set("critic", "beta", value=-1.0), r"critic\.beta: must be > 0"),
    (_set("critic", "beta", value=0.0), r"critic\.beta: must be > 0; got 0\.0"),
    (_set("observer", "alpha", value=0.0), r"observer\.alpha: must be > 0"),
    (_set("x0", value=[1.0, 2.0, 3.0]), r"x0: expected 2 entries; got 3"),
    (_set("xhat0", value=[1.0]), r"xhat0: expected 2 entries; got 1"),
    (_set("critic", "W0", value=[0.4, 0.2]), r"critic\.W0: expected 3 entries; got 2"),
    (_set("critic", "kc", value="fast"), r"critic\.kc: expected a number; got 'fast'"),
    (_set("cost", "R", value=[0.0]), r"cost\.R: entries must be > 0"),
    (_set("system", value="pendulum"), r"system: unknown example 'pendulum'"),
    (
        _set("simulation", "integrator", value="euler_magic"),
        r"simulation\.integrator: unknown scheme 'euler_magic'",
    ),
    (
        _set("observer", "box", "upper", value=[-3.0, 2.0]),
        r"observer\.box\.upper: must exceed observer\.box\.lower",
    ),
    (_set("observer", "L", value=[[1.0], [2.0]]), r"observer\.H: pin all of L, H and K or none"),
    (_set("observer", "jacobian_tol", value=0.0), r"observer\.jacobian_tol: must be > 0; got 0\.0"),
    (
        _set("observer", "jacobian_rtol", value=-0.1),
        r"observer\.jacobian_rtol: must be >= 0; got -0\.1",
    ),
    (_set("points", "kind", value="sobol"), r"points\.kind: must be 'grid' or 'uniform'"),
    (
        _set("critic", "basis_degrees", value=[1]),
        r"critic\.basis_degrees: .*degree 1 is not allowed",
    ),
]


@pytest.mark.parametrize(("edit", "match"), BAD)
def test_bad_scenarios_name_the_key(tmp_path, edit, match):
    with pytest.raises(ScenarioError, match=match):
        load_scenario(_write(tmp_path, edit))


def test_error_message_names_the_file(tmp_path):
    path = _write(tmp_path, _set("input_bound", value=-1.0))
    with pytest.raises(ScenarioError, match=r"bad\.yaml: input_bound"):
        load_scenario(path)


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(tmp_path / "absent.yaml")
    bad = tmp_path / "broken.yaml"
    bad.write_text("system: [unclosed\n")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(bad)


def test_pinned_gains_are_accepted(tmp_path):
    def pin(d):
        d["observer"].update(L=[[-20.0], [10.0]], H=[[1.0], [0.0]], K=[[0.0], [0.0]])

    s = load_scenario(_write(tmp_path, pin))
    assert s.observer.L == [[-20.0], [10.0]]


def test_mimo_file_exists():
    assert MIMO_SCENARIO.is_file()


def test_dump_scenario_reads_back_to_the_resolved_scenario(paper_scenario, tmp_path):
    path = tmp_path / "scenario.yaml"
    path.write_text(dump_scenario(paper_scenario))
    again = load_scenario(path)
    lower, upper = abort_box(paper_scenario)
    resolved = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(
            paper_scenario.simulation,
            abort_box=BoxConfig(lower=lower.tolist(), upper=upper.tolist()),
        ),
    )
    assert again == resolved
    # Floats that need all 17 digits survive the round trip exactly.
    odd = dataclasses.replace(paper_scenario, x0=[0.1 + 0.2, -1.0 / 3.0])
    path.write_text(dump_scenario(odd))
    assert load_scenario(path).x0 == [0.1 + 0.2, -1.0 / 3.0]


def test_the_tolerances_of_the_certified_bounds_reach_them(tmp_path):
    from ofrl_drake.plants import resolve_system
    from ofrl_drake.variants import scenario_bounds

    default = load_scenario(_write(tmp_path, lambda d: d))
    loose = load_scenario(
        _write(tmp_path, _set("observer", "jacobian_rtol", value=0.5)),
    )
    assert loose.observer.jacobian_rtol == 0.5 and default.observer.jacobian_rtol is None
    system = resolve_system(default)
    tight_b, loose_b = scenario_bounds(default, system), scenario_bounds(loose, system)
    # d f2 / d x1 of the two-state plant: each end may lie half its sampled width beyond.
    assert (loose_b.Mf2 - loose_b.Mf1)[1, 0] > (tight_b.Mf2 - tight_b.Mf1)[1, 0] + 0.1
    assert loose_b.excess.converged and tight_b.excess.converged
