"""The one branch and bound, on a toy encloser: sound, convergent, stopped by budgets."""

import time

import numpy as np
import pytest

import ofrl_drake.branch_and_bound as bb
from ofrl_drake.branch_and_bound import RestrictableEncloser, refine
from ofrl_drake.interval import Interval

LO = np.array([-1.0, -0.5, 0.0])
HI = np.array([1.0, 0.5, 3.0])  # x[2] is used by no entry: never split
C = np.array([0.0, 1.0, 2.0, -3.0])


def values(x: np.ndarray) -> np.ndarray:
    """``h_e(x) = x0 x0 - C_e x0 x1``, shape (E, points)."""
    return x[0] * x[0] - C[:, None] * x[0] * x[1]


class Toy:
    """Naive interval arithmetic on ``values``: overestimates, exact at points.

    ``sizes`` records the boxes of each ``enclose`` call.
    """

    used = np.array([0, 1])

    def __init__(self, c=C, chunk=64):
        self.c = np.asarray(c, dtype=float)
        self.n_entries = self.c.size
        self.chunk = chunk
        self.sizes = []

    def _eval(self, lo, hi):
        x0, x1 = Interval(lo[0], hi[0]), Interval(lo[1], hi[1])
        sq, cross = x0 * x0, x0 * x1
        return Interval(
            sq.lo[None] - np.maximum(self.c[:, None] * cross.hi, self.c[:, None] * cross.lo),
            sq.hi[None] - np.minimum(self.c[:, None] * cross.hi, self.c[:, None] * cross.lo),
        )

    def enclose(self, lower, upper):
        self.sizes.append(lower.shape[1])
        c = 0.5 * (lower + upper)
        at_c = self._eval(c, c)
        # Outward by a few ulps, so the centre values hold the true ones.
        at_c = Interval(np.nextafter(at_c.lo, -np.inf), np.nextafter(at_c.hi, np.inf))
        return self._eval(lower, upper), at_c, None


class RestrictableToy(Toy):
    def restrict(self, entries):
        return RestrictableToy(self.c[entries], self.chunk)


def samples(n=200, seed=0):
    """Ranges over random points: the inner estimates given to ``refine``."""
    rng = np.random.default_rng(seed)
    x = LO[:, None] + rng.random((3, n)) * (HI - LO)[:, None]
    v = values(x)
    return v.min(axis=1), v.max(axis=1)


def exact():
    """The exact ranges: on a grid that holds the corners and each entry's minimiser."""
    g = np.meshgrid(np.linspace(LO[0], HI[0], 401), np.linspace(LO[1], HI[1], 401))
    v = values(np.stack([g[0].ravel(), g[1].ravel()]))
    return v.min(axis=1), v.max(axis=1)


@pytest.mark.parametrize("encloser", [Toy(), RestrictableToy()])
def test_converges_to_the_tolerance_and_contains_the_range(encloser):
    s_lo, s_hi = samples()
    out = refine(encloser, LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=10**6)
    assert out.converged and out.stop == "converged" and out.open_entries.size == 0
    d_lo, d_hi = exact()
    assert np.all(out.lo <= d_lo) and np.all(d_hi <= out.hi)
    np.testing.assert_allclose(out.lo, d_lo, atol=1.1e-3)
    np.testing.assert_allclose(out.hi, d_hi, atol=1.1e-3)
    assert out.finest < 1.0 and not out.lo.flags.writeable
    assert isinstance(encloser, RestrictableEncloser) == hasattr(encloser, "restrict")


@pytest.mark.parametrize("encloser", [Toy(), RestrictableToy()])
def test_budgets_stop_it_soundly_and_name_the_open_entries(encloser):
    s_lo, s_hi = samples()
    d_lo, d_hi = exact()
    few = refine(encloser, LO, HI, s_lo, s_hi, tol=1e-9, rtol=0.0, max_boxes=100)
    assert few.stop == "max_boxes" and not few.converged and few.boxes <= 100
    assert np.all(few.lo <= d_lo) and np.all(d_hi <= few.hi) and few.open_entries.size
    now = refine(encloser, LO, HI, s_lo, s_hi, tol=1e-9, rtol=0.0, max_boxes=100, deadline=0.0)
    assert now.stop == "max_wall_time" and now.boxes == 1  # the first box always is enclosed
    assert np.all(now.lo <= d_lo) and np.all(d_hi <= now.hi)


def test_a_clock_that_stops_a_level_midway_keeps_the_parents_hull(monkeypatch):
    s_lo, s_hi = samples()
    d_lo, d_hi = exact()
    encloser = Toy(chunk=4)
    # A clock that ticks at each reading: the deadline falls inside a chunk of the
    # third level, after its first box (slices of one box under a deadline).
    clock = iter(range(10**6))
    monkeypatch.setattr(bb.time, "monotonic", lambda: float(next(clock)))
    out = refine(encloser, LO, HI, s_lo, s_hi, tol=1e-9, rtol=0.0, max_boxes=10**6, deadline=41)
    assert out.stop == "max_wall_time" and out.boxes == sum(encloser.sizes)
    assert np.all(out.lo <= d_lo) and np.all(d_hi <= out.hi)


def test_timed_slices_change_no_bound(monkeypatch):
    s_lo, s_hi = samples()
    free = refine(Toy(), LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=10**6)
    monkeypatch.setattr(bb, "_CHUNK_SECONDS", 1e-12)  # one box per call
    timed = refine(
        Toy(), LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=10**6,
        deadline=time.monotonic() + 3600.0,
    )  # fmt: skip
    assert timed.boxes == free.boxes
    np.testing.assert_array_equal(timed.lo, free.lo)
    np.testing.assert_array_equal(timed.hi, free.hi)


@pytest.mark.parametrize(("max_boxes", "grid"), [(10**6, 256), (100, 64), (5, 4)])
def test_the_level_after_the_whole_box_is_the_largest_grid_the_budget_allows(max_boxes, grid):
    # Two used sides: one enclosure of 256 boxes costs about what one of a box does,
    # so the whole box is split straight into 16 x 16 (4, 16, 64 skipped), within
    # what is left of max_boxes.
    s_lo, s_hi = samples()
    encloser = Toy(chunk=4096)
    out = refine(encloser, LO, HI, s_lo, s_hi, tol=1e-3, rtol=0.0, max_boxes=max_boxes)
    sizes = encloser.sizes
    assert sizes[:2] == [1, grid] and out.boxes == sum(sizes) <= max_boxes
    d_lo, d_hi = exact()
    assert np.all(out.lo <= d_lo) and np.all(d_hi <= out.hi)


@pytest.mark.parametrize(
    ("n_open", "d", "room", "halvings"),
    [
        (1, 2, 256, 4),
        (1, 3, 256, 2),
        (64, 2, 256, 1),
        (65, 2, 256, 0),
        (1, 9, 256, 0),
        (3, 1, 5, 0),
        (5, 2, 4, 0),
        (1, 2, 0, 0),
    ],
)
def test_halvings_keep_the_children_within_the_room(n_open, d, room, halvings):
    assert bb._halvings(n_open, d, room) == halvings
    assert room < n_open * 2 ** ((halvings + 1) * d)  # one more would not fit
    if halvings:
        assert n_open * 2 ** (halvings * d) <= room
