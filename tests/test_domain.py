"""Definedness of f and g on a whole box: the flags, the proof, and the certified bounds."""

import numpy as np
import pytest
from pydrake.symbolic import MakeVectorVariable

from ofrl_drake import ControlAffineSystem
from ofrl_drake.domain import UndefinedOnBoxError, prove_defined
from ofrl_drake.interval import ExpressionEvaluator
from ofrl_drake.jacobian_bounds import BoundsError, jacobian_bounds

pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")

X = MakeVectorVariable(2, "x")


def _ev(*exprs):
    return ExpressionEvaluator(list(exprs), X)


def _box(lo, hi):
    return np.array(lo, dtype=float), np.array(hi, dtype=float)


# ----------------------------------------------------------------- the flags
@pytest.mark.parametrize(
    "expr, partial",
    [
        (np.sin(X[0]) * X[1] ** 2, False),
        (X[0] ** -3 + np.exp(X[1]) / (1 + X[0] ** 2), False),  # poles are not domains
        (np.tanh(X[0]) + np.arctan(X[1]), False),
        (np.sqrt(X[0]), True),
        (np.log(X[0]), True),
        (np.arcsin(X[0]), True),
        (np.arccos(X[1]), True),
        (X[0] ** 1.5, True),
        (X[0] ** X[1], True),
    ],
)
def test_partial_functions_are_found(expr, partial):
    assert _ev(expr).has_partial_functions is partial


def test_possibly_undefined_flags_each_box_and_says_why():
    ev = _ev(np.sqrt(X[0]), np.arcsin(X[1]))
    lo = np.array([[-1.0, 0.0, 0.0, 0.5], [0.0, 0.0, -2.0, -1.0]])
    hi = np.array([[1.0, 1.0, 1.0, 0.5], [0.5, 1.0, 0.0, 1.0]])
    flagged, reasons = ev.possibly_undefined(lo, hi)
    assert flagged.tolist() == [True, False, True, False]
    assert reasons[0] == "sqrt of [-1, 1] in expression sqrt(x(0))"
    assert reasons[1] == "asin of [-2, 0] in expression asin(x(1))"


def test_log_is_flagged_at_zero_and_a_real_power_below_zero():
    ev = _ev(np.log(X[0]), X[1] ** 2.5)
    flagged, _ = ev.possibly_undefined(np.array([[0.0, 1.0], [0.0, -0.1]]), np.ones((2, 2)))
    assert flagged.tolist() == [True, True]
    flagged, _ = ev.possibly_undefined(np.array([1e-300, 0.0]), np.array([1.0, 1.0]))
    assert flagged.tolist() == [False]


# ----------------------------------------------------------------- the proof
def test_an_overestimated_argument_is_proven_defined_by_halving():
    # (x - 1)**2 + 0.5 >= 0.5, but its natural enclosure over [-3, 3] reaches -4.5.
    ev = _ev(np.sqrt(X[0] * X[0] - 2 * X[0] + 1.5) + 0 * X[1])
    flagged, _ = ev.possibly_undefined(*_box([-3, -1], [3, 1]))
    assert flagged.tolist() == [True]
    proof = prove_defined(ev, *_box([-3, -1], [3, 1]))
    assert proof.levels >= 1
    assert proof.boxes > 1


def test_nothing_to_prove_takes_no_halving():
    proof = prove_defined(_ev(np.sqrt(X[0] + 2.0)), *_box([-1, -1], [1, 1]))
    assert (proof.levels, proof.boxes) == (0, 1)


def test_a_strip_thinner_than_any_sample_spacing_is_found():
    # Undefined where |x0 - 0.005| < 1e-6 only.
    ev = _ev(X[1], ((X[0] - 0.005) ** 2 - 1e-12) ** 1.5)
    with pytest.raises(UndefinedOnBoxError, match=r"f\[1\] is nan at x = \(0\.00499"):
        prove_defined(ev, *_box([-1, -1], [1, 1]), names=["f[0]", "f[1]"])
    x0 = float(np.linspace(-1, 1, 101)[np.argmin(np.abs(np.linspace(-1, 1, 101) - 0.005))])
    assert np.isfinite(ev(np.array([x0, 0.0]))).all()  # a 101-point grid misses it


def test_a_box_wholly_outside_a_domain_is_refused():
    with pytest.raises(UndefinedOnBoxError, match=r"undefined on the whole box: log"):
        prove_defined(_ev(np.log(X[0] - 5.0)), *_box([-1, -1], [1, 1]))


def test_an_argument_at_the_domain_edge_on_the_box_edge_is_refused_with_advice():
    # x + 0.5 is exactly 0 at x = -0.5: proven. 3 x - 0.3 at x = 0.1 is 0 only after
    # inexact roundings, which outward rounding cannot tell from a value just below 0.
    assert prove_defined(_ev((X[0] + 0.5) ** 1.5), *_box([-0.5, -1], [1, 1])).levels == 0
    with pytest.raises(UndefinedOnBoxError, match=r"after 8 levels.*Shrink the box away"):
        prove_defined(_ev((3 * X[0] - 0.3) ** 1.5), *_box([0.1, -1], [1, 1]), max_levels=8)


def test_too_many_flagged_boxes_stop_the_proof():
    ev = _ev(np.sqrt(np.sin(8 * X[0]) ** 2 + np.cos(8 * X[0]) ** 2 - 0.999 + 0 * X[1]))
    with pytest.raises(UndefinedOnBoxError, match=r"boxes flagged \(at most 2\)"):
        prove_defined(ev, *_box([-3, -3], [3, 3]), max_boxes=2)


# ----------------------------------------------------- the certified bounds
def _plant(extra):
    def f(x):
        return np.array([x[1], -x[0] - x[1] + 0.1 * extra(x)])

    def g(x):
        return np.array([[0 * x[0]], [1 + 0 * x[0]]])

    return ControlAffineSystem(f, g, C=[[1.0, 0.0]], name="partial")


def test_certified_bounds_refuse_a_plant_undefined_on_a_thin_strip():
    plant = _plant(lambda x: ((x[0] - 0.005) ** 2 - 1e-12) ** 1.5)
    box = ([-1, -1], [1, 1])
    sampled = jacobian_bounds(plant, box, "sampled")  # its samples miss the strip
    assert np.isfinite(sampled.Mf1).all()
    with pytest.raises(BoundsError, match=r"f\[1\] is nan at x = \(0\.00499.*a state of the box"):
        jacobian_bounds(plant, box, "certified")


def test_certified_bounds_of_a_plant_defined_on_the_box_are_unchanged():
    plant = _plant(lambda x: (x[0] + 2.0) ** 1.5)  # defined, only where x0 >= -2
    b = jacobian_bounds(plant, ([-1, -1], [1, 1]), "certified")
    # d/dx0 of -x0 + 0.1 (x0 + 2)**1.5 is -1 + 0.15 sqrt(x0 + 2), over [1, sqrt 3].
    np.testing.assert_allclose(b.Mf1[1, 0], -1 + 0.15, atol=1e-3)
    np.testing.assert_allclose(b.Mf2[1, 0], -1 + 0.15 * np.sqrt(3.0), atol=1e-3)


@pytest.mark.parametrize(
    "extra",
    [
        lambda x: -((x[0] ** 2 + x[1] ** 2) ** 1.5),  # least argument 0 inside the box
        lambda x: (1 - np.cos(x[0])) ** 1.5,  # 1 - cos: least 0 at x0 = 0
        lambda x: np.arctan2(x[1], x[0] + 3.0) - np.sqrt(x[0] ** 2 + x[1] ** 2 + 1.0),
    ],
    ids=["radial", "one_minus_cos", "atan2"],
)
def test_plants_defined_on_the_whole_box_keep_their_certified_bounds(extra):
    # Before the fix of this test: the radial and 1 - cos plants were refused ("could not
    # be proven defined"): 0 + 0 was rounded down to -5e-324, below sqrt's domain, on
    # every box at the origin; a plant with atan2 in f raised UnsupportedExpressionError.
    plant = _plant(extra)
    box = ([-1, -1], [1, 1])
    certified = jacobian_bounds(plant, box, "certified")
    sampled = jacobian_bounds(plant, box, "sampled")
    assert np.all(certified.Mf1 <= sampled.Mf1 + 1e-12)
    assert np.all(certified.Mf2 >= sampled.Mf2 - 1e-12)
    assert np.all(np.isfinite(certified.Mf1)) and np.all(np.isfinite(certified.Mf2))


def test_a_sum_that_rounds_to_zero_is_exact_and_stays_zero():
    ev = _ev(X[0] ** 2 + X[1] ** 2, 1 - np.cos(X[0]))
    enc = ev.interval(np.array([-1.0, -1.0]), np.array([1.0, 1.0]))
    assert enc.lo.tolist() == [0.0, 0.0]
    flagged, _ = _ev(np.sqrt(X[0] ** 2 + X[1] ** 2)).possibly_undefined(
        np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    )
    assert flagged.tolist() == [False]
