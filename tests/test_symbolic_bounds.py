"""Many symbolic expressions certified together: sound, convergent, stopped by a budget."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydrake.symbolic import MakeVectorVariable, cos, sin

from ofrl_drake.branch_and_bound import Refinement, refine
from ofrl_drake.interval import ExpressionEvaluator
from ofrl_drake.symbolic_bounds import TaylorEncloser, independent_groups

X = MakeVectorVariable(3, "x")
r, p, w = X
# A rotation's yaw written in and cancelled (the first is 0, the second sin(r) w),
# one easy entry, and one that needs no Taylor form at all (a constant).
EXPRS = [
    60.0 * (sin(p) ** 2 + cos(p) ** 2) - 60.0 + 0.0 * w,
    ((sin(p) * cos(r) + cos(p) * sin(r)) * cos(p) - (cos(p) * cos(r) - sin(p) * sin(r)) * sin(p))
    * w,
    2.0 * r + w**2,
    1.0 + 0.0 * r,
]
LO = np.array([-0.3, -0.2, -1.0])
HI = np.array([0.3, 0.2, 1.0])


def certify_expressions(exprs, x, lo, hi, inner_lo, inner_hi, **budget) -> Refinement:
    """The one branch and bound with the Taylor encloser of ``exprs``."""
    return refine(TaylorEncloser(exprs, x), lo, hi, inner_lo, inner_hi, **budget)


def _samples(n=20000, seed=0):
    rng = np.random.default_rng(seed)
    P = LO[:, None] + rng.random((3, n)) * (HI - LO)[:, None]
    corners = np.array(np.meshgrid(*zip(LO, HI, strict=True), indexing="ij")).reshape(3, -1)
    values = ExpressionEvaluator(EXPRS, X)(np.hstack([P, corners]))
    return values.min(axis=1), values.max(axis=1)


def test_converges_within_the_tolerance_of_the_samples_and_contains_them():
    s_lo, s_hi = _samples()
    out = certify_expressions(EXPRS, X, LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=200_000)
    assert out.converged and out.stop == "converged" and out.open_entries.size == 0
    assert np.all(out.lo <= s_lo) and np.all(s_hi <= out.hi)
    # Each end within tol of the best inner estimate, which the samples approach.
    np.testing.assert_allclose(out.lo, s_lo, atol=2e-3)
    np.testing.assert_allclose(out.hi, s_hi, atol=2e-3)
    # The exact ranges: 0, sin(0.3) * [-1, 1], 2 r + w^2 in [-0.6, 1.6], 1.
    assert out.lo[0] <= 0.0 <= out.hi[0] and out.hi[0] - out.lo[0] <= 2e-3
    assert out.lo[1] <= -np.sin(0.3) and np.sin(0.3) <= out.hi[1]
    assert out.lo[2] <= -0.6 and 1.6 <= out.hi[2]


def test_a_wall_clock_stop_is_sound_and_names_the_open_entries():
    s_lo, s_hi = _samples()
    rushed = certify_expressions(
        EXPRS, X, LO, HI, s_lo, s_hi, tol=1e-9, rtol=0.0, max_boxes=10**7, deadline=0.0
    )
    assert not rushed.converged and rushed.stop == "max_wall_time"
    assert np.all(rushed.lo <= s_lo) and np.all(s_hi <= rushed.hi)
    assert 0 in rushed.open_entries.tolist()


def test_a_deadline_that_is_not_reached_changes_no_bound(monkeypatch):
    # Under a deadline the boxes go to the encloser in chunks timed to about
    # _CHUNK_SECONDS; each box is enclosed alone, so the bounds are the same.
    import time

    import ofrl_drake.branch_and_bound as bb
    import ofrl_drake.symbolic_bounds as sb

    s_lo, s_hi = _samples()
    free = certify_expressions(EXPRS, X, LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=10**6)
    sizes = []
    enclose = sb.TaylorEncloser.enclose

    def spy(self, lower, upper):
        sizes.append(lower.shape[1])
        return enclose(self, lower, upper)

    monkeypatch.setattr(bb, "_CHUNK_SECONDS", 1e-12)  # one box per call
    monkeypatch.setattr(sb.TaylorEncloser, "enclose", spy)
    timed = certify_expressions(
        EXPRS, X, LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=10**6,
        deadline=time.monotonic() + 3600.0,
    )  # fmt: skip
    assert timed.converged and timed.boxes == free.boxes
    np.testing.assert_array_equal(timed.lo, free.lo)
    np.testing.assert_array_equal(timed.hi, free.hi)
    assert max(sizes[1:]) == 1 and len(sizes) == timed.boxes


def test_a_box_budget_stop_is_sound():
    s_lo, s_hi = _samples()
    few = certify_expressions(EXPRS, X, LO, HI, s_lo, s_hi, tol=1e-9, rtol=0.0, max_boxes=50)
    assert not few.converged and few.stop == "max_boxes" and few.boxes <= 50
    assert np.all(few.lo <= s_lo) and np.all(s_hi <= few.hi)
    assert np.all(np.isfinite(few.lo)) and np.all(np.isfinite(few.hi))


def test_the_encloser_intersects_the_taylor_form_with_the_natural_one():
    enc = TaylorEncloser(EXPRS, X)
    assert enc.used.tolist() == [0, 1, 2] and enc.n_entries == 4
    boxes, centres, spread = enc.enclose(LO[:, None], HI[:, None])
    natural = ExpressionEvaluator(EXPRS, X).interval(LO[:, None], HI[:, None])
    assert np.all(natural.lo <= boxes.lo) and np.all(boxes.hi <= natural.hi)
    # The cancelling entry: the natural form is wide, the Taylor form much narrower.
    assert boxes.hi[0, 0] - boxes.lo[0, 0] < 0.2 * (natural.hi[0, 0] - natural.lo[0, 0])
    assert centres.lo[3, 0] == centres.hi[3, 0] == 1.0
    assert spread.shape == (4, 3, 1) and np.all(spread >= 0)


@pytest.mark.parametrize("rtol", [0.1, 0.5])
def test_rtol_lets_wide_entries_settle_sooner(rtol):
    s_lo, s_hi = _samples()
    tight = certify_expressions(EXPRS, X, LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=10**6)
    loose = certify_expressions(EXPRS, X, LO, HI, s_lo, s_hi, tol=1e-3, rtol=rtol, max_boxes=10**6)
    assert loose.converged and loose.boxes < tight.boxes
    slack = np.maximum(1e-3, rtol * (s_hi - s_lo))
    assert np.all(loose.lo >= s_lo - slack - 1e-12) and np.all(loose.hi <= s_hi + slack + 1e-12)


def test_independent_groups_of_a_block_diagonal_plant():
    # Two copies of a 2-state plant and a term that joins them late (entry 4).
    assert [g.tolist() for g in independent_groups([(0, 1), (2, 3), (1,), (3,)])] == [
        [0, 2],
        [1, 3],
    ]
    joined = independent_groups([(0, 1), (2, 3), (1,), (3,), (0, 3)])
    assert [g.tolist() for g in joined] == [[0, 1, 2, 3, 4]]
    assert [g.tolist() for g in independent_groups([(), (0,), ()])] == [[0], [1], [2]]
    assert independent_groups([]) == []


@given(st.lists(st.sets(st.integers(0, 7), max_size=3), max_size=12))
def test_independent_groups_partition_the_entries_and_share_no_variable(uses):
    groups = independent_groups([sorted(u) for u in uses])
    entries = sorted(int(e) for g in groups for e in g)
    assert entries == list(range(len(uses)))  # a partition
    variables = [set().union(*(uses[e] for e in g)) for g in groups]
    for a in range(len(groups)):
        for b in range(a + 1, len(groups)):
            assert not variables[a] & variables[b]  # no variable shared across groups
    for g, used in zip(groups, variables, strict=True):
        # Within a group, every entry is reached from the first through shared variables.
        reached, frontier = {int(g[0])}, set(uses[int(g[0])])
        grew = True
        while grew:
            new = {int(e) for e in g if int(e) not in reached and uses[int(e)] & frontier}
            grew = bool(new)
            reached |= new
            for e in new:
                frontier |= uses[e]
        assert reached == {int(e) for e in g} and frontier == used
