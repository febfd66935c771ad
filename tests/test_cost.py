"""Stage cost: Q(x), the saturation cost U(u) and its stable form in D."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from ofrl_drake.cost import (
    input_cost,
    input_cost_from_D,
    log_cosh,
    log_cosh_abs,
    stage_cost,
    stage_cost_rate,
    state_cost,
    tanh_abs,
    tanh_log_cosh,
)
from ofrl_drake.errors import ModelError


def test_state_cost_is_quadratic_form():
    Q = np.array([[5.0, 1.0], [1.0, 3.0]])
    x = np.array([0.3, -1.2])
    assert state_cost(x, Q) == pytest.approx(x @ Q @ x, rel=1e-15)
    X = np.stack([x, 2 * x], axis=1)
    np.testing.assert_allclose(state_cost(X, Q), [x @ Q @ x, 4 * x @ Q @ x], rtol=1e-15)


@pytest.mark.parametrize("u", [-2.9, -1.0, 0.0, 0.5, 2.5])
def test_input_cost_matches_its_integral_definition(u):
    lbar, r = 3.0, 1.7
    integral, _ = quad(lambda v: 2 * r * lbar * np.arctanh(v / lbar), 0.0, u)
    assert input_cost(np.array([u]), np.array([r]), lbar) == pytest.approx(
        integral, rel=1e-9, abs=1e-12
    )


def test_input_cost_from_D_equals_u_form():
    lbar, r = 3.0, np.array([1.0, 0.5])
    D = np.array([[0.3, -1.1, 2.0], [-0.2, 0.0, 4.0]])
    u = -lbar * np.tanh(D)
    direct = (
        2 * r[:, None] * lbar * (u * np.arctanh(u / lbar) + lbar / 2 * np.log(1 - u**2 / lbar**2))
    ).sum(0)
    np.testing.assert_allclose(input_cost_from_D(D, r, lbar), direct, rtol=1e-10)


def test_log_cosh_is_finite_and_exact():
    D = np.array([-1e4, -30.0, -1.0, 0.0, 0.5, 2.0, 700.0, 1e4])
    small = np.abs(D) < 30
    np.testing.assert_allclose(
        log_cosh(D[small]), np.log(np.cosh(D[small])), rtol=1e-14, atol=1e-300
    )
    np.testing.assert_allclose(log_cosh(D[~small]), np.abs(D[~small]) - np.log(2), rtol=1e-14)
    # No cancellation near zero: ln cosh d = d^2/2 - d^4/12 + ...
    assert log_cosh(np.array([1e-8]))[0] == pytest.approx(5e-17, rel=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.floats(-1e4, 1e4, allow_nan=False))
def test_U_is_finite_nonnegative_and_even_for_large_D(d):
    D = np.array([d])
    U = input_cost_from_D(D, np.array([1.0]), 3.0)
    assert np.isfinite(U) and U >= 0
    assert input_cost_from_D(-D, np.array([1.0]), 3.0) == pytest.approx(U, rel=1e-12, abs=1e-300)


def test_stage_cost_adds_both_terms():
    x, u = np.array([1.0, -1.0]), np.array([0.5])
    Q, r = 5 * np.eye(2), np.array([1.0])
    assert stage_cost(x, u, Q, r, 3.0) == pytest.approx(state_cost(x, Q) + input_cost(u, r, 3.0))


def test_input_cost_outside_bound_raises():
    with pytest.raises(ModelError, match=r"\|u\| = 3.5 exceeds the input bound 3.0"):
        input_cost(np.array([3.5]), np.array([1.0]), 3.0)


@settings(max_examples=80, deadline=None)
@given(st.floats(-60.0, 60.0, allow_nan=False))
def test_tanh_log_cosh_matches_closed_forms_in_every_branch(d):
    t, lc = tanh_log_cosh(d)
    assert t == pytest.approx(np.tanh(d), rel=4e-16, abs=1e-300)
    # Reference in extended precision: ln cosh d of ~1e-19 relative accuracy in cosh.
    exact = float(np.log(np.cosh(np.longdouble(d))))
    assert lc == pytest.approx(exact, rel=1e-14, abs=1e-18)


@pytest.mark.parametrize("a", [0.0, 1e-300, 1e-8, 0.3, 0.49, 0.5, 0.51, 3.0, 19.0, 40.0, 1e4])
def test_tanh_abs_and_log_cosh_abs_against_closed_forms(a):
    t, e = tanh_abs(a)
    assert t == pytest.approx(np.tanh(a), rel=4e-16, abs=0)
    assert e == pytest.approx(np.expm1(-2 * a), rel=2e-16, abs=0)
    # ln cosh a without cancellation; beyond 40 it is a - ln 2 in double precision.
    exact = float(np.log1p(2 * np.sinh(np.longdouble(a) / 2) ** 2)) if a < 40 else a - np.log(2)
    assert log_cosh_abs(a, t, e) == pytest.approx(exact, rel=1e-15, abs=0)


@pytest.mark.parametrize("d", [0.0, 1e-8, 0.3, 0.5, 0.9, 3.0, 39.9, 40.0, 41.0, 1e4])
def test_tanh_log_cosh_at_branch_edges(d):
    for sign in (1.0, -1.0):
        t, lc = tanh_log_cosh(sign * d)
        assert t == pytest.approx(np.tanh(sign * d), rel=4e-16, abs=1e-300)
        assert lc == pytest.approx(float(log_cosh(np.array([d]))[0]), rel=0, abs=0)
        assert lc >= 0.0


@pytest.mark.parametrize(
    ("x", "u"),
    [([1.0, -1.0], [0.5]), ([0.3, 0.2], [-2.9]), ([0.0, 0.0], [0.0]), ([2.0, 1.0], [3.0])],
)
def test_stage_cost_rate_is_stage_cost(x, u):
    x, u = np.array(x), np.array(u)
    Q, r = np.array([[5.0, 1.0], [1.0, 2.0]]), np.array([1.5])
    rate, worst = stage_cost_rate(x, u, Q, r, 3.0)
    assert rate == pytest.approx(stage_cost(x, u, Q, r, 3.0), rel=1e-14, abs=1e-300)
    assert worst == pytest.approx(abs(u[0]) / 3.0, rel=1e-15)
