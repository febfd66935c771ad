"""Second-order interval Taylor forms of symbolic expressions, by forward differentiation.

Over a box ``X`` with centre ``c`` and ``h = x - c``, a twice continuously
differentiable ``J`` obeys (Taylor's theorem with the Lagrange remainder)

    J(x) = J(c) + grad J(c) . h + 1/2 h^T Hess J(xi) h,   xi on [c, x] in X,

so ``J(c) + grad J(c) . [h] + 1/2 [h]^T [Hess J](X) [h]`` encloses ``J`` over
``X``: the Taylor form. Its overestimation shrinks with the cube of the box
width, against the square for the mean-value form ``J(c) + [grad J](X) . [h]``
and the width itself for the natural interval extension. That matters for
expressions whose variables repeat and cancel, such as a rotation's
``sin(yaw)**2 + cos(yaw)**2`` (Drake's ``QuadrotorPlant``: its attitude
accelerations do not depend on the yaw, but their expressions name it dozens
of times).

:class:`TaylorEvaluator` computes the value, the gradient and the Hessian of
every expression over many boxes at once, in interval arithmetic, by forward
differentiation along the node list of an
:class:`~ofrl_drake.interval.ExpressionEvaluator` (shared subexpressions once):
each node carries its value, its gradient along the ``L`` chosen variables
and the upper triangle of its Hessian, and each kind of node applies the sum,
product or chain rule with the derivatives of its function enclosed over the
argument's interval. Drake's ``Differentiate`` is never called, so no
expression is expanded (symbolically, the Hessians of the quadrotor's
Jacobian take minutes).

Soundness: every operation is the outward-rounded interval operation of
:mod:`ofrl_drake.interval`. Taylor's theorem needs ``J`` twice continuously
differentiable on the box, so a box on which a function is not (an argument of
``log``, ``sqrt``, a fractional power not inside ``(0, inf)``, of ``asin`` or
``acos`` not inside ``(-1, 1)``, a divisor or an argument of ``tan`` that may
be at a pole) gets the whole line as its Taylor form; the kinds ``Abs``,
``Min``, ``Max``, ``Ceil``, ``Floor`` and a non-constant exponent, which are not
differentiable everywhere, are refused when the evaluator is built
(:class:`~ofrl_drake.interval.UnsupportedExpressionError`), so a caller falls
back to the other forms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ofrl_drake.interval import (
    ExpressionEvaluator,
    Interval,
    UnsupportedExpressionError,
    _i_add,
    _i_cosh,
    _i_div,
    _i_monotone,
    _i_mul,
    _i_pow,
    _i_pow_int,
    _i_scale,
    _i_trig,
)

__all__ = ["TAYLOR_KINDS", "Jet", "TaylorEvaluator", "taylor_form"]

_MINUS_ONE = Interval(np.asarray(-1.0), np.asarray(-1.0))

#: The node kinds :class:`TaylorEvaluator` differentiates (``Pow`` with a constant exponent).
#: Written out rather than derived from the interval kinds, since each needs its own
#: derivative rule here; tests/test_interval_taylor.py checks it against the kinds whose
#: derivatives it tests, and that every other interval kind is refused.
TAYLOR_KINDS = frozenset(
    {
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
        "Sinh",
        "Cosh",
        "Tanh",
    }
)


@dataclass(frozen=True)
class Jet:
    """Value, gradient and Hessian (upper triangle) of expressions over boxes.

    Attributes
    ----------
    value : Interval
        Shape ``S + (B,)``.
    gradient : Interval
        Shape ``S + (L, B)``: the derivative along each of the ``L`` variables.
    hessian : Interval
        Shape ``S + (P, B)``, ``P = L (L + 1) / 2``: the second derivatives
        ``(a, b)``, ``a <= b``, in the order of :attr:`TaylorEvaluator.pairs`.
    valid : ndarray of bool
        Shape ``(B,)``: False where some function is not twice continuously
        differentiable on the box (there the derivatives are not enclosures).
    """

    value: Interval
    gradient: Interval
    hessian: Interval
    valid: np.ndarray


class _Jet:
    """One node's jet: value (B,), and along its variables ``vars`` (local indices,
    sorted) its gradient ``g`` (len(vars), B) and Hessian ``h`` (pairs of vars, B);
    ``g``/``h`` None for zero."""

    __slots__ = ("g", "h", "v", "vars")

    def __init__(
        self,
        v: Interval,
        vars: tuple[int, ...] = (),
        g: Interval | None = None,
        h: Interval | None = None,
    ) -> None:
        self.v, self.vars, self.g, self.h = v, vars, g, h


def _neg(a: Interval) -> Interval:
    return Interval(-np.asarray(a.hi), -np.asarray(a.lo))


# The derivative arrays ((rows, B) per node) take most of the work, so their
# sums and products use leaner kernels than ofrl_drake.interval's. A correctly
# rounded + or * of finite doubles is exact up to a relative error u = 2**-53
# (plus 2**-1075 absolute below the normal range), so moving each end outward
# by |x| 2**-51 + 2**-1022 covers it even though that step is itself rounded
# (it moves at least 3 u |x| for |x| >= 2**-971, and 2**-1022 covers the rest).
# Anything not finite (overflow, 0 * inf, an infinite end) goes to the
# library kernels, which handle every special value.
_REL = 2.0**-51
_ABS = 2.0**-1022


def _add(a: Interval, b: Interval) -> Interval:
    """Outward-rounded ``a + b``."""
    lo = a.lo + b.lo
    hi = a.hi + b.hi
    lo = lo - (np.abs(lo) * _REL + _ABS)
    hi = hi + (np.abs(hi) * _REL + _ABS)
    if np.isfinite(lo).all() and np.isfinite(hi).all():
        return Interval(lo, hi)
    return _i_add(a, b)


def _mul(a: Interval, b: Interval) -> Interval:
    """Outward-rounded ``a * b``."""
    p0, p1, p2, p3 = (x * y for x in (a.lo, a.hi) for y in (b.lo, b.hi))
    lo = np.minimum(np.minimum(p0, p1), np.minimum(p2, p3))
    hi = np.maximum(np.maximum(p0, p1), np.maximum(p2, p3))
    lo = lo - (np.abs(lo) * _REL + _ABS)
    hi = hi + (np.abs(hi) * _REL + _ABS)
    if np.isfinite(lo).all() and np.isfinite(hi).all():
        return Interval(lo, hi)
    return _i_mul(a, b)


def _scale(c_lo: float, c_hi: float, a: Interval) -> Interval:
    """Outward-rounded ``[c_lo, c_hi] * a`` for a constant."""
    if c_lo == c_hi and np.isfinite(c_lo):
        lo, hi = (c_lo * a.lo, c_lo * a.hi) if c_lo >= 0 else (c_lo * a.hi, c_lo * a.lo)
        lo = lo - (np.abs(lo) * _REL + _ABS)
        hi = hi + (np.abs(hi) * _REL + _ABS)
        if np.isfinite(lo).all() and np.isfinite(hi).all():
            return Interval(lo, hi)
    elif np.isfinite(c_lo) and np.isfinite(c_hi):
        return _mul(Interval(np.asarray(c_lo), np.asarray(c_hi)), a)
    return _i_scale(c_lo, c_hi, a)


def _add_opt(a: Interval | None, b: Interval | None) -> Interval | None:
    if a is None:
        return b
    if b is None:
        return a
    return _add(a, b)


def _mul_opt(a: Interval, b: Interval | None) -> Interval | None:
    """``a * b`` (``a`` of shape (B,) broadcast over the rows of ``b``), None for zero."""
    if b is None:
        return None
    return _mul(Interval(np.asarray(a.lo)[None], np.asarray(a.hi)[None]), b)


def _pairs(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows ``a``, ``b`` and the diagonal flags of the pairs ``a <= b`` of ``k`` variables."""
    pairs = [(a, b) for a in range(k) for b in range(a, k)]
    ia = np.array([a for a, _ in pairs], dtype=int)
    ib = np.array([b for _, b in pairs], dtype=int)
    return ia, ib, ia == ib


class TaylorEvaluator:
    """Interval values, gradients and Hessians of expressions over many boxes at once.

    Each node is differentiated along the variables it depends on only, so
    the work per node grows with the square of that number, not of ``L``.

    Parameters
    ----------
    expressions : array_like of Expression or float
        Any shape ``S``.
    variables : sequence of pydrake.symbolic.Variable
        The ``n`` variables, in the order of the rows of the boxes.
    along : sequence of int
        The indices (into ``variables``) of the ``L`` variables to differentiate
        along. The others are held as intervals but not differentiated, so the
        expressions must not depend on them for :func:`taylor_form` to be an
        enclosure.

    Raises
    ------
    UnsupportedExpressionError
        If an expression uses a kind outside :data:`TAYLOR_KINDS` or a power
        with a non-constant exponent (or as for ``ExpressionEvaluator``).

    Examples
    --------
    >>> import numpy as np
    >>> from pydrake.symbolic import MakeVectorVariable, sin, cos
    >>> x = MakeVectorVariable(1, "x")
    >>> ev = TaylorEvaluator([sin(x[0]) ** 2 + cos(x[0]) ** 2], x, [0])
    >>> enc = taylor_form(ev, np.array([[-0.1]]), np.array([[0.1]]))
    >>> bool(enc.lo[0, 0] > 0.999 and enc.hi[0, 0] < 1.001)
    True
    """

    def __init__(self, expressions: Any, variables: Any, along: Any) -> None:
        self.values = ExpressionEvaluator(expressions, variables)
        self.along = np.array(sorted({int(j) for j in along}), dtype=int)
        L = self.along.size
        self._local = {int(j): a for a, j in enumerate(self.along)}
        #: The Hessian entries ``(a, b)``, ``a <= b``, in the order of :attr:`Jet.hessian`.
        self.pairs = [(a, b) for a in range(L) for b in range(a, L)]
        self._ia, self._ib, self._diagonal = _pairs(L)
        nodes = self.values.nodes
        for node in nodes:
            if node.kind not in TAYLOR_KINDS:
                raise UnsupportedExpressionError(
                    f"the Taylor form does not support {node.kind} (in expression "
                    f"{node.text}); supported: {', '.join(sorted(TAYLOR_KINDS))}."
                )
            if node.kind == "Pow" and nodes[node.args[1]].kind != "Constant":
                raise UnsupportedExpressionError(
                    f"the Taylor form supports constant exponents only; got {node.text}."
                )
        # The local variables of each node, and the index maps used to lift a
        # child's rows (and pairs) into its parent's.
        self._vars: list[tuple[int, ...]] = []
        for node in nodes:
            if node.kind == "Var":
                i = int(node.value)
                self._vars.append((self._local[i],) if i in self._local else ())
            else:
                used: set[int] = set()
                for a in node.args:
                    used.update(self._vars[a])
                self._vars.append(tuple(sorted(used)))
        self._maps: dict[
            tuple[tuple[int, ...], tuple[int, ...]], tuple[np.ndarray, np.ndarray]
        ] = {}
        self._pair_cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    @property
    def shape(self) -> tuple[int, ...]:
        """The shape ``S`` of the expressions."""
        return self.values.shape

    def jet(self, lower: np.ndarray, upper: np.ndarray, order: int = 2) -> Jet:
        """Enclose the value, gradient and Hessian of every expression over each box.

        Parameters
        ----------
        lower, upper : ndarray, shape (n, B)
            ``B`` boxes (a degenerate box ``[c, c]`` encloses the derivatives at
            the point ``c``).
        order : {1, 2}
            1 skips the Hessians (returned as zeros, not enclosures).

        Returns
        -------
        Jet
            The enclosures; :attr:`Jet.valid` flags the boxes where they hold.
            The values are the natural interval extension, exactly as
            :meth:`ExpressionEvaluator.interval` computes them.
        """
        lo = np.asarray(lower, dtype=float)
        hi = np.asarray(upper, dtype=float)
        B = lo.shape[1]
        L, P = self.along.size, len(self.pairs)
        valid = np.ones(B, dtype=bool)
        jets: list[_Jet] = []
        nodes = self.values.nodes
        with np.errstate(all="ignore"):
            for index, node in enumerate(nodes):
                jets.append(self._node(index, node, jets, nodes, lo, hi, valid, order))
            outs = [jets[i] for i in self.values.outputs]
            E = len(outs)
            value = Interval(
                np.stack([np.broadcast_to(j.v.lo, (B,)) for j in outs]),
                np.stack([np.broadcast_to(j.v.hi, (B,)) for j in outs]),
            )
            g_lo, g_hi = np.zeros((E, L, B)), np.zeros((E, L, B))
            h_lo, h_hi = np.zeros((E, P, B)), np.zeros((E, P, B))
            for e, j in enumerate(outs):
                if j.g is not None:
                    rows = list(j.vars)
                    g_lo[e, rows], g_hi[e, rows] = j.g.lo, j.g.hi
                if j.h is not None:
                    _, where = self._map(j.vars, tuple(range(L)))
                    h_lo[e, where], h_hi[e, where] = j.h.lo, j.h.hi
        shape = self.shape
        return Jet(
            value.reshape((*shape, B)),
            Interval(g_lo.reshape((*shape, L, B)), g_hi.reshape((*shape, L, B))),
            Interval(h_lo.reshape((*shape, P, B)), h_hi.reshape((*shape, P, B))),
            valid,
        )

    # ------------------------------------------------------------- bookkeeping
    def _pairs_of(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if k not in self._pair_cache:
            self._pair_cache[k] = _pairs(k)
        return self._pair_cache[k]

    def _map(self, sub: tuple[int, ...], full: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Rows of ``sub``'s variables in ``full``'s, and of ``sub``'s pairs in ``full``'s."""
        key = (sub, full)
        if key not in self._maps:
            pos = {v: i for i, v in enumerate(full)}
            rows = np.array([pos[v] for v in sub], dtype=int)
            k = len(full)
            index = {(a, b): i for i, (a, b) in enumerate(zip(*self._pairs_of(k)[:2], strict=True))}
            ia, ib, _ = self._pairs_of(len(sub))
            pairs = np.array(
                [
                    index[(min(rows[a], rows[b]), max(rows[a], rows[b]))]
                    for a, b in zip(ia, ib, strict=True)
                ],
                dtype=int,
            )
            self._maps[key] = (rows, pairs)
        return self._maps[key]

    def _lift(
        self, jet: _Jet, full: tuple[int, ...], B: int
    ) -> tuple[Interval | None, Interval | None]:
        """``jet``'s gradient and Hessian in the rows (pairs) of ``full``; None for zero."""
        if jet.vars == full:
            return jet.g, jet.h
        rows, pairs = self._map(jet.vars, full)
        g = h = None
        if jet.g is not None:
            lo_, hi_ = np.zeros((len(full), B)), np.zeros((len(full), B))
            lo_[rows], hi_[rows] = jet.g.lo, jet.g.hi
            g = Interval(lo_, hi_)
        if jet.h is not None:
            P = len(full) * (len(full) + 1) // 2
            lo_, hi_ = np.zeros((P, B)), np.zeros((P, B))
            lo_[pairs], hi_[pairs] = jet.h.lo, jet.h.hi
            h = Interval(lo_, hi_)
        return g, h

    # ------------------------------------------------------------------ rules
    def _node(
        self,
        index: int,
        node: Any,
        jets: list[_Jet],
        nodes: tuple[Any, ...],
        lo: np.ndarray,
        hi: np.ndarray,
        valid: np.ndarray,
        order: int,
    ) -> _Jet:
        k = node.kind
        full = self._vars[index]
        B = lo.shape[1]
        args = [jets[i] for i in node.args]
        if k == "Var":
            value = Interval(lo[int(node.value)], hi[int(node.value)])
            if not full:
                return _Jet(value)
            one = np.ones((1, B))
            return _Jet(value, full, Interval(one, one.copy()))
        if k == "Add":
            g: Interval | None
            h: Interval | None
            if node.value == 0.0:
                v, terms = args[0].v, args[1:]
                g, h = self._lift(args[0], full, B)
            else:
                v, terms = Interval(np.asarray(node.lo), np.asarray(node.hi)), args
                g = h = None
            for t in terms:
                tg, th = self._lift(t, full, B)
                v, g, h = _i_add(v, t.v), _add_opt(g, tg), _add_opt(h, th)
            return _Jet(v, full, g, h)
        if k == "Mul" and args:
            c_lo, c_hi = node.lo, node.hi
            first = args[0]
            out = _Jet(
                _i_scale(c_lo, c_hi, first.v),
                first.vars,
                None if first.g is None else _scale(c_lo, c_hi, first.g),
                None if first.h is None else _scale(c_lo, c_hi, first.h),
            )
            for factor in args[1:]:
                out = self._product(out, factor, B, order)
            return out
        # Every other kind: the value as ExpressionEvaluator encloses it.
        children = {i: jets[i].v for i in node.args}  # indexed like the node list
        value = ExpressionEvaluator._interval(node, children, lo, hi)  # type: ignore[arg-type]
        if not full:
            return _Jet(value)
        if k == "Div":
            u, w = args
            _invalid(valid, (w.v.lo <= 0) & (w.v.hi >= 0))
            r = _i_div(_ones(w.v), w.v)
            if not w.vars:  # a constant divisor scales the derivatives
                return _Jet(value, u.vars, _mul_opt(r, u.g), _mul_opt(r, u.h))
            d1 = _neg(_i_mul(r, r))  # (1/w)' = -1/w^2
            d2 = _i_scale(-2.0, -2.0, _i_mul(d1, r))  # (1/w)'' = 2/w^3
            quotient = self._product(u, self._chain(w, r, d1, d2, order), B, order)
            return _Jet(value, quotient.vars, quotient.g, quotient.h)
        x = args[0].v
        if k == "Pow":
            f1, f2 = self._power_derivatives(x, nodes[node.args[1]], node.text, valid)
        else:
            f1, f2 = self._derivatives(k, x, value, valid)
        return self._chain(args[0], value, f1, f2, order)

    def _product(self, a: _Jet, b: _Jet, B: int, order: int) -> _Jet:
        value = _i_mul(a.v, b.v)
        if not a.vars and not b.vars:
            return _Jet(value)
        full = tuple(sorted(set(a.vars) | set(b.vars)))
        ag, ah = self._lift(a, full, B)
        bg, bh = self._lift(b, full, B)
        g = _add_opt(_mul_opt(a.v, bg), _mul_opt(b.v, ag))
        h = None
        if order == 2:
            h = _add_opt(_mul_opt(a.v, bh), _mul_opt(b.v, ah))
            if ag is not None and bg is not None:
                ia, ib, _ = self._pairs_of(len(full))
                cross = _add(_mul(ag[ia], bg[ib]), _mul(ag[ib], bg[ia]))
                h = _add_opt(h, cross)
        return _Jet(value, full, g, h)

    def _chain(self, w: _Jet, f0: Interval, f1: Interval, f2: Interval, order: int) -> _Jet:
        """``f(w)`` from ``f``, ``f'`` and ``f''`` enclosed over ``w``'s value."""
        g = _mul_opt(f1, w.g)
        h = None
        if order == 2:
            h = _mul_opt(f1, w.h)
            if w.g is not None:
                ia, ib, diag = self._pairs_of(len(w.vars))
                sq = _mul(w.g[ia], w.g[ib])
                # On the diagonal g_a * g_a >= 0.
                sq = Interval(np.where(diag[:, None], np.maximum(sq.lo, 0.0), sq.lo), sq.hi)
                h = _add_opt(h, _mul_opt(f2, sq))
        return _Jet(f0, w.vars, g, h)

    @staticmethod
    def _power_derivatives(
        x: Interval, exponent: Any, text: str, valid: np.ndarray
    ) -> tuple[Interval, Interval]:
        """``k x**(k-1)`` and ``k (k-1) x**(k-2)`` for the constant exponent ``k``."""
        k = Interval(np.asarray(exponent.lo), np.asarray(exponent.hi))
        if exponent.lo == exponent.hi and float(exponent.lo).is_integer():
            kk = float(exponent.lo)
            if kk < 0:
                _invalid(valid, (x.lo <= 0) & (x.hi >= 0))
            f1 = _i_scale(kk, kk, _i_pow_int(x, kk - 1.0))
            f2 = _i_scale(kk * (kk - 1.0), kk * (kk - 1.0), _i_pow_int(x, kk - 2.0))
            return f1, f2
        _invalid(valid, x.lo <= 0)
        tiny = np.finfo(float).tiny  # used only where x > 0 (elsewhere the box is invalid)
        pos = Interval(np.maximum(x.lo, tiny), np.maximum(x.hi, tiny))
        km1 = _i_add(k, _MINUS_ONE)
        km2 = _i_add(km1, _MINUS_ONE)
        f1 = _i_mul(k, _i_pow(pos, km1, text))
        f2 = _i_mul(_i_mul(k, km1), _i_pow(pos, km2, text))
        return f1, f2

    @staticmethod
    def _derivatives(
        k: str, x: Interval, value: Interval, valid: np.ndarray
    ) -> tuple[Interval, Interval]:
        """``f'`` and ``f''`` of a unary function over ``x`` (``value`` is ``f(x)``)."""
        one = _ones(x)
        if k == "Sin":
            return _i_trig("Cos", x), _neg(_i_trig("Sin", x))
        if k == "Cos":
            return _neg(_i_trig("Sin", x)), _neg(_i_trig("Cos", x))
        if k == "Exp":
            return value, value
        if k == "Sinh":
            return _i_cosh(x), value
        if k == "Cosh":
            return _i_monotone(np.sinh, x), value
        if k == "Log":
            _invalid(valid, x.lo <= 0)
            f1 = _i_div(one, x)
            return f1, _neg(_i_mul(f1, f1))
        if k == "Sqrt":
            _invalid(valid, x.lo <= 0)
            f1 = _i_div(_i_scale(0.5, 0.5, one), value)  # 1 / (2 sqrt x)
            return f1, _neg(_i_div(f1, _i_scale(2.0, 2.0, x)))  # -1 / (4 x sqrt x)
        if k == "Tan":
            _invalid(valid, ~(np.isfinite(value.lo) & np.isfinite(value.hi)))
            f1 = _i_add(one, _i_pow_int(value, 2.0))  # 1 + tan^2
            return f1, _i_scale(2.0, 2.0, _i_mul(value, f1))
        if k == "Tanh":
            f1 = _i_add(one, _neg(_i_pow_int(value, 2.0)))  # 1 - tanh^2
            return f1, _i_scale(-2.0, -2.0, _i_mul(value, f1))
        if k == "Atan":
            f1 = _i_div(one, _i_add(one, _i_pow_int(x, 2.0)))
            return f1, _i_scale(-2.0, -2.0, _i_mul(x, _i_pow_int(f1, 2.0)))
        # Asin, Acos: 1 / sqrt(1 - x^2) and x / (1 - x^2)^(3/2), negated for acos.
        _invalid(valid, (x.lo <= -1.0) | (x.hi >= 1.0))
        inside = Interval(np.clip(x.lo, -1.0, 1.0), np.clip(x.hi, -1.0, 1.0))
        s = _i_add(one, _neg(_i_pow_int(inside, 2.0)))
        root = _i_monotone(np.sqrt, Interval(np.maximum(s.lo, 0.0), np.maximum(s.hi, 0.0)))
        f1 = _i_div(one, root)
        f2 = _i_mul(inside, _i_pow_int(f1, 3.0))
        return (_neg(f1), _neg(f2)) if k == "Acos" else (f1, f2)


def _ones(x: Interval) -> Interval:
    shape = np.broadcast(np.asarray(x.lo), np.asarray(x.hi)).shape
    return Interval(np.ones(shape), np.ones(shape))


def _invalid(valid: np.ndarray, where: Any) -> None:
    """Clear ``valid`` (in place) on the boxes ``where`` is True."""
    valid &= ~np.broadcast_to(np.asarray(where, dtype=bool), valid.shape)


def _h(lower: np.ndarray, upper: np.ndarray, along: np.ndarray) -> Interval:
    """``X - c`` along the variables, rounded outward: shape (L, B)."""
    c = 0.5 * (lower + upper)
    return Interval(
        np.nextafter(lower[along] - c[along], -np.inf),
        np.nextafter(upper[along] - c[along], np.inf),
    )


def _sum_rows(a: Interval) -> Interval:
    """Outward-rounded sum over the second-to-last axis."""
    total = a[..., 0, :]
    for r in range(1, a.lo.shape[-2]):
        total = _i_add(total, a[..., r, :])
    return total


def taylor_from_jets(
    evaluator: TaylorEvaluator,
    boxes: Jet,
    centres: Jet,
    lower: np.ndarray,
    upper: np.ndarray,
) -> Interval:
    """The Taylor form over boxes from the jets over them and over their centres.

    Parameters
    ----------
    evaluator : TaylorEvaluator
        The expressions.
    boxes : Jet
        :meth:`TaylorEvaluator.jet` over the ``B`` boxes (order 2).
    centres : Jet
        :meth:`TaylorEvaluator.jet` at their centres, as degenerate boxes
        (order 1 is enough).
    lower, upper : ndarray, shape (n, B)
        The boxes.

    Returns
    -------
    Interval
        Shape ``S + (B,)``; the whole line where a jet is not valid.
    """
    if evaluator.along.size == 0:
        return boxes.value
    ia, ib, diag = evaluator._ia, evaluator._ib, evaluator._diagonal
    h = _h(lower, upper, evaluator.along)
    with np.errstate(all="ignore"):
        # h_a h_b off the diagonal; 1/2 h_a^2 in [0, mag(h_a)^2 / 2] on it.
        hh = _i_mul(h[ia], h[ib])
        m2 = _i_mul(Interval(h.mag[ia], h.mag[ia]), Interval(h.mag[ib], h.mag[ib]))
        hh = Interval(
            np.where(diag[:, None], 0.0, hh.lo), np.where(diag[:, None], 0.5 * m2.hi, hh.hi)
        )
        lead = (None,) * (boxes.value.lo.ndim - 1)
        first = _i_mul(centres.gradient, Interval(h.lo[lead], h.hi[lead]))
        second = _i_mul(boxes.hessian, Interval(hh.lo[lead], hh.hi[lead]))
        total = _i_add(_i_add(centres.value, _sum_rows(first)), _sum_rows(second))
    ok = boxes.valid & centres.valid
    return Interval(np.where(ok, total.lo, -np.inf), np.where(ok, total.hi, np.inf))


def taylor_form(evaluator: TaylorEvaluator, lower: np.ndarray, upper: np.ndarray) -> Interval:
    """The second-order Taylor form of every expression over each box (module docstring).

    Parameters
    ----------
    evaluator : TaylorEvaluator
        The expressions; they must depend on ``evaluator.along`` only.
    lower, upper : ndarray, shape (n, B)
        The boxes.

    Returns
    -------
    Interval
        Shape ``S + (B,)``; the whole line on the boxes where the expressions
        are not twice continuously differentiable.
    """
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    centre = 0.5 * (lower + upper)
    boxes = evaluator.jet(lower, upper)
    centres = evaluator.jet(centre, centre, order=1)
    return taylor_from_jets(evaluator, boxes, centres, lower, upper)
