"""Jacobian bounds: closed forms, containment, certified enclosures, errors."""

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ofrl_drake.errors import OfrlError, WallTimeExceeded
from ofrl_drake.examples import make_system
from ofrl_drake.interval import UnsupportedExpressionError
from ofrl_drake.jacobian_bounds import (
    BoundsError,
    Box,
    BoxError,
    JacobianBounds,
    UncertifiedBoundsError,
    jacobian_bounds,
    symbolic_jacobians,
)
from ofrl_drake.model import ControlAffineSystem

BOX2 = ([-2.0, -2.0], [2.0, 2.0])
BOX4 = ([-2.0] * 4, [2.0] * 4)

# df2/dx1 = -1 - 2 x2 (cos 2x1 + 2) sin 2x1. On [-2, 2]^2, 2x1 covers a full
# period, and max_t (cos t + 2) sin t is reached at cos t = (sqrt(3) - 1) / 2.
_c = (np.sqrt(3.0) - 1.0) / 2.0
_PEAK = (_c + 2.0) * np.sqrt(1.0 - _c**2)
DF2DX1 = (-1.0 - 4.0 * _PEAK, -1.0 + 4.0 * _PEAK)


@pytest.fixture(scope="module")
def two_state():
    return make_system("two_state")


@pytest.fixture(scope="module")
def coupled():
    return make_system("coupled_two_state")


@pytest.fixture(scope="module")
def two_state_bounds(two_state):
    return (
        jacobian_bounds(two_state, BOX2, "sampled"),
        jacobian_bounds(two_state, BOX2, "certified", tol=1e-3),
    )


def _finite_difference_jacobians(system, X, h=1e-5):
    n = system.n
    E = np.eye(n)
    Jf = np.stack(
        [
            (system.f_batch(X + h * E[:, [j]]) - system.f_batch(X - h * E[:, [j]])) / (2 * h)
            for j in range(n)
        ],
        axis=1,
    )
    Jg = np.stack(
        [
            (system.g_batch(X + h * E[:, [j]]) - system.g_batch(X - h * E[:, [j]])) / (2 * h)
            for j in range(n)
        ],
        axis=1,
    )
    return Jf, Jg  # (n, n, N) and (n, n, m, N), indexed [i, j, (k,) point]


def test_two_state_closed_form(two_state_bounds):
    for b in two_state_bounds:
        # Row 1 of f = -x1 + x2 is exact.
        np.testing.assert_array_equal(b.Mf1[0], [-1.0, 1.0])
        np.testing.assert_array_equal(b.Mf2[0], [-1.0, 1.0])
        # g = [0, cos 2x1 + 2]: only dg2/dx1 = -2 sin 2x1 in [-2, 2] is not 0.
        np.testing.assert_array_equal(b.Mg1[0], 0.0)
        np.testing.assert_array_equal(b.Mg2[0], 0.0)
        assert b.Mg1[1, 1, 0] == 0.0 and b.Mg2[1, 1, 0] == 0.0
    sampled, certified = two_state_bounds
    # df2/dx2 = 0.5 (c^2 - 1) with c = cos 2x1 + 2 in [1, 3]: [0, 4].
    assert sampled.Mf1[1, 1] == pytest.approx(0.0, abs=1e-6)
    assert sampled.Mf2[1, 1] == pytest.approx(4.0, abs=1e-12)
    assert sampled.Mg1[1, 0, 0] == pytest.approx(-2.0, abs=1e-5)
    assert sampled.Mg2[1, 0, 0] == pytest.approx(2.0, abs=1e-5)
    assert sampled.Mf1[1, 0] == pytest.approx(DF2DX1[0], abs=1e-3)
    assert sampled.Mf2[1, 0] == pytest.approx(DF2DX1[1], abs=1e-3)
    # Certified: contains the exact ranges, and is within tol = 1e-3 of them.
    exact_lo = np.array([[0.0, DF2DX1[0], -2.0], [0.0, 0.0, 0.0]])
    exact_hi = np.array([[4.0, DF2DX1[1], 2.0], [4.0, 0.0, 0.0]])
    got_lo = np.array([certified.Mf1[1, 1], certified.Mf1[1, 0], certified.Mg1[1, 0, 0]])
    got_hi = np.array([certified.Mf2[1, 1], certified.Mf2[1, 0], certified.Mg2[1, 0, 0]])
    assert np.all(got_lo <= exact_lo[0]) and np.all(got_hi >= exact_hi[0])
    np.testing.assert_allclose(got_lo, exact_lo[0], rtol=0, atol=2e-3)
    np.testing.assert_allclose(got_hi, exact_hi[0], rtol=0, atol=2e-3)


def test_certified_contains_sampled(two_state_bounds, coupled):
    sampled, certified = two_state_bounds
    assert certified.method == "certified" and sampled.method == "sampled"
    assert certified.contains(sampled)
    assert sampled.excess is None
    ex = certified.excess
    assert ex.converged
    assert ex.max == pytest.approx(
        max(a.max() for a in (ex.Mf1, ex.Mf2, ex.Mg1, ex.Mg2)), rel=0, abs=0
    )
    assert 0.0 <= ex.max <= 5e-3
    for arr in (ex.Mf1, ex.Mf2, ex.Mg1, ex.Mg2):
        assert np.all(arr >= 0.0)
    s4 = jacobian_bounds(coupled, BOX4, "sampled")
    c4 = jacobian_bounds(coupled, BOX4, "certified", tol=1e-2)
    assert c4.contains(s4)
    assert c4.excess.converged


@pytest.mark.parametrize(
    ("name", "box", "atol"), [("two_state", BOX2, 1e-5), ("coupled_two_state", BOX4, 1e-5)]
)
def test_sampled_contains_an_independent_dense_sample(name, box, atol):
    # Independent: another seed, and finite differences of f and g themselves.
    # Each entry depends on two states, so its grid is 101 x 101 even in 4-D.
    system = make_system(name)
    b = jacobian_bounds(system, box, "sampled")
    X = np.random.default_rng(20240601).uniform(box[0], box[1], size=(100_000, system.n)).T
    Jf, Jg = _finite_difference_jacobians(system, X)
    assert np.all(b.Mf1[..., None] - atol <= Jf) and np.all(Jf <= b.Mf2[..., None] + atol)
    assert np.all(b.Mg1[..., None] - atol <= Jg) and np.all(Jg <= b.Mg2[..., None] + atol)


def test_certified_contains_every_sample_exactly(coupled):
    # Unlike sampled bounds, certified ones need no tolerance at all (beyond
    # the finite-difference error).
    c = jacobian_bounds(coupled, BOX4, "certified", tol=1e-2)
    X = np.random.default_rng(7).uniform(-2.0, 2.0, size=(4, 100_000))
    Jf, Jg = _finite_difference_jacobians(coupled, X)
    assert np.all(c.Mf1[..., None] - 1e-6 <= Jf) and np.all(Jf <= c.Mf2[..., None] + 1e-6)
    assert np.all(c.Mg1[..., None] - 1e-6 <= Jg) and np.all(Jg <= c.Mg2[..., None] + 1e-6)


def test_mimo_shapes_and_entries(coupled):
    b = jacobian_bounds(coupled, BOX4)
    assert b.Mf1.shape == (4, 4) and b.Mg1.shape == (4, 4, 2)
    # Input 1 drives row 2 through cos(2 x1) + 2; input 2 drives row 4 via x3.
    assert b.Mg1[1, 0, 0] == pytest.approx(-2.0, abs=1e-4)
    assert b.Mg2[3, 2, 1] == pytest.approx(2.0, abs=1e-4)
    assert b.Mg1[1, 2, 0] == 0.0 and b.Mg2[3, 0, 1] == 0.0
    # The coupling 0.1 (x3 - x1) enters rows 1 and 3 exactly.
    assert b.Mf1[0, 2] == b.Mf2[0, 2] == pytest.approx(0.1, abs=1e-15)
    assert b.Mf1[2, 0] == b.Mf2[2, 0] == pytest.approx(0.1, abs=1e-15)


def test_symbolic_jacobians_match_finite_differences(two_state):
    x, Jf, Jg = symbolic_jacobians(two_state)
    p = np.array([0.3, -1.1])
    env = {x[0]: p[0], x[1]: p[1]}
    Jf_num = np.array([[e.Evaluate(env) for e in row] for row in Jf])
    Jg_num = np.array([[[e.Evaluate(env)] for e in row[:, 0]] for row in Jg])
    fd_f, fd_g = _finite_difference_jacobians(two_state, p[:, None])
    np.testing.assert_allclose(Jf_num, fd_f[..., 0], rtol=0, atol=1e-8)
    np.testing.assert_allclose(Jg_num, fd_g[..., 0], rtol=0, atol=1e-8)


def test_max_boxes_stops_early_but_stays_guaranteed(two_state, two_state_bounds):
    sampled, _ = two_state_bounds
    rough = jacobian_bounds(two_state, BOX2, "certified", tol=1e-6, max_boxes=8)
    assert not rough.excess.converged
    assert rough.contains(sampled)
    assert rough.excess.max > 1e-3


@settings(max_examples=12, deadline=None)
@given(
    a=st.floats(-3, 3),
    w=st.floats(0.2, 3),
    c=st.floats(-2, 2),
    d=st.floats(-2, 2),
    half=st.floats(0.1, 3),
)
def test_certified_contains_sampled_for_random_systems(a, w, c, d, half):
    system = ControlAffineSystem(
        f=lambda x: np.array([a * np.sin(w * x[0]) + x[1], c * x[0] * x[1] + d * np.cos(x[1])]),
        g=lambda x: np.array([[1 + 0 * x[0]], [np.exp(0.2 * x[0]) * np.tanh(x[1])]]),
        C=[[1.0, 0.0]],
    )
    box = ([-half, -half], [half, half])
    s = jacobian_bounds(system, box, "sampled", grid=21, n_random=500)
    cert = jacobian_bounds(system, box, "certified", grid=21, n_random=500, tol=1e-2)
    assert cert.contains(s)
    assert cert.excess.converged


def test_to_dict_has_nested_lists(two_state_bounds):
    d = two_state_bounds[0].to_dict()
    assert set(d) == {"Mf1", "Mf2", "Mg1", "Mg2"}
    assert np.array(d["Mf1"]).shape == (2, 2) and np.array(d["Mg2"]).shape == (2, 2, 1)
    assert isinstance(d["Mg1"][1][0][0], float)
    again = JacobianBounds.from_dict(d, BOX2, "sampled")
    np.testing.assert_array_equal(again.Mf2, two_state_bounds[0].Mf2)


def test_box_dataclass_and_its_errors():
    box = Box([-1, -2], [1, 2])
    assert box.n == 2
    np.testing.assert_array_equal(box.width, [2.0, 4.0])
    assert Box.coerce(([-1, -2], [1, 2])) == box
    assert Box.coerce({"lower": [-1, -2], "upper": [1, 2]}) == box
    assert box.contains(np.array([[0.0, 1.5], [0.0, -2.5]])).tolist() == [True, False]
    with pytest.raises(BoxError, match=r"lower\[1\] = 3 is not below upper\[1\] = 2"):
        Box([0, 3], [1, 2])
    with pytest.raises(BoxError, match=r"upper\[0\] = inf is not finite"):
        Box([0, 0], [np.inf, 1])
    with pytest.raises(BoxError, match="lower has length 2 but upper has length 3"):
        Box([0, 0], [1, 1, 1])
    with pytest.raises(BoxError, match="dimension 3 but the system has n = 2"):
        Box.coerce(([0, 0, 0], [1, 1, 1]), n=2)
    with pytest.raises(BoxError, match="must be a Box or a pair"):
        Box.coerce(5)
    assert issubclass(BoxError, OfrlError)


def test_bad_arguments_raise(two_state):
    with pytest.raises(BoundsError, match="method must be one of"):
        jacobian_bounds(two_state, BOX2, "guess")
    with pytest.raises(BoxError, match=r"lower\[0\] = 2 is not below upper\[0\] = -2"):
        jacobian_bounds(two_state, ([2.0, -2.0], [-2.0, 2.0]))
    with pytest.raises(BoundsError, match="tol must be a positive number"):
        jacobian_bounds(two_state, BOX2, "certified", tol=0.0)
    with pytest.raises(BoundsError, match="grid must be a positive integer"):
        jacobian_bounds(two_state, BOX2, grid=0)
    with pytest.raises(BoundsError, match=r"Mf1\[0, 0\] = 1 exceeds Mf2\[0, 0\] = 0"):
        JacobianBounds(
            "given", BOX2, np.eye(2), np.zeros((2, 2)), np.zeros((2, 2, 1)), np.zeros((2, 2, 1))
        )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"seed": -1}, r"seed must be an integer >= 0; got -1\."),
        ({"seed": 2.5}, r"seed must be an integer >= 0; got 2\.5\."),
        ({"tol": "1e-3"}, r"tol must be a positive number; got '1e-3'\."),
        ({"rtol": "0.1"}, r"rtol must be a number >= 0; got '0\.1'\."),
        ({"max_wall_time": "5"}, r"max_wall_time must be a positive number of seconds; got '5'"),
        ({"grid": "abc"}, r"grid must be a positive integer; got 'abc'\."),
        ({"n_random": None}, r"n_random must be a non-negative integer; got None\."),
        ({"max_boxes": "many"}, r"max_boxes must be a positive integer; got 'many'\."),
        (
            {"n_random": 10**12},
            r"n_random: 1000000000000 would need about 4\.47e\+04 GiB for the random points; "
            r"at most 10000000 per call",
        ),
        (
            {"grid": 10**6},
            r"grid: 1000000 points per axis over the 2 states \[0, 1\] that some Jacobian "
            r"entries depend on make 1e\+12 points, .* GiB; at most 10000000\.",
        ),
    ],
)
def test_bad_argument_types_and_sizes_raise_bounds_error(two_state, kwargs, match):
    # Before: numpy's ValueError for the seed, TypeError for strings, MemoryError for sizes.
    with pytest.raises(BoundsError, match=match):
        jacobian_bounds(two_state, BOX2, "certified", **kwargs)


@pytest.mark.parametrize(("system", "got"), [("two_state", "str 'two_state'"), (None, "None")])
def test_a_system_that_is_not_a_model_raises_bounds_error(system, got):
    with pytest.raises(
        BoundsError, match=rf"jacobian_bounds: system must be a ControlAffineSystem; got .*{got}"
    ):
        jacobian_bounds(system, BOX2)


def test_abs_in_f_is_reported_as_not_differentiable():
    # The message listed Abs as supported and never said why the Jacobian branches.
    system = ControlAffineSystem(
        f=lambda x: np.array([np.abs(x[0]) - x[1], -x[1]]),
        g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[0.0, 1.0]],
    )
    for method in ("sampled", "certified"):
        with pytest.raises(
            UnsupportedExpressionError,
            match=r"IfThenElse, a branch.*np\.abs, np\.maximum, np\.minimum or np\.sign inside "
            r"f or g create such branches \(\|x\| is not differentiable at 0.*continuously "
            r"differentiable on the box.*np\.sqrt\(x\*\*2 \+ eps\) for \|x\|",
        ) as caught:
            jacobian_bounds(system, BOX2, method)
        assert "supported: Abs" not in str(caught.value)


def test_unsupported_jacobian_entry_names_the_function():
    # Drake differentiates abs into if-then-else, which neither evaluator handles.
    system = ControlAffineSystem(
        f=lambda x: np.array([np.abs(x[0]) - x[1], -x[1]]),
        g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[0.0, 1.0]],
    )
    with pytest.raises(UnsupportedExpressionError, match=r"IfThenElse.*x\(0\)"):
        jacobian_bounds(system, BOX2)


def test_non_symbolic_dynamics_are_reported():
    import math

    system = ControlAffineSystem(
        f=lambda x: np.array([math.tanh(x[0]) if np.ndim(x[0]) == 0 else np.tanh(x[0]), -x[1]]),
        g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[0.0, 1.0]],
    )
    with pytest.raises(BoundsError, match=r"must accept pydrake\.symbolic\.Expression"):
        jacobian_bounds(system, BOX2)


# ------------------------------------------------ tolerances and budgets
def test_rtol_loosens_the_tolerance_relative_to_the_sampled_width(two_state, two_state_bounds):
    sampled, tight = two_state_bounds
    loose = jacobian_bounds(two_state, BOX2, "certified", tol=1e-6, rtol=0.25)
    assert loose.excess.converged and loose.contains(sampled) and loose.contains(tight)
    widths = [(b.Mf2 - b.Mf1)[1, 0] for b in (sampled, tight, loose)]
    # d f2 / d x1 spans 2 * 4 * _PEAK: each end may now be 0.25 of that beyond.
    assert widths[2] > widths[1] + 1e-2
    assert widths[2] <= widths[0] * 1.5 + 1e-9
    with pytest.raises(BoundsError, match=r"rtol must be a number >= 0; got -0\.1"):
        jacobian_bounds(two_state, BOX2, "certified", rtol=-0.1)


def test_max_wall_time_stops_the_refinement_with_sound_bounds(coupled):
    s4 = jacobian_bounds(coupled, BOX4, "sampled")
    # tol = 1e-15 is out of reach (below the enclosures' own rounding) and max_boxes
    # is not binding: only the clock stops it (the symbolic Jacobians of this n = 4
    # plant take milliseconds of the 2 s).
    rushed = jacobian_bounds(
        coupled, BOX4, "certified", tol=1e-15, max_boxes=10**9, max_wall_time=2.0
    )
    assert not rushed.excess.converged
    assert rushed.contains(s4)
    # How far 2 s of refinement gets depends on the machine's speed, so the
    # refinement's reach is checked on a count of boxes instead: the two copies are
    # refined apart, each with its share of max_boxes, and neither is left at its
    # first box (whose excess is about 3; 10_000 boxes reach about 1e-4).
    counted = jacobian_bounds(coupled, BOX4, "certified", tol=1e-15, max_boxes=10_000)
    assert not counted.excess.converged
    assert counted.contains(s4)
    for row, col in ((1, 0), (3, 2)):  # d f2 / d x1 of one copy, d f4 / d x3 of the other
        assert counted.excess.Mf1[row, col] < 1e-2 and counted.excess.Mf2[row, col] < 1e-2
    assert counted.excess.max < 1e-2
    with pytest.raises(BoundsError, match=r"max_wall_time must be a positive number.*got 0"):
        jacobian_bounds(coupled, BOX4, "certified", max_wall_time=0)


@pytest.mark.parametrize("method", ["sampled", "certified"])
def test_max_wall_time_also_bounds_the_symbolic_jacobians(coupled, method):
    # No sound partial result exists before every row is differentiated: past
    # the deadline the next row is not started, and the error names it.
    with pytest.raises(
        WallTimeExceeded,
        match=r"symbolic Jacobians of f and g were not done by the deadline "
        r"\(max_wall_time, --max-wall\): f\[0\] was next",
    ):
        jacobian_bounds(coupled, BOX4, method, max_wall_time=1e-9)
    # A deadline that is not reached changes nothing.
    x, Jf, Jg = symbolic_jacobians(coupled, deadline=time.monotonic() + 3600.0)
    x0, Jf0, Jg0 = symbolic_jacobians(coupled)
    point = [0.3, -0.7, 1.1, 0.2]
    for J, J0 in ((Jf, Jf0), (Jg, Jg0)):
        values = [e.Evaluate(dict(zip(x, point, strict=True))) for e in J.ravel()]
        values0 = [e.Evaluate(dict(zip(x0, point, strict=True))) for e in J0.ravel()]
        np.testing.assert_array_equal(values, values0)


def test_an_entry_still_infinite_when_the_budget_runs_out_is_named():
    # x1^2 - x1 + 1 >= 3/4, but its natural enclosure on [-1, 2] holds 0, so the
    # first box encloses d f1 / d x1 = -(2 x1 - 1) / (x1^2 - x1 + 1)^2 by the whole line.
    system = ControlAffineSystem(
        f=lambda x: np.array([1 / (x[0] ** 2 - x[0] + 1), -x[1]]),
        g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[1.0, 0.0]],
    )
    box = ([-1.0, -1.0], [2.0, 1.0])
    with pytest.raises(
        UncertifiedBoundsError,
        match=r"certified bound of d f\[0\] / d x\[0\] over Box\(lower=\[-1\.0, -1\.0\], "
        r"upper=\[2\.0, 1\.0\]\) is \[-inf, inf\]: not finite.* If f or g has a pole in "
        r"the box .*'sampled' bounds are wrong; shrink the box to exclude the pole\.",
    ):
        jacobian_bounds(system, box, "certified", max_boxes=1)
    assert issubclass(UncertifiedBoundsError, BoundsError)
    enough = jacobian_bounds(system, box, "certified", tol=1e-2)
    assert enough.excess.converged and np.isfinite(enough.Mf1).all()


def test_independent_copies_are_refined_apart_bit_for_bit(two_state_bounds, coupled):
    # The coupled plant is two copies of the paper's plant joined by a constant
    # term. Its entries of x1, x2 and of x3, x4 share no variable, so each copy is
    # refined on its own 2-d boxes: the same boxes, hence the same bounds to the
    # bit, as the paper's plant alone (refined jointly in 4-d they were not, and
    # took the product of the two box counts).
    _, alone = two_state_bounds
    both = jacobian_bounds(coupled, BOX4, "certified", tol=1e-3)
    for block in (slice(0, 2), slice(2, 4)):
        for name in ("Mf1", "Mf2"):
            got, want = getattr(both, name)[block, block].copy(), getattr(alone, name).copy()
            got[0, 0] = want[0, 0]  # the coupling's constant -0.1 in rows 1 and 3
            np.testing.assert_array_equal(got, want)
        k = 0 if block.start == 0 else 1
        np.testing.assert_array_equal(both.Mg1[block, block, k], alone.Mg1[:, :, 0])
        np.testing.assert_array_equal(both.Mg2[block, block, k], alone.Mg2[:, :, 0])


def test_a_pole_in_the_box_is_refused_with_the_advice_to_exclude_it():
    # 0.01 / (x1 - 0.0123): d f1 / d x1 is unbounded at x1 = 0.0123, inside the box, so no
    # number of boxes bounds it. Before: the advice was only more boxes, or 'sampled'
    # (whose observer verification falsified at r = 1e26).
    system = ControlAffineSystem(
        f=lambda x: np.array([0.01 / (x[0] - 0.0123), -x[1]]),
        g=lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        C=[[1.0, 0.0]],
    )
    with pytest.raises(
        UncertifiedBoundsError,
        match=r"d f\[0\] / d x\[0\] .* is \[-inf, -0\.0097\d+\]: not finite "
        r".*shrink the box to exclude the pole\.",
    ):
        jacobian_bounds(system, ([-1.0, -1.0], [1.0, 1.0]), "certified", max_boxes=200)
