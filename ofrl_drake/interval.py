"""Vectorized point and interval evaluation of ``pydrake.symbolic`` expressions.

Drake's own ``Expression.Evaluate`` works one point at a time. This module walks
an expression tree once (``Expression.get_kind()`` / ``Expression.Unapply()``),
turns it into a flat list of nodes with shared subexpressions merged, and then
evaluates that list with numpy operations on whole arrays:

* :meth:`ExpressionEvaluator.__call__` evaluates at ``N`` points at once, and
* :meth:`ExpressionEvaluator.interval` evaluates over ``B`` axis-aligned boxes
  at once, in interval arithmetic.

The interval arithmetic is *outward-safe*: every computed lower end is rounded
down and every upper end rounded up (by a few units in the last place, more for
library functions than for the correctly rounded ``+ - * /``), ``sin``/``cos``
find their extrema by range reduction with a slack that can only add an
extremum, and ``tan`` returns the whole line when a pole may lie inside. So the
returned interval contains the value of the expression at every point of the
box. Functions that are defined on part of a box only (``log``, ``sqrt``,
``asin``, ``acos``, a real power) are enclosed over that part, as in IEEE 1788;
a box wholly outside the domain raises :class:`IntervalDomainError`.

Supported kinds: ``Constant``, ``Var``, ``Add``, ``Mul``, ``Div``, ``Pow``
(integer and real exponents, variable exponents on positive bases), ``Exp``,
``Log``, ``Sqrt``, ``Sin``, ``Cos``, ``Tan``, ``Asin``, ``Acos``, ``Atan``,
``Sinh``, ``Cosh``, ``Tanh``, ``Abs``, ``Min``, ``Max``, ``Ceil``, ``Floor``;
``Atan2`` at points only. Anything else raises
:class:`UnsupportedExpressionError`, naming the function and the expression.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydrake.symbolic import Expression, Variable

from ofrl_drake.errors import ModelError, OfrlError

__all__ = [
    "ExpressionEvaluator",
    "Interval",
    "IntervalDomainError",
    "UnsupportedExpressionError",
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
        return _i_add(self, _as_interval(other))

    def __mul__(self, other: Interval | float) -> Interval:
        """Outward-rounded product."""
        return _i_mul(self, _as_interval(other))

    __radd__ = __add__
    __rmul__ = __mul__


def _as_interval(v: Interval | float) -> Interval:
    if isinstance(v, Interval):
        return v
    c = np.asarray(v, dtype=float)
    return Interval(c, c)


# --------------------------------------------------------------------- rounding
def _down(x: np.ndarray, ulps: int) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    with np.errstate(invalid="ignore"):
        step = np.abs(np.spacing(x))
    return np.where(np.isfinite(x), x - ulps * step, x)


def _up(x: np.ndarray, ulps: int) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    with np.errstate(invalid="ignore"):
        step = np.abs(np.spacing(x))
    return np.where(np.isfinite(x), x + ulps * step, x)


def _nan_to(x: np.ndarray, value: float) -> np.ndarray:
    return np.where(np.isnan(x), value, x)


# ------------------------------------------------------------ interval kernels
def _i_add(a: Interval, b: Interval) -> Interval:
    with np.errstate(invalid="ignore"):
        lo = _nan_to(a.lo + b.lo, -np.inf)
        hi = _nan_to(a.hi + b.hi, np.inf)
    return Interval(_down(lo, _ULP_ARITH), _up(hi, _ULP_ARITH))


def _i_scale(c: float, a: Interval) -> Interval:
    if c == 0.0:
        zero = np.zeros(np.broadcast(a.lo, a.hi).shape)
        return Interval(zero, zero.copy())
    with np.errstate(invalid="ignore", over="ignore"):
        lo, hi = (c * a.lo, c * a.hi) if c > 0 else (c * a.hi, c * a.lo)
    return Interval(_down(lo, _ULP_ARITH), _up(hi, _ULP_ARITH))


def _i_mul(a: Interval, b: Interval) -> Interval:
    with np.errstate(invalid="ignore", over="ignore"):
        # 0 * inf is 0 for sets (IEEE 1788), not NaN.
        p = [_nan_to(x * y, 0.0) for x in (a.lo, a.hi) for y in (b.lo, b.hi)]
    lo = np.minimum(np.minimum(p[0], p[1]), np.minimum(p[2], p[3]))
    hi = np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))
    return Interval(_down(lo, _ULP_ARITH), _up(hi, _ULP_ARITH))


def _i_recip(a: Interval) -> Interval:
    lo, hi = np.broadcast_arrays(a.lo, a.hi)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        r_lo = 1.0 / hi
        r_hi = 1.0 / lo
    pos = lo > 0
    neg = hi < 0
    # [0, b] -> [1/b, inf]; [a, 0] -> [-inf, 1/a]; a straddle -> everything.
    lo_zero = (lo == 0) & (hi > 0)
    hi_zero = (hi == 0) & (lo < 0)
    out_lo = np.where(pos | neg | lo_zero, r_lo, -np.inf)
    out_hi = np.where(pos | neg | hi_zero, r_hi, np.inf)
    return Interval(_down(out_lo, _ULP_ARITH), _up(out_hi, _ULP_ARITH))


def _i_monotone(fn: Any, a: Interval, increasing: bool = True) -> Interval:
    with np.errstate(over="ignore", invalid="ignore"):
        f_lo, f_hi = fn(a.lo), fn(a.hi)
    if not increasing:
        f_lo, f_hi = f_hi, f_lo
    return Interval(_down(f_lo, _ULP_LIBM), _up(f_hi, _ULP_LIBM))


def _i_even(fn: Any, a: Interval) -> Interval:
    """For ``fn`` even and increasing on ``[0, inf)`` (``cosh``, ``abs``)."""
    with np.errstate(over="ignore"):
        f_lo, f_hi = fn(a.lo), fn(a.hi)
        f0 = fn(np.zeros_like(np.asarray(a.lo, dtype=float)))
    straddles = (a.lo < 0) & (a.hi > 0)
    lo = np.where(straddles, f0, np.minimum(f_lo, f_hi))
    hi = np.maximum(f_lo, f_hi)
    return Interval(_down(lo, _ULP_LIBM), _up(hi, _ULP_LIBM))


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


def _restrict(a: Interval, lower: float, upper: float, name: str, expr: str):
    """Intersect ``a`` with a function's domain ``[lower, upper]``."""
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, dtype=float), np.asarray(a.hi, dtype=float))
    outside = (hi < lower) | (lo > upper)
    if np.any(outside):
        idx = np.flatnonzero(outside.ravel())[0]
        raise IntervalDomainError(
            f"{name} is evaluated on [{lo.ravel()[idx]:.6g}, "
            f"{hi.ravel()[idx]:.6g}], wholly outside its domain "
            f"[{lower:g}, {upper:g}], in expression {expr}; shrink the box so "
            "the function is defined on it."
        )
    return Interval(np.maximum(lo, lower), np.minimum(hi, upper))


def _i_pow_int(a: Interval, p: int) -> Interval:
    if p == 0:
        one = np.ones(np.broadcast(a.lo, a.hi).shape)
        return Interval(one, one.copy())
    k = abs(p)
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, dtype=float), np.asarray(a.hi, dtype=float))
    with np.errstate(over="ignore"):
        p_lo = np.power(lo, k)
        p_hi = np.power(hi, k)
    if k % 2 == 1:
        out = Interval(_down(p_lo, _ULP_LIBM), _up(p_hi, _ULP_LIBM))
    else:
        straddles = (lo < 0) & (hi > 0)
        low = _down(np.minimum(p_lo, p_hi), _ULP_LIBM)
        # x**k >= 0 for even k: keep the exact 0 and never round below it.
        low = np.where(straddles, 0.0, np.maximum(low, 0.0))
        out = Interval(low, _up(np.maximum(p_lo, p_hi), _ULP_LIBM))
    return out if p > 0 else _i_recip(out)


def _i_pow_real(a: Interval, p: float, expr: str) -> Interval:
    d = _restrict(a, 0.0, np.inf, f"pow(., {p:g})", expr)
    with np.errstate(divide="ignore", over="ignore"):
        p_lo, p_hi = np.power(d.lo, p), np.power(d.hi, p)
    if p < 0:
        p_lo, p_hi = p_hi, p_lo
    return Interval(np.maximum(_down(p_lo, _ULP_LIBM), 0.0), _up(p_hi, _ULP_LIBM))


def _i_pow(base: Interval, exponent: Interval, expr: str) -> Interval:
    e_lo, e_hi = np.asarray(exponent.lo), np.asarray(exponent.hi)
    if e_lo.ndim == 0 and e_lo == e_hi and np.isfinite(e_lo):
        p = float(e_lo)
        if p == np.round(p) and abs(p) <= 2**31:
            return _i_pow_int(base, int(p))
        return _i_pow_real(base, p, expr)
    # General case x**y = exp(y log x), defined for x > 0.
    log_base = _i_log(base, expr)
    return _i_monotone(np.exp, _i_mul(exponent, log_base))


def _i_log(a: Interval, expr: str) -> Interval:
    d = _restrict(a, 0.0, np.inf, "log", expr)
    with np.errstate(divide="ignore"):
        return _i_monotone(np.log, d)


# ------------------------------------------------------------------- the nodes
@dataclass(frozen=True)
class _Node:
    kind: str
    args: tuple[int, ...]
    value: float = 0.0  # the constant of Constant, Add and Mul nodes
    text: str = ""


class ExpressionEvaluator:
    """Evaluate an array of symbolic expressions at many points or boxes at once.

    The expressions are converted once into a flat list of nodes (shared
    subexpressions are evaluated once); each evaluation then runs one numpy
    operation per node over all points or boxes, with no Python loop over them.

    Parameters
    ----------
    expressions : array_like of Expression or float
        Any shape ``S``; plain numbers are allowed.
    variables : sequence of pydrake.symbolic.Variable
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

    def __init__(self, expressions: Any, variables: Sequence[Variable]) -> None:
        exprs = np.asarray(expressions, dtype=object)
        self.shape: tuple[int, ...] = exprs.shape
        self.variables: tuple[Variable, ...] = tuple(variables)
        self._var_index = {v.get_id(): i for i, v in enumerate(self.variables)}
        self._nodes: list[_Node] = []
        self._memo: dict[str, list[tuple[Expression, int]]] = {}
        self._outputs = [self._add(self._as_expression(e)) for e in exprs.ravel()]
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

    # ---------------------------------------------------------------- building
    @staticmethod
    def _as_expression(e: Any) -> Expression:
        if isinstance(e, Expression):
            return e
        if isinstance(e, Variable):
            return Expression(e)
        return Expression(float(e))

    def _add(self, e: Expression) -> int:
        key = e.to_string()
        for other, index in self._memo.get(key, []):
            if other.EqualTo(e):
                return index
        kind = e.get_kind().name
        _, raw_args = e.Unapply()
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
            args = [self._add(self._as_expression(a)) for a in raw_args[1:]]
        else:
            args = [self._add(self._as_expression(a)) for a in raw_args]
        index = len(self._nodes)
        self._nodes.append(_Node(kind, tuple(args), value, key))
        self._memo.setdefault(key, []).append((e, index))
        return index

    # -------------------------------------------------------------- inspection
    def variables_used(self) -> list[tuple[int, ...]]:
        """For each expression (flattened), the indices of the variables it uses."""
        return [tuple(sorted(self._uses[i])) for i in self._outputs]

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
            each expression at every point of a box lies in its interval.

        Raises
        ------
        UnsupportedExpressionError
            If an expression uses ``Atan2`` (enclosed at points only).
        IntervalDomainError
            If a function is applied on a box wholly outside its domain.
        """
        unsupported = self._kinds - _INTERVAL_KINDS
        if unsupported:
            node = next(n for n in self._nodes if n.kind in unsupported)
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
        if np.any(lo2 > hi2):
            raise ModelError("every box needs lower <= upper.")
        B = lo2.shape[1]
        vals: list[Interval] = []
        for node in self._nodes:
            vals.append(self._interval(node, vals, lo2, hi2))
        out_lo = np.stack([np.broadcast_to(vals[i].lo, (B,)) for i in self._outputs])
        out_hi = np.stack([np.broadcast_to(vals[i].hi, (B,)) for i in self._outputs])
        out_lo = out_lo.reshape((*self.shape, B))
        out_hi = out_hi.reshape((*self.shape, B))
        if single:
            return Interval(out_lo[..., 0], out_hi[..., 0])
        return Interval(out_lo, out_hi)

    @staticmethod
    def _interval(node: _Node, vals: list[Interval], lo: np.ndarray, hi: np.ndarray) -> Interval:
        k = node.kind
        a = [vals[i] for i in node.args]
        if k == "Constant":
            c = np.asarray(node.value)
            return Interval(c, c)
        if k == "Var":
            i = int(node.value)
            return Interval(lo[i], hi[i])
        if k == "Add":
            c = np.asarray(node.value)
            total = Interval(c, c)
            for term in a:
                total = _i_add(total, term)
            return total
        if k == "Mul":
            c = np.asarray(node.value)
            if not a:
                return Interval(c, c)
            prod = _i_scale(node.value, a[0])
            for factor in a[1:]:
                prod = _i_mul(prod, factor)
            return prod
        if k == "Div":
            return _i_mul(a[0], _i_recip(a[1]))
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
        if k in ("Cosh", "Abs"):
            fn = np.cosh if k == "Cosh" else np.abs
            out = _i_even(fn, a[0])
            return Interval(np.maximum(out.lo, 0.0 if k == "Abs" else 1.0), out.hi)
        monotone = {
            "Exp": np.exp,
            "Atan": np.arctan,
            "Sinh": np.sinh,
            "Tanh": np.tanh,
            "Ceil": np.ceil,
            "Floor": np.floor,
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


def evaluate(expression: Any, variables: Sequence[Variable], points: np.ndarray):
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
