"""Element-wise bounds of the Jacobians of ``f`` and ``g`` over a box.

Assumption 1 of the paper (eqs. aug_jac_f, aug_jac_g) asks for constant
matrices with

    M_f1[i, j]    <= d f_i / d x_j      <= M_f2[i, j]
    M_g1[i, j, k] <= d g[i, k] / d x_j  <= M_g2[i, j, k]

for every ``x`` in a compact set, here an axis-aligned box. The Jacobians are
taken from ``system.f`` and ``system.g`` themselves with
``pydrake.symbolic.Jacobian``; users write no derivatives.

Two methods:

``"sampled"``
    Evaluate the symbolic Jacobian on a dense grid plus seeded random points,
    all at once (:class:`ofrl_drake.interval.ExpressionEvaluator`), and take the
    element-wise min and max. Fast and tight, but only an inner estimate.
``"certified"``
    Guaranteed enclosures, refined by the branch and bound of
    :mod:`ofrl_drake.branch_and_bound`, which bisects the boxes whose enclosure
    reaches more than the tolerance beyond the best known inner estimate. Two
    enclosures, chosen by asking the system:

    * a multibody model (``system.multibody_structure()`` is not None, as for
      :meth:`~ofrl_drake.model.ControlAffineSystem.from_multibody`) is enclosed
      from its structure ``x' = [qdot; M(q)^-1 (tau(q, v) + B u)]``: interval
      values of the small expressions ``M``, ``tau`` and their derivatives and
      interval linear solves with ``[M]``, never a symbolic inverse
      (:mod:`ofrl_drake.multibody_bounds`; all entries refined together);
    * any other model: interval arithmetic on the symbolic Jacobian entries of
      ``f`` and ``g``, each the intersection of the natural interval extension,
      the mean-value form ``h(c) + grad h(X) (X - c)`` and the second-order
      Taylor form, whose overestimation shrinks with the cube of the box width
      (derivatives by forward differentiation on the expression graph,
      :mod:`ofrl_drake.interval_taylor`); all entries refined together, one
      refinement per group of entries that share no state variable
      (:mod:`ofrl_drake.symbolic_bounds`). An entry the Taylor form cannot
      differentiate (``Abs``, ``Min``, ...) is refined alone, with the
      natural and mean-value forms.

    An enclosure that is still infinite when the budget (``max_boxes``,
    ``max_wall_time``) runs out raises :class:`UncertifiedBoundsError`.

Both methods start from the sampled estimate: of the symbolic Jacobians, or,
for a multibody model whose ``f`` or ``g`` has an entry longer than
:data:`SYMBOLIC_MAX_CHARS`, of the structure's Jacobians at the points
(:meth:`~ofrl_drake.multibody_bounds.MultibodyStructure.jacobians`), whose
chunks stop at ``max_wall_time``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydrake.symbolic import Expression, Jacobian

from ofrl_drake.branch_and_bound import Refinement, refine
from ofrl_drake.checks import integer_at_least, is_real_number
from ofrl_drake.domain import UndefinedOnBoxError, prove_defined
from ofrl_drake.errors import ModelError, OfrlError, WallTimeExceeded
from ofrl_drake.interval import (
    ExpressionEvaluator,
    Interval,
    IntervalDomainError,
    UnsupportedExpressionError,
)
from ofrl_drake.interval_taylor import TaylorEvaluator
from ofrl_drake.model import ControlAffineSystem, SymbolicDynamics, require_system
from ofrl_drake.multibody_bounds import MultibodyJacobianEncloser, MultibodyStructure
from ofrl_drake.symbolic_bounds import TaylorEncloser, independent_groups

__all__ = [
    "DEFAULT_TOL",
    "MAX_POINTS",
    "BoundsError",
    "BoundsExcess",
    "Box",
    "BoxError",
    "JacobianBounds",
    "UncertifiedBoundsError",
    "jacobian_bounds",
    "symbolic_jacobians",
]

METHODS = ("sampled", "certified")
#: Default ``rtol`` of certified bounds for multibody models: each end may lie
#: 10% of the entry's sampled width beyond the sampled bound, so the certified
#: widths are at most 1.2 times the sampled ones (plus ``tol``).
MULTIBODY_RTOL = 0.1
#: Points (plus the centre) at which a multibody structure is compared with ``f`` and ``g``.
_STRUCTURE_POINTS = 16
#: Relative tolerance of that comparison: ``|a - b| <= rtol (1 + |b|)``.
STRUCTURE_RTOL = 1e-8
#: A multibody model whose symbolic ``f`` or ``g`` has an entry longer than
#: this (characters) takes its sampled estimates from its structure
#: (:meth:`~ofrl_drake.multibody_bounds.MultibodyStructure.jacobians`):
#: differentiating such expressions takes minutes (a cart with three
#: pendulums: rows of 600,000 characters, 54 s for one entry). The shipped
#: multibody plants stay below 20,000.
SYMBOLIC_MAX_CHARS = 100_000
_POINT_BUDGET = 100_000
_CHUNK = 20_000
#: Branch and bound of one entry: the most values (nodes x boxes) enclosed at once.
_NODE_VALUES = 2_000_000


class BoxError(OfrlError):
    """A box is malformed: wrong length, non-finite, or lower >= upper."""


class BoundsError(OfrlError):
    """Jacobian bounds cannot be computed as asked (bad method or parameters)."""


class UncertifiedBoundsError(BoundsError):
    """A certified bound is still infinite when the refinement's budget runs out."""


# ------------------------------------------------------------------------ Box
@dataclass(frozen=True, eq=False)
class Box:
    """An axis-aligned box ``lower <= x <= upper`` in ``R^n``.

    Parameters
    ----------
    lower, upper : array_like, shape (n,)
        Finite corners with ``lower < upper`` element-wise.

    Raises
    ------
    BoxError
        If the corners are not 1-D, differ in length, are not finite, or some
        ``lower[i] >= upper[i]``; the message names the offending entry.

    Examples
    --------
    >>> Box([-2, -2], [2, 2]).width.tolist()
    [4.0, 4.0]
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self) -> None:
        try:
            lo = np.array(self.lower, dtype=float)
            hi = np.array(self.upper, dtype=float)
        except (TypeError, ValueError) as err:
            raise BoxError(
                f"box corners must be numbers; got lower={self.lower!r}, "
                f"upper={self.upper!r} ({err})."
            ) from None
        if lo.ndim != 1 or hi.ndim != 1 or lo.size == 0:
            raise BoxError(
                f"box lower and upper must be 1-D arrays of length n; got shapes "
                f"{lo.shape} and {hi.shape}."
            )
        if lo.shape != hi.shape:
            raise BoxError(
                f"box lower has length {lo.size} but upper has length {hi.size}; "
                "give one bound per state."
            )
        for name, arr in (("lower", lo), ("upper", hi)):
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                raise BoxError(
                    f"box {name}[{bad[0]}] = {arr[bad[0]]} is not finite; Jacobian "
                    "bounds need a compact box."
                )
        bad = np.flatnonzero(lo >= hi)
        if bad.size:
            i = bad[0]
            raise BoxError(
                f"box lower[{i}] = {lo[i]:g} is not below upper[{i}] = {hi[i]:g}; "
                "each side needs lower < upper."
            )
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @classmethod
    def coerce(cls, box: Any, n: int | None = None) -> Box:
        """Return ``box`` as a :class:`Box`, checking its dimension.

        Parameters
        ----------
        box : Box or (lower, upper) or mapping with keys ``lower``, ``upper``
            The box.
        n : int, optional
            The required dimension.

        Raises
        ------
        BoxError
            If ``box`` has another form, is malformed, or is not ``n``-dimensional.
        """
        if isinstance(box, Box):
            out = box
        elif isinstance(box, dict):
            if set(box) != {"lower", "upper"}:
                raise BoxError(
                    f"a box mapping needs exactly the keys 'lower' and 'upper'; got {sorted(box)}."
                )
            out = cls(box["lower"], box["upper"])
        else:
            try:
                lower, upper = box
            except (TypeError, ValueError):
                raise BoxError(
                    f"box must be a Box or a pair (lower, upper); got {box!r}."
                ) from None
            out = cls(lower, upper)
        if n is not None and out.n != n:
            raise BoxError(
                f"box has dimension {out.n} but the system has n = {n} states; "
                f"give {n} lower and {n} upper bounds."
            )
        return out

    @property
    def n(self) -> int:
        """The dimension."""
        return int(self.lower.size)

    @property
    def width(self) -> np.ndarray:
        """``upper - lower``."""
        return self.upper - self.lower

    @property
    def center(self) -> np.ndarray:
        """``(lower + upper) / 2``."""
        return 0.5 * (self.lower + self.upper)

    def contains(self, X: np.ndarray) -> np.ndarray:
        """Whether each column of ``X`` (shape ``(n,)`` or ``(n, N)``) is inside."""
        X = np.asarray(X, dtype=float)
        lo = self.lower.reshape((-1,) + (1,) * (X.ndim - 1))
        hi = self.upper.reshape((-1,) + (1,) * (X.ndim - 1))
        return np.all((lo <= X) & (X <= hi), axis=0)

    def to_dict(self) -> dict[str, list[float]]:
        """``{"lower": [...], "upper": [...]}``."""
        return {"lower": self.lower.tolist(), "upper": self.upper.tolist()}

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Box):
            return NotImplemented
        return bool(
            np.array_equal(self.lower, other.lower) and np.array_equal(self.upper, other.upper)
        )

    def __hash__(self) -> int:
        return hash((tuple(self.lower), tuple(self.upper)))

    def __repr__(self) -> str:
        return f"Box(lower={self.lower.tolist()}, upper={self.upper.tolist()})"


# --------------------------------------------------------------- the results
def _frozen_array(a: Any) -> np.ndarray:
    arr = np.array(a, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class BoundsExcess:
    """How much wider certified bounds are than sampled ones (all entries >= 0).

    Attributes
    ----------
    Mf1, Mf2 : ndarray, shape (n, n)
        ``sampled.Mf1 - certified.Mf1`` and ``certified.Mf2 - sampled.Mf2``.
    Mg1, Mg2 : ndarray, shape (n, n, m)
        The same for ``g``.
    max : float
        The largest entry of the four arrays.
    converged : bool
        Whether the branch and bound met ``tol`` for every entry before running
        out of ``max_boxes``.
    """

    Mf1: np.ndarray
    Mf2: np.ndarray
    Mg1: np.ndarray
    Mg2: np.ndarray
    max: float
    converged: bool

    def to_dict(self) -> dict[str, Any]:
        """Nested lists plus ``max`` and ``converged``."""
        return {
            "Mf1": self.Mf1.tolist(),
            "Mf2": self.Mf2.tolist(),
            "Mg1": self.Mg1.tolist(),
            "Mg2": self.Mg2.tolist(),
            "max": float(self.max),
            "converged": bool(self.converged),
        }


@dataclass(frozen=True, eq=False)
class JacobianBounds:
    """Element-wise Jacobian bounds of ``f`` and ``g`` over a box.

    Attributes
    ----------
    method : str
        ``"sampled"``, ``"certified"`` or ``"given"`` (numbers supplied by hand).
    box : Box
        Where the bounds hold.
    Mf1, Mf2 : ndarray, shape (n, n)
        ``Mf1[i, j] <= d f_i / d x_j <= Mf2[i, j]``.
    Mg1, Mg2 : ndarray, shape (n, n, m)
        ``Mg1[i, j, k] <= d g[i, k] / d x_j <= Mg2[i, j, k]``.
    excess : BoundsExcess or None
        For ``"certified"``: how much wider than the sampled bounds. Else None.

    Raises
    ------
    BoundsError
        If the shapes do not match the box or a lower bound exceeds an upper one.
    """

    method: str
    box: Box
    Mf1: np.ndarray
    Mf2: np.ndarray
    Mg1: np.ndarray
    Mg2: np.ndarray
    excess: BoundsExcess | None = field(default=None)

    def __post_init__(self) -> None:
        if self.method not in (*METHODS, "given"):
            raise BoundsError(
                f"JacobianBounds.method must be one of {(*METHODS, 'given')}; got {self.method!r}."
            )
        object.__setattr__(self, "box", Box.coerce(self.box))
        n = self.box.n
        arrays = {k: _frozen_array(getattr(self, k)) for k in self._KEYS}
        for key in ("Mf1", "Mf2"):
            if arrays[key].shape != (n, n):
                raise BoundsError(
                    f"{key} must have shape ({n}, {n}) for a {n}-D box; got {arrays[key].shape}."
                )
        for key in ("Mg1", "Mg2"):
            a = arrays[key]
            if a.ndim != 3 or a.shape[:2] != (n, n) or a.shape != arrays["Mg1"].shape:
                raise BoundsError(
                    f"{key} must have shape ({n}, {n}, m) (indexed [i, j, k] = "
                    f"d g[i, k] / d x_j); got {a.shape}."
                )
        for lo, hi in (("Mf1", "Mf2"), ("Mg1", "Mg2")):
            bad = np.argwhere(~(arrays[lo] <= arrays[hi]))
            if bad.size:
                idx = tuple(int(i) for i in bad[0])
                raise BoundsError(
                    f"{lo}{list(idx)} = {arrays[lo][idx]:g} exceeds "
                    f"{hi}{list(idx)} = {arrays[hi][idx]:g} (or is NaN)."
                )
        for key, arr in arrays.items():
            object.__setattr__(self, key, arr)

    _KEYS = ("Mf1", "Mf2", "Mg1", "Mg2")

    @property
    def n(self) -> int:
        """State dimension."""
        return self.box.n

    @property
    def m(self) -> int:
        """Input dimension."""
        return int(self.Mg1.shape[2])

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(Mf1, Mf2, Mg1, Mg2)``."""
        return self.Mf1, self.Mf2, self.Mg1, self.Mg2

    def contains(self, other: JacobianBounds, atol: float = 0.0) -> bool:
        """Whether ``[other.M1, other.M2]`` lies inside ``[M1 - atol, M2 + atol]``."""
        return bool(
            np.all(self.Mf1 - atol <= other.Mf1)
            and np.all(other.Mf2 <= self.Mf2 + atol)
            and np.all(self.Mg1 - atol <= other.Mg1)
            and np.all(other.Mg2 <= self.Mg2 + atol)
        )

    def to_dict(self) -> dict[str, list]:
        """``{"Mf1", "Mf2", "Mg1", "Mg2"}`` as nested lists."""
        return {k: getattr(self, k).tolist() for k in self._KEYS}

    @classmethod
    def from_dict(cls, data: dict[str, Any], box: Any, method: str = "given") -> JacobianBounds:
        """Rebuild from :meth:`to_dict` output and the box."""
        missing = [k for k in cls._KEYS if k not in data]
        if missing:
            raise BoundsError(f"jacobian_bounds is missing keys {missing}.")
        return cls(method, Box.coerce(box), *(data[k] for k in cls._KEYS))


# ------------------------------------------------------------------ Jacobians
def symbolic_jacobians(
    system: ControlAffineSystem,
    deadline: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Symbolic Jacobians of ``f`` and ``g`` from ``pydrake.symbolic.Jacobian``.

    Parameters
    ----------
    system : ControlAffineSystem
        The plant; ``f`` and ``g`` are called on symbolic states.
    deadline : float, optional
        A ``time.monotonic()`` instant after which no further row of ``f`` or
        column of ``g`` is differentiated (one already started cannot be
        interrupted). Default: none.

    Returns
    -------
    x : ndarray of Variable, shape (n,)
        The state variables.
    Jf : ndarray of Expression, shape (n, n)
        ``Jf[i, j] = d f_i / d x_j``.
    Jg : ndarray of Expression, shape (n, n, m)
        ``Jg[i, j, k] = d g[i, k] / d x_j``.

    Raises
    ------
    BoundsError
        If ``f`` or ``g`` cannot be called on ``pydrake.symbolic.Expression``
        states (for example because they call scipy or use ``if`` on the state).
    WallTimeExceeded
        If ``deadline`` passes before every row is differentiated.
    """
    model, Jf, Jg = _traced_jacobians(system, deadline)
    return model.x, Jf, Jg


def _traced_jacobians(
    system: ControlAffineSystem, deadline: float | None
) -> tuple[SymbolicDynamics, np.ndarray, np.ndarray]:
    """:func:`symbolic_jacobians`, with the traced ``f`` and ``g`` they come from."""
    n, m = system.n, system.m
    try:
        model = system.symbolic()
    except ModelError as err:
        raise BoundsError(f"{err} They must be, to be differentiated.") from err
    x, fx, gx = model.x, model.f, model.g
    Jf = np.empty((n, n), dtype=object)
    Jg = np.empty((n, n, m), dtype=object)
    start = time.monotonic()
    for name, rows, out in (
        *((f"f[{i}]", fx[i : i + 1], Jf[i : i + 1]) for i in range(n)),
        *((f"g[:, {k}]", gx[:, k], Jg[:, :, k]) for k in range(m)),
    ):
        now = time.monotonic()
        if deadline is not None and now > deadline:
            raise WallTimeExceeded(
                f"the symbolic Jacobians of f and g were not done by the deadline "
                f"(max_wall_time, --max-wall): {name} was next after {now - start:.3g} s; "
                "allow more wall time, simplify f and g, or build a multibody plant with "
                "from_multibody, whose bounds come from its mass-matrix structure.",
                step="symbolic Jacobians",
            )
        out[...] = Jacobian(rows, x)
    return model, Jf, Jg


# ------------------------------------------------------------------- sampling
def _default_grid(n: int) -> int:
    g = int(np.floor(_POINT_BUDGET ** (1.0 / n) + 1e-9))
    g = min(g, 101)
    if g < 2:
        return 1
    return g - 1 if (g % 2 == 0 and g > 2) else g


def _grid_points(box: Box, dims: tuple[int, ...], grid: int) -> np.ndarray:
    """A ``grid``-per-axis grid over the axes ``dims``; other axes at the centre.

    Raises
    ------
    BoundsError
        If the grid would have more than :data:`MAX_POINTS` points.
    """
    if grid == 1 or not dims:
        return box.center[:, None]
    size = grid ** len(dims)
    if size > MAX_POINTS:
        raise BoundsError(
            f"grid: {grid} points per axis over the {len(dims)} states {list(dims)} that some "
            f"Jacobian entries depend on make {size:.3g} points, which would need about "
            f"{size * 8 * (box.n + len(dims)) / 2**30:.3g} GiB; at most {MAX_POINTS}. "
            "Use a smaller grid (or the default)."
        )
    axes = [np.linspace(box.lower[i], box.upper[i], grid) for i in dims]
    mesh = np.meshgrid(*axes, indexing="ij")
    G = np.repeat(box.center[:, None], mesh[0].size, axis=1)
    for axis, values in zip(dims, mesh, strict=True):
        G[axis] = values.ravel()
    return G


def _random_points(box: Box, n_random: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return box.lower[:, None] + rng.random((box.n, n_random)) * box.width[:, None]


def _sampled_bounds(
    entries: np.ndarray,
    x: np.ndarray,
    box: Box,
    grid: int | None,
    n_random: int,
    seed: int,
    names: list[str],
) -> tuple[np.ndarray, np.ndarray]:
    """Min and max of each entry over grids plus random points.

    Entries are grouped by the state variables they depend on; each group gets
    a dense grid over its own variables only (a 4-state system whose entries each
    depend on two states is gridded in 2-D, not 4-D). The random points cover
    the whole box for every entry.
    """
    evaluator = ExpressionEvaluator(entries, x)
    lo, hi = _sampled_range(evaluator, _random_points(box, n_random, seed), names)
    lo_c, hi_c = _sampled_range(evaluator, box.center[:, None], names)
    lo, hi = np.minimum(lo, lo_c), np.maximum(hi, hi_c)
    groups: dict[tuple[int, ...], list[int]] = {}
    for e, used in enumerate(evaluator.variables_used()):
        if used:
            groups.setdefault(used, []).append(e)
    for dims, idx in groups.items():
        g = _default_grid(len(dims)) if grid is None else int(grid)
        sub = ExpressionEvaluator(entries[idx], x)
        g_lo, g_hi = _sampled_range(sub, _grid_points(box, dims, g), [names[i] for i in idx])
        lo[idx] = np.minimum(lo[idx], g_lo)
        hi[idx] = np.maximum(hi[idx], g_hi)
    return lo, hi


def _too_large_to_differentiate(system: ControlAffineSystem) -> bool:
    """Whether some entry of the symbolic ``f`` or ``g`` exceeds :data:`SYMBOLIC_MAX_CHARS`.

    Tracing a multibody plant's ``f`` cannot be stopped part-way (Drake's
    symbolic ``M(q)^-1``; most of a minute for three links with skew axes);
    the steps after it check the deadline (the symbolic Jacobians, or the
    samples and the Taylor derivatives of the structure).
    """
    try:
        model = system.symbolic()
    except ModelError:
        return False  # symbolic_jacobians reports it
    return any(
        len(e.to_string()) > SYMBOLIC_MAX_CHARS for e in (*np.ravel(model.f), *np.ravel(model.g))
    )


def _structure_samples(
    structure: MultibodyStructure,
    box: Box,
    grid: int | None,
    n_random: int,
    seed: int,
    names: list[str],
    deadline: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Sampled minima and maxima of every Jacobian entry from the multibody structure.

    The same seeded random points and centre as :func:`_sampled_bounds`, and one
    grid over the states the structure depends on, evaluated by
    :meth:`MultibodyStructure.jacobians` (interval-free, no symbolic Jacobian of
    ``f``) in chunks; after ``deadline`` no further chunk is started (the
    centre and the first chunk always are).
    """
    used = structure.used_states()
    g = _default_grid(len(used)) if grid is None else int(grid)
    points = np.concatenate(
        [
            box.center[:, None],
            _random_points(box, n_random, seed),
            _grid_points(box, used, g),
        ],
        axis=1,
    )
    n, m = structure.n, structure.m

    def values(chunk: np.ndarray) -> np.ndarray:
        Jf, Jg = structure.jacobians(chunk)
        return np.concatenate([Jf.reshape(n * n, -1), Jg.reshape(n * n * m, -1)])

    return _range_over_points(values, n * n + n * n * m, points, names, deadline)


def _entry_names(n: int, m: int) -> list[str]:
    names = [f"d f[{i}] / d x[{j}]" for i in range(n) for j in range(n)]
    names += [f"d g[{i}, {k}] / d x[{j}]" for i in range(n) for j in range(n) for k in range(m)]
    return names


def _sampled_range(
    evaluator: ExpressionEvaluator, points: np.ndarray, names: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    E = int(np.prod(evaluator.shape))
    return _range_over_points(lambda chunk: evaluator(chunk).reshape(E, -1), E, points, names)


def _range_over_points(
    values: Callable[[np.ndarray], np.ndarray],
    E: int,
    points: np.ndarray,
    names: list[str],
    deadline: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Minima and maxima over ``points`` of the ``E`` entries ``values(chunk)`` (E, k).

    Chunk by chunk; after ``deadline`` (``time.monotonic()``) no further chunk
    is started, the first always is.

    Raises
    ------
    BoundsError
        At the first non-finite value, naming its entry and point.
    """
    lo = np.full(E, np.inf)
    hi = np.full(E, -np.inf)
    for start in range(0, points.shape[1], _CHUNK):
        if start and deadline is not None and time.monotonic() > deadline:
            break
        chunk = points[:, start : start + _CHUNK]
        vals = values(chunk)
        bad = ~np.isfinite(vals)
        if bad.any():
            e, p = np.argwhere(bad)[0]
            raise BoundsError(
                f"the Jacobian entry {names[e]} is not finite "
                f"({vals[e, p]}) at x = {chunk[:, p].tolist()}; f and g must be "
                "continuously differentiable on the box (shrink it)."
            )
        lo = np.minimum(lo, vals.min(axis=1))
        hi = np.maximum(hi, vals.max(axis=1))
    return lo, hi


# ---------------------------------------------------------- branch and bound
class _EntryEncloser:
    """Interval enclosure of one Jacobian entry over many boxes at once.

    An :class:`~ofrl_drake.branch_and_bound.Encloser` with one entry and no
    ``spread`` (boxes are split along their relatively widest side). The entry
    and its gradient are one evaluator, and the box centres are enclosed as
    degenerate boxes beside the boxes, so one enclosure is one walk of the
    expression tree (shared subexpressions evaluated once).
    """

    n_entries = 1

    def __init__(self, expr: Expression, x: np.ndarray) -> None:
        self.value = ExpressionEvaluator([expr], x)
        self.used = np.array(self.value.variables_used()[0], dtype=int)
        self.with_gradient: ExpressionEvaluator | None = None
        if self.used.size:
            try:
                grad = Jacobian(np.array([expr]), x[self.used])[0]
                both = ExpressionEvaluator([expr, *grad], x)
            except (UnsupportedExpressionError, RuntimeError):
                both = None  # the natural extension only
            if both is not None and both.supports_intervals:
                self.with_gradient = both
        widest = self.value if self.with_gradient is None else self.with_gradient
        # Boxes and centres side by side: 2 B columns per evaluation.
        self.chunk = int(np.clip(_NODE_VALUES // (2 * max(widest.node_count, 1)), 64, 4096))

    def _natural(self, lo: np.ndarray, hi: np.ndarray) -> tuple[Interval, Interval, None]:
        natural = self.value.interval(lo, hi)
        centre = self.value(0.5 * (lo + hi))  # NaN where h is undefined
        return natural, Interval(centre, centre), None

    def enclose(self, lo: np.ndarray, hi: np.ndarray) -> tuple[Interval, Interval, None]:
        """Enclosures of ``h`` over the boxes, and of ``h`` at their centres (shape (1, B)).

        Over a box: the natural extension intersected with the mean-value form
        ``h(c) + grad h(X) (X - c)``. At a centre ``c``: an interval that holds
        ``h(c)`` (NaN ends where ``h`` is undefined), for the inner estimate.
        """
        if self.with_gradient is None:
            return self._natural(lo, hi)
        B = lo.shape[1]
        c = 0.5 * (lo + hi)
        try:
            both = self.with_gradient.interval(np.hstack([lo, c]), np.hstack([hi, c]))
        except IntervalDomainError:  # the gradient (or h at a centre) is undefined somewhere
            return self._natural(lo, hi)
        at_c = Interval(both.lo[:1, B:], both.hi[:1, B:])
        total = at_c
        for r, j in enumerate(self.used):
            step = Interval(np.nextafter(lo[j] - c[j], -np.inf), np.nextafter(hi[j] - c[j], np.inf))
            total = total + Interval(both.lo[1 + r : 2 + r, :B], both.hi[1 + r : 2 + r, :B]) * step
        natural = Interval(both.lo[:1, :B], both.hi[:1, :B])
        boxes = Interval(np.maximum(natural.lo, total.lo), np.minimum(natural.hi, total.hi))
        return boxes, at_c, None


def _taylor_supported(entries: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Which entries the Taylor form can differentiate (no ``Abs``, ``Min``, ...)."""
    try:
        TaylorEvaluator(entries, x, [])
        return np.ones(entries.size, dtype=bool)
    except UnsupportedExpressionError:
        out = np.zeros(entries.size, dtype=bool)
        for e, expr in enumerate(entries):
            try:
                TaylorEvaluator([expr], x, [])
                out[e] = True
            except UnsupportedExpressionError:
                pass
        return out


def _joint_budget(results: list[Refinement]) -> str:
    """What the refinements of independent groups spent together, for messages."""
    if len(results) == 1:
        return results[0].budget
    stops = sorted({r.stop for r in results if not r.converged}) or ["converged"]
    return (
        f"{sum(r.boxes for r in results)} boxes in {sum(r.seconds for r in results):.3g} s "
        f"over {len(results)} independent groups of entries, stopped by {' and '.join(stops)}"
    )


def _prove_defined(
    model: SymbolicDynamics,
    entries: np.ndarray,
    box: Box,
    names: list[str],
    deadline: float | None,
) -> None:
    """Refuse a box where ``f``, ``g`` or a Jacobian entry may be undefined (:mod:`.domain`).

    Plants without ``log``, ``sqrt``, ``asin``, ``acos`` or real powers (every
    shipped one) pass at the cost of one scan of the expression graph.
    """
    n, m = model.g.shape
    expressions = np.concatenate([model.f.ravel(), model.g.ravel(), entries])
    labels = [
        *(f"f[{i}]" for i in range(n)),
        *(f"g[{i}, {k}]" for i in range(n) for k in range(m)),
        *(f"the Jacobian entry {name}" for name in names),
    ]
    evaluator = ExpressionEvaluator(expressions, model.x)
    if not evaluator.supports_intervals:
        # f or g uses atan2 (enclosed at points only), defined everywhere; the
        # Jacobian entries, which the bounds enclose, hold no atan2.
        labels = labels[n + n * m :]
        evaluator = ExpressionEvaluator(entries, model.x)
    if not evaluator.has_partial_functions:
        return
    try:
        prove_defined(evaluator, box.lower, box.upper, names=labels, deadline=deadline)
    except UndefinedOnBoxError as err:
        raise BoundsError(f"certified bounds over {box!r}: {err}") from err


def _certify_symbolic(
    entries: np.ndarray,
    x: np.ndarray,
    box: Box,
    s_lo: np.ndarray,
    s_hi: np.ndarray,
    tol: float,
    rtol: float,
    max_boxes: int,
    deadline: float | None,
    names: list[str],
) -> tuple[np.ndarray, np.ndarray, bool, str]:
    """Certified bounds of symbolic Jacobian entries: ``(lo, hi, converged, budget note)``.

    Constant entries are enclosed once. The others are refined together with a
    :class:`~ofrl_drake.symbolic_bounds.TaylorEncloser` (natural, mean-value
    and second-order Taylor forms, one branch and bound for all of them; one
    per group of entries that share no variable with the others, so that each
    splits only its own variables; each group gets an equal share of the
    boxes and of the time the groups before it left);
    entries the Taylor form cannot differentiate (``Abs``, ``Min``, ...) are
    refined one by one with the natural and mean-value forms
    (:class:`_EntryEncloser`), as is every entry when an enclosure is
    undefined on a box (so that the error names the entry). All three use the
    one branch and bound, :func:`ofrl_drake.branch_and_bound.refine`.
    """
    c_lo = np.empty_like(s_lo)
    c_hi = np.empty_like(s_hi)
    evaluator = ExpressionEvaluator(entries, x)
    constant = evaluator.is_constant().ravel()
    if constant.any():
        idx = np.flatnonzero(constant)
        try:
            enc = ExpressionEvaluator(entries[idx], x).interval(box.lower, box.upper)
        except IntervalDomainError as err:
            raise BoundsError(f"{names[int(idx[0])]}: {err}") from err
        c_lo[idx], c_hi[idx] = enc.lo, enc.hi
    varying = np.flatnonzero(~constant)
    supported = _taylor_supported(entries[varying], x)
    joint, alone = varying[supported], varying[~supported]
    converged, budget = True, "converged"
    if joint.size:
        uses = evaluator.variables_used()
        results: list[Refinement] = []
        # The groups with fewest variables first: they settle soonest and leave
        # the boxes and the time they do not use to the harder ones after them.
        groups = sorted(
            independent_groups([uses[e] for e in joint]),
            key=lambda g: (len(set().union(*(uses[joint[e]] for e in g))), g.size),
        )
        try:
            for g, group in enumerate(groups):
                # An equal share of what the groups before have left, of boxes and time.
                left = len(groups) - g
                boxes = max(1, (max_boxes - sum(r.boxes for r in results)) // left)
                share = None
                if deadline is not None:
                    now = time.monotonic()
                    share = now + max(deadline - now, 0.0) / left
                results.append(
                    refine(
                        TaylorEncloser(entries[joint[group]], x),
                        box.lower,
                        box.upper,
                        s_lo[joint[group]],
                        s_hi[joint[group]],
                        tol=tol,
                        rtol=rtol,
                        max_boxes=boxes,
                        deadline=share,
                    )
                )
                c_lo[joint[group]], c_hi[joint[group]] = results[-1].lo, results[-1].hi
        except IntervalDomainError:
            alone = varying  # the per-entry refinement names the entry
        else:
            converged = all(r.converged for r in results)
            budget = _joint_budget(results)
    for e in alone:
        try:
            one = refine(
                _EntryEncloser(entries[e], x),
                box.lower,
                box.upper,
                s_lo[e : e + 1],
                s_hi[e : e + 1],
                tol=tol,
                rtol=rtol,
                max_boxes=max_boxes,
                deadline=deadline,
            )
        except IntervalDomainError as err:
            raise BoundsError(f"{names[e]}: {err}") from err
        c_lo[e], c_hi[e] = one.lo[0], one.hi[0]
        converged = converged and one.converged
        if not one.converged:
            budget = f"{names[e]}: {one.budget}"
    return c_lo, c_hi, converged, budget


# ------------------------------------------------------------------ the entry
#: The default absolute tolerance of the certified bounds' refinement (``tol``).
DEFAULT_TOL = 1e-3

#: Most random points (``n_random``) one call draws, and most points of one
#: grid: the cap of :func:`~ofrl_drake.verification.verify_observer`'s samples
#: (memory grows with them).
MAX_POINTS = 10_000_000


def _is_whole(value: Any, least: int) -> bool:
    """Whether ``value`` is a whole number ``>= least``: an int, or a float such as ``1e4``."""
    return is_real_number(value) and math.isfinite(value) and int(value) == value and value >= least


def jacobian_bounds(
    system: ControlAffineSystem,
    box: Any,
    method: str = "sampled",
    *,
    grid: int | None = None,
    n_random: int = 10_000,
    seed: int = 0,
    tol: float = DEFAULT_TOL,
    rtol: float | None = None,
    max_boxes: int = 200_000,
    max_wall_time: float | None = None,
) -> JacobianBounds:
    """Element-wise bounds of the Jacobians of ``f`` and ``g`` over ``box``.

    Parameters
    ----------
    system : ControlAffineSystem
        The plant. ``f`` and ``g`` must accept ``pydrake.symbolic.Expression``
        states; they are differentiated with ``pydrake.symbolic.Jacobian``.
    box : Box or (lower, upper)
        The compact set, an axis-aligned box of dimension ``n``.
    method : {"sampled", "certified"}
        ``"sampled"``: min and max over a grid plus random points (an inner
        estimate). ``"certified"``: guaranteed interval enclosures, refined by
        branch and bound until each is within the tolerance of the best known
        inner estimate (the samples plus the centres of the boxes visited);
        multibody models are enclosed through their mass-matrix structure
        (module docstring). A plant with ``log``, ``sqrt``, ``asin``,
        ``acos`` or a real power is first proven defined, with its Jacobian
        entries, at every state of the box (:mod:`ofrl_drake.domain`): the
        enclosures alone cover only where they are defined.
    grid : int, optional
        Points per axis of the grid (the corners are included). Each Jacobian
        entry is gridded over the ``d`` states it depends on only. Default: the
        largest odd number up to 101 with ``grid**d <= 100000``.
    n_random : int
        Uniform random points added to the grid.
    seed : int
        Seed of the random points.
    tol : float
        Certified only: absolute tolerance, in the units of the Jacobian entry.
    rtol : float, optional
        Certified only: relative tolerance; an entry's enclosure may reach
        ``max(tol, rtol * w)`` beyond each end of its inner estimate of width
        ``w``. Default: :data:`MULTIBODY_RTOL` for multibody models, 0 (``tol``
        alone) for the others.
    max_boxes : int
        Certified only: the most boxes evaluated for all entries together (per
        entry for those refined alone, module docstring; at least one box per
        group of entries that share no variable). When it is reached,
        the (still guaranteed) enclosure is returned as it is, and
        ``excess.converged`` is False.
    max_wall_time : float, optional
        Seconds after which no further row of ``f`` is differentiated
        symbolically (:func:`symbolic_jacobians`: past it,
        :class:`~ofrl_drake.errors.WallTimeExceeded`) and, certified, no
        further boxes are refined (the enclosure reached is returned, as for
        ``max_boxes``). Default: no limit.

    Returns
    -------
    JacobianBounds
        For ``"certified"``, ``excess`` records how much wider the bounds are
        than the sampled ones (same grid, points and seed).

    Raises
    ------
    BoundsError
        For a ``system`` that is not a :class:`ControlAffineSystem`, an unknown
        method or bad parameters (``n_random``, or the points of a grid, above
        :data:`MAX_POINTS`; a negative ``seed``; a string for a number), if
        ``f``/``g`` cannot be differentiated symbolically, a Jacobian entry
        is not finite, or (certified) ``f``, ``g`` or a Jacobian entry is, or
        cannot be proven not to be, undefined at some state of the box.
    UncertifiedBoundsError
        If a certified bound is still infinite when ``max_boxes`` or
        ``max_wall_time`` runs out (the message names the entry and the box).
    WallTimeExceeded
        If ``max_wall_time`` runs out before the symbolic Jacobians are formed.
    BoxError
        If ``box`` is malformed or not ``n``-dimensional.
    UnsupportedExpressionError
        If a Jacobian entry uses a function the evaluator does not support,
        such as the branch (``IfThenElse``) that ``np.abs``, ``np.maximum``,
        ``np.minimum`` or ``np.sign`` in ``f`` or ``g`` put in the Jacobian.

    Examples
    --------
    >>> from ofrl_drake.examples import make_system
    >>> b = jacobian_bounds(make_system("two_state"), ([-2, -2], [2, 2]))
    >>> b.Mf1[0].tolist(), b.Mf2[0].tolist()
    ([-1.0, 1.0], [-1.0, 1.0])
    """
    start = time.monotonic()
    require_system(system, "jacobian_bounds: system", BoundsError)
    if method not in METHODS:
        raise BoundsError(
            f"method must be one of {METHODS}; got {method!r}. Use 'sampled' for "
            "fast estimates or 'certified' for guaranteed enclosures."
        )
    box = Box.coerce(box, system.n)
    n, m = system.n, system.m
    if grid is not None and not _is_whole(grid, 1):
        raise BoundsError(f"grid must be a positive integer; got {grid!r}.")
    if not _is_whole(n_random, 0):
        raise BoundsError(f"n_random must be a non-negative integer; got {n_random!r}.")
    if n_random > MAX_POINTS:
        raise BoundsError(
            f"n_random: {n_random} would need about {n_random * 8 * 3 * n / 2**30:.3g} GiB "
            f"for the random points; at most {MAX_POINTS} per call (a finer grid, "
            "or method 'certified', covers the box more surely)."
        )
    integer_at_least("seed", seed, error=BoundsError)
    if not (is_real_number(tol) and math.isfinite(tol) and tol > 0):
        raise BoundsError(f"tol must be a positive number; got {tol!r}.")
    if rtol is not None and not (is_real_number(rtol) and math.isfinite(rtol) and rtol >= 0):
        raise BoundsError(f"rtol must be a number >= 0; got {rtol!r}.")
    if not _is_whole(max_boxes, 1):
        raise BoundsError(f"max_boxes must be a positive integer; got {max_boxes!r}.")
    if max_wall_time is not None and not (
        is_real_number(max_wall_time) and math.isfinite(max_wall_time) and max_wall_time > 0
    ):
        raise BoundsError(
            f"max_wall_time must be a positive number of seconds; got {max_wall_time!r}."
        )
    deadline = None if max_wall_time is None else start + float(max_wall_time)

    names = _entry_names(n, m)
    structure = system.multibody_structure()
    entries: np.ndarray | None = None
    if structure is not None and _too_large_to_differentiate(system):
        s_lo, s_hi = _structure_samples(structure, box, grid, int(n_random), seed, names, deadline)
    else:
        model, Jf, Jg = _traced_jacobians(system, deadline)
        x = model.x
        entries = np.concatenate([Jf.ravel(), Jg.ravel()])
        s_lo, s_hi = _sampled_bounds(entries, x, box, grid, int(n_random), seed, names)

    def split(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return v[: n * n].reshape(n, n), v[n * n :].reshape(n, n, m)

    if method == "sampled":
        (Mf1, Mg1), (Mf2, Mg2) = split(s_lo), split(s_hi)
        return JacobianBounds("sampled", box, Mf1, Mf2, Mg1, Mg2)

    if structure is not None:
        _check_structure(system, structure, box, seed)
        result = refine(
            MultibodyJacobianEncloser(structure, deadline),
            box.lower,
            box.upper,
            s_lo,
            s_hi,
            tol=float(tol),
            rtol=MULTIBODY_RTOL if rtol is None else float(rtol),
            max_boxes=int(max_boxes),
            deadline=deadline,
        )
        c_lo, c_hi, converged = np.array(result.lo), np.array(result.hi), result.converged
        budget = result.budget
    else:
        assert entries is not None  # no multibody structure: the symbolic Jacobians
        _prove_defined(model, entries, box, names, deadline)
        c_lo, c_hi, converged, budget = _certify_symbolic(
            entries,
            x,
            box,
            s_lo,
            s_hi,
            float(tol),
            0.0 if rtol is None else float(rtol),
            int(max_boxes),
            deadline,
            names,
        )
    infinite = np.flatnonzero(~(np.isfinite(c_lo) & np.isfinite(c_hi)))
    if infinite.size:
        e = int(infinite[0])
        raise UncertifiedBoundsError(
            f"the certified bound of {names[e]} over {box!r} is [{c_lo[e]:g}, {c_hi[e]:g}]: "
            f"not finite ({budget}); {infinite.size} entries are. Allow more boxes or "
            "wall time (max_boxes, max_wall_time, --max-wall), shrink the box, or use "
            "jacobian_method 'sampled' (not guaranteed). If f or g has a pole in the box "
            "(a division by an expression of the state that is zero there, tan at pi/2), "
            "the Jacobian is unbounded there: no budget bounds it and 'sampled' bounds "
            "are wrong; shrink the box to exclude the pole."
        )
    (Mf1, Mg1), (Mf2, Mg2) = split(c_lo), split(c_hi)
    (sMf1, sMg1), (sMf2, sMg2) = split(s_lo), split(s_hi)
    ex = [sMf1 - Mf1, Mf2 - sMf2, sMg1 - Mg1, Mg2 - sMg2]
    xMf1, xMf2, xMg1, xMg2 = (_frozen_array(a) for a in ex)
    excess = BoundsExcess(
        xMf1,
        xMf2,
        xMg1,
        xMg2,
        max=float(max(a.max() for a in ex)),
        converged=converged,
    )
    return JacobianBounds("certified", box, Mf1, Mf2, Mg1, Mg2, excess)


def _check_structure(
    system: ControlAffineSystem, structure: MultibodyStructure, box: Box, seed: int
) -> None:
    """The structure must give the system's own ``f`` and ``g`` (at points of the box)."""
    X = np.concatenate([box.center[:, None], _random_points(box, _STRUCTURE_POINTS, seed)], axis=1)
    f, g = structure.dynamics(X)
    for name, mine, theirs in (("f", f, system.f_batch(X)), ("g", g, system.g_batch(X))):
        err = np.abs(mine - theirs)
        bad = ~(err <= STRUCTURE_RTOL * (1.0 + np.abs(theirs)))
        if bad.any():
            p = int(np.argwhere(bad)[0][-1])
            raise BoundsError(
                f"{system.name}: the multibody structure (M, tau, B) gives a {name} that "
                f"differs from the system's own by {err.max():.3g} at x = {X[:, p].tolist()}; "
                "multibody_structure() must describe this system's f and g (a shifted "
                "system shifts its structure)."
            )
