"""A numpy-style function backed by ``pydrake.symbolic`` expressions.

:class:`ExpressionFunction` turns an array of expressions in variables ``x``
into a callable that follows the :class:`~ofrl_drake.model.ControlAffineSystem`
conventions for ``f`` and ``g``:

* ``F(x)`` for floats ``x`` of shape ``(n,)`` returns shape ``S``;
* ``F(X)`` for a batch ``X`` of shape ``(n, N)`` returns shape ``S + (N,)``,
  evaluated without a Python loop over points
  (:class:`~ofrl_drake.interval.ExpressionEvaluator`);
* ``F(x)`` for ``pydrake.symbolic`` states substitutes them (so the Jacobian
  bounds and Drake's ``SymbolicVectorSystem`` see the expressions themselves);
* ``F(x)`` for ``AutoDiffXd`` states returns values with derivatives by the
  chain rule through the symbolic Jacobian.

>>> import numpy as np
>>> from pydrake.symbolic import MakeVectorVariable
>>> x = MakeVectorVariable(2, "x")
>>> F = ExpressionFunction([x[1], -np.sin(x[0])], x)
>>> F(np.array([[0.0, np.pi / 2], [1.0, 2.0]])).round(12).tolist()
[[1.0, 2.0], [-0.0, -1.0]]
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from pydrake.autodiffutils import AutoDiffXd
from pydrake.symbolic import Expression, Jacobian, Variable

from ofrl_drake.errors import ModelError
from ofrl_drake.interval import ExpressionEvaluator, as_expression

__all__ = ["ExpressionFunction"]


class ExpressionFunction:
    """Evaluate an array of symbolic expressions like a numpy function of ``x``.

    Parameters
    ----------
    expressions : array_like of Expression
        Shape ``S``; plain numbers are allowed.
    variables : sequence of pydrake.symbolic.Variable
        The ``n`` state variables, in order.

    Attributes
    ----------
    expressions : ndarray of Expression, shape S
        The expressions as given, as Drake expressions.
    variables : tuple of Variable

    Raises
    ------
    UnsupportedExpressionError
        If an expression uses a function the vectorized evaluator lacks or a
        variable outside ``variables``.
    """

    def __init__(self, expressions: Any, variables: Iterable[Variable]) -> None:
        exprs = np.asarray(expressions, dtype=object)
        self.expressions = np.vectorize(as_expression, otypes=[object])(exprs).reshape(exprs.shape)
        self.variables = tuple(variables)
        self._evaluator = ExpressionEvaluator(self.expressions, self.variables)
        self._jacobian: ExpressionEvaluator | None = None

    @property
    def shape(self) -> tuple[int, ...]:
        """``S``, the shape of one evaluation."""
        return self.expressions.shape

    def __call__(self, x: Any) -> np.ndarray:
        """Evaluate at ``x`` (floats ``(n,)`` or ``(n, N)``, symbolic or AutoDiffXd)."""
        arr = np.asarray(x)
        n = len(self.variables)
        if arr.shape[:1] != (n,) or arr.ndim > 2:
            raise ModelError(
                f"the state must have shape ({n},) or ({n}, N); got shape {arr.shape}."
            )
        if arr.dtype != object:
            return self._evaluator(arr.astype(float))
        first = arr.flat[0]
        if arr.ndim == 1 and isinstance(first, Expression | Variable):
            subst = {v: as_expression(e) for v, e in zip(self.variables, arr, strict=True)}
            flat = self.expressions.ravel()
            out = np.array([e.Substitute(subst) for e in flat], dtype=object)
            return out.reshape(self.shape)
        if arr.ndim == 1 and isinstance(first, AutoDiffXd):
            return self._autodiff(arr)
        try:
            values = arr.astype(float)
        except (TypeError, ValueError):
            raise ModelError(
                f"cannot evaluate the expressions at a state of {type(first).__name__}; "
                "pass floats, pydrake.symbolic or AutoDiffXd values."
            ) from None
        return self._evaluator(values)

    def _autodiff(self, x: np.ndarray) -> np.ndarray:
        if self._jacobian is None:
            flat = self.expressions.ravel()
            J = Jacobian(flat, list(self.variables)) if flat.size else np.zeros((0, 0))  # type: ignore[call-overload]  # pydrake array stub
            self._jacobian = ExpressionEvaluator(J, self.variables)
        value = np.array([v.value() for v in x])
        dx = np.stack([np.asarray(v.derivatives(), dtype=float) for v in x])
        if dx.ndim == 1:  # no derivatives at all
            dx = dx.reshape(len(x), 0)
        vals = np.asarray(self._evaluator(value), dtype=float).ravel()
        J = np.asarray(self._jacobian(value), dtype=float).reshape(vals.size, len(x))
        grads = J @ dx
        out = np.array([AutoDiffXd(v, g) for v, g in zip(vals, grads, strict=True)], dtype=object)
        return out.reshape(self.shape)

    def __repr__(self) -> str:
        return f"ExpressionFunction(shape={self.shape}, n={len(self.variables)})"
