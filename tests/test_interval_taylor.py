"""Second-order interval Taylor forms: derivatives, soundness, convergence, refusals."""

from fractions import Fraction

import numpy as np
import pytest
from pydrake.symbolic import (
    Jacobian,
    MakeVectorVariable,
    acos,
    asin,
    atan,
    ceil,
    cos,
    cosh,
    exp,
    floor,
    log,
    sin,
    sinh,
    sqrt,
    tan,
    tanh,
)
from pydrake.symbolic import max as sym_max
from pydrake.symbolic import min as sym_min

from ofrl_drake.interval import ExpressionEvaluator, Interval, UnsupportedExpressionError
from ofrl_drake.interval_taylor import (
    TAYLOR_KINDS,
    TaylorEvaluator,
    _add,
    _mul,
    _scale,
    taylor_form,
)

X = MakeVectorVariable(3, "x")
x0, x1, x2 = X
# Every kind the Taylor form differentiates, composed, on a box where all are smooth.
EXPRESSIONS = [
    sin(x0) * cos(x1) ** 2 + 3.0 * x2,
    exp(0.3 * x0) / (2.0 + cos(x1)),
    log(2.0 + x0 * x1) + sqrt(1.5 + x2),
    tan(0.5 * x0) * atan(x1 + x2),
    asin(0.4 * x0) - acos(0.3 * x1) + sinh(x2) * cosh(x0),
    tanh(x0 - x1) * (1.0 + x2) ** 3 + (2.0 + x0) ** 0.5,
    (x0 * x1 - x2) / (3.0 + x0**2),
    1.0 / (1.5 + x0) ** 2 + 0.1 * x0 * x1 * x2,
]
LO = np.array([-0.6, -0.4, -0.5])
HI = np.array([0.5, 0.7, 0.4])


def _symbolic_derivatives():
    grad = Jacobian(np.array(EXPRESSIONS), X)  # (E, 3)
    hess = np.array([Jacobian(grad[e], X) for e in range(len(EXPRESSIONS))])  # (E, 3, 3)
    return (
        ExpressionEvaluator(EXPRESSIONS, X),
        ExpressionEvaluator(grad, X),
        ExpressionEvaluator(hess, X),
    )


@pytest.fixture(scope="module")
def taylor():
    return TaylorEvaluator(EXPRESSIONS, X, [0, 1, 2])


@pytest.fixture(scope="module")
def symbolic():
    return _symbolic_derivatives()


def _points(n, seed=0):
    rng = np.random.default_rng(seed)
    return LO[:, None] + rng.random((3, n)) * (HI - LO)[:, None]


def test_jet_at_points_is_the_symbolic_gradient_and_hessian(taylor, symbolic):
    value, grad, hess = symbolic
    P = _points(50)
    jet = taylor.jet(P, P)
    want_g = grad(P)  # (E, 3, N)
    want_h = hess(P)  # (E, 3, 3, N)
    pairs = taylor.pairs
    want_h = np.stack([want_h[:, a, b] for a, b in pairs], axis=1)  # (E, P, N)
    for got, want in ((jet.value, value(P)), (jet.gradient, want_g), (jet.hessian, want_h)):
        assert np.all(got.lo <= want) and np.all(want <= got.hi)
        np.testing.assert_allclose(got.hi - got.lo, 0.0, atol=1e-10 * (1 + np.abs(want)).max())
    assert jet.valid.all()


def test_jet_over_boxes_encloses_the_derivatives_everywhere_in_them(taylor, symbolic):
    value, grad, hess = symbolic
    rng = np.random.default_rng(1)
    # 40 random sub-boxes of the box, 200 points in each.
    a, b = _points(40, seed=2), _points(40, seed=3)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    jet = taylor.jet(lo, hi)
    t = rng.random((3, 40, 200))
    P = lo[:, :, None] + t * (hi - lo)[:, :, None]  # (3, boxes, points)
    flat = P.reshape(3, -1)
    v = value(flat).reshape(-1, 40, 200)
    g = grad(flat).reshape(len(EXPRESSIONS), 3, 40, 200)
    h = hess(flat).reshape(len(EXPRESSIONS), 3, 3, 40, 200)
    assert np.all(jet.value.lo[..., None] <= v) and np.all(v <= jet.value.hi[..., None])
    assert np.all(jet.gradient.lo[..., None] <= g) and np.all(g <= jet.gradient.hi[..., None])
    for p, (i, j) in enumerate(taylor.pairs):
        hij = h[:, i, j]
        assert np.all(jet.hessian.lo[:, p, :, None] <= hij)
        assert np.all(hij <= jet.hessian.hi[:, p, :, None])


def test_taylor_form_encloses_samples(taylor, symbolic):
    value = symbolic[0]
    c = 0.5 * (LO + HI)
    for scale in (1.0, 0.25):
        lo = (c + scale * (LO - c))[:, None]
        hi = (c + scale * (HI - c))[:, None]
        form = taylor_form(taylor, lo, hi)
        P = lo + np.random.default_rng(4).random((3, 5000)) * (hi - lo)
        v = value(P)
        assert np.all(form.lo <= v.min(axis=1, keepdims=True))
        assert np.all(v.max(axis=1, keepdims=True) <= form.hi)


def test_cancelling_variables_converge_with_the_cube_of_the_width():
    # sin(y)^2 + cos(y)^2 = 1, and a yaw-free product written with the yaw (rotation).
    y, r = MakeVectorVariable(2, "y")
    exprs = [
        60.0 * (sin(y) ** 2 + cos(y) ** 2) - 60.0,
        (sin(y) * cos(r) + cos(y) * sin(r)) * cos(y) - (cos(y) * cos(r) - sin(y) * sin(r)) * sin(y),
    ]  # 0 and sin(r)
    ev = TaylorEvaluator(exprs, [y, r], [0, 1])
    widths = []
    for half in (0.2, 0.1, 0.05):
        form = taylor_form(ev, np.array([[-half], [0.3 - half]]), np.array([[half], [0.3 + half]]))
        assert form.lo[0, 0] <= 0.0 <= form.hi[0, 0]
        assert form.lo[1, 0] <= np.sin(0.3 - half) and np.sin(0.3 + half) <= form.hi[1, 0]
        widths.append(form.hi[0, 0] - form.lo[0, 0])
    assert widths[1] < widths[0] / 6 and widths[2] < widths[1] / 6  # cubic: / 8 per halving
    natural = ExpressionEvaluator(exprs, [y, r]).interval(
        np.array([-0.05, 0.25]), np.array([0.05, 0.35])
    )
    assert widths[2] < 0.01 * (natural.hi[0] - natural.lo[0])


@pytest.mark.parametrize(
    ("expr", "lo", "hi"),
    [
        (log(x0), 0.0, 1.0),
        (sqrt(x0), 0.0, 1.0),
        (x0**0.5, -1.0, 1.0),
        (1.0 / x0, -1.0, 1.0),
        (x0**-2, -1.0, 1.0),
        (tan(x0), 1.0, 2.0),
        (asin(x0), 0.5, 1.0),
    ],
)
def test_boxes_where_a_function_is_not_smooth_get_the_whole_line(expr, lo, hi):
    ev = TaylorEvaluator([expr], X, [0])
    lower = np.array([[lo, 0.2], [0.0, 0.0], [0.0, 0.0]])
    upper = np.array([[hi, 0.4], [0.0, 0.0], [0.0, 0.0]])
    form = taylor_form(ev, lower, upper)
    assert form.lo[0, 0] == -np.inf and form.hi[0, 0] == np.inf  # not smooth on the first box
    assert np.isfinite(form.lo[0, 1]) and np.isfinite(form.hi[0, 1])  # smooth on the second


def test_taylor_kinds_are_the_kinds_whose_derivatives_are_tested():
    # TAYLOR_KINDS is written out; it must name exactly the kinds of EXPRESSIONS, whose
    # gradients and Hessians the tests above check against Drake's symbolic ones.
    kinds = {node.kind for node in ExpressionEvaluator(EXPRESSIONS, X).nodes}
    assert kinds == TAYLOR_KINDS


@pytest.mark.parametrize(
    "expr",
    [abs(x0), sym_min(x0, x1), sym_max(x0, x1), ceil(x0), floor(x0)],
    ids=["Abs", "Min", "Max", "Ceil", "Floor"],
)
def test_kinds_outside_taylor_kinds_are_refused(expr):
    # Interval arithmetic encloses these (not smooth); the Taylor form refuses them.
    kinds = {node.kind for node in ExpressionEvaluator([expr + x2], X).nodes}
    assert len(kinds - TAYLOR_KINDS) == 1
    ExpressionEvaluator([expr + x2], X).interval(LO, HI)
    with pytest.raises(UnsupportedExpressionError, match=r"Taylor form does not support"):
        TaylorEvaluator([expr + x2], X, [0, 1, 2])


def test_unsupported_kinds_and_variable_exponents_are_refused():
    with pytest.raises(UnsupportedExpressionError, match=r"Taylor form does not support Abs"):
        TaylorEvaluator([abs(x0) + x1], X, [0, 1])
    with pytest.raises(UnsupportedExpressionError, match=r"constant exponents only"):
        TaylorEvaluator([x0**x1], X, [0, 1])


def _exact(a, op, b):
    return op(Fraction(float(a)), Fraction(float(b)))


@pytest.mark.parametrize("magnitude", [1e-320, 1e-300, 1.0, 1e150, 1e300])
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_lean_kernels_round_outward(magnitude):
    rng = np.random.default_rng(5)
    a_lo = rng.standard_normal(300) * magnitude
    b_lo = rng.standard_normal(300) * magnitude
    a = Interval(a_lo, a_lo + np.abs(rng.standard_normal(300)) * magnitude)
    b = Interval(b_lo, b_lo + np.abs(rng.standard_normal(300)) * magnitude)
    s, p = _add(a, b), _mul(a, b)
    c = _scale(-0.1, -0.1, a)
    for i in range(300):
        for x in (a.lo[i], a.hi[i]):
            for y in (b.lo[i], b.hi[i]):
                exact_sum = _exact(x, lambda u, v: u + v, y)
                exact_prod = _exact(x, lambda u, v: u * v, y)
                if np.isfinite(s.lo[i]):
                    assert Fraction(float(s.lo[i])) <= exact_sum <= Fraction(float(s.hi[i]))
                if np.isfinite(p.lo[i]) and np.isfinite(p.hi[i]):
                    assert Fraction(float(p.lo[i])) <= exact_prod <= Fraction(float(p.hi[i]))
            exact_scaled = Fraction(-0.1) * Fraction(float(x))
            assert Fraction(float(c.lo[i])) <= exact_scaled <= Fraction(float(c.hi[i]))
    # Overflow and 0 * inf go to the library kernels: never NaN, never a wrong infinity.
    big = Interval(np.array([1e300, 0.0]), np.array([1e300, 0.0]))
    inf = Interval(np.array([1e300, -np.inf]), np.array([1e300, np.inf]))
    q = _mul(big, inf)
    assert 1e308 < q.lo[0] < np.inf and q.hi[0] == np.inf  # 1e600 is beyond the largest double
    assert -1e-300 < q.lo[1] <= 0.0 <= q.hi[1] < 1e-300  # [0, 0] * [-inf, inf] is {0}
