"""Vectorized point and interval evaluation of ``pydrake.symbolic`` expressions.

Drake's own ``Expression.Evaluate`` works one point at a time. This module walks
an expression tree once (``Expression.get_kind()`` / ``Expression.Unapply()``),
turns it into a flat list of nodes with shared subexpressions merged, and then
evaluates that list with numpy operations on whole arrays:

* :meth:`ExpressionEvaluator.__call__` evaluates at ``N`` points at once, and
* :meth:`ExpressionEvaluator.interval` evaluates over ``B`` axis-aligned boxes
  at once, in interval arithmetic.

What the interval evaluation guarantees
---------------------------------------
For every box, the returned ``[lo, hi]`` contains the real value of the
expression at every point of the box where it is defined, where the expression
is the tree Drake stores and each stored constant stands for every real number
within one ulp of it (see *Constants*). In particular:

* Ends are rounded outward: one ulp for the correctly rounded ``+ - * /``, eight
  for numpy's library functions (accurate to a few ulp); a sum that rounds to 0
  (exact, with gradual underflow) and a change of sign are exact and kept. A lower end never is
  +inf and an upper end never -inf: an end that overflows becomes the largest
  finite double, or the infinity on the outward side (IEEE 1788). Division is
  done by its case table, never as ``a * (1 / b)``; integer powers call ``pow``
  at the ends, never ``1 / x**k``.
* No end is NaN. ``0 * inf`` is 0 for sets; the other indeterminate forms
  cannot arise because of the rule on infinite ends, and a stray NaN in the
  rounding step would become the outward infinity.
* ``sin``/``cos`` find their extrema by range reduction with a slack that can
  only add an extremum (arguments beyond 1e12 give [-1, 1]); ``tan`` gives the
  whole line when a pole may be inside.
* Functions defined on part of a box only (``log``, ``sqrt``, ``asin``,
  ``acos``, a real power) are enclosed over that part, as in IEEE 1788. Values
  at a pole (``1/x``, ``x**-k`` at 0) are undefined: the side of the pole the
  box reaches is unbounded, and a divisor box ``[0, 0]`` gives the whole line.
* ``pow(x, y)`` is enclosed wherever numpy and Drake define it: ``x**k`` for an
  integer constant ``k`` of any magnitude (handled as an integer, also above
  2**31) on any base; otherwise on ``x >= 0`` for every ``y``, and on ``x < 0``
  at the integers the exponent box holds (a variable or widened exponent).
* A point value of ``inf`` (numpy's overflow) lies inside when the real value
  is beyond the largest double: ``exp(710)`` encloses as ``[1.797e308, inf]``.

Constants
---------
Drake folds constant subexpressions into one double while it builds an
expression (``-x - 0.1 * x`` is stored as ``-1.1000000000000001 * x``, the
derivative of ``x / 3`` as the double nearest 1/3), so a stored constant may
carry the rounding error of a fold that cannot be seen afterwards. Every stored
constant (a ``Constant``, the constant term of a sum, the constant factor of a
product, an exponent) is therefore widened to ``[nextafter(c, -inf),
nextafter(c, inf)]``, which holds the exact result of any fold with one
rounding, except when ``c`` is a multiple of ``2**-10`` with ``|c| <= 2**20``
(integers, halves, quarters, ...). Those are taken as exact: they are the
constants written exactly (exponents, polynomial coefficients, ``0.5``), their
sums stay exact in this range, and keeping them points keeps the
enclosures of constant Jacobian entries points. Constants ``+-inf`` stand for
``[max double, inf]`` and ``[-inf, -max double]``.

Not guaranteed: a fold whose accumulated error exceeds one ulp of its result
(``x + 1e16 + 1 - 1e16`` is stored as ``x``), a fold of other numbers whose
result rounds onto an exact constant or cancels away (``10 * (0.1 * x)`` is
stored as ``x``, though ``10 * 0.1`` is 1 + 5.6e-17 exactly), and anything
outside the tree Drake stores (the user's decimal literals are the doubles
Python gives them).

Refused
-------
* Kinds other than the supported ones (below), Drake's ``NaN`` kind (what
  Drake folds an undefined constant to, e.g. ``sin(inf)``) and a variable not
  in ``variables``: :class:`UnsupportedExpressionError` when the evaluator is
  built, naming the function and the expression. ``Atan2`` evaluates at points
  only; :meth:`ExpressionEvaluator.interval` refuses it the same way.
* A box on which some function has no defined value at all (``log`` of
  ``[-2, -1]``, ``pow(x, 0.5)`` or ``pow(x, y)`` with ``x < 0`` and no integer
  ``y``): :class:`IntervalDomainError`.
* Boxes with a NaN corner, ``lower > upper``, or no real point (``lower = +inf``
  or ``upper = -inf``): :class:`~ofrl_drake.errors.ModelError`.

Supported kinds: ``Constant``, ``Var``, ``Add``, ``Mul``, ``Div``, ``Pow``,
``Exp``, ``Log``, ``Sqrt``, ``Sin``, ``Cos``, ``Tan``, ``Asin``, ``Acos``,
``Atan``, ``Sinh``, ``Cosh``, ``Tanh``, ``Abs``, ``Min``, ``Max``, ``Ceil``,
``Floor``; ``Atan2`` at points only.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydrake.symbolic import Expression, Variable

from ofrl_drake.errors import SMOOTH_FORMS, ModelError, OfrlError

__all__ = [
    "ExpressionEvaluator",
    "Interval",
    "IntervalDomainError",
    "UnsupportedExpressionError",
    "as_expression",
    "evaluate",
    "evaluate_interval",
]

_TWO_PI = 2.0 * np.pi
# Rounding slack, in units in the last place: IEEE + - * / and sqrt are
# correctly rounded (1 ulp covers them); libm functions are not (numpy's are
# accurate to a few ulp), so they get a generous margin.
_ULP_ARITH = 1
_ULP_LIBM = 8
# Beyond this magnitude, range reduction of sin/cos/tan is not trusted.
_TRIG_MAX_ARG = 1e12
_MAX = float(np.finfo(float).max)
_MAX_ULP = 2.0**971  # the gap below the largest double
# Constants that are multiples of 2**-10 of magnitude at most 2**20 are taken as
# exact; every other stored constant is widened by one ulp each way.
_EXACT_SCALE = 1024.0
_EXACT_MAX = 2.0**20

_POINT_KINDS = {
    "Constant",
    "Var",
    "Add",
    "Mul",
    "Div",
    "Pow",
    "Exp",
    "Log",
    "Sqrt",
    "Sin",
    "Cos",
    "Tan",
    "Asin",
    "Acos",
    "Atan",
    "Atan2",
    "Sinh",
    "Cosh",
    "Tanh",
    "Abs",
    "Min",
    "Max",
    "Ceil",
    "Floor",
}
_INTERVAL_KINDS = _POINT_KINDS - {"Atan2"}
#: Functions defined on part of the real line only (``Pow``: with an exponent
#: that is not a constant integer, on ``x >= 0`` only).
_PARTIAL_KINDS = {"Log", "Sqrt", "Asin", "Acos", "Pow"}


class UnsupportedExpressionError(OfrlError):
    """An expression uses a function this module cannot evaluate."""


class IntervalDomainError(OfrlError):
    """A function is evaluated on an interval wholly outside its domain."""


@dataclass(frozen=True)
class Interval:
    """Element-wise intervals ``[lo, hi]`` (arrays of one shape).

    Attributes
    ----------
    lo, hi : ndarray
        Lower and upper ends; ``lo <= hi`` element-wise.
    """

    lo: np.ndarray
    hi: np.ndarray

    def contains(self, values: np.ndarray) -> np.ndarray:
        """Element-wise ``lo <= values <= hi`` (broadcasting)."""
        return (self.lo <= values) & (values <= self.hi)

    @property
    def width(self) -> np.ndarray:
        """``hi - lo``."""
        return self.hi - self.lo

    def __add__(self, other: Interval | float) -> Interval:
        """Outward-rounded sum."""
        with np.errstate(all="ignore"):  # see "Floating-point flags" below
            return _i_add(self, _as_interval(other))

    def __mul__(self, other: Interval | float) -> Interval:
        """Outward-rounded product."""
        with np.errstate(all="ignore"):
            return _i_mul(self, _as_interval(other))

    __radd__ = __add__
    __rmul__ = __mul__

    def __neg__(self) -> Interval:
        """``[-hi, -lo]`` (exact)."""
        return Interval(-np.asarray(self.hi), -np.asarray(self.lo))

    def __sub__(self, other: Interval | float) -> Interval:
        """Outward-rounded difference."""
        return self + (-_as_interval(other))

    def __rsub__(self, other: Interval | float) -> Interval:
        return _as_interval(other) + (-self)

    def __truediv__(self, other: Interval | float) -> Interval:
        """Outward-rounded quotient (the whole line where the divisor holds 0)."""
        with np.errstate(all="ignore"):
            return _i_div(self, _as_interval(other))

    def __getitem__(self, index: Any) -> Interval:
        """The intervals ``lo[index]``, ``hi[index]``."""
        return Interval(np.asarray(self.lo)[index], np.asarray(self.hi)[index])

    def reshape(self, shape: tuple[int, ...]) -> Interval:
        """Both ends reshaped to ``shape``."""
        return Interval(np.reshape(self.lo, shape), np.reshape(self.hi, shape))

    @property
    def mag(self) -> np.ndarray:
        """``max(|lo|, |hi|)``, the largest magnitude in each interval (exact)."""
        return np.maximum(np.abs(self.lo), np.abs(self.hi))


def _as_interval(v: Interval | float) -> Interval:
    if isinstance(v, Interval):
        return v
    c = np.asarray(v, dtype=float)
    return Interval(c, c)


# --------------------------------------------------------------------- rounding
# Floating-point flags: overflow to inf, inf - inf and 0 * inf are expected in
# the kernels below and handled where they arise, so numpy's warnings (or a
# user's ``np.seterr(all="raise")``) must not fire. The two entry points,
# ``ExpressionEvaluator.interval`` and the ``Interval`` operators, set
# ``np.errstate(all="ignore")`` once around the whole computation; the kernels
# assume it (one context per call, not one per array operation).
def _ulp(x: np.ndarray) -> np.ndarray:
    """The gap from finite ``x`` to the next double away from zero (``2**971`` at the top)."""
    return np.minimum(np.abs(np.spacing(x)), _MAX_ULP)


def _down(x: np.ndarray, ulps: int) -> np.ndarray:
    """Round a computed lower end down by ``ulps`` units in the last place.

    A lower end that overflowed to +inf becomes the largest finite double (the
    exact value is larger still, but it is a real number, so +inf would be
    wrong); -inf stays; a NaN, which the kernels never produce, would become -inf.
    """
    x = np.asarray(x, dtype=float)
    if np.isfinite(x).all():  # the common case, without the special values
        return x - ulps * _ulp(x)
    x = np.where(x == np.inf, _MAX, np.where(np.isnan(x), -np.inf, x))
    return np.where(np.isfinite(x), x - ulps * _ulp(x), x)


def _up(x: np.ndarray, ulps: int) -> np.ndarray:
    """Round a computed upper end up (the mirror image of :func:`_down`)."""
    x = np.asarray(x, dtype=float)
    if np.isfinite(x).all():
        return x + ulps * _ulp(x)
    x = np.where(x == -np.inf, -_MAX, np.where(np.isnan(x), np.inf, x))
    return np.where(np.isfinite(x), x + ulps * _ulp(x), x)


def _is_exact_constant(c: float) -> bool:
    """Whether a stored constant is taken as exact (see the module docstring)."""
    return abs(c) <= _EXACT_MAX and float(c * _EXACT_SCALE).is_integer()


def _constant_interval(c: float) -> tuple[float, float]:
    """The enclosure of a constant as Drake stores it (Drake keeps NaN as its own kind)."""
    if c == np.inf:
        return _MAX, np.inf
    if c == -np.inf:
        return -np.inf, -_MAX
    if _is_exact_constant(c):
        return c, c
    return float(np.nextafter(c, -np.inf)), float(np.nextafter(c, np.inf))


# ------------------------------------------------------------ interval kernels
def _i_add(a: Interval, b: Interval) -> Interval:
    # Ends are never +inf (lower) or -inf (upper), so inf - inf cannot occur. A sum
    # that rounds to 0 is exact (with gradual underflow, x + y is 0 only if x = -y):
    # it stays 0, so that an argument whose least value is 0 (x**2 + y**2 at the
    # origin) is not pushed below a function's domain by a rounding that never was.
    lo = a.lo + b.lo
    hi = a.hi + b.hi
    return Interval(
        np.where(lo == 0.0, 0.0, _down(lo, _ULP_ARITH)),
        np.where(hi == 0.0, 0.0, _up(hi, _ULP_ARITH)),
    )


def _i_scale(c_lo: float, c_hi: float, a: Interval) -> Interval:
    """``[c_lo, c_hi] * a``, with a fast path for an exact finite constant."""
    if c_lo == c_hi == 0.0:
        zero = np.zeros(np.broadcast(a.lo, a.hi).shape)
        return Interval(zero, zero.copy())
    if c_lo != c_hi or not np.isfinite(c_lo):
        return _i_mul(Interval(np.asarray(c_lo), np.asarray(c_hi)), a)
    c = c_lo
    lo, hi = (c * a.lo, c * a.hi) if c > 0 else (c * a.hi, c * a.lo)
    if abs(c) == 1.0:  # a sign change is exact
        return Interval(lo, hi)
    return Interval(_down(lo, _ULP_ARITH), _up(hi, _ULP_ARITH))


def _i_mul(a: Interval, b: Interval) -> Interval:
    # 0 * inf is 0 for sets (IEEE 1788), not NaN.
    p = [_nan_to(x * y, 0.0) for x in (a.lo, a.hi) for y in (b.lo, b.hi)]
    lo = np.minimum(np.minimum(p[0], p[1]), np.minimum(p[2], p[3]))
    hi = np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))
    return Interval(_down(lo, _ULP_ARITH), _up(hi, _ULP_ARITH))


def _nan_to(x: np.ndarray, value: float) -> np.ndarray:
    return np.where(np.isnan(x), value, x)


def _i_div(a: Interval, b: Interval) -> Interval:
    """``a / b`` by the IEEE 1788 case table, one correctly rounded quotient per end.

    Never through ``1 / b`` (which overflows for ``|b| < 2**-1024`` although
    ``a / b`` may be moderate). The ends are never +inf (lower) or -inf (upper),
    so no quotient below is ``inf / inf`` or ``0 / 0``. Values at ``b = 0`` are
    undefined; a divisor box ``[0, 0]`` gives the whole line.
    """
    alo, ahi, blo, bhi = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (a.lo, a.hi, b.lo, b.hi))
    )
    a_ge0, a_le0 = alo >= 0, ahi <= 0
    # b > 0
    pos_lo = np.where(a_ge0, alo / bhi, alo / blo)
    pos_hi = np.where(ahi >= 0, ahi / blo, ahi / bhi)
    # b < 0
    neg_lo = np.where(ahi >= 0, ahi / bhi, ahi / blo)
    neg_hi = np.where(a_ge0, alo / blo, alo / bhi)
    # b = [0, bhi] with bhi > 0, and b = [blo, 0] with blo < 0
    zp_lo = np.where(a_ge0, alo / bhi, -np.inf)
    zp_hi = np.where(a_le0, ahi / bhi, np.inf)
    zn_lo = np.where(a_le0, ahi / blo, -np.inf)
    zn_hi = np.where(a_ge0, alo / blo, np.inf)
    b_pos, b_neg = blo > 0, bhi < 0
    b_zp = (blo == 0) & (bhi > 0)
    b_zn = (bhi == 0) & (blo < 0)
    a_zero = a_ge0 & a_le0
    lo = np.select([b_pos, b_neg, a_zero, b_zp, b_zn], [pos_lo, neg_lo, 0.0, zp_lo, zn_lo], -np.inf)
    hi = np.select([b_pos, b_neg, a_zero, b_zp, b_zn], [pos_hi, neg_hi, 0.0, zp_hi, zn_hi], np.inf)
    return Interval(_down(lo, _ULP_ARITH), _up(hi, _ULP_ARITH))


def _i_monotone(fn: Any, a: Interval, increasing: bool = True) -> Interval:
    f_lo, f_hi = fn(a.lo), fn(a.hi)
    if not increasing:
        f_lo, f_hi = f_hi, f_lo
    return Interval(_down(f_lo, _ULP_LIBM), _up(f_hi, _ULP_LIBM))


def _i_cosh(a: Interval) -> Interval:
    """``cosh``: even, increasing on ``[0, inf)``, at least 1."""
    f_lo, f_hi = np.cosh(a.lo), np.cosh(a.hi)
    straddles = (a.lo < 0) & (a.hi > 0)
    lo = np.where(straddles, 1.0, _down(np.minimum(f_lo, f_hi), _ULP_LIBM))
    hi = _up(np.maximum(f_lo, f_hi), _ULP_LIBM)
    return Interval(np.maximum(lo, 1.0), hi)


def _i_abs(a: Interval) -> Interval:
    """``|x|``, exact (no rounding)."""
    m_lo, m_hi = np.abs(a.lo), np.abs(a.hi)
    straddles = (a.lo < 0) & (a.hi > 0)
    return Interval(np.where(straddles, 0.0, np.minimum(m_lo, m_hi)), np.maximum(m_lo, m_hi))


def _contains_grid_point(lo: np.ndarray, hi: np.ndarray, offset: float, period: float):
    """Whether ``[lo, hi]`` may contain ``offset + k * period`` for an integer k.

    The test is done with a slack of a few ulps of ``x / period`` so that it can
    only err towards "yes" (which widens, never narrows, the enclosure).
    """
    t_lo = (lo - offset) / period
    t_hi = (hi - offset) / period
    slack_lo = 8 * np.finfo(float).eps * (np.abs(t_lo) + 1.0)
    slack_hi = 8 * np.finfo(float).eps * (np.abs(t_hi) + 1.0)
    return np.floor(t_hi + slack_hi) >= np.ceil(t_lo - slack_lo)


def _i_trig(kind: str, a: Interval) -> Interval:
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, dtype=float), np.asarray(a.hi, dtype=float))
    fn = np.sin if kind == "Sin" else np.cos
    max_at = 0.5 * np.pi if kind == "Sin" else 0.0
    min_at = -0.5 * np.pi if kind == "Sin" else np.pi
    bad = (
        ~np.isfinite(lo)
        | ~np.isfinite(hi)
        | (hi - lo >= _TWO_PI)
        | (np.abs(lo) > _TRIG_MAX_ARG)
        | (np.abs(hi) > _TRIG_MAX_ARG)
    )
    lo_s = np.where(bad, 0.0, lo)
    hi_s = np.where(bad, 0.0, hi)
    f_lo, f_hi = fn(lo_s), fn(hi_s)
    has_max = _contains_grid_point(lo_s, hi_s, max_at, _TWO_PI)
    has_min = _contains_grid_point(lo_s, hi_s, min_at, _TWO_PI)
    out_lo = np.where(has_min, -1.0, _down(np.minimum(f_lo, f_hi), _ULP_LIBM))
    out_hi = np.where(has_max, 1.0, _up(np.maximum(f_lo, f_hi), _ULP_LIBM))
    out_lo = np.where(bad, -1.0, np.maximum(out_lo, -1.0))
    out_hi = np.where(bad, 1.0, np.minimum(out_hi, 1.0))
    return Interval(out_lo, out_hi)


def _i_tan(a: Interval) -> Interval:
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, dtype=float), np.asarray(a.hi, dtype=float))
    bad = (
        ~np.isfinite(lo)
        | ~np.isfinite(hi)
        | (hi - lo >= np.pi)
        | (np.abs(lo) > _TRIG_MAX_ARG)
        | (np.abs(hi) > _TRIG_MAX_ARG)
    )
    lo_s = np.where(bad, 0.0, lo)
    hi_s = np.where(bad, 0.0, hi)
    pole = bad | _contains_grid_point(lo_s, hi_s, 0.5 * np.pi, np.pi)
    out_lo = np.where(pole, -np.inf, _down(np.tan(lo_s), _ULP_LIBM))
    out_hi = np.where(pole, np.inf, _up(np.tan(hi_s), _ULP_LIBM))
    return Interval(out_lo, out_hi)


def _domain_error(
    name: str, lo: np.ndarray, hi: np.ndarray, outside: np.ndarray, domain: str, expr: str
):
    idx = np.flatnonzero(np.broadcast_to(outside, np.shape(lo)).ravel())[0]
    return IntervalDomainError(
        f"{name} is evaluated on [{np.ravel(lo)[idx]:.6g}, {np.ravel(hi)[idx]:.6g}], "
        f"wholly outside its domain {domain}, in expression {expr}; shrink the box "
        "so the function is defined on it."
    )


def _restrict(a: Interval, lower: float, upper: float, name: str, expr: str):
    """Intersect ``a`` with a function's domain ``[lower, upper]``."""
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, dtype=float), np.asarray(a.hi, dtype=float))
    outside = (hi < lower) | (lo > upper)
    if np.any(outside):
        raise _domain_error(name, lo, hi, outside, f"[{lower:g}, {upper:g}]", expr)
    return Interval(np.maximum(lo, lower), np.minimum(hi, upper))


def _i_pow_int(a: Interval, k: Any) -> Interval:
    """``x**k`` for integer-valued (finite, any magnitude) ``k``, a scalar or an array.

    ``pow`` is evaluated at the ends directly (never as ``1 / x**|k|``, which
    would lose a result near the overflow threshold), and the piecewise
    monotonicity of ``x**k`` picks the ends. At a pole (``0`` in the box for
    ``k < 0``) the side of the pole the box reaches is unbounded.
    """
    lo, hi, kk = np.broadcast_arrays(
        np.asarray(a.lo, dtype=float), np.asarray(a.hi, dtype=float), np.asarray(k, dtype=float)
    )
    p_lo = np.power(lo, kk)
    p_hi = np.power(hi, kk)
    odd = np.fmod(kk, 2.0) != 0
    k_pos, k_neg = kk > 0, kk < 0
    straddles = (lo < 0) & (hi > 0)
    has_zero = (lo <= 0) & (hi >= 0)
    # Even k: x**k is |x|**k, monotone in |x|.
    even_lo = np.where(k_pos & straddles, 0.0, np.minimum(p_lo, p_hi))
    even_hi = np.where(k_neg & has_zero, np.inf, np.maximum(p_lo, p_hi))
    # Odd k > 0: increasing. Odd k < 0: decreasing on each side of the pole.
    right = (lo == 0) & (hi > 0)  # only the right side of the pole
    left = (hi == 0) & (lo < 0)  # only the left side
    odd_lo = np.select([k_pos, ~has_zero, right], [p_lo, p_hi, p_hi], -np.inf)
    odd_hi = np.select([k_pos, ~has_zero, left], [p_hi, p_lo, p_lo], np.inf)
    out_lo = _down(np.where(odd, odd_lo, even_lo), _ULP_LIBM)
    out_hi = _up(np.where(odd, odd_hi, even_hi), _ULP_LIBM)
    out_lo = np.where(odd, out_lo, np.maximum(out_lo, 0.0))  # even powers are >= 0
    zero = kk == 0  # x**0 is 1 everywhere (numpy and Drake: also at 0 and inf)
    return Interval(np.where(zero, 1.0, out_lo), np.where(zero, 1.0, out_hi))


def _corner_powers(x1, x2, y1, y2) -> tuple[np.ndarray, np.ndarray]:
    """Min and max of ``x**y`` over the corners of ``[x1, x2] x [y1, y2]``, ``x >= 0``.

    For ``x >= 0``, ``x**y`` is monotone in ``x`` for fixed ``y`` and monotone
    in ``y`` for fixed ``x`` (in directions that may depend on the other), so
    its extremes over the rectangle are at corners.
    """
    c = [np.power(x, y) for x in (x1, x2) for y in (y1, y2)]
    lo = np.minimum(np.minimum(c[0], c[1]), np.minimum(c[2], c[3]))
    hi = np.maximum(np.maximum(c[0], c[1]), np.maximum(c[2], c[3]))
    return lo, hi


def _i_pow(base: Interval, exponent: Interval, expr: str) -> Interval:
    """``x**y`` wherever numpy and Drake define it.

    Exactly integer constant exponents go to :func:`_i_pow_int`. Otherwise the
    box splits into ``x >= 0``, where ``x**y`` is defined for every ``y`` (and is
    enclosed by its corner values), and ``x < 0``, where it is defined only at
    integer ``y``: for one integer ``k`` in ``[y1, y2]`` that is ``x**k``, for
    several it is bounded by ``+-max |x|**y`` over the corners. A box where
    neither part has a defined value raises :class:`IntervalDomainError`.
    """
    y_lo = np.asarray(exponent.lo, dtype=float)
    y_hi = np.asarray(exponent.hi, dtype=float)
    if y_lo.ndim == 0 and y_lo == y_hi and np.isfinite(y_lo) and float(y_lo).is_integer():
        return _i_pow_int(base, float(y_lo))
    lo, hi, y1, y2 = np.broadcast_arrays(
        np.asarray(base.lo, dtype=float), np.asarray(base.hi, dtype=float), y_lo, y_hi
    )
    # x >= 0 (adding 0.0 turns -0.0 into +0.0, so pow(0, odd negative) is +inf).
    has_pos = hi >= 0
    p_lo, p_hi = _corner_powers(np.maximum(lo, 0.0) + 0.0, np.maximum(hi, 0.0) + 0.0, y1, y2)
    p_lo = np.maximum(_down(p_lo, _ULP_LIBM), 0.0)
    p_hi = _up(p_hi, _ULP_LIBM)
    # x < 0, integer exponents only.
    k1, k2 = np.ceil(y1), np.floor(y2)
    has_neg = (lo < 0) & (k1 <= k2)
    single = has_neg & (k1 == k2)
    neg_hi = np.minimum(hi, 0.0)
    one = _i_pow_int(Interval(lo, neg_hi), np.where(single, k1, 1.0))
    _, m = _corner_powers(-neg_hi + 0.0, np.maximum(-lo, 0.0), k1, k2)
    m = _up(m, _ULP_LIBM)
    n_lo = np.where(single, one.lo, -m)
    n_hi = np.where(single, one.hi, m)
    defined = has_pos | has_neg
    if not np.all(defined):
        raise _domain_error(
            "pow", lo, hi, ~defined, "(x >= 0, or x < 0 with an integer exponent)", expr
        )
    out_lo = np.minimum(np.where(has_pos, p_lo, np.inf), np.where(has_neg, n_lo, np.inf))
    out_hi = np.maximum(np.where(has_pos, p_hi, -np.inf), np.where(has_neg, n_hi, -np.inf))
    return Interval(out_lo, out_hi)


def _i_log(a: Interval, expr: str) -> Interval:
    d = _restrict(a, 0.0, np.inf, "log", expr)
    return _i_monotone(np.log, d)


# ------------------------------------------------------------------- the nodes
@dataclass(frozen=True)
class _Node:
    kind: str
    args: tuple[int, ...]
    value: float = 0.0  # the constant of Constant, Add and Mul nodes
    text: str = ""
    lo: float = 0.0  # the enclosure of ``value`` (see _constant_interval)
    hi: float = 0.0


def as_expression(e: Any) -> Expression:
    """``e`` as a Drake ``Expression``: an expression as it is, a variable or a number wrapped."""
    if isinstance(e, Expression):
        return e
    if isinstance(e, Variable):
        return Expression(e)
    return Expression(float(e))


class ExpressionEvaluator:
    """Evaluate an array of symbolic expressions at many points or boxes at once.

    The expressions are converted once into a flat list of nodes (shared
    subexpressions are evaluated once); each evaluation then runs one numpy
    operation per node over all points or boxes, with no Python loop over them.

    Parameters
    ----------
    expressions : array_like of Expression or float
        Any shape ``S``; plain numbers are allowed.
    variables : iterable of pydrake.symbolic.Variable
        The ``n`` variables, in the order of the rows of the points and boxes.

    Raises
    ------
    UnsupportedExpressionError
        If an expression uses a function outside the supported kinds (listed in
        the module docstring) or a variable not in ``variables``.

    Examples
    --------
    >>> import numpy as np
    >>> from pydrake.symbolic import MakeVectorVariable
    >>> x = MakeVectorVariable(1, "x")
    >>> ev = ExpressionEvaluator([np.sin(x[0]) ** 2], x)
    >>> ev(np.array([[0.0, np.pi / 2]])).round(12).tolist()
    [[0.0, 1.0]]
    >>> box = ev.interval(np.array([0.0]), np.array([np.pi]))
    >>> bool(box.lo[0] <= 0.0 and box.hi[0] >= 1.0)
    True
    """

    def __init__(self, expressions: Any, variables: Iterable[Variable]) -> None:
        exprs = np.asarray(expressions, dtype=object)
        self.shape: tuple[int, ...] = exprs.shape
        self.variables: tuple[Variable, ...] = tuple(variables)
        self._var_index = {v.get_id(): i for i, v in enumerate(self.variables)}
        self._nodes: list[_Node] = []
        self._memo: dict[str, list[tuple[Expression, int]]] = {}
        self._outputs = [self._add(as_expression(e)) for e in exprs.ravel()]
        self._kinds = {node.kind for node in self._nodes}
        self._uses: list[frozenset[int]] = []
        for node in self._nodes:
            if node.kind == "Var":
                self._uses.append(frozenset({int(node.value)}))
            else:
                used: frozenset[int] = frozenset()
                for arg in node.args:
                    used = used | self._uses[arg]
                self._uses.append(used)
        # The nodes applying a function defined on part of the line (possibly_undefined).
        self._partial = [i for i, node in enumerate(self._nodes) if self._is_partial(node)]

    # ---------------------------------------------------------------- building
    def _add(self, e: Expression) -> int:
        key = e.to_string()
        for other, index in self._memo.get(key, []):
            if other.EqualTo(e):
                return index
        kind = e.get_kind().name
        # Unapply returns (function, args), the args a float, a Variable or Expressions
        # by kind; pydrake's stub types it as object.
        raw_args: list[Any]
        _, raw_args = e.Unapply()  # type: ignore[misc]  # pydrake stub: Unapply() -> object
        if kind == "IfThenElse":
            raise UnsupportedExpressionError(
                f"unsupported function IfThenElse, a branch, in expression {key}. In a "
                "Jacobian of f or g, np.abs, np.maximum, np.minimum or np.sign inside f or g "
                "create such branches (|x| is not differentiable at 0, so its derivative is a "
                "branch), while f and g must be continuously differentiable on the box, for "
                f"jacobian_method 'sampled' and 'certified' alike. {SMOOTH_FORMS}; or give "
                "Jacobian bounds found by hand (design_observer's bounds=JacobianBounds(...))."
            )
        if kind not in _POINT_KINDS:
            raise UnsupportedExpressionError(
                f"unsupported function {kind} in expression {key}; supported: "
                f"{', '.join(sorted(_POINT_KINDS))}. Rewrite f and g with these."
            )
        value = 0.0
        args: list[int] = []
        if kind == "Constant":
            value = float(raw_args[0])
        elif kind == "Var":
            var = raw_args[0]
            if var.get_id() not in self._var_index:
                raise UnsupportedExpressionError(
                    f"expression {key} uses variable {var.get_name()}, which is "
                    f"not one of {[v.get_name() for v in self.variables]}."
                )
            value = float(self._var_index[var.get_id()])
        elif kind in ("Add", "Mul"):
            value = float(raw_args[0])
            args = [self._add(as_expression(a)) for a in raw_args[1:]]
        else:
            args = [self._add(as_expression(a)) for a in raw_args]
        index = len(self._nodes)
        c_lo, c_hi = (value, value) if kind == "Var" else _constant_interval(value)
        self._nodes.append(_Node(kind, tuple(args), value, key, c_lo, c_hi))
        self._memo.setdefault(key, []).append((e, index))
        return index

    # -------------------------------------------------------------- inspection
    def variables_used(self) -> list[tuple[int, ...]]:
        """For each expression (flattened), the indices of the variables it uses."""
        return [tuple(sorted(self._uses[i])) for i in self._outputs]

    @property
    def nodes(self) -> tuple[Any, ...]:
        """The merged expression graph, children before parents.

        Each node has ``kind`` (Drake's expression kind), ``args`` (indices of
        its children in this tuple), ``value`` (the constant of ``Constant``,
        ``Add`` and ``Mul`` nodes, the variable index of ``Var``), ``lo``,
        ``hi`` (the enclosure of that constant) and ``text``.
        """
        return tuple(self._nodes)

    @property
    def outputs(self) -> tuple[int, ...]:
        """The node of each expression (flattened), an index into :attr:`nodes`."""
        return tuple(self._outputs)

    @property
    def node_count(self) -> int:
        """Nodes of the merged expression graph: one array per node per evaluation."""
        return len(self._nodes)

    @property
    def supports_intervals(self) -> bool:
        """Whether :meth:`interval` can enclose every expression (no ``Atan2``)."""
        return not self._kinds - _INTERVAL_KINDS

    def is_constant(self) -> np.ndarray:
        """Boolean array of shape ``S``: which expressions use no variable."""
        flags = [not self._uses[i] for i in self._outputs]
        return np.array(flags, dtype=bool).reshape(self.shape)

    # ------------------------------------------------------------ point values
    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Evaluate at the columns of ``points``.

        Parameters
        ----------
        points : ndarray, shape (n,) or (n, N)
            One point, or ``N`` points as columns.

        Returns
        -------
        ndarray
            Shape ``S`` for one point, ``S + (N,)`` for ``N`` points. Points where
            a function is undefined give NaN (no warning).
        """
        X = np.asarray(points, dtype=float)
        single = X.ndim == 1
        X2 = X[:, None] if single else X
        if X2.ndim != 2 or X2.shape[0] != len(self.variables):
            raise ModelError(
                f"points must have {len(self.variables)} rows (one per variable); "
                f"got shape {X.shape}."
            )
        N = X2.shape[1]
        vals: list[np.ndarray] = []
        with np.errstate(all="ignore"):
            for node in self._nodes:
                vals.append(self._point(node, vals, X2))
            out = np.stack([np.broadcast_to(vals[i], (N,)) for i in self._outputs])
        out = out.reshape((*self.shape, N))
        return out[..., 0] if single else out

    @staticmethod
    def _point(node: _Node, vals: list[np.ndarray], X: np.ndarray) -> np.ndarray:
        k = node.kind
        a = [vals[i] for i in node.args]
        if k == "Constant":
            return np.asarray(node.value)
        if k == "Var":
            return X[int(node.value)]
        if k == "Add":
            total = np.asarray(node.value)
            for term in a:
                total = total + term
            return total
        if k == "Mul":
            prod = np.asarray(node.value)
            for factor in a:
                prod = prod * factor
            return prod
        binary = {
            "Div": np.divide,
            "Pow": np.power,
            "Min": np.minimum,
            "Max": np.maximum,
            "Atan2": np.arctan2,
        }
        if k in binary:
            return binary[k](a[0], a[1])
        unary = {
            "Exp": np.exp,
            "Log": np.log,
            "Sqrt": np.sqrt,
            "Sin": np.sin,
            "Cos": np.cos,
            "Tan": np.tan,
            "Asin": np.arcsin,
            "Acos": np.arccos,
            "Atan": np.arctan,
            "Sinh": np.sinh,
            "Cosh": np.cosh,
            "Tanh": np.tanh,
            "Abs": np.abs,
            "Ceil": np.ceil,
            "Floor": np.floor,
        }
        return unary[k](a[0])

    # --------------------------------------------------------- interval values
    def interval(self, lower: np.ndarray, upper: np.ndarray) -> Interval:
        """Enclose the expressions over boxes ``lower <= x <= upper``.

        Parameters
        ----------
        lower, upper : ndarray, shape (n,) or (n, B)
            One box, or ``B`` boxes as columns.

        Returns
        -------
        Interval
            ``lo``, ``hi`` of shape ``S`` (one box) or ``S + (B,)``; the value of
            each expression at every point of a box where it is defined lies in
            its interval (:meth:`possibly_undefined` tells where that may not
            be every point).

        Raises
        ------
        UnsupportedExpressionError
            If an expression uses ``Atan2`` (enclosed at points only).
        IntervalDomainError
            If a function is applied on a box wholly outside its domain.
        ModelError
            If the boxes have the wrong shape, ``lower > upper``, a NaN corner,
            or contain no real point (``lower = +inf`` or ``upper = -inf``).
        """
        vals, B, single = self._node_intervals(lower, upper)
        out_lo = np.stack([np.broadcast_to(vals[i].lo, (B,)) for i in self._outputs])
        out_hi = np.stack([np.broadcast_to(vals[i].hi, (B,)) for i in self._outputs])
        out_lo = out_lo.reshape((*self.shape, B))
        out_hi = out_hi.reshape((*self.shape, B))
        if single:
            return Interval(out_lo[..., 0], out_hi[..., 0])
        return Interval(out_lo, out_hi)

    def _node_intervals(
        self, lower: np.ndarray, upper: np.ndarray
    ) -> tuple[list[Interval], int, bool]:
        """Every node's enclosure over the boxes, their number, and whether one was given."""
        if not self.supports_intervals:
            node = next(n for n in self._nodes if n.kind not in _INTERVAL_KINDS)
            raise UnsupportedExpressionError(
                f"interval arithmetic does not support {node.kind} (in expression "
                f"{node.text}); supported: {', '.join(sorted(_INTERVAL_KINDS))}. "
                "Use method='sampled' or rewrite f and g with these functions."
            )

        lo = np.asarray(lower, dtype=float)
        hi = np.asarray(upper, dtype=float)
        single = lo.ndim == 1
        lo2 = lo[:, None] if single else lo
        hi2 = hi[:, None] if single else hi
        n = len(self.variables)
        if lo2.shape != hi2.shape or lo2.shape[0] != n:
            raise ModelError(
                f"lower and upper must both have shape ({n},) or ({n}, B); got "
                f"{lo.shape} and {hi.shape}."
            )
        if np.any(np.isnan(lo2)) or np.any(np.isnan(hi2)):
            raise ModelError("box corners must not be NaN.")
        if np.any(lo2 > hi2):
            raise ModelError("every box needs lower <= upper.")
        if np.any(lo2 == np.inf) or np.any(hi2 == -np.inf):
            raise ModelError(
                "every box must contain a real point: lower = +inf or upper = -inf is empty."
            )
        vals: list[Interval] = []
        with np.errstate(all="ignore"):  # see "Floating-point flags" above the kernels
            for node in self._nodes:
                vals.append(self._interval(node, vals, lo2, hi2))
        return vals, lo2.shape[1], single

    @property
    def has_partial_functions(self) -> bool:
        """Whether a function defined on part of the real line only is applied.

        ``log``, ``sqrt``, ``asin``, ``acos``, and ``pow`` with an exponent that
        is not a constant integer; without them an expression is defined
        wherever its divisions and integer powers have no pole.
        """
        return bool(self._partial)

    def _is_partial(self, node: _Node) -> bool:
        if node.kind != "Pow":
            return node.kind in _PARTIAL_KINDS
        exponent = self._nodes[node.args[1]]
        return not (
            exponent.kind == "Constant"
            and exponent.lo == exponent.hi
            and np.isfinite(exponent.value)
            and float(exponent.value).is_integer()
        )

    def possibly_undefined(
        self, lower: np.ndarray, upper: np.ndarray
    ) -> tuple[np.ndarray, list[str]]:
        """Boxes where a function may be applied outside its domain.

        :meth:`interval` encloses a function defined on part of the line (see
        :attr:`has_partial_functions`) over the part of a box where it is
        defined. This tells, per box, whether that part may be less than the
        whole box: an argument's enclosure reaches outside the function's
        domain (``log`` of a box reaching 0 or below, ``sqrt`` below 0,
        ``asin``/``acos`` beyond [-1, 1], a non-integer power of a base below
        0). Enclosures overestimate, so a flagged box may be defined all the
        same; an unflagged one is proven defined everywhere (poles of
        divisions and negative integer powers aside: those give unbounded
        enclosures).

        Parameters
        ----------
        lower, upper : ndarray
            The boxes, as for :meth:`interval`.

        Returns
        -------
        flagged : ndarray of bool, shape (B,)
            Whether each box may hold a point where some expression is undefined.
        reasons : list of str
            For each flagged box in order, the first such function, its
            argument's enclosure and the expression.

        Raises
        ------
        IntervalDomainError
            If a function is applied on a box wholly outside its domain.
        UnsupportedExpressionError, ModelError
            As :meth:`interval`.
        """
        vals, B, _ = self._node_intervals(lower, upper)
        flagged = np.zeros(B, dtype=bool)
        first = np.full(B, -1)
        for index in self._partial:
            node = self._nodes[index]
            arg = vals[node.args[0]]
            lo = np.broadcast_to(arg.lo, (B,))
            hi = np.broadcast_to(arg.hi, (B,))
            if node.kind == "Log":
                bad = lo <= 0.0
            elif node.kind in ("Asin", "Acos"):
                bad = (lo < -1.0) | (hi > 1.0)
            else:  # Sqrt; Pow with an exponent that may not be an integer
                bad = lo < 0.0
            first = np.where(bad & ~flagged, index, first)
            flagged |= bad
        reasons = []
        for b in np.flatnonzero(flagged):
            node = self._nodes[int(first[b])]
            arg = vals[node.args[0]]
            lo_b = float(np.broadcast_to(arg.lo, (B,))[b])
            hi_b = float(np.broadcast_to(arg.hi, (B,))[b])
            reasons.append(
                f"{node.kind.lower()} of [{lo_b:.6g}, {hi_b:.6g}] in expression {node.text}"
            )
        return flagged, reasons

    @staticmethod
    def _interval(node: _Node, vals: list[Interval], lo: np.ndarray, hi: np.ndarray) -> Interval:
        k = node.kind
        a = [vals[i] for i in node.args]
        if k == "Constant":
            return Interval(np.asarray(node.lo), np.asarray(node.hi))
        if k == "Var":
            i = int(node.value)
            return Interval(lo[i], hi[i])
        if k == "Add":
            if node.value == 0.0:
                total, terms = a[0], a[1:]
            else:
                total, terms = Interval(np.asarray(node.lo), np.asarray(node.hi)), a
            for term in terms:
                total = _i_add(total, term)
            return total
        if k == "Mul":
            if not a:
                return Interval(np.asarray(node.lo), np.asarray(node.hi))
            prod = _i_scale(node.lo, node.hi, a[0])
            for factor in a[1:]:
                prod = _i_mul(prod, factor)
            return prod
        if k == "Div":
            return _i_div(a[0], a[1])
        if k == "Pow":
            return _i_pow(a[0], a[1], node.text)
        if k in ("Min", "Max"):
            op = np.minimum if k == "Min" else np.maximum
            return Interval(op(a[0].lo, a[1].lo), op(a[0].hi, a[1].hi))
        if k in ("Sin", "Cos"):
            return _i_trig(k, a[0])
        if k == "Tan":
            return _i_tan(a[0])
        if k == "Log":
            return _i_log(a[0], node.text)
        if k == "Sqrt":
            d = _restrict(a[0], 0.0, np.inf, "sqrt", node.text)
            r = _i_monotone(np.sqrt, d)
            return Interval(np.maximum(r.lo, 0.0), r.hi)
        if k in ("Asin", "Acos"):
            d = _restrict(a[0], -1.0, 1.0, k.lower(), node.text)
            fn = np.arcsin if k == "Asin" else np.arccos
            return _i_monotone(fn, d, increasing=k == "Asin")
        if k == "Cosh":
            return _i_cosh(a[0])
        if k == "Abs":
            return _i_abs(a[0])
        if k in ("Ceil", "Floor"):  # exact, and monotone
            rounding = np.ceil if k == "Ceil" else np.floor
            return Interval(rounding(a[0].lo), rounding(a[0].hi))
        monotone = {
            "Exp": np.exp,
            "Atan": np.arctan,
            "Sinh": np.sinh,
            "Tanh": np.tanh,
        }
        out = _i_monotone(monotone[k], a[0])
        if k == "Exp":
            return Interval(np.maximum(out.lo, 0.0), out.hi)
        if k == "Tanh":
            return Interval(np.maximum(out.lo, -1.0), np.minimum(out.hi, 1.0))
        if k == "Atan":
            half = np.nextafter(0.5 * np.pi, np.inf)
            return Interval(np.maximum(out.lo, -half), np.minimum(out.hi, half))
        return out


def evaluate(expression: Any, variables: Sequence[Variable], points: np.ndarray) -> np.ndarray:
    """Evaluate expression(s) at the columns of ``points`` (see ExpressionEvaluator).

    Parameters
    ----------
    expression : Expression or array_like of Expression
        What to evaluate.
    variables : sequence of Variable
        The variables, in the order of the rows of ``points``.
    points : ndarray, shape (n,) or (n, N)
        The points.

    Returns
    -------
    ndarray
        Shape ``S`` or ``S + (N,)``, ``S`` the shape of ``expression``.
    """
    return ExpressionEvaluator(expression, variables)(points)


def evaluate_interval(
    expression: Any,
    variables: Sequence[Variable],
    lower: np.ndarray,
    upper: np.ndarray,
) -> Interval:
    """Enclose expression(s) over the box(es) ``[lower, upper]``.

    Parameters
    ----------
    expression : Expression or array_like of Expression
        What to enclose.
    variables : sequence of Variable
        The variables, in the order of the rows of ``lower`` and ``upper``.
    lower, upper : ndarray, shape (n,) or (n, B)
        The box(es).

    Returns
    -------
    Interval
        See :meth:`ExpressionEvaluator.interval`.
    """
    return ExpressionEvaluator(expression, variables).interval(lower, upper)
