"""Interval matrix products and the interval linear solver: enclosure, tightness, failure."""

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from ofrl_drake.errors import ModelError
from ofrl_drake.interval import Interval
from ofrl_drake.interval_linalg import IntervalLinearSystem, interval_matmul


def _exact_solve(A: np.ndarray, b: np.ndarray) -> list[list[Fraction]]:
    """``A^-1 b`` in exact rational arithmetic (Gaussian elimination, partial pivoting)."""
    k, r = b.shape
    M = [[Fraction(float(A[i, j])) for j in range(k)] + [Fraction(float(v)) for v in b[i]]
         for i in range(k)]  # fmt: skip
    for c in range(k):
        p = max(range(c, k), key=lambda i: abs(M[i][c]))
        M[c], M[p] = M[p], M[c]
        for i in range(k):
            if i != c and M[i][c] != 0:
                f = M[i][c] / M[c][c]
                M[i] = [a - f * b_ for a, b_ in zip(M[i], M[c], strict=True)]
    return [[M[i][k + j] / M[i][i] for j in range(r)] for i in range(k)]


def _realizations(lo: np.ndarray, hi: np.ndarray, rng, count: int) -> list[np.ndarray]:
    """Corner picks (each entry at an end) and uniform points of ``[lo, hi]``."""
    out = []
    for t in range(count):
        if t % 2 == 0:
            out.append(np.where(rng.random(lo.shape) < 0.5, lo, hi))
        else:
            out.append(lo + rng.random(lo.shape) * (hi - lo))
    return out


@st.composite
def interval_systems(draw):
    k = draw(st.integers(1, 4))
    r = draw(st.integers(1, 3))
    seed = draw(st.integers(0, 2**32 - 1))
    spread = draw(st.floats(0.0, 0.3))
    scale = draw(st.sampled_from([1e-3, 1.0, 1e3]))
    rng = np.random.default_rng(seed)
    mid = rng.normal(size=(k, k)) + (k + 1.0) * np.eye(k) * rng.choice([-1.0, 1.0], size=k)
    rad = spread * rng.random((k, k)) * np.abs(mid).mean()
    b_mid = rng.normal(size=(k, r)) * scale
    b_rad = spread * rng.random((k, r)) * scale
    return Interval(mid - rad, mid + rad), Interval(b_mid - b_rad, b_mid + b_rad), seed


#: Found by hypothesis: A holds singular matrices, so x has infinite ends.
_SINGULAR_CASE = (
    Interval(
        np.array([[5.06183913, -0.83270933], [0.36758187, -0.49936334]]),
        np.array([[5.08052133, -0.21145611], [0.39268115, 0.18915466]]),
    ),
    Interval(np.array([[-0.00085681], [0.00261034]]), np.array([[-0.00041149], [0.00270936]])),
    4811825,
)


@settings(max_examples=60, deadline=None)
@given(case=interval_systems())
@example(case=_SINGULAR_CASE)
def test_solver_contains_every_solution_of_random_interval_systems(case):
    A, b, seed = case
    x = IntervalLinearSystem(A).solve(b)
    assert x.lo.shape == b.lo.shape
    rng = np.random.default_rng(seed)
    for A_s, b_s in zip(
        _realizations(A.lo, A.hi, rng, 24), _realizations(b.lo, b.hi, rng, 24), strict=True
    ):
        exact = _exact_solve(A_s, b_s)
        for i in range(b_s.shape[0]):
            for j in range(b_s.shape[1]):
                # exact rational comparison: no tolerance (an infinite end, of an A that
                # holds a singular matrix, contains everything)
                lo, hi = float(x.lo[i, j]), float(x.hi[i, j])
                assert lo == -math.inf or Fraction(lo) <= exact[i][j]
                assert hi == math.inf or exact[i][j] <= Fraction(hi)


@settings(max_examples=25, deadline=None)
@given(case=interval_systems())
def test_batched_solves_match_one_at_a_time(case):
    A, b, _ = case
    # The same systems stacked along a trailing axis of 3, with the middle one widened.
    wide = Interval(A.lo - 0.01, A.hi + 0.01)
    A3 = Interval(np.stack([A.lo, wide.lo, A.lo], -1), np.stack([A.hi, wide.hi, A.hi], -1))
    b3 = Interval(np.stack([b.lo] * 3, -1), np.stack([b.hi] * 3, -1))
    x3 = IntervalLinearSystem(A3).solve(b3)
    x1 = IntervalLinearSystem(A).solve(b)
    # Equal up to the rounding of a batched inverse (a few ulps of the ends).
    atol = 1e-12 * (1.0 + np.abs(x1.lo).max() + np.abs(x1.hi).max())
    for s in (0, 2):
        np.testing.assert_allclose(x3.lo[..., s], x1.lo, rtol=1e-12, atol=atol)
        np.testing.assert_allclose(x3.hi[..., s], x1.hi, rtol=1e-12, atol=atol)
    assert np.all(x3.lo[..., 1] <= x1.lo + atol) and np.all(x1.hi - atol <= x3.hi[..., 1])
    part = IntervalLinearSystem(A3).select(slice(2, 3)).solve(b3[..., 2:3])
    np.testing.assert_allclose(part.lo[..., 0], x3.lo[..., 2], rtol=1e-12, atol=atol)
    np.testing.assert_allclose(part.hi[..., 0], x3.hi[..., 2], rtol=1e-12, atol=atol)


def test_thin_systems_are_solved_to_a_few_ulps():
    rng = np.random.default_rng(4)
    for k in (1, 2, 3, 5):
        A = rng.normal(size=(k, k)) + 3 * np.eye(k)
        b = rng.normal(size=(k, 2))
        x = IntervalLinearSystem(Interval(A, A)).solve(Interval(b, b))
        exact = np.linalg.solve(A, b)
        assert np.all(x.lo <= exact + 1e-13) and np.all(exact - 1e-13 <= x.hi)
        np.testing.assert_array_less(x.hi - x.lo, 1e-13 * (1 + np.abs(exact)))


def test_one_by_one_matches_the_residual_form_by_hand():
    # [2, 4] x = [1, 2]: the solution set is [1/4, 1]. By hand: C = 1/3,
    # x~ = 1/2, z = C ([1, 2] - [2, 4] / 2) = [-1/3, 1/3], G = [2/3, 4/3],
    # e = z / G = [-1/2, 1/2]: the enclosure is [0, 1] (the residual form
    # counts [A] twice, the price of its quadratic convergence on thin systems).
    x = IntervalLinearSystem(Interval(np.array([[2.0]]), np.array([[4.0]]))).solve(
        Interval(np.array([[1.0]]), np.array([[2.0]]))
    )
    assert x.lo[0, 0] <= 0.25 and x.hi[0, 0] >= 1.0
    assert x.lo[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert x.hi[0, 0] == pytest.approx(1.0, abs=1e-12)


def test_a_matrix_box_that_may_be_singular_gives_the_whole_line():
    # [-1, 1] holds 0; the second system [[1, 2], [1, 2 +- 0.5]] holds a singular matrix.
    A = Interval(
        np.stack([np.array([[-1.0, 0.0], [0.0, 1.0]]), np.array([[1.0, 2.0], [1.0, 1.5]])], -1),
        np.stack([np.array([[1.0, 0.0], [0.0, 1.0]]), np.array([[1.0, 2.0], [1.0, 2.5]])], -1),
    )
    b = Interval(np.ones((2, 1, 2)), np.ones((2, 1, 2)))
    system = IntervalLinearSystem(A)
    assert np.all(system.beta >= 1.0)
    x = system.solve(b)
    assert np.all(x.lo == -np.inf) and np.all(x.hi == np.inf)
    # Infinite ends are a failure too, not a NaN.
    inf = Interval(np.full((2, 2), -np.inf), np.full((2, 2), np.inf))
    x = IntervalLinearSystem(inf).solve(Interval(np.ones((2, 1)), np.ones((2, 1))))
    assert np.all(x.lo == -np.inf) and np.all(x.hi == np.inf)


def test_infinite_right_hand_sides_give_infinite_ends_not_nan():
    A = Interval(np.eye(2), np.eye(2))
    b = Interval(np.array([[0.0], [-np.inf]]), np.array([[1.0], [np.inf]]))
    x = IntervalLinearSystem(A).solve(b)
    assert not np.any(np.isnan(x.lo)) and not np.any(np.isnan(x.hi))
    assert x.lo[1, 0] == -np.inf and x.hi[1, 0] == np.inf


@settings(max_examples=40, deadline=None)
@given(
    k=st.integers(1, 4),
    l=st.integers(1, 4),
    r=st.integers(1, 3),
    seed=st.integers(0, 2**32 - 1),
)
def test_matmul_contains_every_product(k, l, r, seed):
    rng = np.random.default_rng(seed)
    A_mid, X_mid = rng.normal(size=(k, l)) * 10, rng.normal(size=(l, r))
    A = Interval(A_mid - rng.random((k, l)), A_mid + rng.random((k, l)))
    X = Interval(X_mid - rng.random((l, r)), X_mid + rng.random((l, r)))
    P = interval_matmul(A, X)
    for A_s, X_s in zip(
        _realizations(A.lo, A.hi, rng, 30), _realizations(X.lo, X.hi, rng, 30), strict=True
    ):
        exact = [
            [sum(Fraction(float(A_s[i, t])) * Fraction(float(X_s[t, j])) for t in range(l))
             for j in range(r)]
            for i in range(k)
        ]  # fmt: skip
        for i in range(k):
            for j in range(r):
                assert Fraction(float(P.lo[i, j])) <= exact[i][j] <= Fraction(float(P.hi[i, j]))


def test_a_non_square_matrix_is_refused_by_shape():
    with pytest.raises(ModelError, match=r"square interval matrices.*got lo \(2, 3\)"):
        IntervalLinearSystem(Interval(np.zeros((2, 3)), np.zeros((2, 3))))
