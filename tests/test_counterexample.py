"""The paper design's counterexample: an equilibrium where no gain acts, and an
estimate that does not converge from inside the certificate's invariant set."""

import dataclasses

import numpy as np
import pytest

from ofrl_drake import ModelError, ScenarioError, simulate
from ofrl_drake.examples import make_system
from ofrl_drake.examples.two_state import f, g
from ofrl_drake.scenario import validate_scenario
from ofrl_drake.unobservable import linearization, unobservable_equilibria
from ofrl_drake.verification import error_jacobians

BOX = ([-2.0, -2.0], [2.0, 2.0])


@pytest.fixture(scope="module")
def equilibria():
    return unobservable_equilibria(make_system("two_state"), BOX, 3.0)


def test_the_two_equilibria_are_found_from_f_and_g(equilibria):
    assert len(equilibria) == 2
    minus, plus = equilibria
    np.testing.assert_allclose(plus.x, -minus.x, rtol=1e-9)
    np.testing.assert_allclose(plus.u, -minus.u, rtol=1e-9)
    for eq in equilibria:
        x, u = eq.x, eq.u
        assert x[0] == pytest.approx(x[1], abs=1e-12)  # row 1: x1' = -x1 + x2
        np.testing.assert_allclose(f(x) + g(x) @ u, 0.0, atol=1e-12)
        # a21 = d(f2 + g2 u)/dx1 vanishes, by central differences of f and g.
        h = np.array([1e-6, 0.0])
        a21 = (f(x + h)[1] + g(x + h)[1] @ u - f(x - h)[1] - g(x - h)[1] @ u) / 2e-6
        assert abs(a21) < 1e-8
        np.testing.assert_allclose(eq.A, linearization(make_system("two_state"), x, u))
        np.testing.assert_allclose(eq.modes, [-1.0], atol=1e-9)
        assert abs(u[0]) < 3.0 and np.all(np.abs(x) < 2.0)
    assert plus.x[0] == pytest.approx(1.64741, abs=1e-5)
    assert plus.u[0] == pytest.approx(1.60914, abs=1e-5)


def test_the_mode_minus_one_is_in_the_error_dynamics_whatever_the_gains(equilibria, paper_design):
    system = make_system("two_state")
    for eq in equilibria:
        A = error_jacobians(paper_design, system, eq.x[:, None], eq.u[:, None])[0]
        assert np.min(np.abs(np.linalg.eigvals(A) + 1.0)) < 1e-9


def test_only_single_input_single_output_plants_are_searched():
    with pytest.raises(ModelError, match=r"needs one input and one output; .* m = 2, q = 2"):
        unobservable_equilibria(make_system("coupled_two_state"), ([-2] * 4, [2] * 4), 3.0)


def _held(scenario, x0, xhat0, u, duration=3.0):
    return dataclasses.replace(
        scenario,
        x0=list(x0),
        xhat0=list(xhat0),
        variant=dataclasses.replace(
            scenario.variant, controller="constant", constant_input=list(u)
        ),
        simulation=dataclasses.replace(scenario.simulation, duration=duration),
    )


def _invariant_level(P, x, lower, upper):
    """Largest c with {e : e^T P e <= c} inside {e : x - e in the box}."""
    Pinv = np.linalg.inv(P)
    gaps = np.concatenate([x - np.asarray(lower), np.asarray(upper) - x])
    return float(np.min(gaps**2 / np.tile(np.diag(Pinv), 2)))


@pytest.mark.parametrize(("e0", "inside"), [([0.1, 0.0], True), ([0.0, 0.1], False)])
def test_paper_observer_does_not_converge_at_the_negative_equilibrium(
    paper_scenario, paper_design, equilibria, e0, inside
):
    eq = equilibria[0]
    assert eq.x[0] < 0
    e0 = np.asarray(e0)
    s = _held(paper_scenario, eq.x, eq.x - e0, eq.u)
    r = simulate(s, design=paper_design, progress=False)
    # The plant stays at its equilibrium, the input at u*.
    np.testing.assert_allclose(r.x, np.tile(eq.x, (r.t.size, 1)), atol=1e-9)
    np.testing.assert_allclose(r.u, np.tile(eq.u, (r.t.size, 1)), rtol=0, atol=0)
    # For e0 = (0.1, 0) the sublevel set {V <= V(e0)} keeps xhat in the box, so the
    # certificate claims it invariant and V decaying to 0; (0, 0.1) starts outside it.
    P = paper_design.P
    assert bool(e0 @ P @ e0 < _invariant_level(P, eq.x, *BOX)) == inside
    # Instead |e| settles near 2.37 and xhat leaves the box (to about 4.0).
    assert np.linalg.norm(r.e[-1]) > 1.0
    assert np.linalg.norm(r.e[-1]) == pytest.approx(2.37, abs=0.01)
    assert np.max(np.abs(r.xhat)) > 3.9
    assert r.validity.estimate_outside is True and not r.validity.valid
    assert r.validity.state_outside is False


def test_from_a_small_error_at_the_positive_equilibrium_it_converges(
    paper_scenario, paper_design, equilibria
):
    eq = equilibria[1]
    r = simulate(
        _held(paper_scenario, eq.x, eq.x - np.array([1e-3, 0.0]), eq.u, duration=10.0),
        design=paper_design,
        progress=False,
    )
    assert np.linalg.norm(r.e[-1]) < 1e-5
    assert r.validity.valid


def test_the_constant_controller_needs_its_input_within_the_bound(paper_scenario):
    held = dataclasses.replace(
        paper_scenario, variant=dataclasses.replace(paper_scenario.variant, controller="constant")
    )
    with pytest.raises(ScenarioError, match=r"variant.constant_input: expected 1 entries; got 0"):
        validate_scenario(held)
    beyond = dataclasses.replace(
        held, variant=dataclasses.replace(held.variant, constant_input=[3.5])
    )
    with pytest.raises(ScenarioError, match=r"variant.constant_input: entries must satisfy"):
        validate_scenario(beyond)


def test_the_sound_design_converges_there_at_its_certified_rate(equilibria):
    from ofrl_drake.scenario import load_scenario
    from ofrl_drake.variants import design_for
    from tests.conftest import ROOT

    scenario = load_scenario(ROOT / "diagrams" / "two_state_sound.yaml")
    design = design_for(scenario)
    eq = equilibria[0]
    for e0 in ([0.1, 0.0], [0.0, 0.1]):
        s = _held(scenario, eq.x, eq.x - np.asarray(e0), eq.u)
        r = simulate(s, design=design, progress=False)
        assert r.validity.valid  # x and xhat stay in the box: the certificate applies
        V = np.einsum("ti,ij,tj->t", r.e, design.P, r.e)
        bound = V[0] * np.exp(-2 * design.alpha * r.t)
        assert np.all(V <= bound * (1 + 1e-3) + 1e-12)
