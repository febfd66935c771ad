"""simulate(): argument checks, the validity monitor per observer, and save()."""

import copy
import dataclasses
import io
import json
import re

import numpy as np
import pytest
from pydrake.systems.framework import BasicVector, LeafSystem

from ofrl_drake import (
    ModelError,
    OutputError,
    RunFolderError,
    ScenarioError,
    SimulationResult,
    SwapError,
    build_closed_loop,
    simulate,
)
from ofrl_drake.simulation import EXTRA_LOGS_FILE, SHIFTED_KEYS, SUMMARY_KEYS, TRAJECTORY_KEYS
from ofrl_drake.systems import CriticWeights
from ofrl_drake.systems.baselines import FullStateObserver
from ofrl_drake.validity import validity_report

LBAR = 3.0  # the paper scenario's input bound


def _short(scenario, duration=0.5, observer=None, variant=None, **top):
    return dataclasses.replace(
        scenario,
        observer=dataclasses.replace(scenario.observer, **(observer or {})),
        simulation=dataclasses.replace(scenario.simulation, duration=duration),
        variant=dataclasses.replace(scenario.variant, **(variant or {})),
        **top,
    )


def _fixed_box(scenario):
    o = scenario.observer
    return np.asarray(o.box.lower, float), np.asarray(o.box.upper, float)


class _Constant(LeafSystem):
    """A block with one constant output port ``name`` and no inputs."""

    def __init__(self, name, value):
        super().__init__()
        value = np.atleast_1d(np.asarray(value, float))
        self.DeclareVectorOutputPort(
            name,
            value.size,
            lambda _c, out: out.SetFromVector(value),
            prerequisites_of_calc={self.nothing_ticket()},  # a constant depends on nothing
        )


# --------------------------------------------------------- simulate(loop=...)
@pytest.fixture(scope="module")
def short_scenario(paper_scenario):
    return _short(paper_scenario)


@pytest.fixture(scope="module")
def short_loop(short_scenario, paper_design):
    return build_closed_loop(short_scenario, design=paper_design)


def test_loop_with_design_raises_naming_design(short_scenario, short_loop, paper_design):
    with pytest.raises(
        SwapError,
        match=r"^design: simulate\(\.\.\., loop=\.\.\.\) runs the loop as built.*pass design= "
        r"to build_closed_loop\(scenario, design=\.\.\.\) instead, or drop loop=",
    ):
        simulate(short_scenario, loop=short_loop, design=paper_design, progress=False)


def test_loop_with_a_swap_raises_naming_the_slot(short_scenario, short_loop):
    with pytest.raises(
        SwapError,
        match=r"^critic: simulate\(\.\.\., loop=\.\.\.\) cannot swap blocks of a loop that is "
        r"already built; pass critic=\.\.\. to build_closed_loop\(scenario, critic=\.\.\.\)",
    ):
        simulate(
            short_scenario,
            loop=short_loop,
            critic=CriticWeights(short_scenario.critic.W0, kc=0.0),
            progress=False,
        )


def test_loop_built_from_another_scenario_raises_naming_the_difference(short_scenario, short_loop):
    other = _short(short_scenario, duration=0.25)
    with pytest.raises(
        ScenarioError,
        match=r"^scenario: the loop was built from a different scenario \(it differs in "
        r"simulation\); pass the scenario the loop was built from \(loop\.parts\.scenario\), "
        r"or rebuild the loop with build_closed_loop\(scenario\)\.$",
    ):
        simulate(other, loop=short_loop, progress=False)
    renamed = dataclasses.replace(short_scenario, name="other", input_bound=2.0)
    with pytest.raises(ScenarioError, match=r"differs in input_bound, name\)"):
        simulate(renamed, loop=short_loop, progress=False)


@pytest.mark.parametrize("scenario", [{}, None, 42])
def test_simulate_refuses_what_is_neither_a_scenario_nor_a_path(scenario):
    with pytest.raises(
        ScenarioError,
        match=r"^simulate: scenario must be a Scenario or the path of a scenario file; got "
        rf"{type(scenario).__name__}\. Load one with ofrl_drake\.load_scenario\(path\)\.$",
    ) as err:
        simulate(scenario)
    assert isinstance(err.value, TypeError)  # what simulate raised before


def test_loop_must_be_a_built_loop(short_scenario):
    with pytest.raises(
        SwapError,
        match=r"^loop: expected a ClosedLoop; got str\. Build one with "
        r"build_closed_loop\(scenario\), or omit loop=",
    ):
        simulate(short_scenario, loop="x", progress=False)


def test_loop_with_an_equal_scenario_runs(short_scenario, short_loop):
    same = copy.deepcopy(short_scenario)
    assert same is not short_scenario
    r = simulate(same, loop=short_loop, progress=False)
    assert r.t[-1] == pytest.approx(0.5, abs=1e-9)
    # Equal values held as numpy arrays compare equal too.
    as_arrays = dataclasses.replace(short_scenario, x0=np.asarray(short_scenario.x0))
    r = simulate(as_arrays, loop=short_loop, progress=False)
    assert r.t[-1] == pytest.approx(0.5, abs=1e-9)


# ------------------------------------------------ initial values and parameters
def _arrays(result):
    """Every logged array of a run, by name."""
    arrays = {k: np.asarray(getattr(result, k)) for k in TRAJECTORY_KEYS}
    arrays.update({f"extra.{k}": np.asarray(v) for k, v in result.extra.items()})
    return arrays


def _assert_same_run(a, b):
    """The two runs logged the same arrays, bit for bit."""
    A, B = _arrays(a), _arrays(b)
    assert A.keys() == B.keys()
    for key in A:
        assert np.array_equal(A[key], B[key]), key


def _load(name, duration):
    from ofrl_drake import load_scenario
    from tests.conftest import ROOT

    s = load_scenario(ROOT / "diagrams" / f"{name}.yaml")
    return dataclasses.replace(s, simulation=dataclasses.replace(s.simulation, duration=duration))


#: Loops whose blocks differ in how they hold a state: the symbolic and the Python plant
#: and observer, Drake's Luenberger observer, the re-designed observer, the moving points,
#: and a multibody truth behind noisy sampled sensors with a sampled controller.
RERUN_CASES = {
    "symbolic": lambda: _load("two_state_paper", 1.0),
    "python": lambda: _with_simulation(_load("two_state_paper", 1.0), blocks="python"),
    "drake_luenberger": lambda: _variant(
        _load("two_state_paper", 1.0), observer="drake_luenberger"
    ),
    "scheduled": lambda: _observer(_load("two_state_paper", 0.5), schedule_period=0.2),
    "around_estimate": lambda: _variant(_load("two_state_paper", 1.0), points="around_estimate"),
    "multibody_real_world": lambda: _load("cart_pole_real_world", 0.5),
}


def _with_simulation(s, **changes):
    return dataclasses.replace(s, simulation=dataclasses.replace(s.simulation, **changes))


def _variant(s, **changes):
    return dataclasses.replace(s, variant=dataclasses.replace(s.variant, **changes))


def _observer(s, **changes):
    return dataclasses.replace(s, observer=dataclasses.replace(s.observer, **changes))


@pytest.mark.parametrize("case", sorted(RERUN_CASES))
def test_a_built_loop_reruns_from_another_state_as_a_fresh_build(case):
    """Writing x0 and xhat0 into a fresh context: the runs of a loop built for each state."""
    scenario = RERUN_CASES[case]()
    x0 = 0.8 * np.asarray(scenario.x0, dtype=float)
    xhat0 = x0 + 0.5 * (np.asarray(scenario.xhat0) - np.asarray(scenario.x0))
    other = dataclasses.replace(scenario, x0=x0.tolist(), xhat0=xhat0.tolist())
    loop = build_closed_loop(scenario)
    for s in (other, scenario, other):  # another state, the loop's own, the other again
        reused = simulate(s, loop=loop, progress=False)
        fresh = simulate(s, design=loop.design, progress=False)
        assert reused.status == fresh.status == "ok"
        _assert_same_run(reused, fresh)
    assert reused.x[0] == pytest.approx(x0, abs=1e-12)


def test_a_built_loop_reruns_under_another_noise_seed_as_a_fresh_build():
    scenario = _load("cart_pole_real_world", 0.5)
    loop = build_closed_loop(scenario)
    other = dataclasses.replace(
        scenario, measurement=dataclasses.replace(scenario.measurement, seed=7)
    )
    reused = simulate(other, loop=loop, progress=False)
    _assert_same_run(reused, simulate(other, design=loop.design, progress=False))
    assert reused.provenance["seeds"] == {"measurement": 7}
    assert not np.array_equal(reused.xhat, simulate(scenario, loop=loop, progress=False).xhat)
    noisier = dataclasses.replace(
        scenario, measurement=dataclasses.replace(scenario.measurement, noise_std=[0.1, 0.1])
    )
    with pytest.raises(ScenarioError, match=r"\(it differs in measurement\.noise_std\)"):
        simulate(noisier, loop=loop, progress=False)


def test_initial_weights_and_gamma_are_written_under_manual_gains(short_scenario, short_loop):
    critic = dataclasses.replace(
        short_scenario.critic, W0=[0.5, 0.1, 0.9], Gamma0=(20.0 * np.eye(3)).tolist()
    )
    other = dataclasses.replace(short_scenario, critic=critic)
    reused = simulate(other, loop=short_loop, progress=False)
    _assert_same_run(reused, simulate(other, design=short_loop.design, progress=False))
    np.testing.assert_array_equal(reused.W[0], [0.5, 0.1, 0.9])
    np.testing.assert_array_equal(reused.Gamma[0], 20.0 * np.eye(3))


def test_only_the_values_a_run_writes_may_differ_from_the_loops_scenario(
    short_scenario, short_loop
):
    gains = dataclasses.replace(short_scenario.critic, kc=0.02)
    with pytest.raises(ScenarioError, match=r"\(it differs in critic\.kc\); pass the scenario"):
        simulate(dataclasses.replace(short_scenario, critic=gains), loop=short_loop)
    pendulum = _load("pendulum_upright", 0.2)  # critic.gains: auto, derived from W0
    loop = build_closed_loop(pendulum)
    W0 = dataclasses.replace(pendulum.critic, W0=[1.0, 0.0, 1.0])
    with pytest.raises(ScenarioError, match=r"\(it differs in critic\.W0\)"):
        simulate(dataclasses.replace(pendulum, critic=W0), loop=loop)


def _gain_setters(loop, context, *, kc, beta, nu, gamma_bound=None):
    """Write the learning gains into the blocks' contexts of ``context``."""
    sub = {slot: loop.blocks[slot].GetMyMutableContextFromRoot(context) for slot in loop.blocks}
    loop.critic.set_kc(sub["critic"], kc)
    loop.gamma.set_kc(sub["gamma"], kc)
    loop.gamma.set_beta(sub["gamma"], beta)
    loop.gamma.set_gamma_bound(sub["gamma"], gamma_bound)
    loop.bellman.set_nu(sub["bellman"], nu)


def test_gains_set_in_the_context_run_as_a_loop_built_with_them(short_scenario, short_loop):
    context = short_loop.diagram.CreateDefaultContext()
    _gain_setters(short_loop, context, kc=0.05, beta=0.5, nu=0.3)
    reused = simulate(short_scenario, loop=short_loop, parameters=context, progress=False)
    critic = dataclasses.replace(short_scenario.critic, kc=0.05, beta=0.5, nu=0.3)
    rebuilt = simulate(
        dataclasses.replace(short_scenario, critic=critic),
        design=short_loop.design,
        progress=False,
    )
    _assert_same_run(reused, rebuilt)
    # The context given is not modified, and a run without it uses the loop's own gains.
    assert short_loop.critic.get_kc(short_loop.critic.GetMyContextFromRoot(context)) == 0.05
    own = simulate(short_scenario, loop=short_loop, progress=False)
    _assert_same_run(own, simulate(short_scenario, design=short_loop.design, progress=False))
    assert not np.array_equal(own.W, reused.W)


def test_bounded_forgetting_gains_set_in_the_context(tmp_path):
    """policy_iteration's gamma_bound and the derived gains, written out as manual ones."""
    pendulum = _load("pendulum_upright", 2.0)
    resolved = build_closed_loop(pendulum).resolved_scenario()  # critic.gains: manual
    loop = build_closed_loop(resolved)
    g = resolved.critic
    changed = {"kc": 2 * g.kc, "beta": 0.5 * g.beta, "nu": 3 * g.nu, "gamma_bound": 1.5}
    context = loop.diagram.CreateDefaultContext()
    _gain_setters(loop, context, **changed)
    reused = simulate(resolved, loop=loop, parameters=context, progress=False)
    rebuilt = dataclasses.replace(resolved, critic=dataclasses.replace(g, **changed))
    _assert_same_run(reused, simulate(rebuilt, design=loop.design, progress=False))
    # W0 (the critic's and the policy in force's) and Gamma0 written into the context.
    W0 = (1.1 * np.asarray(g.W0)).tolist()
    other = dataclasses.replace(
        resolved, critic=dataclasses.replace(g, W0=W0, Gamma0=(2 * np.asarray(g.Gamma0)).tolist())
    )
    reused = simulate(other, loop=loop, progress=False)
    _assert_same_run(reused, simulate(other, design=loop.design, progress=False))
    np.testing.assert_array_equal(reused.W_policy[0], W0)


def test_parameters_need_a_loop(short_scenario, short_loop):
    context = short_loop.diagram.CreateDefaultContext()
    with pytest.raises(SwapError, match=r"^parameters: a context of a built loop's diagram"):
        simulate(short_scenario, parameters=context)


def test_parameters_must_be_a_root_context_of_the_loops_diagram(short_scenario, short_loop):
    from pydrake.systems.primitives import Adder

    with pytest.raises(
        SwapError,
        match=r"^parameters: expected a Context of loop\.diagram; got int; pass "
        r"loop\.diagram\.CreateDefaultContext\(\)",
    ):
        simulate(short_scenario, loop=short_loop, parameters=3, progress=False)
    own = short_loop.diagram.CreateDefaultContext()
    others = {
        "another system's": Adder(2, 1).CreateDefaultContext(),  # Drake aborted on it
        "another loop's": build_closed_loop(
            short_scenario, observer="kalman"
        ).diagram.CreateDefaultContext(),  # silently taken
        "a block's": short_loop.critic.GetMyContextFromRoot(own),
    }
    for name, context in others.items():
        with pytest.raises(
            SwapError,
            match=r"^parameters: the context is not a root context of this loop's diagram "
            r"'closed_loop_two_state_paper' .*; pass loop\.diagram\.CreateDefaultContext\(\)",
        ):
            simulate(short_scenario, loop=short_loop, parameters=context, progress=False)
            pytest.fail(f"{name} context taken")


class _PlantWithoutSetter(LeafSystem):
    """The paper's plant with no ``set_state``: it starts from its own default state."""

    def __init__(self, x0):
        super().__init__()
        from ofrl_drake.examples import make_system

        self.system = make_system("two_state")
        state = self.DeclareContinuousState(BasicVector(np.asarray(x0, dtype=float)))
        self._u = self.DeclareVectorInputPort("u", 1)
        self.DeclareStateOutputPort("state", state)
        self.DeclareVectorOutputPort(
            "y",
            1,
            lambda c, out: out.SetFromVector(c.get_continuous_state_vector().CopyToVector()[:1]),
            prerequisites_of_calc={self.xc_ticket()},
        )

    def DoCalcTimeDerivatives(self, context, derivatives):
        x = context.get_continuous_state_vector().CopyToVector()
        derivatives.SetFromVector(self.system.dynamics(x, self._u.Eval(context)))


def test_swapped_blocks_keep_their_own_initial_values(short_scenario):
    W_own = [0.1, 0.0, 0.1]
    loop = build_closed_loop(short_scenario, critic=CriticWeights(W_own, kc=0.0))
    r = simulate(short_scenario, loop=loop, progress=False)
    np.testing.assert_array_equal(r.W[0], W_own)  # not the scenario's W0
    # A run from another x0 writes it into the blocks that take it, W0 stays the block's.
    other = dataclasses.replace(short_scenario, x0=[0.5, -0.5], xhat0=[0.6, -0.4])
    r = simulate(other, loop=loop, progress=False)
    np.testing.assert_array_equal(r.x[0], [0.5, -0.5])
    np.testing.assert_array_equal(r.xhat[0], [0.6, -0.4])
    np.testing.assert_array_equal(r.W[0], W_own)
    # A stateless observer has nothing to set.
    swapped = build_closed_loop(short_scenario, observer=FullStateObserver(2))
    assert simulate(other, loop=swapped, progress=False).status == "ok"
    # A block without the setter starts from its own state, and cannot start from another.
    swapped = build_closed_loop(short_scenario, plant=_PlantWithoutSetter(short_scenario.x0))
    r = simulate(short_scenario, loop=swapped, progress=False)
    np.testing.assert_array_equal(r.x[0], short_scenario.x0)
    with pytest.raises(
        SwapError,
        match=r"^plant: the block _PlantWithoutSetter has no set_state\(context, value\), so a "
        r"run cannot start it from x0 = \[0\.5, -0\.5\]; give it one",
    ):
        simulate(other, loop=swapped, progress=False)


# ------------------------------------------------------- validity per observer
def test_fixed_design_is_checked_against_its_box(paper_result, paper_scenario):
    v = paper_result.validity
    assert v.box_check == "fixed" and v.note is None
    design = paper_result.design
    expected = validity_report(
        paper_result.t,
        paper_result.x,
        paper_result.xhat,
        paper_result.u,
        _fixed_box(paper_scenario),
        LBAR,
        C=design["C"],
        H=design["H"],
        K=design["K"],
    )
    assert v == expected
    # xhat(0) = (2, 1.5) sits on the box edge and overshoots it; x stays inside.
    assert v.estimate_outside is True and v.state_outside is False
    # The K injection point xhat + K ytil starts outside: K = [-2.79, 0]^T, ytil(0) = -0.5.
    assert v.injection_check == "checked" and v.injection_k_outside is True
    assert v.first_exit_time == 0.0
    np.testing.assert_allclose(
        v.box_excursions["xhat + K ytil"]["worst_point"], [3.3934, 1.5], atol=1e-4
    )


def test_observer_without_design_still_checks_the_input_bound(paper_scenario, tmp_path):
    r = simulate(_short(paper_scenario, variant={"observer": "true_state"}), progress=False)
    assert r.design is None
    v = r.validity
    assert v is not None and v.box_check == "not_applicable" and not v.box_checked
    assert v.note == (
        "no observer design (observer block FullStateObserver): box checks not applicable; "
        "only |u_k| <= lambda_bar was checked"
    )
    assert v.state_outside is None and v.estimate_outside is None
    assert v.input_exceeded is False and v.valid
    r.save(tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["validity"]["box_checked"] is False
    assert summary["validity"]["note"].startswith("no observer design")


def test_drake_luenberger_reports_its_local_certificate_and_no_box(paper_scenario):
    r = simulate(_short(paper_scenario, variant={"observer": "drake_luenberger"}), progress=False)
    d = r.design
    assert d["kind"] == "linearized_luenberger" and d["certified"] is True
    assert d["certificate_max_eigenvalue"] < 0
    # Poles placed at -2 alpha (1 + k/n) = -4, -6 for the paper's alpha = 2.
    np.testing.assert_allclose(sorted(d["poles"]["real"]), [-6.0, -4.0], rtol=1e-9)
    np.testing.assert_allclose(d["poles"]["imag"], [0.0, 0.0], atol=1e-12)
    v = r.validity
    assert v.box_check == "not_applicable" and v.valid
    assert v.note.startswith(
        "observer LinearizedLuenbergerObserver runs the linearization: its gain has a local "
        "certificate"
    )


def test_input_above_the_bound_is_reported_without_a_design(paper_scenario):
    s = _short(paper_scenario, variant={"observer": "true_state"})
    r = simulate(
        s,
        controller=_Constant("u", 3.5),  # |u| = 3.5 > lambda_bar = 3
        running_cost=_Constant("cost", 0.0),  # U(u) is undefined beyond the bound
        progress=False,
    )
    np.testing.assert_array_equal(r.u, np.full((r.t.size, 1), 3.5))
    v = r.validity
    assert v.box_check == "not_applicable"
    assert v.input_exceeded is True and not v.valid
    assert v.first_exit_time == pytest.approx(0.0, abs=1e-12)
    assert v.fraction_outside == pytest.approx(1.0, abs=1e-12)
    assert v.state_outside is None and v.estimate_outside is None
    assert v.warning().startswith(
        "warning: |u| exceeded the input bound at t = 0.000 s (100.0% of the horizon in "
        "violation); x and xhat were not checked against a box: no observer design "
        "(observer block FullStateObserver)"
    )


def test_a_certificate_without_injection_gains_leaves_them_unchecked(paper_scenario, paper_design):
    # A user's observer may certify a box with a design dict of its own, without H and K.
    from ofrl_drake.observer import ObserverGains
    from ofrl_drake.observer_certificate import ObserverCertificate
    from ofrl_drake.systems import ThreeGainObserver

    class OwnCertificate(ThreeGainObserver):
        def observer_certificate(self):
            return ObserverCertificate(
                "design", design={"P": paper_design.P.tolist()}, box=paper_design.box
            )

    def observer(parts):
        return OwnCertificate(parts.system, ObserverGains.from_design(parts.system, paper_design))

    r = simulate(_short(paper_scenario), design=paper_design, observer=observer, progress=False)
    v = r.validity
    assert v.box_check == "fixed" and v.injection_check == "no_gains"
    assert v.injection_k_outside is None and v.estimate_outside is True


def test_observer_that_ignores_the_design_gets_no_box_check(paper_scenario, paper_design):
    r = simulate(
        _short(paper_scenario), design=paper_design, observer=FullStateObserver(2), progress=False
    )
    assert r.design is not None  # the design is still reported ...
    v = r.validity
    assert v.box_check == "not_applicable"  # ... but the observer does not run it
    assert v.note == (
        "the observer block (FullStateObserver) does not run the observer design's gains: "
        "box checks not applicable; only |u_k| <= lambda_bar was checked"
    )
    assert v.state_outside is None and v.input_exceeded is False


def test_the_input_bound_checked_is_the_one_of_the_design_the_observer_runs(paper_scenario):
    from ofrl_drake.design import design_observer
    from ofrl_drake.observer import ObserverGains
    from ofrl_drake.systems import ThreeGainObserver

    s = _short(paper_scenario, duration=1.0)
    small_box = ([-1.0, -1.0], [1.0, 1.0])

    def observer(parts):
        small = design_observer(parts.system, small_box, 0.1, 0.1)  # |u_k| <= 0.1 only
        gains = ObserverGains.from_design(parts.system, small)
        return ThreeGainObserver(parts.system, gains, design=small)

    r = simulate(s, observer=observer, progress=False)
    assert r.design["input_bound"] == 0.1
    assert np.max(np.abs(r.u)) > 1.0  # the controller saturates at 3, not 0.1
    v = r.validity
    assert v.input_exceeded is True and not v.valid  # was reported within the bound
    assert v.note == (
        "|u_k| checked against the observer design's input_bound = 0.1, below the "
        "scenario's input_bound = 3"
    )
    expected = validity_report(
        r.t,
        r.x,
        r.xhat,
        r.u,
        tuple(map(np.asarray, small_box)),
        0.1,
        note=v.note,
        C=r.design["C"],
        H=r.design["H"],
        K=r.design["K"],
    )
    assert v == expected


# ----------------------------------------------------------- scheduled observer
SCHEDULE = {"schedule_period": 0.1, "schedule_half_width": [1.0, 1.0]}


@pytest.fixture(scope="module")
def scheduled(paper_scenario, paper_design):
    # xhat(0) inside [-2, 2]^2; the boxes xhat +- 1 around the estimate do not always hold x.
    s = _short(paper_scenario, observer=SCHEDULE, xhat0=[-0.5, 0.5])
    return s, simulate(s, design=paper_design, progress=False)


RESOLVE_TIMES = (0.1, 0.2, 0.3, 0.4)  # a re-solve due at T = 0.5 does not run


def _in_force(r, design_box):
    """Reference box in force at each sample, rebuilt from the xhat and solve_failed logs.

    The re-solve at t_k centres its box on xhat(t_k); the logs sample discrete
    state before an update due at the same time, so its outcome shows on the
    samples after t_k.
    """
    lower = np.tile(design_box[0], (r.t.size, 1))
    upper = np.tile(design_box[1], (r.t.size, 1))
    failed = []
    for tk in RESOLVE_TIMES:
        later = r.t > tk + 1e-9
        failed.append(bool(r.extra["solve_failed"][later][0, 0] > 0.5))
        if not failed[-1]:
            lower[later] = r.at("xhat", tk) - 1.0
            upper[later] = r.at("xhat", tk) + 1.0
    return lower, upper, np.array(failed)


def test_scheduled_observer_logs_the_box_in_force_and_exact_counts(scheduled, paper_scenario):
    _, r = scheduled
    lower, upper, failed = _in_force(r, _fixed_box(paper_scenario))
    np.testing.assert_allclose(r.extra["certified_box"], np.hstack([lower, upper]), atol=1e-12)
    # solve_counts = [re-solves run, failed], sample by sample.
    run = np.array([np.sum(np.array(RESOLVE_TIMES) < t - 1e-9) for t in r.t])
    fails = np.array([np.sum(failed[np.array(RESOLVE_TIMES) < t - 1e-9]) for t in r.t])
    np.testing.assert_array_equal(r.extra["solve_counts"], np.column_stack([run, fails]))
    # Both outcomes occur in this run, so the checks are not vacuous.
    assert failed.any() and not failed.all()
    counts = r.solve_counts()
    assert counts["resolves"] == 4 and counts["failed_solves"] == int(failed.sum())


def test_scheduled_observer_is_checked_against_the_box_in_force(scheduled, paper_scenario):
    _, r = scheduled
    v = r.validity
    assert v.box_check == "scheduled"
    assert v.note.startswith(
        "observer ScheduledThreeGainObserver re-designs its gains along the run"
    )
    lower, upper, failed = _in_force(r, _fixed_box(paper_scenario))
    x_out = np.any((r.x < lower - 1e-9) | (r.x > upper + 1e-9), axis=1)
    xhat_out = np.any((r.xhat < lower - 1e-9) | (r.xhat > upper + 1e-9), axis=1)
    assert v.state_outside == bool(x_out.any()) and v.estimate_outside == bool(xhat_out.any())
    assert v.first_exit_time == pytest.approx(r.t[np.argmax(x_out | xhat_out)], abs=1e-12)
    # Here x leaves a box centred on the estimate, although it never leaves the
    # fixed design box: a fixed-box check would call this run valid.
    assert v.state_outside is True and not v.valid
    first_ok = np.array(RESOLVE_TIMES)[~failed][0]
    assert v.first_exit_time > first_ok
    fixed = validity_report(r.t, r.x, r.xhat, r.u, _fixed_box(paper_scenario), LBAR)
    assert fixed.valid


def test_scheduled_observer_whose_resolves_all_fail_keeps_the_design_box(
    paper_scenario, paper_design
):
    # No design certifies alpha = 500: every re-solve fails, the first box stays.
    s = _short(paper_scenario, observer={"schedule_period": 0.2, "alpha": 500.0})
    r = simulate(s, design=paper_design, progress=False)
    np.testing.assert_array_equal(r.extra["solve_counts"][-1], [2, 2])
    np.testing.assert_array_equal(
        r.extra["certified_box"], np.tile(np.hstack(_fixed_box(paper_scenario)), (r.t.size, 1))
    )
    v = r.validity
    assert v.box_check == "scheduled" and "(0 box changes)" in v.note
    d = paper_design
    fixed = validity_report(
        r.t, r.x, r.xhat, r.u, _fixed_box(paper_scenario), LBAR, C=d.C, H=d.H, K=d.K
    )
    assert (v.first_exit_time, v.fraction_outside) == (
        fixed.first_exit_time,
        fixed.fraction_outside,
    )
    assert (v.state_outside, v.estimate_outside, v.input_exceeded) == (
        fixed.state_outside,
        fixed.estimate_outside,
        fixed.input_exceeded,
    )
    assert r.summary()["failed_solves"] == 2


# ------------------------------------------------------------------------ save
def test_save_writes_extra_logs_and_the_failed_solve_count(scheduled, tmp_path):
    _, r = scheduled
    r.save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        EXTRA_LOGS_FILE,
        "summary.json",
        "trajectories.npz",
    ]
    with np.load(tmp_path / "trajectories.npz") as data:
        assert data.files == list(TRAJECTORY_KEYS)
    extra_keys = [
        "certificate",
        "certified_box",
        "lyapunov_matrix",
        "observer_gains",
        "solve_counts",
        "solve_failed",
        "t",
        "verification",
    ]
    with np.load(tmp_path / EXTRA_LOGS_FILE) as data:
        assert sorted(data.files) == extra_keys
        np.testing.assert_array_equal(data["t"], r.t)
        for key in set(extra_keys) - {"t"}:
            np.testing.assert_array_equal(data[key], r.extra[key])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["failed_solves"] == int(r.extra["solve_counts"][-1, 1])
    assert summary["observer_resolves"]["resolves"] == 4
    assert summary["extra_logs"] == extra_keys
    assert summary["validity"]["box_check"] == "scheduled"


def test_save_without_extra_logs_writes_no_extra_file_and_removes_a_stale_one(
    paper_result, tmp_path
):
    (tmp_path / EXTRA_LOGS_FILE).write_bytes(b"stale")
    paper_result.save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json", "trajectories.npz"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert "failed_solves" not in summary and "extra_logs" not in summary


def _synthetic(counts):
    T = len(counts)
    return SimulationResult(
        t=np.arange(T, dtype=float),
        x=np.zeros((T, 1)),
        xhat=np.zeros((T, 1)),
        W=np.zeros((T, 1)),
        W_policy=np.zeros((T, 1)),
        Gamma=np.ones((T, 1, 1)),
        u=np.zeros((T, 1)),
        learning_condition=np.ones(T),
        cost=np.zeros(T),
        extra={"solve_counts": np.asarray(counts, float)},
    )


def test_solve_counts_read_the_last_sample_and_the_first_failure():
    counts = _synthetic([[0, 0], [1, 0], [2, 1], [3, 1], [4, 3]]).solve_counts()
    assert counts == {
        "resolves": 4,
        "failed_solves": 3,
        "at_time": 4.0,
        "first_failure_logged_at": 2.0,
    }
    assert _synthetic([[0, 0], [1, 0]]).summary()["failed_solves"] == 0
    assert _synthetic([[0, 0], [1, 0]]).solve_counts()["first_failure_logged_at"] is None


def test_at_and_original_refuse_a_bad_key_or_time():
    r = _synthetic([[0, 0], [1, 0], [2, 1]])  # samples at t = 0, 1, 2
    np.testing.assert_array_equal(r.at("x", 1.0), [0.0])
    for time, why in (
        (float("nan"), r"SimulationResult\.at: time must be finite; got nan\."),
        (-1.0, r"SimulationResult\.at: time must be >= 0; got -1\.0\."),
        (5.0, r"no sample of 'x' at t = 5\.0; the log ends at 2\.0\."),
    ):
        with pytest.raises(ModelError, match=rf"^{why}$"):
            r.at("x", time)
    with pytest.raises(ModelError, match=r"^SimulationResult\.at: no log 'foo'; choose one of "):
        r.at("foo", 0.1)
    with pytest.raises(
        ModelError,
        match=r"^SimulationResult\.original: no log 'foo' has the plant's own coordinates; "
        r"choose one of \['x', 'xhat', 'u'\]",
    ):
        r.original("foo")


def test_save_into_a_file_raises_an_output_error(tmp_path):
    target = tmp_path / "taken"
    target.write_text("not a folder")
    with pytest.raises(
        OutputError,
        match=r"^SimulationResult\.save: directory: .*taken is a file, so .*trajectories\.npz "
        r"cannot be created; choose another path\.$",
    ):
        _synthetic([[0, 0], [1, 0]]).save(target)
    assert target.read_text() == "not a folder"


def test_save_replaces_files_atomically(tmp_path):
    r = _synthetic([[0, 0], [1, 1], [2, 1]])
    r.save(tmp_path)
    before = (tmp_path / "summary.json").read_bytes()
    names = {"trajectories.npz", EXTRA_LOGS_FILE, "summary.json"}
    assert {p.name for p in tmp_path.iterdir()} == names
    r.design = {"not_json": object()}  # summary.json fails half-way through
    with pytest.raises(TypeError, match=r"not JSON serializable"):
        r.save(tmp_path)
    assert {p.name for p in tmp_path.iterdir()} == names  # no temporary file left behind
    assert (tmp_path / "summary.json").read_bytes() == before  # the old one is intact
    with np.load(tmp_path / "trajectories.npz") as data:
        assert data.files == list(TRAJECTORY_KEYS)


def test_progress_bar_gives_the_same_schedule(scheduled, paper_design, capsys):
    s, r = scheduled
    shown = simulate(s, design=paper_design, progress=True)
    assert "100%" in capsys.readouterr().err
    np.testing.assert_array_equal(shown.extra["solve_counts"], r.extra["solve_counts"])
    # The bar is drawn by the simulator's monitor, which takes no steps: bit for bit.
    np.testing.assert_array_equal(shown.extra["certified_box"], r.extra["certified_box"])
    np.testing.assert_array_equal(shown.x, r.x)
    assert shown.validity.box_check == "scheduled"


# ------------------------------------------------------------------------ load
def _assert_same_result(loaded, saved):
    """Every array and every figure input of ``saved``, bit for bit, in ``loaded``."""
    _assert_same_run(loaded, saved)
    for key in ("x_equilibrium", "u_equilibrium"):
        np.testing.assert_array_equal(getattr(loaded, key), getattr(saved, key))
    for key in ("x", "xhat", "u"):
        np.testing.assert_array_equal(loaded.original(key), saved.original(key))
    np.testing.assert_array_equal(loaded.e, saved.e)
    for key in (
        "scenario_name",
        "state_units",
        "input_units",
        "wall_time",
        "integrator",
        "design",
        "provenance",
        "reports",
        "status",
        "regulated",
    ):
        assert getattr(loaded, key) == getattr(saved, key), key
    assert (loaded.stop.status, loaded.stop.reason, loaded.stop.time) == (
        saved.stop.status,
        saved.stop.reason,
        saved.stop.time,
    )
    np.testing.assert_allclose(loaded.stop.x, saved.stop.x, rtol=0, atol=1e-14)
    assert loaded.validity.to_dict() == json.loads(json.dumps(saved.validity.to_dict()))
    assert json.loads(json.dumps(loaded.summary())) == json.loads(json.dumps(saved.summary()))


@pytest.fixture(scope="module")
def cart_pole_result():
    """A run with an equilibrium (x* = [0, pi, 0, 0]), units and extra logs."""
    return simulate(_load("cart_pole", 0.5), progress=False)


def test_load_gives_back_what_save_wrote_with_an_equilibrium(cart_pole_result, tmp_path):
    r = cart_pole_result
    r.save(tmp_path)
    loaded = SimulationResult.load(tmp_path)
    _assert_same_result(loaded, r)
    assert loaded.state_units == ("m", "rad", "m/s", "rad/s")
    assert loaded.original("x")[0, 1] == pytest.approx(np.pi + 0.15)  # x*_2 added once
    assert sorted(loaded.extra) == ["policy_updates"]
    assert loaded.integrator["accuracy"] == 1e-4
    # The plant's own coordinates in the file, the method's beside them, bit for bit.
    with np.load(tmp_path / "trajectories.npz") as data:
        np.testing.assert_array_equal(data["x"], r.original("x"))
        np.testing.assert_array_equal(data[SHIFTED_KEYS["x"]], r.x)
    loaded.save(tmp_path / "again")
    for name in ("trajectories.npz", "extra_logs.npz"):
        with np.load(tmp_path / name) as a, np.load(tmp_path / "again" / name) as b:
            assert a.files == b.files
            for key in a.files:
                np.testing.assert_array_equal(a[key], b[key])


def test_load_gives_back_a_scheduled_observers_logs_and_validity(scheduled, tmp_path):
    _, r = scheduled
    r.save(tmp_path)
    loaded = SimulationResult.load(tmp_path)
    _assert_same_result(loaded, r)
    assert loaded.validity.box_check == "scheduled"
    assert loaded.solve_counts() == r.solve_counts()


def test_load_of_a_folder_saved_before_the_shifted_logs_shifts_back_within_rounding(
    cart_pole_result, tmp_path
):
    r = cart_pole_result
    r.save(tmp_path)
    with np.load(tmp_path / "trajectories.npz") as data:
        old = {k: data[k] for k in data.files if k not in SHIFTED_KEYS.values()}
    np.savez(tmp_path / "trajectories.npz", **old)
    loaded = SimulationResult.load(tmp_path)
    np.testing.assert_allclose(loaded.x, r.x, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(loaded.original("x"), r.original("x"))


def test_load_without_units_reads_none(paper_result, tmp_path):
    paper_result.save(tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert "units" not in summary  # the paper's toy has no units
    loaded = SimulationResult.load(tmp_path)
    assert loaded.state_units is loaded.input_units is None
    assert loaded.x_equilibrium is None
    _assert_same_result(loaded, paper_result)


def test_summary_keys_are_every_entry_summary_computes(cart_pole_result, scheduled):
    # Both ways: a key summary() adds but SUMMARY_KEYS lacks would be read back as a
    # report; a key SUMMARY_KEYS keeps but summary() no longer writes is a stale copy.
    results = (cart_pole_result, scheduled[1])  # between them, every optional entry
    own = [set(r.summary()) - set(r.reports) for r in results]
    assert set().union(*own) == set(SUMMARY_KEYS)
    assert len(SUMMARY_KEYS) == len(set(SUMMARY_KEYS))
    assert not set(SUMMARY_KEYS) & set(cart_pole_result.reports)


def _edit_npz(path, **changes):
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(changes)
    for key in [k for k, v in arrays.items() if v is None]:
        del arrays[key]
    np.savez(path, **arrays)


def _npy_bytes(array):
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _edit_summary(path, **changes):
    data = json.loads(path.read_text())
    data.update(changes)
    path.write_text(json.dumps(data))


def _edit_t(folder, change, **others):
    """``t`` (and the arrays in ``others``) of ``folder``'s trajectories, changed."""
    with np.load(folder / "trajectories.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["t"] = change(arrays["t"])
    for key, edit in others.items():
        arrays[key] = edit(arrays[key])
    np.savez(folder / "trajectories.npz", **arrays)


def _edit_stop(folder, **changes):
    data = json.loads((folder / "summary.json").read_text())
    data["stop"].update(changes)
    (folder / "summary.json").write_text(json.dumps(data))


#: A damaged run folder, what is refused, and the message (after the folder's path).
LOAD_ERRORS = {
    "no trajectories": (
        lambda d: (d / "trajectories.npz").unlink(),
        r"trajectories\.npz: no such file, so .* is not a run folder; give the --out folder "
        r"of ofrl-drake run",
    ),
    "no summary": (
        lambda d: (d / "summary.json").unlink(),
        r"summary\.json: no such file, so .* is not a run folder",
    ),
    "truncated npz": (
        lambda d: (d / "trajectories.npz").write_bytes((d / "trajectories.npz").read_bytes()[:200]),
        r"trajectories\.npz: not a readable \.npz archive \(File is not a zip file\); the file "
        r"is damaged or was not written by SimulationResult\.save; write the run again "
        r"\(ofrl-drake run RUN_DIR/scenario\.yaml --out NEW_DIR\)\.$",
    ),
    "a .npy file": (
        lambda d: d.joinpath("trajectories.npz").write_bytes(_npy_bytes(np.zeros(3))),
        r"trajectories\.npz: not a readable \.npz archive \(one \.npy array",
    ),
    "pickled objects": (
        lambda d: _edit_npz(d / "trajectories.npz", t=np.array([{}], dtype=object)),
        r"trajectories\.npz: not a readable \.npz archive \(Object arrays cannot be loaded",
    ),
    "text in an array": (
        lambda d: _edit_npz(d / "trajectories.npz", cost=np.array(["a"])),
        r"trajectories\.npz: cost holds <U1 values, not real numbers",
    ),
    "complex values": (
        lambda d: _edit_t(d, lambda t: t, x=lambda x: x + 0j),
        r"trajectories\.npz: x holds complex128 values, not real numbers; the file is damaged",
    ),
    "a time that is not finite": (
        lambda d: _edit_t(d, lambda t: np.where(np.arange(t.size) == 5, np.nan, t)),
        r"trajectories\.npz: t\[5\] = nan; a run's times are finite; the file is damaged",
    ),
    "times that decrease": (
        lambda d: _edit_t(d, lambda t: t[::-1].copy()),
        r"trajectories\.npz: t\[1\] = 0\.48 comes before t\[0\] = 0\.5; a run's times do not "
        r"decrease; the file is damaged",
    ),
    "integer times": (
        lambda d: _edit_t(d, lambda t: t.astype(int)),
        r"trajectories\.npz: t holds int64 values, not the float times of a run",
    ),
    "an accuracy that is text": (
        lambda d: _edit_summary(d / "summary.json", integrator={"accuracy": "1e-4"}),
        r"summary\.json: integrator = \{'accuracy': '1e-4'\} cannot be read back \(expected "
        r"a number, got str\)",
    ),
    "a stop of no status a run has": (
        lambda d: _edit_stop(d, status="finished"),
        r"summary\.json: stop = .* cannot be read back \(status 'finished' is not one of "
        r"\['ok', 'diverged', 'timeout'\]\)",
    ),
    "a validity report with an entry it has not": (
        lambda d: _edit_summary(d / "summary.json", validity={"state_box": "nope"}),
        r"summary\.json: validity = .* cannot be read back \(no entries \['state_box'\] in a "
        r"validity report\)",
    ),
    "a missing array": (
        lambda d: _edit_npz(d / "trajectories.npz", Gamma=None),
        r"trajectories\.npz: no Gamma; a run's trajectories hold \['t', 'x'",
    ),
    "a shorter array": (
        lambda d: _edit_npz(d / "trajectories.npz", cost=np.zeros(3)),
        r"trajectories\.npz: cost has 3 samples but t has 26; ",
    ),
    "a flat state": (
        lambda d: _edit_npz(d / "trajectories.npz", x=np.zeros(26)),
        r"trajectories\.npz: x has shape \(26,\); expected 2 dimensions, time first",
    ),
    "xhat narrower than x": (
        lambda d: _edit_npz(d / "trajectories.npz", xhat=np.zeros((26, 3))),
        r"trajectories\.npz: xhat has shape \(26, 3\); expected \(26, 4\) \(from x and W\)",
    ),
    "an equilibrium of another size": (
        lambda d: _edit_npz(d / "trajectories.npz", x_equilibrium=np.zeros(2)),
        r"trajectories\.npz: x_equilibrium is of shape \(2,\); expected shape \(4,\)",
    ),
    "x edited by hand": (
        lambda d: _edit_npz(d / "trajectories.npz", x=np.ones((26, 4))),
        r"trajectories\.npz: x_shifted \+ the equilibrium is not x \(the file was edited",
    ),
    "corrupt summary": (
        lambda d: (d / "summary.json").write_text('{"scenario": '),
        r"summary\.json: not readable JSON \(Expecting value: line 1 column 14",
    ),
    "a summary that is a list": (
        lambda d: (d / "summary.json").write_text("[]"),
        r"summary\.json: a JSON list, not an object of the run's entries",
    ),
    "units of another size": (
        lambda d: _edit_summary(d / "summary.json", units={"state": ["m"], "input": None}),
        r"summary\.json: units = \{'state': \['m'\], 'input': None\} cannot be read back "
        r"\(expected 4 units, one per entry\)",
    ),
    "a stop without its time": (
        lambda d: _edit_summary(d / "summary.json", stop={"status": "ok"}),
        r"summary\.json: stop = \{'status': 'ok'\} cannot be read back \('x'\)",
    ),
    "a status the stop does not say": (
        lambda d: _edit_summary(d / "summary.json", status="diverged"),
        r"summary\.json: status = 'diverged' but stop says 'ok'",
    ),
    "no extra logs file": (
        lambda d: (d / "extra_logs.npz").unlink(),
        r"extra_logs\.npz: no such file, though the run folder needs it \(removed\?\); write "
        r"the run again \(ofrl-drake run RUN_DIR/scenario\.yaml --out NEW_DIR\)\.$",
    ),
    "extra logs not listed": (
        lambda d: _edit_summary(d / "summary.json", extra_logs=["t"]),
        r"extra_logs\.npz: holds \['policy_updates', 't'\] but summary\.json lists "
        r"extra_logs = \['t'\]",
    ),
    "extra logs of other samples": (
        lambda d: _edit_npz(d / "extra_logs.npz", t=np.zeros(26)),
        r"extra_logs\.npz: its t is not the t of trajectories\.npz",
    ),
}


@pytest.mark.parametrize("case", sorted(LOAD_ERRORS))
def test_load_refuses_a_damaged_run_folder_naming_the_file(cart_pole_result, tmp_path, case):
    cart_pole_result.save(tmp_path)
    damage, message = LOAD_ERRORS[case]
    damage(tmp_path)
    with pytest.raises(RunFolderError, match=rf"^{re.escape(str(tmp_path))}/{message}"):
        SimulationResult.load(tmp_path)


def test_load_refuses_what_is_not_a_folder(tmp_path):
    with pytest.raises(
        RunFolderError,
        match=rf"^{re.escape(str(tmp_path))}/nothing: not a folder, so not a run folder; "
        r"give the --out folder of ofrl-drake run",
    ):
        SimulationResult.load(tmp_path / "nothing")
