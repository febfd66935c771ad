"""Bellman-error extrapolation points, as arrays of shape ``(n, N)``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from ofrl_drake.checks import integer_at_least
from ofrl_drake.errors import ModelError

__all__ = ["grid_points", "uniform_points"]


def _check_box(lower: ArrayLike, upper: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    if lo.shape != hi.shape or lo.ndim != 1:
        raise ModelError(
            f"points: lower {lo.tolist()} and upper {hi.tolist()} must be vectors "
            "of the same length n."
        )
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
        raise ModelError(
            f"points: need finite lower < upper element-wise; got lower={lo.tolist()}, "
            f"upper={hi.tolist()}."
        )
    return lo, hi


def grid_points(lower: ArrayLike, upper: ArrayLike, counts: Sequence[int]) -> np.ndarray:
    """A tensor grid: ``linspace(lower_j, upper_j, counts_j)`` in each axis.

    The paper's 100 points are ``grid_points([-1, -1], [1, 1], [10, 10])``.
    Points are ordered with the first coordinate varying slowest.

    Raises
    ------
    ModelError
        If ``lower`` and ``upper`` are not finite vectors of one length n with
        ``lower < upper``, or ``counts`` is not n integers >= 1.
    """
    lo, hi = _check_box(lower, upper)
    given = list(counts) if isinstance(counts, (Sequence, np.ndarray)) else None
    if given is None or len(given) != lo.size:
        raise ModelError(f"points.counts must hold {lo.size} positive integers; got {counts!r}.")
    sizes = [integer_at_least(f"points.counts[{j}]", c, 1) for j, c in enumerate(given)]
    axes = [np.linspace(a, b, c) for a, b, c in zip(lo, hi, sizes, strict=True)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=0)


def uniform_points(lower: ArrayLike, upper: ArrayLike, number: int, seed: int) -> np.ndarray:
    """``number`` points drawn uniformly in the box from ``numpy`` generator ``seed``.

    Raises
    ------
    ModelError
        If ``lower`` and ``upper`` are not finite vectors of one length with
        ``lower < upper``, ``number`` is not an integer >= 1 or ``seed`` not an
        integer >= 0.
    """
    lo, hi = _check_box(lower, upper)
    count = integer_at_least("points.number", number, 1)
    rng = np.random.default_rng(integer_at_least("points.seed", seed, 0))
    return lo[:, None] + (hi - lo)[:, None] * rng.random((lo.size, count))
