"""User plants named as ``system: "module.path:callable"``, through the CLI and Python."""

import json
import os
import re
import sys
import textwrap

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump, yaml_load

from ofrl_drake import load_scenario
from ofrl_drake.ablation import read_rows
from ofrl_drake.cli import main
from ofrl_drake.errors import ScenarioError
from ofrl_drake.plants import locate_system_entry, resolve_system
from tests.cli_helpers import run_cli

from .conftest import PAPER_SCENARIO, ROOT, edited_two_state

#: The paper's plant, written out by a user in their own module.
USER_PLANT = textwrap.dedent(
    """
    import numpy as np
    from ofrl_drake import ControlAffineSystem

    def f(x):
        c = np.cos(2 * x[0]) + 2
        return np.array([-x[0] + x[1], -x[0] - 0.5 * x[1] * (1 - c**2)])

    def g(x):
        return np.array([[0 * x[0]], [np.cos(2 * x[0]) + 2]])

    def make_plant():
        return ControlAffineSystem(f, g, [[0.0, 1.0]], name="users_plant")

    def returns_a_number():
        return 42

    def raises():
        raise RuntimeError("the user's plant\\nis broken")

    not_a_function = 3
    """
)


def _scenario(folder, system, duration=1.0):
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    data["system"] = system
    data["simulation"]["duration"] = duration
    path = folder / "scenario.yaml"
    path.write_text(yaml_dump(data))
    return path


@pytest.fixture
def plant_folder(tmp_path):
    folder = tmp_path / "experiment"
    folder.mkdir()
    (folder / "users_plant.py").write_text(USER_PLANT)
    (folder / "fails_on_import.py").write_text("import numpy\n1 / 0\n")
    (folder / "missing_dependency.py").write_text("import no_such_package_ofrl\n")
    return folder


def test_cli_runs_a_plant_from_a_module_beside_the_scenario(plant_folder, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    scenario = _scenario(plant_folder, "users_plant:make_plant")
    out = tmp_path / "out"
    proc = run_cli("run", scenario, "--out", out, "--quiet", cwd=elsewhere)
    assert proc.returncode == 0, proc.stderr
    mine = np.load(out / "trajectories.npz")
    # The same equations as the registered example: the same closed loop.
    reference = _scenario(tmp_path, "two_state")
    assert main(["run", str(reference), "--out", str(tmp_path / "ref"), "--quiet"]) == 0
    ref = np.load(tmp_path / "ref" / "trajectories.npz")
    np.testing.assert_allclose(mine["x"], ref["x"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(mine["W"], ref["W"], rtol=0, atol=1e-12)
    assert json.loads((out / "summary.json").read_text())["final_time"] == pytest.approx(1.0)


def test_the_module_is_located_once_and_shipped_as_an_absolute_file(plant_folder, monkeypatch):
    scenario = load_scenario(_scenario(plant_folder, "users_plant:make_plant"))
    assert scenario.system == f"{(plant_folder / 'users_plant.py').resolve()}:make_plant"
    # A process that starts in another folder (a Dask worker) builds it too.
    monkeypatch.chdir(ROOT)
    assert resolve_system(scenario).name == "users_plant"


def test_modules_on_sys_path_and_registered_names_stay_as_written(tmp_path):
    assert locate_system_entry("ofrl_drake.examples:two_state", tmp_path) == (
        "ofrl_drake.examples:two_state"
    )
    assert locate_system_entry("two_state", tmp_path) == "two_state"
    scenario = load_scenario(_scenario(tmp_path, "ofrl_drake.examples:two_state"))
    assert scenario.system == "ofrl_drake.examples:two_state"


ERRORS = [
    (
        "no_such_module:make_plant",
        r"system: 'no_such_module:make_plant': no module 'no_such_module' beside the "
        r"scenario file or on sys.path",
    ),
    (
        "users_plant:no_such_function",
        r"system: '.*users_plant.py:no_such_function': module .*users_plant.py has no "
        r"attribute 'no_such_function'",
    ),
    (
        "fails_on_import:make_plant",
        r"system: '.*fails_on_import.py:make_plant': importing .*fails_on_import.py failed: "
        r"ZeroDivisionError: division by zero",
    ),
    (
        "missing_dependency:make_plant",
        r"importing .*missing_dependency.py failed: ModuleNotFoundError: No module named "
        r"'no_such_package_ofrl'",
    ),
    (
        "users_plant:returns_a_number",
        r"system: '.*users_plant.py:returns_a_number' returned an object of type int; it must "
        r"return an ofrl_drake.ControlAffineSystem",
    ),
    (
        "users_plant:raises",
        r"system: '.*users_plant.py:raises' raised RuntimeError: the user's plant is broken",
    ),
    (
        "users_plant:not_a_function",
        r"system: '.*users_plant.py:not_a_function' is an object of type int, not a callable",
    ),
    ("users_plant:", r"system: 'users_plant:' is not an import path; write 'module.path:callable'"),
    ("no_such_example", r"system: unknown example 'no_such_example'.*'module.path:callable'"),
]


@pytest.mark.parametrize(("entry", "match"), ERRORS, ids=[e for e, _ in ERRORS])
def test_bad_entries_raise_a_scenario_error_naming_the_entry(plant_folder, entry, match):
    with pytest.raises(ScenarioError, match=match):
        load_scenario(_scenario(plant_folder, entry))


@pytest.mark.parametrize(("entry", "match"), ERRORS, ids=[e for e, _ in ERRORS])
def test_cli_prints_bad_entries_on_one_line_and_exits_2(plant_folder, tmp_path, entry, match):
    out = tmp_path / "out"
    proc = run_cli("run", _scenario(plant_folder, entry), "--out", out, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    assert "scenario.yaml: " in lines[0]
    assert not list(tmp_path.glob("out*"))
    assert re.search(match, lines[0]), lines[0]
    assert "Traceback" not in proc.stderr


def _worker_view():
    """What a worker sees: its folder, and whether the user's module imports by name."""
    import importlib.util

    return os.getcwd(), importlib.util.find_spec("users_plant") is not None


def test_ablate_on_a_dask_cluster_whose_workers_start_elsewhere(
    plant_folder, tmp_path, capsys, monkeypatch
):
    """Workers import the user's module from its absolute path, not from their folder."""
    from distributed import Client, LocalCluster

    elsewhere = tmp_path / "workers_start_here"
    elsewhere.mkdir()
    scenario = _scenario(plant_folder, "users_plant:make_plant")
    variants = tmp_path / "variants.yaml"
    variants.write_text("baseline: {}\n")
    out = tmp_path / "ablation"
    monkeypatch.chdir(elsewhere)
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        with Client(cluster) as client:
            views = list(client.run(_worker_view).values())
        assert views == [(str(elsewhere), False)]
        code = main(
            [
                "ablate",
                str(scenario),
                "--out",
                str(out),
                "--variants",
                str(variants),
                "--scheduler",
                cluster.scheduler_address,
            ]
        )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert f"wrote {out}: 1 runs (1 ok)" in captured.out
    (row,) = read_rows(out / "ablation.csv")
    assert row["status"] == "ok"
    assert row["optimal_cost"] > 0  # J* solved by the worker, with the user's plant


def test_status_line_names_the_error_on_one_line():
    from ofrl_drake.errors import WallTimeExceeded, status_line

    assert status_line(ZeroDivisionError("a\n  b")) == "ZeroDivisionError: a b"
    assert status_line(ImportError()) == "ImportError"  # an empty message: the type alone
    late = WallTimeExceeded("the LMI ran out", step="LMI solve")
    assert status_line(late) == "timeout: the LMI ran out"


@pytest.mark.parametrize(
    ("truth", "sizes"),
    [
        ({"system": "two_state"}, r"\(2, 1, 1\)"),  # was truth.equilibrium.x: expected 2 entries
        ({"system": "coupled_two_state"}, r"\(4, 2, 2\)"),  # was truth.equilibrium.u
    ],
)
def test_a_truth_of_other_sizes_with_an_equilibrium_names_both_sizes(tmp_path, truth, sizes):
    # The cart-pole model (4 states, 1 input, 2 outputs) runs about its equilibrium;
    # the truth's size, not a key truth.equilibrium.x, is what is wrong.
    data = yaml_load(data=(ROOT / "diagrams" / "cart_pole.yaml").read_text())
    data["truth"] = truth
    path = tmp_path / "truth.yaml"
    path.write_text(yaml_dump(data))
    with pytest.raises(
        ScenarioError,
        match=rf"truth\.yaml: truth: the truth '{truth['system']}' has \(n, m, q\) = {sizes} "
        r"\(states, inputs, outputs\), the model 'cart_pole' \(4, 1, 2\); they must agree.* "
        r"Name a truth of the model's sizes",
    ):
        load_scenario(path)


def test_a_name_registered_again_resolves_to_the_new_plant():
    """Before: the first plant built under a name was cached by the name and kept."""
    import dataclasses

    from ofrl_drake.examples import EXAMPLES, register, two_state

    scenario = dataclasses.replace(load_scenario(PAPER_SCENARIO), system="reregistered")
    register("reregistered", two_state)
    try:
        first = resolve_system(scenario)
        assert resolve_system(scenario) is first  # built once per registration
        register("reregistered", edited_two_state(f_scale=0.5))
        second = resolve_system(scenario)
        x = np.array([0.3, -0.7])
        np.testing.assert_allclose(second.f(x), 0.5 * first.f(x), rtol=1e-15)
        register("reregistered", two_state)  # the first factory again: its plant again
        assert resolve_system(scenario) is first
    finally:
        EXAMPLES.pop("reregistered")


_SLIDER = """<?xml version="1.0"?>
<sdf version="1.7"><model name="slider">
  <link name="block"><inertial><mass>{mass}</mass></inertial></link>
  <joint name="slide" type="prismatic"><parent>world</parent><child>block</child>
    <axis><xyz>1 0 0</xyz></axis></joint>
</model></sdf>
"""


def _edit(path, text):
    """Rewrite ``path`` with a modification time a second later (coarse file systems)."""
    before = path.stat().st_mtime_ns
    path.write_text(text)
    os.utime(path, ns=(before + 10**9, before + 10**9))


def test_an_edited_plant_module_or_model_file_is_built_again(plant_folder, tmp_path, monkeypatch):
    """Before: both were cached by the scenario's text, so the edit went unseen in the process
    (and into a sweep's fingerprint): a notebook, or a long-lived Dask worker, ran the old plant.
    """
    import dataclasses

    from ofrl_drake.plants import dynamics_fingerprints
    from ofrl_drake.scenario import PlantConfig

    scenario = load_scenario(_scenario(plant_folder, "users_plant:make_plant"))
    module = plant_folder / "users_plant.py"
    monkeypatch.setattr(sys, "dont_write_bytecode", False)  # as Python runs by default
    second = module.stat().st_mtime_ns // 10**9 * 10**9
    os.utime(module, ns=(second + 100, second + 100))
    first = resolve_system(scenario)
    assert resolve_system(scenario) is first  # unchanged file: built once
    x = np.array([0.3, -0.7])
    # Rewritten within the same second at the same size (a script that writes the plant
    # file for a parameter study): Python's bytecode cache takes it for the old file.
    module.write_text(USER_PLANT.replace("[-x[0] + x[1],", "[-x[0] - x[1],"))
    os.utime(module, ns=(second + 200, second + 200))
    edited = resolve_system(scenario)
    np.testing.assert_allclose(edited.f(x)[0], -x[0] - x[1], rtol=1e-15)
    assert edited.fingerprint() != first.fingerprint()

    # A multibody model file: its edit, and a relative path read from another folder.
    model = tmp_path / "slider.sdf"
    model.write_text(_SLIDER.format(mass=1.0))
    slider = dataclasses.replace(
        scenario, system="", plant=PlantConfig(multibody="slider.sdf", C=[[1.0, 0.0]])
    )
    monkeypatch.chdir(tmp_path)
    light = dynamics_fingerprints(slider)["model"]
    _edit(model, _SLIDER.format(mass=4.0))
    heavy = dynamics_fingerprints(slider)["model"]
    assert heavy != light
    other = tmp_path / "other"
    other.mkdir()
    (other / "slider.sdf").write_text(_SLIDER.format(mass=1.0))
    monkeypatch.chdir(other)
    assert dynamics_fingerprints(slider)["model"] == light


#: What a task of a sweep says when its worker's plant is not the client's.
_OTHER_PLANT = (
    r"ScenarioError: the model dynamics on \S+ \(pid \d+\) differ from those the sweep was "
    r"started with \(fingerprint \w+ against {client}\): give every worker the same copy of the "
    r"plant's module and model files as the client, and restart workers after an edit; then "
    r"--resume --retry-failed runs these rows again\."
)


def test_a_worker_whose_plant_differs_from_the_clients_runs_nothing(paper_scenario):
    """A worker on another machine builds the plant from its own copy of the plant's code.

    Before, a copy that differed ran its own plant under the same name, and its
    rows were mixed with the others; now every task of the sweep checks the
    client's fingerprints first.
    """
    import dataclasses

    from ofrl_drake.ablation_grid import Variant
    from ofrl_drake.ablation_tasks import run_variant_states, solve_optimal_task
    from ofrl_drake.examples import EXAMPLES, register, two_state
    from ofrl_drake.monte_carlo import run_seeds
    from ofrl_drake.plants import check_dynamics, dynamics_fingerprints

    simulation = dataclasses.replace(paper_scenario.simulation, duration=0.5)
    scenario = dataclasses.replace(paper_scenario, system="worker_copy", simulation=simulation)
    register("worker_copy", two_state)
    try:
        client = dynamics_fingerprints(scenario)
        check_dynamics(scenario, client)
        check_dynamics(scenario, None)
        states = [[-1.0, 1.0], [0.5, 0.5]]
        assert all(
            r.status == "ok"
            for r in run_variant_states(scenario, Variant("b"), states, dynamics=client)
        )
        register("worker_copy", edited_two_state(g_scale=0.5))  # the worker's own copy
        message = _OTHER_PLANT.format(client=client["model"])
        with pytest.raises(ScenarioError, match=message[len("ScenarioError: ") :]):
            check_dynamics(scenario, client)
        runs = run_variant_states(scenario, Variant("b"), states, dynamics=client)
        assert len(runs) == 2 and all(re.fullmatch(message, r.status) for r in runs)
        optimum = solve_optimal_task(scenario, states[0], None, dynamics=client)
        assert not optimum.converged and re.fullmatch(message, optimum.status)
        rows = run_seeds(scenario, 3, [0, 1], 0.0, client)
        assert [r["row"]["seed"] for r in rows] == ["3", "4"]
        assert all(re.fullmatch(message, r["row"]["status"]) for r in rows)
        # Its own fingerprint, or none, runs the worker's plant as before.
        mine = dynamics_fingerprints(scenario)
        assert (
            run_variant_states(scenario, Variant("b"), states[:1], dynamics=mine)[0].status == "ok"
        )
    finally:
        EXAMPLES.pop("worker_copy")


def test_ablate_and_montecarlo_hand_every_task_the_clients_fingerprints(
    paper_scenario, monkeypatch
):
    """The sweeps pass the fingerprints they computed (and wrote into their plan) to tasks."""
    import dataclasses

    from ofrl_drake import ablation, monte_carlo
    from ofrl_drake.ablation import ablate
    from ofrl_drake.monte_carlo import montecarlo

    client = {"model": "clientsplant", "truth": None}
    monkeypatch.setattr(ablation, "dynamics_fingerprints", lambda scenario: client)
    monkeypatch.setattr(monte_carlo, "dynamics_fingerprints", lambda scenario: client)
    message = _OTHER_PLANT.format(client="clientsplant")
    short = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(paper_scenario.simulation, duration=0.5),
    )
    rows = ablate(short, {"baseline": {}, "lqr": {"controller": "lqr"}}, progress=False)
    assert len(rows) == 2 and all(re.fullmatch(message, r["status"]) for r in rows)
    rows = montecarlo(short, 2, progress=False, optimal_cost=1.0)
    assert len(rows) == 2 and all(re.fullmatch(message, r["status"]) for r in rows)


#: A user's plant with an ``if`` on the state: it simulates (with the true state fed
#: back), but Drake cannot trace it for J* or for the baselines that linearize it.
BRANCHY_PLANT = textwrap.dedent(
    """
    import numpy as np
    from ofrl_drake import ControlAffineSystem

    def f(x):
        return np.array([x[1], -x[0] - (x[1] if x[1] > 0 else 0.0)])

    def g(x):
        return np.array([[0.0], [1.0]])

    def make_plant():
        return ControlAffineSystem(f, g, [[1.0, 0.0]], name="branchy")
    """
)


@pytest.fixture
def branchy(tmp_path):
    """The scenario of :data:`BRANCHY_PLANT`, with the true state fed back, over 1 s."""
    folder = tmp_path / "branchy"
    folder.mkdir()
    (folder / "branchy.py").write_text(BRANCHY_PLANT)
    data = yaml_load(data=PAPER_SCENARIO.read_text())
    data["system"] = "branchy:make_plant"
    data["simulation"]["duration"] = 1.0
    data["variant"] = {"observer": "true_state"}
    path = folder / "scenario.yaml"
    path.write_text(yaml_dump(data))
    return path


@pytest.mark.filterwarnings("ignore:branchy. f and g do not accept a batch")
def test_j_star_and_the_linearizing_baselines_of_a_plant_drake_cannot_trace(branchy, tmp_path):
    """Before: run --optimal simulated, then exited 2 and dropped the run; montecarlo stopped
    with advice to "run without --optimal" it has no option for; controller lqr blamed the
    user's code with a raw TypeError."""
    import dataclasses
    import warnings

    from ofrl_drake.diagram import build_closed_loop
    from ofrl_drake.errors import ModelError
    from ofrl_drake.monte_carlo import OptimalCostWarning, montecarlo

    out = tmp_path / "run"
    proc = run_cli("run", branchy, "--out", out, "--optimal", "--quiet")
    assert proc.returncode == 2 and not out.exists(), proc.stderr
    assert re.fullmatch(
        r"error: --optimal: optimal control: J\* .* needs f and g that Drake can trace on "
        r"symbolic states, and those of the model 'branchy' cannot be .*; without them J\* is "
        r"not available\. Run without --optimal\. \(at .*branchy\.py:6, in f\)",
        proc.stderr.splitlines()[-1],
    ), proc.stderr
    assert run_cli("run", branchy, "--out", out, "--quiet").returncode == 0
    scenario = load_scenario(branchy)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = montecarlo(scenario, 2, progress=False)
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert all(np.isnan(r["optimal_cost"]) and np.isnan(r["optimality_ratio"]) for r in rows)
    (warning,) = [w.message for w in caught if isinstance(w.message, OptimalCostWarning)]
    assert all(str(warning).endswith(f"J/J*: {r['optimal_status']}") for r in rows), rows
    assert re.match(
        r"montecarlo two_state_paper: J\* of the nominal problem is not available, so the rows "
        r"have no J/J\*: optimal control: J\* .*model 'branchy' cannot be",
        str(warning),
    ), warning
    lqr = dataclasses.replace(
        scenario, variant=dataclasses.replace(scenario.variant, controller="lqr")
    )
    with pytest.raises(
        ModelError,
        match=r"^the baselines that linearize the plant \(controller lqr, observer "
        r"drake_luenberger or kalman\) trace f and g on symbolic states, and those of the model "
        r"'branchy' cannot be traced \(.*\); write f and g with numpy functions",
    ):
        build_closed_loop(lqr)
