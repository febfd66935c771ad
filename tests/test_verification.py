"""Falsification of observer designs against the true nonlinear error dynamics."""

import json
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ofrl_drake.design import ObserverDesign
from ofrl_drake.examples import make_system
from ofrl_drake.observer import ObserverGains, observer_rhs, observer_rhs_batch
from ofrl_drake.plants import resolve_system
from ofrl_drake.scenario import load_scenario
from ofrl_drake.variants import design_for
from ofrl_drake.verification import (
    VerificationError,
    error_jacobians,
    error_rates,
    small_error_rates,
    verify_observer,
)
from tests.conftest import PAPER_SCENARIO, ROOT

SOUND_SCENARIO = ROOT / "diagrams" / "two_state_sound.yaml"


@pytest.fixture(scope="module")
def two_state():
    return make_system("two_state")


@pytest.fixture(scope="module")
def sound_design():
    return design_for(load_scenario(SOUND_SCENARIO))


def _edot(system, design, X, Xhat, U):
    """e' = x' - xhat' from the single-point observer, column by column."""
    gains = ObserverGains.from_design(system, design)
    out = []
    for x, xh, u in zip(X.T, Xhat.T, U.T, strict=True):
        xdot = system.f(x) + system.g(x) @ u
        out.append(xdot - observer_rhs(system, gains, xh, system.output(x), u))
    return np.stack(out, axis=1)


# ------------------------------------------------------------ structure
def test_batched_observer_matches_the_single_point_observer(two_state, paper_design):
    rng = np.random.default_rng(0)
    gains = ObserverGains.from_design(two_state, paper_design)
    X, Xhat = rng.uniform(-2, 2, (2, 50)), rng.uniform(-2, 2, (2, 50))
    U = rng.uniform(-3, 3, (1, 50))
    U[0, :5] = 0.0
    batch = observer_rhs_batch(two_state, gains, Xhat, two_state.output_matrix @ X, U)
    single = np.stack(
        [
            observer_rhs(two_state, gains, xh, two_state.output(x), u)
            for x, xh, u in zip(X.T, Xhat.T, U.T, strict=True)
        ],
        axis=1,
    )
    np.testing.assert_allclose(batch, single, rtol=1e-12, atol=1e-12)


def test_rates_are_the_quotient_of_the_true_error_dynamics(two_state, paper_design):
    rng = np.random.default_rng(1)
    X, Xhat = rng.uniform(-2, 2, (2, 20)), rng.uniform(-2, 2, (2, 20))
    U = rng.choice([-3.0, 0.0, 3.0], (1, 20))
    E = X - Xhat
    Edot = _edot(two_state, paper_design, X, Xhat, U)
    P = paper_design.P
    expected = 2 * np.einsum("iN,iN->N", P @ E, Edot) / np.einsum("iN,iN->N", P @ E, E)
    np.testing.assert_allclose(
        error_rates(paper_design, two_state, X, Xhat, U), expected, rtol=1e-10
    )


# ---------------------------------------------- derivatives vs finite differences
@pytest.mark.parametrize("u", [-3.0, 0.0, 3.0])
def test_error_jacobian_matches_central_differences_of_the_nonlinear_dynamics(
    two_state, paper_design, u
):
    rng = np.random.default_rng(2)
    X = rng.uniform(-2, 2, (2, 6))
    U = np.full((1, 6), u)
    A = error_jacobians(paper_design, two_state, X, U)
    h = 1e-6
    for j in range(2):
        step = np.zeros((2, 1))
        step[j] = h
        # xhat = x - e: e = +h e_j and e = -h e_j
        fd = (
            _edot(two_state, paper_design, X, X - step, U)
            - _edot(two_state, paper_design, X, X + step, U)
        ) / (2 * h)
        np.testing.assert_allclose(A[:, :, j], fd.T, rtol=1e-6, atol=1e-6)


def test_small_error_limit_is_the_limit_of_the_finite_rates(two_state, paper_design):
    rng = np.random.default_rng(3)
    X = rng.uniform(-1.9, 1.9, (2, 8))
    U = rng.choice([-3.0, 3.0], (1, 8))
    rates, directions = small_error_rates(paper_design, two_state, X, U)
    for eps, rtol in ((1e-3, 2e-2), (1e-5, 2e-4)):
        finite = error_rates(paper_design, two_state, X, X - eps * directions.T, U)
        np.testing.assert_allclose(finite, rates, rtol=rtol, atol=rtol)


@settings(max_examples=30, deadline=None)
@given(
    st.floats(-2, 2),
    st.floats(-2, 2),
    st.floats(-3, 3),
    st.floats(0, 2 * np.pi),
)
def test_no_direction_beats_the_worst_small_error_direction(
    two_state, paper_design, x1, x2, u, angle
):
    X, U = np.array([[x1], [x2]]), np.array([[u]])
    rate, _ = small_error_rates(paper_design, two_state, X, U)
    d = np.array([[np.cos(angle)], [np.sin(angle)]])
    along = error_rates(paper_design, two_state, X, X - 1e-6 * d, U)
    assert along[0] <= rate[0] + 1e-3 * max(1.0, abs(rate[0]))


# ------------------------------------------------------------ falsification
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_paper_design_is_falsified_within_the_default_budget(two_state, paper_design, seed):
    report = verify_observer(paper_design, two_state, seed=seed)
    assert report.falsified
    assert report.claimed_rate == -4.0
    assert report.worst_rate > 70.0  # about +79, against a claim of -4
    assert report.violating_fraction > 0.3
    box = paper_design.box
    for point in (report.x, report.xhat):
        assert np.all(box.lower <= point) and np.all(point <= box.upper)
    assert abs(report.u[0]) == pytest.approx(3.0)
    # The reported point reproduces the rate from the dynamics alone.
    if report.direction is not None:
        xhat = report.x - 1e-6 * report.direction
    else:
        xhat = report.xhat
    again = error_rates(
        paper_design, two_state, report.x[:, None], xhat[:, None], report.u[:, None]
    )
    assert again[0] == pytest.approx(report.worst_rate, rel=1e-3)
    assert "falsified: r = +" in report.summary_line()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_refinement_reaches_the_finite_error_counterexample(two_state, paper_design, seed):
    """docs/theory.md: worst r = +78.8 at x = (0.677, -2), xhat = (0.615, -1.995), or its
    mirror image. The finite errors' region (both injection points in the box) is left by
    L-BFGS-B's first trial step, which ended the search at its start (58.6 at seed 0)."""
    sampled = verify_observer(paper_design, two_state, seed=seed, refine=False)
    report = verify_observer(paper_design, two_state, seed=seed)
    assert sampled.worst_finite_rate < 61.0
    assert report.kind == "finite_error"
    assert report.worst_rate == pytest.approx(78.814, abs=2e-3)
    assert report.worst_rate > report.worst_small_error_rate
    sign = np.sign(report.x[0])
    np.testing.assert_allclose(report.x, sign * np.array([0.677, -2.0]), atol=1e-3)
    np.testing.assert_allclose(report.xhat, sign * np.array([0.6149, -1.995]), atol=1e-3)
    # A point of the region, whose rate the dynamics reproduce.
    box = paper_design.box
    for point in (report.x, report.xhat):
        assert np.all(box.lower <= point) and np.all(point <= box.upper)
    again = error_rates(
        paper_design, two_state, report.x[:, None], report.xhat[:, None], report.u[:, None]
    )
    assert again[0] == pytest.approx(report.worst_rate, rel=1e-9)


def test_sampling_alone_finds_the_paper_counterexample(two_state, paper_design):
    report = verify_observer(paper_design, two_state, samples=2000, seed=5, refine=False)
    assert report.falsified and not report.refined


def test_the_verdict_prints_alpha_and_the_margin_as_they_are(two_state, sound_design):
    """alpha = 0.9999999 read "alpha = 1: worst r = -2 <= -2": the rate no design reaches."""
    import dataclasses

    report = verify_observer(sound_design, two_state, samples=200)
    edge = dataclasses.replace(report, alpha=0.9999999, worst_rate=-2.0)
    assert edge.verdict(True).startswith(
        "decay-certified and not falsified (alpha = 0.9999999: worst r = -2 <= -1.9999998 over"
    )
    # Above the claim by less than the tolerance: printed on its side of it, and said so.
    close = dataclasses.replace(edge, worst_rate=-1.99999975)
    assert "worst r = -1.9999997 within tolerance of -1.9999998 over" in close.verdict(True)
    assert "claims alpha = 0.9999999 (r <= -1.9999998); not falsified: worst r = -1.9999997" in (
        close.verdict(False)
    )
    # Falsified, as near the claim: on its side of it too (read "r = -2" against r <= -2).
    near = dataclasses.replace(report, alpha=1.0, worst_rate=-1.99999)
    assert near.falsified and "(r <= -2); falsified: r = -1.99999 at" in near.summary_line()
    # Round numbers read as before.
    assert f"(alpha = 0.9: worst r = {report.worst_rate:+.4g} <= -1.8 over" in report.verdict(True)


def test_report_is_json_ready(two_state, sound_design):
    data = json.loads(json.dumps(verify_observer(sound_design, two_state, samples=200).to_dict()))
    assert data["falsified"] is False
    assert data["claimed_rate"] == pytest.approx(-2 * sound_design.alpha)
    assert data["samples"] == 200 and data["seed"] == 0
    assert data["jacobians"] == "symbolic"
    assert data["summary"].startswith("claims alpha = 0.9")


# ---------------------------------------------------------------- errors
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"samples": 0}, r"samples must be an integer >= 1; got 0"),
        ({"samples": 1.5}, r"samples must be an integer >= 1; got 1.5"),
        ({"seed": -1}, r"seed must be an integer >= 0; got -1"),
        ({"starts": -2}, r"starts must be an integer >= 0; got -2"),
        ({"tol": float("nan")}, r"tol must be a finite number >= 0; got nan"),
    ],
)
def test_bad_arguments_raise(two_state, sound_design, kwargs, match):
    with pytest.raises(VerificationError, match=match):
        verify_observer(sound_design, two_state, **kwargs)


def test_a_design_without_positive_definite_P_has_nothing_to_verify(two_state, sound_design):
    bad = ObserverDesign.from_gains(
        two_state,
        sound_design.box,
        3.0,
        0.5,
        L=sound_design.L,
        H=sound_design.H,
        K=sound_design.K,
        P=-np.eye(2),
        bounds=sound_design.bounds,
    )
    with pytest.raises(VerificationError, match=r"design.P is not positive definite"):
        verify_observer(bad, two_state)


def test_something_that_is_not_a_design_raises(two_state):
    with pytest.raises(VerificationError, match=r"design must be an ObserverDesign"):
        verify_observer(object(), two_state)


# ------------------------------------------------------- scheduled observer
def test_scheduled_observer_verifies_every_design_it_puts_in_force(paper_scenario, paper_design):
    import dataclasses

    from ofrl_drake import simulate
    from ofrl_drake.observer import unpack_gains
    from ofrl_drake.systems.scheduled_observer import VERIFY_SAMPLES

    s = dataclasses.replace(
        paper_scenario,
        observer=dataclasses.replace(
            paper_scenario.observer, schedule_period=1.0, schedule_half_width=[1.0, 1.0]
        ),
        simulation=dataclasses.replace(paper_scenario.simulation, duration=2.5),
    )
    r = simulate(s, design=paper_design, progress=False)
    system = make_system("two_state")
    logged, P, box = r.extra["verification"], r.extra["lyapunov_matrix"], r.extra["certified_box"]
    n, q = system.n, system.q
    L, H, K = unpack_gains(r.extra["observer_gains"], n, q)
    assert logged.shape == (r.t.size, 3)
    # Before the first re-solve: the initial (paper) design, falsified.
    first = verify_observer(paper_design, system, samples=VERIFY_SAMPLES, seed=0, refine=False)
    np.testing.assert_allclose(logged[0], [first.worst_rate, -4.0, 1.0], rtol=1e-12)
    # After each re-solve: the design in force, rebuilt from the logs, verified again.
    for count, t in ((1, 1.5), (2, 2.4)):
        k = int(np.argmin(np.abs(r.t - t)))
        design = ObserverDesign.from_gains(
            system,
            (box[k, :n], box[k, n:]),
            s.input_bound,
            s.observer.alpha,
            L=L[k],
            H=H[k],
            K=K[k],
            P=P[k].reshape(n, n),
            formulation=s.observer.formulation,
        )
        again = verify_observer(design, system, samples=VERIFY_SAMPLES, seed=count, refine=False)
        np.testing.assert_allclose(
            logged[k], [again.worst_rate, -4.0, float(again.falsified)], rtol=1e-9
        )


# ------------------------------------------------- every shipped scenario
SCENARIOS = sorted((ROOT / "diagrams").glob("*.yaml"))


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_every_shipped_design_is_falsified_exactly_when_it_is_not_sound(path):
    """Sound designs (polytopic, structured: a proof on their box) survive; the paper's
    (lmi2) does not."""
    scenario = load_scenario(path)
    system = resolve_system(scenario)
    design = design_for(scenario, system)
    report = verify_observer(design, system, seed=0)  # the default budget
    assert report.input_vertices == 3**system.m
    if scenario.observer.formulation != "paper":
        assert design.is_decay_certified
        assert not report.falsified, f"{path.name}: {report.summary_line()}"
        assert report.worst_rate <= report.claimed_rate
        assert report.violating_fraction == 0.0 and report.finite_violating_fraction == 0.0
        assert "decay-certified and not falsified" in report.verdict(True)
    else:
        assert report.falsified, f"{path.name}: {report.summary_line()}"


def test_the_search_stops_at_its_deadline(two_state, sound_design, monkeypatch):
    """The verification ran as long as its search took, whatever --max-wall said."""
    import time
    import types

    from ofrl_drake import WallTimeExceeded, verification

    report = verify_observer(sound_design, two_state, samples=500, starts=2)
    later = verify_observer(
        sound_design, two_state, samples=500, starts=2, deadline=time.monotonic() + 3600
    )
    assert later.worst_rate == report.worst_rate and later.x.tolist() == report.x.tolist()
    with pytest.raises(
        WallTimeExceeded,
        match=r"^the observer's verification ran out of wall time [\d.e-]+ s into its search, "
        r"before chunk 1 of 1 of the small-error search$",
    ) as err:
        verify_observer(sound_design, two_state, samples=500, deadline=time.monotonic())
    assert err.value.step == "verification"
    # A deadline that passes during the search: here after the two sampled searches.
    readings = iter(range(2))
    clock = types.SimpleNamespace(
        monotonic=lambda: next(readings, 10), perf_counter=time.perf_counter
    )
    monkeypatch.setattr(verification, "time", clock)
    with pytest.raises(WallTimeExceeded, match=r"before refinement 1 of the small-error limit$"):
        verify_observer(sound_design, two_state, samples=500, starts=2, deadline=5.0)
    with pytest.raises(VerificationError, match=r"deadline must be a time\.monotonic\(\) reading"):
        verify_observer(sound_design, two_state, deadline="soon")


_DUFFING = """
import numpy as np
from ofrl_drake import ControlAffineSystem

def make_plant():
    f = lambda x: np.array([x[1], -x[0] - x[1] - 0.3 * x[0] ** 3])
    g = lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]])
    return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name="duffing")
"""


def test_pairs_whose_injection_points_leave_the_box_are_not_counterexamples(
    paper_scenario, tmp_path
):
    # Before: falsified at r = +1.37 with x = (1, 0.95), xhat = (-1, -0.82), where the
    # injection point xhat + H C e = (3, -0.82) is outside the box: no claim is made there.
    import dataclasses

    from ofrl_drake.variants import design_for

    (tmp_path / "duffing.py").write_text(_DUFFING)
    scenario = dataclasses.replace(
        load_scenario(PAPER_SCENARIO),
        system=str(tmp_path / "duffing.py") + ":make_plant",
    )
    observer = dataclasses.replace(
        scenario.observer,
        alpha=0.2,
        formulation="polytopic",
        jacobian_method="certified",
        box=dataclasses.replace(scenario.observer.box, lower=[-1.0, -1.0], upper=[1.0, 1.0]),
        L=[[0.0], [0.0]],
        H=[[2.0], [0.0]],
        K=[[0.0], [0.0]],
    )
    scenario = dataclasses.replace(
        scenario, observer=observer, input_bound=1.0, x0=[0.5, 0.0], xhat0=[0.0, 0.0]
    )
    design = design_for(scenario)
    assert design.is_decay_certified
    report = verify_observer(design, resolve_system(scenario), samples=4000, seed=0)
    assert not report.falsified, report.summary_line()
    assert report.worst_rate <= report.threshold
    # About half of the uniform pairs put xhat + 2 (x1 - xhat1) outside [-1, 1].
    assert 0.3 < report.finite_outside_fraction < 0.9
    assert report.to_dict()["finite_outside_fraction"] == report.finite_outside_fraction


def test_a_sample_where_the_dynamics_are_undefined_falsifies_and_is_named():
    # Before: a NaN sample made np.argmax pick it and 'nan > best' dropped the whole chunk:
    # the small-error search reported -inf and "not falsified" beside 0.9 % violating samples.
    from ofrl_drake import ControlAffineSystem
    from ofrl_drake.design import design_observer

    def g(x):
        return np.array([[0 * x[0]], [1 + 0 * x[0]]])

    model = ControlAffineSystem(lambda x: np.array([x[1], -x[0] - x[1]]), g, [[1.0, 0.0]])
    design = design_observer(model, ([-2, -2], [2, 2]), 1.0, 0.3)

    def undefined_below(x):  # a negligible term, NaN for x0 < -1.8
        return np.array([x[1], -x[0] - x[1] + 1e-12 * np.sqrt(x[0] + 1.8)])

    truth = ControlAffineSystem(undefined_below, g, [[1.0, 0.0]])
    with np.errstate(invalid="ignore"):
        report = verify_observer(design, truth, samples=2000, seed=0, refine=False)
    assert report.falsified
    assert report.worst_small_error_rate == np.inf and report.x[0] < -1.8
    assert re.match(
        r"claims alpha = 0\.3 \(r <= -0\.6\); falsified: the error dynamics are not finite "
        r"at x = \(-1\.\d+, \S+\), u = \(\S+\) \(f or g is undefined or overflows there",
        report.summary_line(),
    ), report.summary_line()
    with np.errstate(invalid="ignore"):
        defined = verify_observer(design, model, samples=2000, seed=0, refine=False)
    assert not defined.falsified and np.isfinite(defined.worst_rate)
