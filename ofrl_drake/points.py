"""Bellman-error extrapolation points, as arrays of shape ``(n, N)``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

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
    """
    lo, hi = _check_box(lower, upper)
    counts = [int(c) for c in counts]
    if len(counts) != lo.size or min(counts) < 1:
        raise ModelError(
            f"points.counts must hold {lo.size} positive integers; got {list(counts)}."
        )
    axes = [np.linspace(a, b, c) for a, b, c in zip(lo, hi, counts, strict=True)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=0)


def uniform_points(lower: ArrayLike, upper: ArrayLike, number: int, seed: int) -> np.ndarray:
    """``number`` points drawn uniformly in the box from ``numpy`` generator ``seed``."""
    lo, hi = _check_box(lower, upper)
    if int(number) < 1:
        raise ModelError(f"points.number must be a positive integer; got {number}.")
    rng = np.random.default_rng(seed)
    return lo[:, None] + (hi - lo)[:, None] * rng.random((lo.size, int(number)))
