"""Certified bounds of many symbolic expressions over a box, refined together.

For a plant given as symbolic ``f`` and ``g`` (not a multibody structure),
:func:`ofrl_drake.jacobian_bounds.jacobian_bounds` encloses every entry of
their Jacobians over the observer box. Each entry ``J`` is enclosed over a box
``X`` with centre ``c`` by the intersection of three forms, computed in one
pass over the expression graph of all entries
(:class:`~ofrl_drake.interval_taylor.TaylorEvaluator`, no symbolic
differentiation):

* the natural interval extension ``[J](X)``;
* the mean-value form ``J(c) + [grad J](X) (X - c)``;
* the second-order Taylor form ``J(c) + grad J(c) (X - c) + 1/2 (X - c)^T
  [Hess J](X) (X - c)``, whose overestimation shrinks with the cube of the box
  width, so that expressions whose variables repeat and cancel (a rotation's
  ``sin^2 + cos^2``) still converge.

The bounds come from the one branch and bound,
:func:`ofrl_drake.branch_and_bound.refine`, with a :class:`TaylorEncloser`:
boxes are split along the variable with the largest share, relative to the
tolerance, of the unsettled entries' Taylor forms (the encloser's
``spread``). The encloser can be restricted (:meth:`TaylorEncloser.restrict`),
so an entry settled on every open box leaves the refinement (its enclosures
there join its bound) and the evaluator is rebuilt for the entries left: the
work per box follows the entries still open, not all of them. The result is
the hull of each entry's enclosures over boxes that cover the box: always
sound, tight when the refinement converged.

Entries that share no variable, directly or through other entries, are
refined apart (:func:`independent_groups`): each group's boxes split only its
own variables. Refined together, two groups of ``d1`` and ``d2`` variables
would need the product of their box counts; apart, the sum. (Two copies of
the paper's plant: 32,529 boxes together against 2 x 641 apart.)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ofrl_drake.interval import Interval
from ofrl_drake.interval_taylor import TaylorEvaluator, taylor_from_jets

__all__ = ["TaylorEncloser", "independent_groups"]

#: Boxes enclosed per call: at most this many interval values (entries x
#: derivative rows x boxes) per derivative array.
_VALUES = 2_000_000
_MIN_CHUNK, _MAX_CHUNK = 64, 4096


def independent_groups(uses: Sequence[Sequence[int]]) -> list[np.ndarray]:
    """Partition entries into groups that share no variable, directly or through others.

    Parameters
    ----------
    uses : sequence of sequence of int
        For each entry, the indices of the variables it depends on.

    Returns
    -------
    list of ndarray of int
        The entries of each group, ascending; the groups in the order of their
        first entry. An entry that uses no variable is a group alone.

    Examples
    --------
    >>> [g.tolist() for g in independent_groups([(0, 1), (2,), (1,), (), (2, 3)])]
    [[0, 2], [1, 4], [3]]
    """
    # Connected components of the graph whose nodes are the entries and the
    # variables, an edge joining an entry to each variable it uses.
    E = len(uses)
    entries = [e for e, used in enumerate(uses) for _ in used]
    variables = [E + int(v) for used in uses for v in used]
    nodes = max(variables, default=E - 1) + 1
    graph = coo_matrix((np.ones(len(entries)), (entries, variables)), shape=(nodes, nodes))
    _, label = connected_components(graph, directed=False)
    groups = [np.flatnonzero(label[:E] == c) for c in np.unique(label[:E])]
    return sorted(groups, key=lambda g: int(g[0]))


class TaylorEncloser:
    """Enclosures of expressions over many boxes at once (module docstring).

    Parameters
    ----------
    expressions : sequence of Expression
        The ``E`` expressions (twice continuously differentiable where they
        are defined, of the kinds :data:`~ofrl_drake.interval_taylor.TAYLOR_KINDS`).
    variables : sequence of Variable
        The ``n`` state variables, in the order of the rows of the boxes.

    Attributes
    ----------
    used : ndarray of int
        The variables the expressions depend on (the others are not bisected).
    n_entries : int
        ``E``.
    chunk : int
        The most boxes enclosed in one evaluation (bounds the memory).

    Raises
    ------
    UnsupportedExpressionError
        If an expression uses a kind the Taylor form does not support.
    """

    def __init__(self, expressions: Any, variables: Any) -> None:
        from ofrl_drake.interval import ExpressionEvaluator

        self.expressions = list(expressions)
        self.variables = tuple(variables)
        used = ExpressionEvaluator(self.expressions, self.variables).variables_used()
        self.used = np.array(sorted({v for u in used for v in u}), dtype=int)
        self.taylor = TaylorEvaluator(self.expressions, self.variables, self.used)
        self.n_entries = len(used)
        L = self.used.size
        per_box = max(1, self.n_entries * (1 + L + L * (L + 1) // 2))
        self.chunk = int(np.clip(_VALUES // per_box, _MIN_CHUNK, _MAX_CHUNK))

    def restrict(self, entries: np.ndarray) -> TaylorEncloser:
        """The encloser of the expressions ``entries`` only (a smaller expression graph)."""
        return TaylorEncloser([self.expressions[e] for e in entries], self.variables)

    def enclose(
        self, lower: np.ndarray, upper: np.ndarray
    ) -> tuple[Interval, Interval, np.ndarray]:
        """Enclose every expression over each box, and at each box's centre.

        Parameters
        ----------
        lower, upper : ndarray, shape (n, B)
            ``B`` boxes.

        Returns
        -------
        boxes : Interval
            Shape ``(E, B)``: the natural form intersected with the mean-value
            and Taylor forms (the natural form alone where those do not hold).
        centres : Interval
            Shape ``(E, B)``: each expression at each box's centre (a few ulps
            wide; NaN-free, possibly infinite where undefined).
        spread : ndarray
            Shape ``(E, L, B)``: ``mag(h_l) (mag(dJ/dx_l(c)) + sum_m
            mag([d2J/dx_l dx_m](X)) mag(h_m))`` (``h = X - c``), the share of each
            used variable in the Taylor form's width.
        """
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        centre = 0.5 * (lower + upper)
        on_boxes = self.taylor.jet(lower, upper)
        at_centres = self.taylor.jet(centre, centre, order=1)
        natural = on_boxes.value
        if not self.used.size:
            return natural, at_centres.value, np.zeros((self.n_entries, 0, lower.shape[1]))
        with np.errstate(all="ignore"):
            h = Interval(
                np.nextafter(lower[self.used] - centre[self.used], -np.inf),
                np.nextafter(upper[self.used] - centre[self.used], np.inf),
            )
            mean_value = at_centres.value
            for a in range(self.used.size):
                mean_value = mean_value + on_boxes.gradient[:, a] * h[a][None]
            taylor = taylor_from_jets(self.taylor, on_boxes, at_centres, lower, upper)
            # Each variable's share of the Taylor form's width: the first-order term
            # mag(dJ/dx_l(c)) mag(h_l) and mag(h_l) sum_m mag(H_lm(X)) mag(h_m).
            spread = at_centres.gradient.mag * h.mag[None]
            hessian = on_boxes.hessian.mag
            for p, (a, b) in enumerate(self.taylor.pairs):
                w = hessian[:, p] * (h.mag[a] * h.mag[b])[None]
                spread[:, a] += w
                if a != b:
                    spread[:, b] += w
        ok = on_boxes.valid & at_centres.valid
        lo = np.maximum(natural.lo, np.where(ok, np.maximum(mean_value.lo, taylor.lo), -np.inf))
        hi = np.minimum(natural.hi, np.where(ok, np.minimum(mean_value.hi, taylor.hi), np.inf))
        spread = np.where(ok & np.isfinite(spread), spread, np.inf)
        return Interval(lo, hi), at_centres.value, spread
