"""Scenario files: the paper's parameters, and every bad input named by its key."""

import dataclasses
import math
import os
import re
import shutil

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump, yaml_load

from ofrl_drake import ModelError, ScenarioError, load_scenario
from ofrl_drake.plants import resolve_truth
from ofrl_drake.points import grid_points, uniform_points
from ofrl_drake.scenario import BoxConfig, abort_box, dump_scenario

from .conftest import MIMO_SCENARIO, PAPER_SCENARIO, ROOT
from .test_plants import USER_PLANT


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


def _write(folder, edit, source=PAPER_SCENARIO, name="bad.yaml"):
    """``source`` changed in place by ``edit(data)``, written to ``folder / name``."""
    data = yaml_load(data=source.read_text())
    edit(data)
    path = folder / name
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
        r"critic\.Gamma0: must be symmetric; entry \[0\]\[1\] is 2 but \[1\]\[0\] is 0\.$",
    ),
    (_set("input_bound", value=math.inf), r"input_bound: must be a finite number; got inf\.$"),
    (  # in a list, the check was skipped: internal error: OverflowError
        _set("x0", value=[10**400, 0.0]),
        r"x0\[0\]: the integer 10000000000\d+\.\.\. is beyond the largest float",
    ),
    (  # was let through (estimated 1.86 GiB) and took 3.6 GB
        _set(
            "points", value={"kind": "uniform", "lower": [-1, -1], "upper": [1, 1], "number": 10**7}
        ),
        r"points\.number: 1e\+07 points would need about 3\.73 GiB for the Bellman features",
    ),
    (
        _set("simulation", "duration", value=10**400),
        r"simulation\.duration: the integer 10000000000\d+\.\.\. is beyond the largest float",
    ),
    (
        _set("simulation", "accuracy", value=1e-15),
        r"simulation\.accuracy: must be between 1e-12 and 0\.1; got 1e-15: below that the "
        r"error estimate is at double-precision round-off",
    ),
    (
        _set("simulation", "accuracy", value=2.0),
        r"simulation\.accuracy: must be between 1e-12 and 0\.1; got 2: Drake's integrators use "
        r"at most 0\.1",
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


def test_a_plant_object_as_the_system_says_how_to_name_it():
    from ofrl_drake.examples import make_system
    from ofrl_drake.scenario import validate_scenario

    scenario = dataclasses.replace(load_scenario(PAPER_SCENARIO), system=make_system("two_state"))
    with pytest.raises(
        ScenarioError,
        match=r"^system: expected a string; got .*; a scenario names its plant: an example's "
        r"name, or 'module\.path:callable' .*ofrl_drake\.examples\.register\(name, factory\)",
    ):
        validate_scenario(scenario)


def test_an_empty_file_or_a_long_list_is_named_in_a_short_line(tmp_path):
    empty = tmp_path / "empty.yaml"
    empty.write_text("# only a comment\n")
    with pytest.raises(
        ScenarioError, match=r"scenario: expected a mapping of keys; got nothing \(the file or"
    ):
        load_scenario(empty)
    listed = tmp_path / "list.yaml"
    listed.write_text(yaml_dump(list(range(50_000))))
    with pytest.raises(ScenarioError, match=r"got \[0, 1, 2, .*\.\.\.\.$") as err:
        load_scenario(listed)
    assert len(str(err.value)) < 400  # was the whole list: 600 KB on one line


def test_a_path_that_is_not_a_regular_file_says_what_it_is(tmp_path):
    with pytest.raises(
        ScenarioError, match=r"^the scenario path is empty \(''\); give the path of a"
    ):
        load_scenario("")
    with pytest.raises(
        ScenarioError,
        match=rf"^{re.escape(str(tmp_path))}: is a directory, not a scenario file; give the "
        "path of a scenario YAML file in it",
    ):
        load_scenario(tmp_path)
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)  # never opened: a read would block until a writer came
    with pytest.raises(
        ScenarioError, match=r"fifo\.yaml: is a named pipe \(FIFO\), not a regular file; "
    ):
        load_scenario(fifo)
    with pytest.raises(ScenarioError, match=r"^/dev/null: is a character device, not a regular"):
        load_scenario("/dev/null")


def test_yaml_nested_too_deep_is_refused_naming_the_nesting(tmp_path):
    from ofrl_drake.scenario import MAX_YAML_DEPTH

    path = tmp_path / "deep.yaml"

    def nested(levels):  # name: holds ``levels`` lists, the root mapping one level more
        text = PAPER_SCENARIO.read_text()
        path.write_text(
            text.replace("name: two_state_paper", f"name: {'[' * levels}{']' * levels}")
        )
        return path

    deep = r"deep\.yaml: line 3: lists and mappings nested more than 20 levels deep; .*Write the"
    for levels in (5000, MAX_YAML_DEPTH):
        with pytest.raises(ScenarioError, match=deep):
            load_scenario(nested(levels))
    with pytest.raises(ScenarioError, match=r"name: expected a string"):  # 20 deep: allowed
        load_scenario(nested(MAX_YAML_DEPTH - 1))


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


def _replace(scenario, path, value):
    """``scenario`` with the field at dotted ``path`` set to ``value`` (nothing else changed)."""
    head, _, rest = path.partition(".")
    if not rest:
        return dataclasses.replace(scenario, **{head: value})
    return dataclasses.replace(scenario, **{head: _replace(getattr(scenario, head), rest, value)})


# A scenario built in Python is held to the schema a YAML file is held to.
BAD_FIELDS = [
    (
        "cost.Q",
        np.eye(2),
        r"cost\.Q: expected a list; got a numpy array of shape \(2, 2\); .*tolist",
    ),
    ("critic.Gamma0", 50 * np.eye(3), r"critic\.Gamma0: expected a list; got a numpy array"),
    ("observer.L", np.zeros((2, 1)), r"observer\.L: expected a list; got a numpy array"),
    ("observer.schedule_half_width", np.ones(2), r"observer\.schedule_half_width: expected a list"),
    ("x0", np.array([-1.0, 1.0]), r"x0: expected a list; got a numpy array of shape \(2,\)"),
    ("x0", ["a", "b"], r"x0\[0\]: expected a number; got 'a'"),
    ("x0", (-1.0, 1.0), r"x0: expected a list; got the tuple \(-1\.0, 1\.0\); pass a list"),
    ("x0", [np.float32(-1.0), 1.0], r"x0\[0\]: expected a number; got the numpy scalar"),
    ("simulation.duration", None, r"simulation\.duration: a value is required; got None"),
    ("simulation.duration", "1", r"simulation\.duration: expected a number; got '1'"),
    ("input_bound", None, r"input_bound: a value is required; got None"),
    ("observer.alpha", None, r"observer\.alpha: a value is required; got None"),
    ("observer.jacobian_tol", "1e-3", r"observer\.jacobian_tol: expected a number; got '1e-3'"),
    (
        "simulation.regulation_tolerance",
        "0.1",
        r"simulation\.regulation_tolerance: expected a number; got '0\.1'",
    ),
    ("name", None, r"name: a value is required; got None"),
    (
        "observer.box",
        {"lower": [-2.0, -2.0], "upper": [2.0, 2.0]},
        r"observer\.box: expected an instance of BoxConfig; got \{.*BoxConfig\(lower=\.\.\., upper",
    ),
    (
        "cost",
        {"Q": [[5.0, 0.0], [0.0, 5.0]], "R": [1.0]},
        r"cost: expected an instance of CostConfig",
    ),
    ("variant", {}, r"variant: expected an instance of VariantConfig; got \{\}"),
    ("equilibrium", {"x": [0.0, 0.0]}, r"equilibrium: expected an instance of EquilibriumConfig"),
    ("points.seed", 1.5, r"points\.seed: expected an integer; got 1\.5"),
    ("points.seed", True, r"points\.seed: expected an integer; got True"),
    ("points.seed", np.int64(1), r"points\.seed: expected an integer; got the numpy scalar"),
    ("points.counts", [2.5, 10], r"points\.counts\[0\]: expected an integer; got 2\.5"),
    ("points.number", 2.5, r"points\.number: expected an integer; got 2\.5"),
]


@pytest.mark.parametrize(("path", "value", "match"), BAD_FIELDS)
def test_a_scenario_built_in_python_is_held_to_the_schema(paper_scenario, path, value, match):
    from ofrl_drake.scenario import validate_scenario

    bad = _replace(paper_scenario, path, value)
    with pytest.raises(ScenarioError, match=match):
        validate_scenario(bad)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("period", None, r"measurement\.period: a value is required; got None"),
        ("seed", 1.5, r"measurement\.seed: expected an integer; got 1\.5"),
    ],
)
def test_measurement_fields_are_held_to_the_schema(paper_scenario, field, value, match):
    from ofrl_drake.scenario import MeasurementConfig, validate_scenario

    bad = dataclasses.replace(paper_scenario, measurement=MeasurementConfig(**{field: value}))
    with pytest.raises(ScenarioError, match=match):
        validate_scenario(bad)


def test_validation_leaves_a_python_built_scenario_unchanged(paper_scenario):
    from ofrl_drake.scenario import MeasurementConfig, validate_scenario

    good = dataclasses.replace(
        paper_scenario, x0=[-1, 1], measurement=MeasurementConfig(seed=3, period=0.01)
    )
    before = dataclasses.asdict(good)
    validate_scenario(good)
    assert dataclasses.asdict(good) == before


@pytest.mark.parametrize("seed", [2**32, 99999999999999999999])
def test_a_measurement_seed_beyond_what_drake_keeps_is_refused(tmp_path, paper_scenario, seed):
    from ofrl_drake.scenario import MeasurementConfig, validate_scenario

    # Drake's RandomGenerator keeps 32 bits: 2**32 would draw seed 0's noise.
    refused = rf"measurement\.seed: must be at most 2\*\*32 - 1 = 4294967295 .*got {seed}\."
    path = tmp_path / "seed.yaml"
    path.write_text(PAPER_SCENARIO.read_text() + f"measurement:\n  seed: {seed}\n")
    with pytest.raises(ScenarioError, match=rf"seed\.yaml: {refused}"):
        load_scenario(path)
    with pytest.raises(ScenarioError, match=refused):
        validate_scenario(
            dataclasses.replace(paper_scenario, measurement=MeasurementConfig(seed=seed))
        )
    path.write_text(PAPER_SCENARIO.read_text() + "measurement:\n  seed: 4294967295\n")
    assert load_scenario(path).measurement.seed == 2**32 - 1
    # points.seed feeds numpy only, which takes any integer >= 0.
    points = dataclasses.replace(paper_scenario.points, kind="uniform", seed=seed)
    validate_scenario(dataclasses.replace(paper_scenario, points=points))


#: (section, key, what, smallest): the paper's 30 s horizon allows 10,000,000 steps
#: (MAX_STEPS) and 10,000 LMI re-solves (MAX_SCHEDULE_SOLVES).
TINY_PERIODS = [
    ("simulation", "max_step", r"integrator steps or more.*10,000,000 \(MAX_STEPS\)", 3e-6),
    ("observer", "schedule_period", r"LMI re-solves.*10,000 \(MAX_SCHEDULE_SOLVES\)", 0.003),
    ("measurement", "period", r"samples \(each ends an integrator step\).*MAX_STEPS", 3e-6),
    ("actuation", "period", r"held inputs \(each ends an integrator step\).*MAX_STEPS", 3e-6),
]


@pytest.mark.parametrize(("section", "key", "what", "smallest"), TINY_PERIODS)
def test_a_period_too_small_for_the_horizon_is_refused_naming_the_smallest(
    tmp_path, section, key, what, smallest
):
    def load(period):
        def edit(d):
            d.setdefault(section, {})[key] = period

        return load_scenario(_write(tmp_path, edit))

    with pytest.raises(
        ScenarioError,
        match=rf"bad\.yaml: {section}\.{key}: 1e-09 s over simulation\.duration = 30 s means "
        rf"3e\+10 {what}.*Use a {key} of at least {smallest:g} s \(or a shorter",
    ):
        load(1e-9)
    assert getattr(getattr(load(smallest), section), key) == smallest  # the named one passes
    with pytest.raises(ScenarioError, match=rf"{section}\.{key}: .*at least {smallest:g} s"):
        load(smallest * (1 - 1e-9))


SHIPPED = sorted((ROOT / "diagrams").glob("*.yaml")) + sorted(
    (ROOT / "benchmarks" / "scenarios").glob("*.yaml")
)


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_every_shipped_scenario_loads_far_within_the_step_bounds(path):
    from ofrl_drake.scenario import MAX_SCHEDULE_SOLVES, MAX_STEPS

    s = load_scenario(path)
    periods = [
        s.simulation.max_step,
        s.measurement.period if s.measurement else 0.0,
        s.actuation.period if s.actuation else 0.0,
    ]
    steps = max(s.simulation.duration / p for p in periods if p > 0)
    assert steps * 5000 <= MAX_STEPS  # as scenario.MAX_STEPS's comment says
    if s.observer.schedule_period > 0:
        assert s.simulation.duration / s.observer.schedule_period <= MAX_SCHEDULE_SOLVES


@pytest.mark.parametrize("degrees", [[3], [3, 5]])
def test_a_basis_of_odd_degrees_only_is_refused(tmp_path, degrees):
    from ofrl_drake.basis import PolynomialBasis

    size = PolynomialBasis(2, degrees).size

    def edit(d):
        d["critic"].update(basis_degrees=degrees, W0=[0.0] * size)
        d["critic"]["Gamma0"] = np.eye(size).tolist()

    with pytest.raises(
        ScenarioError, match=r"critic\.basis_degrees: \[3.*only odd degrees.*add an even degree"
    ):
        load_scenario(_write(tmp_path, edit))


def test_a_basis_with_an_even_degree_and_odd_ones_is_accepted(tmp_path):
    def edit(d):
        d["critic"].update(basis_degrees=[2, 3], W0=[0.4, 0.2, 0.8] + [0.0] * 4)
        d["critic"]["Gamma0"] = (50 * np.eye(7)).tolist()

    assert load_scenario(_write(tmp_path, edit)).critic.basis_degrees == [2, 3]


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: grid_points([-1, -1], [1, 1], [2.5, 10]), r"points\.counts\[0\] .*integer.*2\.5"),
        (lambda: grid_points([-1, -1], [1, 1], [0, 10]), r"points\.counts\[0\] .*>= 1; got 0"),
        (lambda: grid_points([-1, -1], [1, 1], [True, 3]), r"points\.counts\[0\] .*got True"),
        (lambda: grid_points([-1, -1], [1, 1], 10), r"points\.counts must hold 2 .*got 10"),
        (lambda: uniform_points([-1], [1], 2.5, 0), r"points\.number .*integer >= 1; got 2\.5"),
        (lambda: uniform_points([-1], [1], 3, 1.5), r"points\.seed .*integer >= 0; got 1\.5"),
        (lambda: uniform_points([-1], [1], 3, -1), r"points\.seed .*integer >= 0; got -1"),
    ],
)
def test_point_counts_and_seeds_must_be_integers(call, match):
    with pytest.raises(ModelError, match=match):
        call()


def test_point_counts_and_seeds_accept_numpy_integers():
    np.testing.assert_array_equal(
        grid_points([-1, -1], [1, 1], np.array([2, 3])), grid_points([-1, -1], [1, 1], [2, 3])
    )
    np.testing.assert_array_equal(
        uniform_points([-1], [1], np.int64(3), np.int64(2)), uniform_points([-1], [1], 3, 2)
    )


# --------------------------------------------------------------------------
# truth: entries are found beside the scenario file, as the model's are.
# --------------------------------------------------------------------------
#: A Drake System factory a user writes beside the scenario, for truth.plant.drake_system.
USER_DRAKE_PLANT = """
from pydrake.examples import PendulumPlant


def make_pendulum():
    return PendulumPlant()
"""


def _truth_scenario(folder, source, truth):
    """``source`` (a shipped scenario) written into ``folder`` with ``truth`` added."""

    def edit(data):
        data["truth"] = truth
        data["simulation"]["duration"] = 0.2

    return _write(folder, edit, ROOT / "diagrams" / source, "scenario.yaml")


@pytest.fixture
def truth_folder(tmp_path):
    """A folder holding a user's plant module, a Drake plant module and a model file."""
    folder = tmp_path / "experiment"
    (folder / "models").mkdir(parents=True)
    (folder / "users_plant.py").write_text(USER_PLANT)
    (folder / "users_pendulum.py").write_text(USER_DRAKE_PLANT)
    shutil.copy(ROOT / "diagrams" / "models" / "cart_double_pendulum.urdf", folder / "models")
    (tmp_path / "elsewhere").mkdir()
    return folder


@pytest.mark.parametrize(
    ("source", "truth", "key", "file"),
    [
        (
            "two_state_paper.yaml",
            {"system": "users_plant:make_plant"},
            "system",
            "users_plant.py:make_plant",
        ),
        (
            "pendulum_upright.yaml",
            {"plant": {"drake_system": "users_pendulum:make_pendulum", "C": [[1.0, 0.0]]}},
            "plant.drake_system",
            "users_pendulum.py:make_pendulum",
        ),
        (
            "cart_double_pendulum.yaml",
            {"plant": {"multibody": "models/cart_double_pendulum.urdf"}},
            "plant.multibody",
            "models/cart_double_pendulum.urdf",
        ),
    ],
)
def test_truth_entries_are_found_beside_the_scenario_from_another_cwd(
    truth_folder, monkeypatch, source, truth, key, file
):
    path = _truth_scenario(truth_folder, source, truth)
    monkeypatch.chdir(truth_folder.parent / "elsewhere")
    scenario = load_scenario(path)
    value = scenario.truth.system if key == "system" else getattr(scenario.truth.plant, key[6:])
    assert value == str(truth_folder.resolve() / file)
    assert resolve_truth(scenario) is not None


def test_a_missing_truth_module_file_is_named_beside_the_scenario(truth_folder, monkeypatch):
    path = _truth_scenario(truth_folder, "two_state_paper.yaml", {"system": "gone.py:make_plant"})
    monkeypatch.chdir(truth_folder.parent / "elsewhere")
    gone = re.escape(str((truth_folder / "gone.py").resolve()))
    with pytest.raises(
        ScenarioError, match=rf"truth\.system: '{gone}:make_plant': no such module file {gone}\."
    ):
        load_scenario(path)


def test_a_run_with_a_truth_beside_its_scenario_writes_a_scenario_yaml_that_reloads(
    truth_folder, tmp_path, monkeypatch
):
    from ofrl_drake.cli import main

    path = _truth_scenario(
        truth_folder, "two_state_paper.yaml", {"system": "users_plant:make_plant"}
    )
    monkeypatch.chdir(tmp_path / "elsewhere")
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--quiet", "--checkpoints", "0"]) == 0
    monkeypatch.chdir(ROOT)  # as a later run, or a Dask worker, starts elsewhere
    again = load_scenario(out / "scenario.yaml")
    assert again.truth.system == f"{(truth_folder / 'users_plant.py').resolve()}:make_plant"
    assert resolve_truth(again).name == "users_plant"


# --------------------------------------------------------------------------
# Numbers in exponent form: YAML 1.2 numbers where a float is expected.
# --------------------------------------------------------------------------
def _write_text(tmp_path, old, new):
    """The paper scenario with the line text ``old`` replaced by ``new``, as written."""
    text = PAPER_SCENARIO.read_text()
    assert text.count(old) == 1, old
    path = tmp_path / "edited.yaml"
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize(
    ("old", "new", "get", "expected"),
    [
        ("kc: 0.01", "kc: 1e-2", lambda s: s.critic.kc, float("1e-2")),
        ("duration: 30.0", "duration: 1e1", lambda s: s.simulation.duration, 10.0),
        ("duration: 30.0", "duration: 5.0e0", lambda s: s.simulation.duration, 5.0),
        ("duration: 30.0", "duration: 3E+1", lambda s: s.simulation.duration, 30.0),
        ("accuracy: 1.0e-4", "accuracy: 1e-4", lambda s: s.simulation.accuracy, 1e-4),
        ("x0: [-1.0, 1.0]", "x0: [-1e0, .5e1]", lambda s: s.x0, [-1.0, 5.0]),
        ("x0: [-1.0, 1.0]", "x0: [-.5, +.25]", lambda s: s.x0, [-0.5, 0.25]),
        ("kc: 0.01", "kc: +.01", lambda s: s.critic.kc, 0.01),
        (
            "Gamma0: [[50.0, 0.0, 0.0]",
            "Gamma0: [[5e1, 0e0, 0.0]",
            lambda s: s.critic.Gamma0[0],
            [50.0, 0.0, 0.0],
        ),
    ],
)
def test_yaml_1_2_numbers_are_read_as_python_reads_them(tmp_path, old, new, get, expected):
    value = get(load_scenario(_write_text(tmp_path, old, new)))
    assert value == expected
    assert all(type(v) is float for v in (value if isinstance(value, list) else [value]))


def test_an_exponent_where_a_string_is_expected_stays_as_written(tmp_path):
    path = _write_text(tmp_path, "kc: 0.01", "kc: 1e-2")
    path.write_text(path.read_text().replace("name: two_state_paper", "name: 1e3"))
    scenario = load_scenario(path)
    assert scenario.name == "1e3"
    assert scenario.critic.kc == 0.01  # and where a number is, the number (as 1.0e-2 gives)


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        (
            "counts: [10, 10]",
            "counts: [1e1, 10]",
            r"points\.counts\[0\]: expected an integer; got 1e1; write it as the integer 10 ",
        ),
        (
            "counts: [10, 10]",
            "counts: [1.0e+1, 10]",
            r"points\.counts\[0\]: expected an integer; got 10\.0; write it as the integer 10 ",
        ),
        (
            "counts: [10, 10]",
            "counts: [2.5e0, 10]",
            r"points\.counts\[0\]: expected an integer; got 2\.5e0\.$",
        ),
        (
            "basis_degrees: [2]",
            "basis_degrees: [2e0]",
            r"critic\.basis_degrees\[0\]: expected an integer; got 2e0; write it as the integer 2",
        ),
        (
            "kc: 0.01",
            'kc: "1e-2"',
            r"critic\.kc: expected a number; got '1e-2' \(a quoted string\); write the number "
            "without quotes",
        ),
        (
            "kc: 0.01",
            "kc: '0.01'",
            r"critic\.kc: expected a number; got '0\.01' \(a quoted string\)",
        ),
    ],
)
def test_integers_in_exponent_form_and_quoted_numbers_are_refused_naming_the_fix(
    tmp_path, old, new, match
):
    with pytest.raises(ScenarioError, match=match):
        load_scenario(_write_text(tmp_path, old, new))


def test_an_unknown_yaml_tag_is_refused_naming_its_line(tmp_path):
    path = _write_text(tmp_path, "input_bound: 3.0", "input_bound: !Big 3.0")
    with pytest.raises(ScenarioError, match=r"edited\.yaml: not valid YAML: .*'!Big'.* line 7,"):
        load_scenario(path)


# --------------------------------------------------------------------------
# The logs of a run are bounded: a tiny log_period is refused, not run out of memory.
# --------------------------------------------------------------------------
def test_a_log_period_whose_logs_would_not_fit_in_memory_is_refused(tmp_path):
    path = _write_text(tmp_path, "log_period: 0.02", "log_period: 1.0e-12")
    with pytest.raises(
        ScenarioError,
        match=r"simulation\.log_period: 1e-12 s over simulation\.duration = 30 s logs 3e\+13 "
        r"samples, about .* GiB \(27 numbers each: x, xhat, W, Gamma, u, \.\.\.\); the logs may "
        r"take at most 2 GiB\. Use a log_period of at least 3\.02e-06 s",
    ):
        load_scenario(path)
    # The period the message names is accepted (before: 'above 2.01e-06' for 20 s, refused).
    load_scenario(_write_text(tmp_path, "log_period: 0.02", "log_period: 3.02e-06"))


def test_the_log_cap_passes_fine_log_periods_and_refuses_just_above_it(paper_scenario):
    from ofrl_drake.scenario import MAX_LOG_BYTES, validate_scenario

    fine = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, log_period=1e-5)
    )
    validate_scenario(fine)  # 3 million samples of the two-state example
    # Just above the cap (27 numbers of 8 bytes per sample): refused.
    period = 30.0 * 27 * 8 / MAX_LOG_BYTES / 1.001
    tight = dataclasses.replace(
        paper_scenario, simulation=dataclasses.replace(paper_scenario.simulation, log_period=period)
    )
    with pytest.raises(ScenarioError, match=r"simulation\.log_period: .* at most 2 GiB"):
        validate_scenario(tight)


@pytest.mark.parametrize("where", [(), ("critic",)])
def test_an_unknown_number_key_beside_text_keys_is_named(tmp_path, where):
    # Sorting the unknown keys raised TypeError when one of them was a number.
    def edit(data):
        for key in where:
            data = data[key]
        data[1] = "a"
        data["zz"] = "b"

    prefix = "".join(f"{key}\\." for key in where)
    with pytest.raises(ScenarioError, match=rf": {prefix}1: unknown key in "):
        load_scenario(_write(tmp_path, edit))
