"""ofrl_drake.checks: accepted values pass through; bad ones raise, naming themselves."""

import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ofrl_drake.checks import (
    MAX_DRAKE_SEED,
    array_of_shape,
    drake_seed,
    finite_array,
    finite_vector,
    initial_vector,
    nonnegative_matrix,
    positive_number,
    positive_vector,
    spd_matrix,
)
from ofrl_drake.errors import ModelError, ScenarioError


def test_accepted_values_come_back_as_float_arrays():
    np.testing.assert_array_equal(finite_vector("w", [1, -2, 0]), [1.0, -2.0, 0.0])
    np.testing.assert_array_equal(positive_vector("r", [0.5, 2], size=2), [0.5, 2.0])
    assert positive_number("k", 0, allow_zero=True) == 0.0
    assert positive_number("k", np.float32(2.5)) == 2.5
    np.testing.assert_array_equal(spd_matrix("G", [[2, 1], [1, 2]], size=2), [[2, 1], [1, 2]])
    np.testing.assert_array_equal(nonnegative_matrix("Q", np.zeros((2, 2))), np.zeros((2, 2)))


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: positive_number("k", 0.0), r"k must be > 0; got 0.0"),
        (lambda: positive_number("k", -1e-9, allow_zero=True), r"k must be >= 0"),
        (lambda: positive_number("k", [1.0, 2.0]), r"k must be a number; got shape \(2,\)"),
        (lambda: positive_number("k", np.inf), r"k must be finite"),
        (lambda: positive_number("k", "fast"), r"k must be a number; got 'fast'"),
        (
            lambda: finite_vector("w", [], None),
            r"w must be a non-empty 1-D vector; got shape",
        ),
        (lambda: finite_vector("w", [1.0, 2.0], 3), r"w must have length 3; got 2"),
        (lambda: positive_vector("r", [1.0, -1.0]), r"r must have entries > 0; got \[1.0, -1.0\]"),
        (lambda: spd_matrix("G", np.eye(3), 2), r"G must have shape \(2, 2\); got \(3, 3\)"),
        (
            lambda: spd_matrix("G", [[1.0, 0.5], [0.0, 1.0]]),
            r"G must be symmetric; max \|M - M\^T\|",
        ),
        (lambda: spd_matrix("G", np.diag([1.0, 0.0])), r"G must be positive definite; .* is 0"),
        (lambda: nonnegative_matrix("Q", np.diag([1.0, -0.1])), r"Q must be positive semidefinite"),
    ],
)
def test_bad_values_raise_model_error_naming_the_value(call, message):
    with pytest.raises(ModelError, match=message):
        call()


@given(arrays(np.float64, (3, 3), elements=st.floats(-10, 10)))
def test_gram_matrices_pass_and_their_negations_fail(A):
    """A A^T + I is positive definite; its negation never is."""
    M = A @ A.T + np.eye(3)
    np.testing.assert_allclose(spd_matrix("M", M), M, rtol=0, atol=0)
    with pytest.raises(ModelError, match="positive definite"):
        spd_matrix("M", -M)


@pytest.mark.parametrize("value", ["10", b"10", True, np.bool_(True)])
def test_a_string_or_bool_is_not_a_positive_number(value):
    with pytest.raises(ModelError, match=r"^x must be a number; got"):
        positive_number("x", value)


@pytest.mark.parametrize("value", [0.0, np.nan, "10", [1.0, 2.0], object()])
def test_a_module_gets_its_own_error_class_from_positive_number(value):
    """``error=`` raises the caller's class (not a ModelError) for every refusal."""
    with pytest.raises(ScenarioError, match=r"^k must be") as caught:
        positive_number("k", value, error=ScenarioError)
    assert not isinstance(caught.value, ModelError)


def test_finite_array_raises_the_given_class():
    with pytest.raises(ScenarioError, match=r"^a must be finite; got \[1.0, inf\]"):
        finite_array("a", [1.0, np.inf], error=ScenarioError)


@pytest.mark.parametrize(
    ("value", "shape", "message"),
    [
        (np.zeros((2, 3)), (2, 2), r"^A must have shape \(n, n\) = \(2, 2\); got \(2, 3\)\.$"),
        (np.zeros((2, 0)), (2, None), r"^A must have shape \(n, n\) = \(2, N\); got \(2, 0\)\.$"),
        (np.zeros(3), (2,), r"^A must have shape \(n, n\) = \(2,\); got \(3,\)\.$"),
        ([[1.0, np.nan]], (1, 2), r"^A must be finite; got \[\[1.0, nan\]\]"),
    ],
)
def test_array_of_shape_names_the_shape_wanted_and_got(value, shape, message):
    with pytest.raises(ModelError, match=message):
        array_of_shape("A", value, shape, meaning="(n, n)")


def test_array_of_shape_takes_any_length_on_a_none_axis():
    np.testing.assert_array_equal(array_of_shape("P", [[1, 2, 3]], (1, None)), [[1.0, 2.0, 3.0]])


def test_a_drake_seed_is_a_32_bit_integer():
    assert drake_seed("seed", 0) == 0
    assert drake_seed("seed", np.uint32(MAX_DRAKE_SEED)) == 2**32 - 1
    with pytest.raises(
        ScenarioError, match=r"^seed must be at most 2\*\*32 - 1 = 4294967295 .*got 4294967296"
    ):
        drake_seed("seed", 2**32, error=ScenarioError)
    with pytest.raises(ModelError, match=r"^seed must be an integer >= 0; got -1"):
        drake_seed("seed", -1)


def test_initial_vector_is_zeros_when_omitted_else_a_checked_vector():
    """The blocks' default state: one check for every block that takes ``initial_state``."""
    zeros = initial_vector("B: initial_state", None, 3)
    assert zeros.dtype == float
    np.testing.assert_array_equal(zeros, np.zeros(3))
    np.testing.assert_array_equal(initial_vector("B: initial_state", [1, -2], 2), [1.0, -2.0])
    with pytest.raises(ModelError, match=r"^B: initial_state must have length 2; got 3\.$"):
        initial_vector("B: initial_state", [1.0, 2.0, 3.0], 2)
    with pytest.raises(ModelError, match=r"^B: initial_state must be finite; got \[nan, 0\.0\]"):
        initial_vector("B: initial_state", [np.nan, 0.0], 2)


def test_numbers_written_to_json_read_back_with_non_finite_ones_as_null():
    from ofrl_drake.checks import (
        number_to_json,
        optional_number_from_json,
        vector_from_json,
        vector_to_json,
    )

    values = np.array([1.5, np.nan, -np.inf, np.inf, -0.0, 3])
    text = json.dumps(vector_to_json(values), allow_nan=False)  # strict JSON
    assert text == "[1.5, null, null, null, -0.0, 3.0]"
    back = vector_from_json(json.loads(text), values.size)
    np.testing.assert_array_equal(back, [1.5, np.nan, np.nan, np.nan, -0.0, 3.0])
    assert [number_to_json(v) for v in (None, np.float32(2.5), np.nan, 7)] == [None, 2.5, None, 7.0]
    assert optional_number_from_json(json.loads(json.dumps(number_to_json(np.inf)))) is None
    assert vector_to_json(np.array([[1.0, np.nan]])) == [1.0, None]


def test_json_ready_makes_nested_numpy_values_strict_json():
    from ofrl_drake.checks import json_ready

    value = {
        "a": np.array([[1.0, np.nan], [np.inf, 2.0]]),
        "b": (np.float32(0.5), np.int64(3), np.bool_(True), None, "text"),
        "c": [{"d": -np.inf}],
    }
    ready = json_ready(value)
    assert ready == {
        "a": [[1.0, None], [None, 2.0]],
        "b": [0.5, 3, True, None, "text"],
        "c": [{"d": None}],
    }
    assert json.loads(json.dumps(ready, allow_nan=False)) == ready
    assert type(ready["b"][1]) is int and type(ready["b"][2]) is bool


def test_one_line_joins_whitespace_and_cuts_at_the_limit():
    from ofrl_drake.errors import one_line

    err = ValueError("sqrt(-1) :\n  numerical   argument\tout of domain")
    assert one_line(err) == "sqrt(-1) : numerical argument out of domain"
    assert one_line(err, 8) == "sqrt(-1)"
    assert one_line("") == ""
