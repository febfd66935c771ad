"""Interval and vectorized point evaluation of pydrake symbolic expressions."""

import numpy as np
import pydrake.symbolic as sym
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ofrl_drake.errors import ModelError, OfrlError
from ofrl_drake.interval import (
    ExpressionEvaluator,
    Interval,
    IntervalDomainError,
    UnsupportedExpressionError,
    evaluate,
    evaluate_interval,
)

X = sym.MakeVectorVariable(2, "x")
x, y = sym.Expression(X[0]), sym.Expression(X[1])
X0 = [X[0]]

# numpy's object loops flag "invalid value" when calling np.cos etc. on Drake
# expressions; the results are right, so silence that for the whole module.
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")

# Expressions defined on all of R^2 (no domain restriction).
EVERYWHERE = [
    np.sin(x) * y**2,
    np.cos(2 * x) + 2,
    np.sin(3 * x - y),
    np.cos(x * y),
    np.tan(0.2 * x) ** 3,
    x**3 - 2 * x * y + 0.5,
    y**4 - x**2,
    (1 + x**2) ** -1,
    np.exp(0.3 * x) * np.tanh(y),
    x / (2 + np.cos(y)),
    abs(x - y) * np.cosh(0.1 * y),
    sym.min(x, y) - sym.max(x**2, y),
    np.arctan(x) * np.sinh(0.2 * y),
    sym.ceil(x) + sym.floor(y),
    np.sqrt(x**2 + y**2 + 0.1),
    np.log(1 + x**2) * y,
    (x**2 + 1) ** 0.7 - (y**2 + 2) ** -1.5,
    np.arcsin(0.9 * np.sin(x)) + np.arccos(0.5 * np.cos(y)),
    -3 * x * np.sin(y) * np.cos(x) * (np.cos(2 * x) + 2),
]


def _points_in(lo, hi, rng, n=400):
    """Corners, centre and uniform points of the box [lo, hi] in R^2."""
    corners = np.array([[lo[0], lo[0], hi[0], hi[0]], [lo[1], hi[1], lo[1], hi[1]]])
    centre = (0.5 * (np.asarray(lo) + np.asarray(hi)))[:, None]
    inside = (
        np.asarray(lo)[:, None] + rng.random((2, n)) * (np.asarray(hi) - np.asarray(lo))[:, None]
    )
    return np.concatenate([corners, centre, inside], axis=1)


@settings(max_examples=60, deadline=None)
@given(
    lo=st.tuples(st.floats(-6, 6), st.floats(-6, 6)),
    width=st.tuples(st.floats(0, 4), st.floats(0, 4)),
    seed=st.integers(0, 2**32 - 1),
)
def test_enclosure_contains_point_values(lo, width, seed):
    lo = np.array(lo)
    hi = lo + np.array(width)
    ev = ExpressionEvaluator(EVERYWHERE, X)
    box = ev.interval(lo, hi)
    pts = _points_in(lo, hi, np.random.default_rng(seed))
    values = ev(pts)
    assert values.shape == (len(EVERYWHERE), pts.shape[1])
    finite = np.isfinite(values)
    inside = (box.lo[:, None] <= values) & (values <= box.hi[:, None])
    bad = finite & ~inside
    assert not bad.any(), [str(EVERYWHERE[i]) for i in np.flatnonzero(bad.any(axis=1))]


@settings(max_examples=40, deadline=None)
@given(
    lo=st.floats(-50, 50),
    width=st.floats(0, 7),
    k=st.sampled_from([1.0, 2.0, 0.5, -3.0]),
)
def test_sin_and_cos_enclose_with_range_reduction(lo, width, k):
    hi = lo + width
    grid = np.linspace(lo, hi, 2001)
    for fn in (np.sin, np.cos):
        expr = fn(k * x)
        box = evaluate_interval(expr, X0, np.array([lo]), np.array([hi]))
        vals = fn(k * grid)
        assert box.lo <= vals.min() and vals.max() <= box.hi
        assert -1.0 <= box.lo and box.hi <= 1.0
        # Tight: the natural range of one sin/cos is exact up to rounding.
        assert box.lo >= vals.min() - 1e-5 and box.hi <= vals.max() + 1e-5


def test_trig_extrema_inside_the_box_are_found():
    box = evaluate_interval(np.sin(x), X0, np.array([1.5]), np.array([1.7]))
    assert box.hi == 1.0
    assert box.lo == pytest.approx(np.sin(1.7), abs=1e-12)  # sin(1.7) < sin(1.5)
    box = evaluate_interval(np.cos(x), X0, np.array([3.0]), np.array([3.3]))
    assert box.lo == -1.0
    box = evaluate_interval(np.cos(x), X0, np.array([0.0]), np.array([7.0]))
    assert (box.lo, box.hi) == (-1.0, 1.0)


def test_degenerate_boxes_enclose_the_float_value_outwards():
    rng = np.random.default_rng(5)
    ev = ExpressionEvaluator(EVERYWHERE, X)
    P = rng.uniform(-3, 3, size=(2, 200))
    box = ev.interval(P, P)
    vals = ev(P)
    assert np.all(box.lo <= vals) and np.all(vals <= box.hi)
    width = box.hi - box.lo
    # Outward rounding costs a few ulps, not more.
    assert np.all(width <= 1e-12 * (1 + np.abs(vals)) * 1e3)


def test_powers():
    lo, hi = np.array([-2.0]), np.array([3.0])
    b = evaluate_interval(x**2, X0, lo, hi)
    assert b.lo == 0.0 and b.hi == pytest.approx(9.0, rel=1e-14)
    b = evaluate_interval(x**3, X0, lo, hi)
    assert b.lo == pytest.approx(-8.0, rel=1e-14) and b.hi == pytest.approx(27.0, rel=1e-14)
    b = evaluate_interval(x**-1, X0, lo, hi)  # the pole at 0 is inside
    assert b.lo == -np.inf and b.hi == np.inf
    b = evaluate_interval(x**-2, X0, np.array([1.0]), np.array([2.0]))
    assert b.lo == pytest.approx(0.25, rel=1e-14) and b.hi == pytest.approx(1.0, rel=1e-14)
    b = evaluate_interval(x**0.5, X0, np.array([4.0]), np.array([9.0]))
    assert b.lo == pytest.approx(2.0, rel=1e-14) and b.hi == pytest.approx(3.0, rel=1e-14)
    b = evaluate_interval(sym.pow(2.0, x), X0, np.array([-1.0]), np.array([3.0]))
    assert b.lo == pytest.approx(0.5, rel=1e-12) and b.hi == pytest.approx(8.0, rel=1e-12)


def test_point_evaluation_matches_drake_evaluate():
    rng = np.random.default_rng(11)
    P = rng.uniform(-2, 2, size=(2, 7))
    ours = evaluate(EVERYWHERE, X, P)
    for j in range(P.shape[1]):
        env = {X[0]: P[0, j], X[1]: P[1, j]}
        drake = [e.Evaluate(env) for e in EVERYWHERE]
        np.testing.assert_allclose(ours[:, j], drake, rtol=1e-12, atol=1e-12)
    # One point gives shape S; a batch gives S + (N,).
    assert evaluate(EVERYWHERE, X, P[:, 0]).shape == (len(EVERYWHERE),)


def test_shared_subexpressions_are_evaluated_once():
    c = np.cos(2 * x) + 2
    ev = ExpressionEvaluator([c * y, c**2, c], X)
    kinds = [node.kind for node in ev._nodes]
    assert kinds.count("Cos") == 1
    assert ev.variables_used() == [(0, 1), (0,), (0,)]
    assert not ev.is_constant().any()
    assert ExpressionEvaluator([sym.Expression(3.0), y], X).is_constant().tolist() == [True, False]


def test_interval_operators_round_outwards():
    a = Interval(np.array(0.1), np.array(0.1))
    s = a + 0.2
    assert s.lo < 0.1 + 0.2 < s.hi  # the float sum, rounded both ways
    assert s.lo <= 0.3 <= s.hi  # and the exact decimal sum
    p = Interval(np.array(-1.0), np.array(2.0)) * Interval(np.array(-3.0), np.array(0.5))
    assert p.lo <= -6.0 and p.hi >= 3.0
    assert p.contains(np.array([-6.0, 3.0, 0.0])).all()


def test_unsupported_functions_raise_with_name_and_expression():
    with pytest.raises(UnsupportedExpressionError, match=r"UninterpretedFunction.*foo\(x\(0\)\)"):
        ExpressionEvaluator([sym.uninterpreted_function("foo", [x])], X)
    # Drake differentiates abs into if-then-else.
    d_abs = sym.Jacobian(np.array([abs(x) * y]), X)[0, 0]
    with pytest.raises(UnsupportedExpressionError, match="IfThenElse"):
        ExpressionEvaluator([d_abs], X)
    # atan2 evaluates at points, but has no interval extension here.
    ev = ExpressionEvaluator([sym.atan2(y, x)], X)
    assert ev(np.array([1.0, 1.0]))[0] == pytest.approx(np.pi / 4, abs=1e-15)
    with pytest.raises(UnsupportedExpressionError, match=r"does not support Atan2.*atan2"):
        ev.interval(np.zeros(2), np.ones(2))
    assert issubclass(UnsupportedExpressionError, OfrlError)


def test_foreign_variables_are_rejected():
    z = sym.Variable("z")
    with pytest.raises(UnsupportedExpressionError, match="uses variable z"):
        ExpressionEvaluator([x + z], X)


def test_domain_errors_only_when_wholly_outside():
    with pytest.raises(IntervalDomainError, match=r"log .*wholly outside"):
        evaluate_interval(np.log(x), X0, np.array([-2.0]), np.array([-1.0]))
    with pytest.raises(IntervalDomainError, match="sqrt"):
        evaluate_interval(np.sqrt(x), X0, np.array([-2.0]), np.array([-1.0]))
    # Partly outside: enclosed over the part of the box where it is defined.
    b = evaluate_interval(np.sqrt(x), X0, np.array([-1.0]), np.array([4.0]))
    assert b.lo == 0.0 and b.hi == pytest.approx(2.0, rel=1e-14)


def test_bad_box_shapes_raise():
    ev = ExpressionEvaluator([x + y], X)
    with pytest.raises(ModelError, match=r"shape \(2,\) or \(2, B\)"):
        ev.interval(np.zeros(3), np.ones(3))
    with pytest.raises(ModelError, match="lower <= upper"):
        ev.interval(np.ones(2), np.zeros(2))
    with pytest.raises(ModelError, match="2 rows"):
        ev(np.zeros((3, 4)))
