"""The soundness gaps of issue 14, one explicit case each, against exact values.

Exact values are rationals (``fractions.Fraction``, stored doubles taken
exactly) where the expression is rational, and numpy values far from any
rounding question (``exp(-710)`` is a normal subnormal result) otherwise.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pydrake.symbolic as sym
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from ofrl_drake.errors import ModelError
from ofrl_drake.examples import make_system
from ofrl_drake.interval import (
    ExpressionEvaluator,
    Interval,
    IntervalDomainError,
    evaluate_interval,
)
from ofrl_drake.jacobian_bounds import jacobian_bounds

X = sym.MakeVectorVariable(2, "x")
x, y = sym.Expression(X[0]), sym.Expression(X[1])
MAX = float(np.finfo(float).max)

pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")


def enclose(expr, lo, hi) -> tuple[float, float]:
    box = evaluate_interval(expr, X, np.array(lo, dtype=float), np.array(hi, dtype=float))
    lo_, hi_ = float(box.lo), float(box.hi)
    assert not (math.isnan(lo_) or math.isnan(hi_))
    assert lo_ <= hi_ and lo_ <= MAX and hi_ >= -MAX  # a real number always fits
    return lo_, hi_


def contains(bounds: tuple[float, float], value: Fraction | float) -> bool:
    lo, hi = bounds
    v = Fraction(value) if isinstance(value, float) else value
    return (lo == -math.inf or Fraction(lo) <= v) and (hi == math.inf or v <= Fraction(hi))


# ------------------------------------------------------- 1. overflow and underflow
def test_division_by_a_subnormal_does_not_go_through_an_overflowing_reciprocal():
    b = enclose(x / y, [1e-310, 1e-310], [2e-310, 2e-310])
    for num, den in [(1e-310, 2e-310), (2e-310, 1e-310), (1e-310, 1e-310)]:
        assert contains(b, Fraction(num) / Fraction(den))
    assert b[1] < 2.1  # [0.5, 2], not [inf, inf]
    b = enclose(1e-8 / y, [0, 1e-310], [0, 1e-310])
    assert contains(b, Fraction(1e-8) / Fraction(1e-310))
    assert b[1] < 1.1e302


def test_negative_integer_powers_near_overflow():
    b = enclose(x**-2, [1e155, 0], [1e155, 0])
    assert contains(b, Fraction(1e155) ** -2)  # 1e-310, not [-5e-324, 5e-324]
    assert b[0] > 9e-311
    b = enclose(x**-3, [1e103, 0], [2e103, 0])
    assert contains(b, Fraction(1e103) ** -3) and contains(b, Fraction(2e103) ** -3)
    b = enclose(x**-2, [1e-200, 0], [1e-200, 0])  # 1e400 overflows: the lower end stays finite
    assert b == (pytest.approx(MAX, rel=1e-14), math.inf)


@pytest.mark.parametrize(
    ("expr", "lo", "hi", "value"),
    [
        (1 / np.exp(x), 710.0, 710.0, np.exp(-710.0)),
        (np.exp(-x), 710.0, 710.0, np.exp(-710.0)),
        (1 / np.cosh(x), 711.0, 711.0, 2 * np.exp(-711.0)),
        (1 / np.sinh(x), 711.0, 711.0, 2 * np.exp(-711.0)),
        (-1 / np.sinh(x), -711.0, -711.0, 2 * np.exp(-711.0)),
    ],
)
def test_exp_cosh_sinh_near_overflow(expr, lo, hi, value):
    b = enclose(expr, [lo, 0], [hi, 0])
    assert contains(b, float(value)) and b[1] < 1e-300


def test_overflowing_ends_go_to_the_largest_double_or_outward_infinity():
    assert enclose(np.exp(x), [710, 0], [710, 0]) == (pytest.approx(MAX, rel=1e-14), math.inf)
    assert enclose(np.cosh(x), [710, 0], [711, 0])[1] == math.inf
    assert enclose(np.sinh(x), [-711, 0], [-710, 0])[0] == -math.inf
    assert enclose(-np.exp(x), [710, 0], [710, 0])[1] == pytest.approx(-MAX, rel=1e-14)
    assert enclose(x * y, [1e200, 1e200], [1e200, 1e200])[0] == pytest.approx(MAX, rel=1e-14)
    assert enclose(x + y, [MAX, MAX], [MAX, MAX])[0] == pytest.approx(MAX, rel=1e-14)


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        ((1.0, 2.0), (-2.0, -1.0), (-2.0, -0.5)),
        ((-2.0, -1.0), (-2.0, -1.0), (0.5, 2.0)),
        ((-1.0, 2.0), (4.0, 8.0), (-0.25, 0.5)),
        ((1.0, 2.0), (0.0, 1.0), (1.0, math.inf)),
        ((-2.0, -1.0), (0.0, 1.0), (-math.inf, -1.0)),
        ((1.0, 2.0), (-1.0, 0.0), (-math.inf, -1.0)),
        ((-2.0, -1.0), (-1.0, 0.0), (1.0, math.inf)),
        ((0.0, 0.0), (-1.0, 1.0), (0.0, 0.0)),
        ((1.0, 2.0), (-1.0, 1.0), (-math.inf, math.inf)),
        ((-1.0, 1.0), (0.0, 0.0), (-math.inf, math.inf)),
    ],
)
def test_division_case_table(a, b, expected):
    lo, hi = enclose(x / y, [a[0], b[0]], [a[1], b[1]])
    assert lo <= expected[0] and expected[1] <= hi
    assert lo == pytest.approx(expected[0], rel=1e-15, abs=1e-300)
    assert hi == pytest.approx(expected[1], rel=1e-15, abs=1e-300)


# --------------------------------------------- 2. pow on a non-positive base
def test_variable_exponent_on_a_negative_base_is_enclosed_at_integer_exponents():
    assert contains(enclose(sym.pow(x, y), [-2, 2], [1, 2]), 4.0)  # was [0, 1]
    assert contains(enclose(sym.pow(x, y), [-2, 3], [1, 3]), -8.0)
    b = enclose(sym.pow(x, y), [-2, 1], [-1, 3])
    for base in (-2.0, -1.5, -1.0):
        for k in (1, 2, 3):
            assert contains(b, Fraction(base) ** k)
    b = enclose(sym.pow(-2.0, y), [0, 1], [0, 3])  # a constant negative base
    assert all(contains(b, v) for v in (-2.0, 4.0, -8.0))


def test_negative_base_without_an_integer_exponent_is_outside_the_domain():
    with pytest.raises(IntervalDomainError, match=r"pow .*wholly outside.*pow\(x\(0\), x\(1\)\)"):
        enclose(sym.pow(x, y), [-2, 0.2], [-1, 0.8])
    # Partly defined: only x >= 0 has values, and they are enclosed.
    b = enclose(sym.pow(x, y), [-2, 0.5], [4, 0.5])
    assert b[0] <= 0.0 and contains(b, 2.0) and b[1] < 2.0001


# ------------------------------------------------- 3. large integer exponents
@pytest.mark.parametrize(
    ("k", "values"),
    [(2147483650.0, [1.0]), (2147483651.0, [-1.0]), (-2147483650.0, [1.0]), (2.0**60, [1.0])],
)
def test_integer_exponents_above_2_31_are_integers(k, values):
    b = enclose(sym.pow(x, k), [-1, 0], [0, 0])
    assert all(contains(b, v) for v in values)
    b = enclose(sym.pow(x, k), [-1, 0], [-1, 0])
    assert all(contains(b, v) for v in values)


# ------------------------------------------------------------------- 4. NaN
def test_an_infinite_constant_times_an_interval_holding_zero_has_no_nan():
    inf_x = sym.Expression(np.inf) * x
    assert inf_x.get_kind() == sym.ExpressionKind.Mul
    assert enclose(inf_x, [-1, 0], [1, 0]) == (-math.inf, math.inf)
    lo, hi = enclose(inf_x, [0, 0], [0, 0])  # inf * 0 is undefined; the bound is still real
    assert lo <= 0.0 <= hi
    assert enclose(inf_x, [1, 0], [2, 0])[1] == math.inf
    # The Interval operators follow the same rule.
    p = Interval(np.array(0.0), np.array(math.inf)) * Interval(np.array(-math.inf), np.array(0.0))
    assert p.lo == -math.inf and p.hi >= 0.0


def test_boxes_without_a_real_point_or_with_nan_are_refused():
    ev = ExpressionEvaluator([x + y], X)
    with pytest.raises(ModelError, match="NaN"):
        ev.interval(np.array([0.0, np.nan]), np.ones(2))
    with pytest.raises(ModelError, match=r"real point.*\+inf"):
        ev.interval(np.array([0.0, np.inf]), np.array([1.0, np.inf]))
    b = ev.interval(np.array([-np.inf, 0.0]), np.array([np.inf, 1.0]))  # unbounded is fine
    assert (b.lo, b.hi) == (-math.inf, math.inf)


# -------------------------------------------------- 5. constants folded by Drake
def test_a_folded_constant_is_widened_to_hold_the_exact_value():
    folded = -x - 0.1 * x  # Drake stores -1.1 * x, rounded
    assert "1.1000000000000001" in str(folded)
    b = enclose(folded, [1, 0], [1, 0])
    assert contains(b, -1 - Fraction(0.1)) and not contains((-1.1, -1.1), -1 - Fraction(0.1))
    d = sym.Jacobian([x / 3], [X[0]])[0, 0]  # Drake stores 1/3 rounded
    assert d.get_kind() == sym.ExpressionKind.Constant
    assert contains(enclose(d, [0, 0], [0, 0]), Fraction(1, 3))
    assert contains(enclose(x + 0.1 + 0.2, [0, 0], [0, 0]), Fraction(0.1) + Fraction(0.2))


def test_exact_constants_stay_exact():
    for c in (2.0, -1.5, 0.75, 1000.0, 3 / 1024):
        assert enclose(sym.Expression(c), [0, 0], [0, 0]) == (c, c)
    assert enclose(sym.Expression(0.1), [0, 0], [0, 0]) == (
        np.nextafter(0.1, -1.0),
        np.nextafter(0.1, 1.0),
    )
    assert enclose(x**2, [-2, 0], [3, 0])[0] == 0.0  # integer exponents stay integers


@settings(max_examples=100, deadline=None, derandomize=True)
@given(c1=st.floats(-100, 100), c2=st.floats(-100, 100))
def test_a_coefficient_folded_from_two_constants_holds_their_exact_sum(c1, c2):
    folded = c1 + c2
    # A sum that rounds onto a multiple of 2**-10 below 2**20 is taken as exact;
    # the module docstring states that exception.
    assume(not (abs(folded) <= 2**20 and (folded * 1024).is_integer()))
    d = sym.Jacobian([c1 * x + c2 * x], [X[0]])[0, 0]  # the constant fl(c1 + c2)
    assert d.get_kind() == sym.ExpressionKind.Constant
    assert contains(enclose(d, [0, 0], [0, 0]), Fraction(c1) + Fraction(c2))


def test_coupled_two_state_certified_bounds_hold_the_exact_derivative():
    b = jacobian_bounds(make_system("coupled_two_state"), ([-2] * 4, [2] * 4), "certified")
    exact = -1 - Fraction(0.1)
    assert Fraction(b.Mf1[0, 0]) <= exact <= Fraction(b.Mf2[0, 0])
    assert Fraction(b.Mf1[0, 2]) <= Fraction(0.1) <= Fraction(b.Mf2[0, 2])
    assert b.Mf1[0, 1] == b.Mf2[0, 1] == 1.0  # exact constants add no width
