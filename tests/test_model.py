"""ControlAffineSystem: dimensions, shape errors and scalar types."""

import numpy as np
import pytest
from pydrake.autodiffutils import ExtractGradient, InitializeAutoDiff
from pydrake.symbolic import Expression, MakeVectorVariable

from ofrl_drake import ControlAffineSystem
from ofrl_drake.errors import ModelError, ScenarioError
from ofrl_drake.examples import EXAMPLES, make_system


def _f(x):
    return np.array([x[1], -x[0]])


def _g(x):
    return np.array([[0 * x[0]], [1 + 0 * x[0]]])


@pytest.mark.parametrize(
    ("name", "dims"), [("two_state", (2, 1, 1)), ("coupled_two_state", (4, 2, 2))]
)
def test_example_dimensions(name, dims):
    system = make_system(name)
    assert (system.n, system.m, system.q) == dims
    assert system.vectorized


def test_two_state_matches_paper_equations():
    system = make_system("two_state")
    x = np.array([0.3, -0.7])
    c = np.cos(2 * x[0]) + 2
    expected_f = [-x[0] + x[1], -x[0] - 0.5 * x[1] * (1 - c**2)]
    np.testing.assert_allclose(system.f(x), expected_f, rtol=0, atol=1e-15)
    np.testing.assert_allclose(system.g(x), [[0.0], [c]], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(system.output_matrix, [[0.0, 1.0]])


def test_coupled_example_structure():
    system = make_system("coupled_two_state")
    base = make_system("two_state")
    x = np.array([0.3, -0.7, -0.2, 0.5])
    fx = system.f(x)
    a, b = base.f(x[:2]), base.f(x[2:])
    np.testing.assert_allclose(
        fx, [a[0] + 0.1 * (x[2] - x[0]), a[1], b[0] + 0.1 * (x[0] - x[2]), b[1]], atol=1e-15
    )
    gx = system.g(x)
    np.testing.assert_allclose(gx[[0, 2]], 0.0, atol=0)
    np.testing.assert_allclose(gx[1], [np.cos(2 * x[0]) + 2, 0.0], atol=1e-15)
    np.testing.assert_allclose(gx[3], [0.0, np.cos(2 * x[2]) + 2], atol=1e-15)
    np.testing.assert_array_equal(system.output_matrix, [[0, 1, 0, 0], [0, 0, 0, 1]])


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_batch_matches_pointwise(name):
    system = make_system(name)
    X = np.random.default_rng(0).uniform(-2, 2, size=(system.n, 7))
    fX, gX = system.f_batch(X), system.g_batch(X)
    for i in range(X.shape[1]):
        np.testing.assert_allclose(fX[:, i], system.f(X[:, i]), rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(gX[..., i], system.g(X[:, i]), rtol=1e-14, atol=1e-14)


# numpy's object-dtype loop for np.cos leaves a stale floating-point flag behind.
@pytest.mark.filterwarnings("ignore:invalid value encountered in cos:RuntimeWarning")
def test_same_function_runs_on_autodiff_and_symbolic():
    system = make_system("two_state")
    x = np.array([0.4, -0.3])
    J = ExtractGradient(system.f(InitializeAutoDiff(x).flatten()))
    c, s = np.cos(2 * x[0]) + 2, np.sin(2 * x[0])
    np.testing.assert_allclose(J, [[-1, 1], [-1 - 2 * x[1] * c * s, -0.5 * (1 - c**2)]], atol=1e-14)
    fs = system.f(MakeVectorVariable(2, "x"))
    assert all(isinstance(e, Expression) for e in fs)


def test_scalar_constants_fall_back_with_warning():
    with pytest.warns(UserWarning, match="do not accept a batch"):
        system = ControlAffineSystem(_f, lambda x: np.array([[0.0], [1.0]]), [[1.0, 0.0]])
    assert not system.vectorized
    assert system.g_batch(np.zeros((2, 3))).shape == (2, 1, 3)


@pytest.mark.parametrize(
    ("f", "g", "C", "match"),
    [
        (
            lambda x: np.array([x[0], x[1], x[0]]),
            _g,
            [[1.0, 0.0]],
            r"f\(x\) must return shape \(n,\) = \(2,\).*got shape \(3,\)",
        ),
        (
            _f,
            lambda x: np.array([0 * x[0], 1 + 0 * x[0]]),
            [[1.0, 0.0]],
            r"g\(x\) must return shape \(n, m\) = \(2, m\).*got shape \(2,\)",
        ),
        (_f, _g, [1.0, 0.0], r"C must be a 2-D array of shape \(q, n\); got shape \(2,\)"),
        (_f, _g, [[1.0, 0.0, 0.0]], r"f\(x\) must return shape \(n,\) = \(3,\)"),
        (
            lambda x: np.array([np.inf * x[0], x[1]]),
            _g,
            [[1.0, 0.0]],
            r"f\(x\) returned non-finite",
        ),
        (_f, _g, [[np.nan, 1.0]], r"C must be finite"),
        (lambda x: None, _g, [[1.0, 0.0]], r"f\(x\) returned None .*a missing return statement"),
        (
            lambda x: np.array([x[1], -x[0] + 1j * x[0]]),
            _g,
            [[1.0, 0.0]],
            r"f\(x\) returned complex values .*; f must be real",
        ),
        (_f, lambda x: "g", [[1.0, 0.0]], r"g\(x\) returned 'g' .*not an array of numbers"),
    ],
)
def test_bad_models_raise(f, g, C, match):
    with pytest.raises(ModelError, match=match):
        ControlAffineSystem(f, g, C)


def test_dynamics_needs_one_input_per_column_of_g():
    system = ControlAffineSystem(_f, _g, [[1.0, 0.0]], name="mine")
    np.testing.assert_allclose(
        system.dynamics(np.array([0.5, 1.0]), np.array([2.0])),
        _f(np.array([0.5, 1.0])) + _g(np.array([0.5, 1.0])) @ np.array([2.0]),
        rtol=0,
        atol=0,
    )
    with pytest.raises(
        ModelError,
        match=r"^mine: dynamics\(x, u\) needs u of shape \(m,\) = \(1,\); got shape \(2,\)",
    ):
        system.dynamics(np.array([0.5, 1.0]), np.array([1.0, 2.0]))


def test_unknown_example_names_choices():
    with pytest.raises(ScenarioError, match=r"unknown example 'nope'.*two_state"):
        make_system("nope")


@pytest.mark.parametrize(
    ("C", "shown"),
    [
        ([[1.0], [1.0, 0.0]], r"\[\[1\.0\], \[1\.0, 0\.0\]\]"),
        ("abc", "'abc'"),
        ([[1.0, 2j]], r"\[\[1\.0, 2j\]\]"),
        (np.array([[1.0, 2j]]), r"array\(\[\[1\.\+0\.j, 0\.\+2\.j\]\]\)"),
    ],
)
def test_output_matrix_of_ragged_rows_strings_or_complex_numbers_raises(C, shown):
    # numpy raised its own ValueError/TypeError, or dropped the imaginary part.
    with pytest.raises(
        ModelError,
        match=rf"C must be a 2-D array of real numbers, shape \(q, n\); got {shown}\. "
        r"Pass C as a list of rows of equal length",
    ):
        ControlAffineSystem(_f, _g, C)


def test_complex_equilibrium_raises():
    system = ControlAffineSystem(_f, _g, [[1.0, 0.0]])
    with pytest.raises(ModelError, match=r"equilibrium x must be a list of 2 numbers; got array"):
        system.shifted(np.array([1j, 0.0]))


@pytest.mark.parametrize("tol", [None, "1e-3", True, -1.0, float("nan")])
def test_shifted_tol_must_be_a_nonnegative_number(tol):
    system = ControlAffineSystem(_f, _g, [[1.0, 0.0]], name="osc")
    with pytest.raises(
        ModelError,
        match=rf"osc: shifted: tol must be a number >= 0 \(the largest accepted "
        rf"\|f\(x\*\) \+ g\(x\*\) u\*\|, default 1e-08; inf checks nothing\); got {tol!r}",
    ):
        system.shifted([0.0, 0.0], tol=tol)


def test_shifted_with_an_infinite_tol_checks_nothing():
    # What plants.resolve_truth asks for a truth whose equilibrium is the model's.
    system = ControlAffineSystem(_f, _g, [[1.0, 0.0]], name="osc")
    shifted = system.shifted([0.3, 0.0], tol=float("inf"))  # not an equilibrium of osc
    np.testing.assert_allclose(shifted.x_eq, [0.3, 0.0])


def test_a_model_in_its_own_coordinates_has_its_equilibrium_at_zero():
    # Before: no equilibrium accessor; callers tested isinstance(system, ShiftedSystem).
    system = ControlAffineSystem(_f, _g, [[1.0, 0.0]], name="osc")
    assert system.is_shifted is False
    x_eq, u_eq = system.equilibrium
    np.testing.assert_array_equal(x_eq, [0.0, 0.0])
    np.testing.assert_array_equal(u_eq, [0.0])
    assert not x_eq.flags.writeable and not u_eq.flags.writeable
    assert system.multibody_plant is None  # a hand-written model: no plant to run


def test_a_loop_over_points_at_every_evaluation_is_refused_where_it_would_run():
    # Before: only the construction's warning; a block moving its points looped every step.
    with pytest.warns(UserWarning, match="do not accept a batch"):
        looping = ControlAffineSystem(_f, lambda x: np.array([[0.0], [1.0]]), [[1.0, 0.0]])
    with pytest.raises(
        ModelError,
        match=r"MovingBellmanExtrapolator: the model 'control_affine_system' evaluates f and "
        r"g at every step .* \(vectorized = False\).* Write constants as 0 \* x\[0\]",
    ):
        looping.require_vectorized("MovingBellmanExtrapolator")
    ControlAffineSystem(_f, _g, [[1.0, 0.0]]).require_vectorized("MovingBellmanExtrapolator")


def test_the_fingerprint_follows_the_dynamics_not_the_object():
    from ofrl_drake.examples import two_state

    base = two_state()
    fp = base.fingerprint()
    assert len(fp) == 24 and fp == two_state().fingerprint()  # another object, same code
    assert base.fingerprint() is fp  # computed once
    slower = ControlAffineSystem(lambda x: 0.999 * base.f(x), base.g, C=base.C)
    other_g = ControlAffineSystem(base.f, lambda x: -base.g(x), C=base.C)
    other_C = ControlAffineSystem(base.f, base.g, C=2.0 * np.asarray(base.C))
    prints = {s.fingerprint() for s in (slower, other_g, other_C)}
    assert len(prints) == 3 and fp not in prints

    # A model undefined at a probe state (NaN there, or raising) still has one.
    def f(x):
        if x[0] < 0:
            raise ValueError("x1 < 0 is outside the model")
        return np.array([x[1], np.sqrt(np.abs(x[0]) - 0.08)])

    g = lambda x: np.array([[0.0 * x[0]], [1.0 + 0.0 * x[0]]])  # noqa: E731
    with pytest.warns(UserWarning, match="do not accept a batch"):
        partial = ControlAffineSystem(f, g, C=[[1.0, 0.0]])
    assert len(partial.fingerprint()) == 24


@pytest.mark.parametrize(
    "branch",
    [
        lambda x: np.maximum(x[0], 0.0 * x[0]),
        lambda x: np.clip(x[0], -1.0, 1.0),
        lambda x: np.where(x[0] > 0, x[0], 0.0 * x[0]),
        lambda x: np.sign(x[0]),
    ],
    ids=["maximum", "clip", "where", "sign"],
)
def test_a_branch_on_the_state_is_named_with_its_smooth_form(branch):
    """Drake's own text ("__bool__ on Formula ... make a map with Variable") said nothing
    of the branch, and "write them with numpy functions" contradicted np.maximum."""
    system = ControlAffineSystem(
        lambda x: np.array([x[1], -branch(x)]),
        lambda x: np.array([[0.0 * x[0]], [1.0 + 0.0 * x[0]]]),
        C=[[1.0, 0.0]],
        name="kinked",
    )
    with pytest.raises(
        ModelError,
        match=r"^kinked: f or g branches on the state \(a comparison such as np\.maximum.*"
        r"np\.sqrt\(x\*\*2 \+ eps\) for \|x\|.*for max\(a, b\)\.$",
    ) as err:
        system.symbolic()
    assert "EqualToDict" not in str(err.value)
