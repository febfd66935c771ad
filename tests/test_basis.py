"""PolynomialBasis: the paper's basis, analytic gradients, sigma(0) = grad(0) = 0."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ofrl_drake import PolynomialBasis
from ofrl_drake.errors import ModelError


def test_default_is_the_papers_quadratic_basis():
    basis = PolynomialBasis(2)
    x = np.array([1.7, -0.3])
    np.testing.assert_allclose(basis(x), [x[0] ** 2, x[0] * x[1], x[1] ** 2], rtol=1e-15)
    np.testing.assert_allclose(
        basis.gradient(x), [[2 * x[0], 0], [x[1], x[0]], [0, 2 * x[1]]], rtol=1e-15
    )
    assert basis.labels() == ["x1^2", "x1 x2", "x2^2"]


@pytest.mark.parametrize(
    ("n", "degrees", "size"), [(2, [2], 3), (2, [2, 4], 8), (4, [2], 10), (3, [2, 3], 16)]
)
def test_sizes(n, degrees, size):
    assert PolynomialBasis(n, degrees).size == size


@pytest.mark.parametrize(("n", "degrees"), [(2, [2, 4]), (3, [2, 3]), (4, [2])])
def test_gradient_matches_central_differences_on_a_grid(n, degrees):
    basis = PolynomialBasis(n, degrees)
    X = np.random.default_rng(1).uniform(-1.5, 1.5, size=(n, 25))
    G = basis.gradient(X)
    h = 1e-6
    for j in range(n):
        dx = np.zeros((n, 1))
        dx[j] = h
        fd = (basis(X + dx) - basis(X - dx)) / (2 * h)
        np.testing.assert_allclose(G[:, j, :], fd, rtol=1e-7, atol=1e-7)


def test_batch_matches_pointwise():
    basis = PolynomialBasis(3, [2, 3])
    X = np.random.default_rng(2).normal(size=(3, 6))
    S, G = basis(X), basis.gradient(X)
    for i in range(6):
        np.testing.assert_allclose(S[:, i], basis(X[:, i]), rtol=1e-14)
        np.testing.assert_allclose(G[..., i], basis.gradient(X[:, i]), rtol=1e-14)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 5),
    degrees=st.lists(st.integers(2, 5), min_size=1, max_size=3, unique=True),
)
def test_every_basis_vanishes_with_its_gradient_at_the_origin(n, degrees):
    basis = PolynomialBasis(n, degrees)
    assert np.all(basis(np.zeros(n)) == 0)
    assert np.all(basis.gradient(np.zeros(n)) == 0)


@pytest.mark.parametrize(
    ("degrees", "match"),
    [
        ([1], r"degree 1 is not allowed; degrees must be integers >= 2"),
        ([], "degrees is empty"),
        ([2, 2], "repeat"),
    ],
)
def test_bad_degrees_raise(degrees, match):
    with pytest.raises(ModelError, match=match):
        PolynomialBasis(2, degrees)


@pytest.mark.parametrize(("n", "degrees"), [(2, [2]), (2, [2, 4]), (4, [2]), (3, [2, 3])])
def test_value_gradient_is_gradient_transposed_times_weights(n, degrees):
    basis = PolynomialBasis(n, degrees)
    rng = np.random.default_rng(7)
    x, W = rng.normal(size=n), rng.normal(size=basis.size)
    np.testing.assert_allclose(basis.value_gradient(x, W), basis.gradient(x).T @ W, rtol=1e-13)
    out = np.empty(n)
    assert basis.value_gradient(x, W, out=out) is out


def test_symbolic_monomials_equal_the_numeric_basis():
    from pydrake.symbolic import Evaluate, MakeVectorVariable

    basis = PolynomialBasis(3, (2, 4))
    x = MakeVectorVariable(3, "x")
    point = np.array([0.7, -1.3, 0.4])
    values = Evaluate(basis.expressions(x).reshape(-1, 1), dict(zip(x, point, strict=True))).ravel()
    np.testing.assert_allclose(values, basis(point), rtol=1e-15, atol=0)


@pytest.mark.parametrize(
    ("x", "W", "out", "match"),
    [
        ([1.0, 2.0], np.ones(1), None, r".* W shape \(L,\) = \(8,\); got \(2,\) and \(1,\)"),
        ([1.0, 2.0, 3.0], np.ones(8), None, r"x must have shape \(n,\) = \(2,\).*got \(3,\)"),
        ([1.0, 2.0], np.ones(8), np.empty(2, dtype=int), r"out must be a writable float64.*int64"),
        ([1.0, 2.0], np.ones(8), np.empty(3), r"out must be .* shape \(n,\) = \(2,\).*\(3,\)"),
        ("ab", np.ones(8), None, r"x and W must be numeric arrays.*got 'ab'"),
    ],
)
def test_value_gradient_refuses_arrays_of_the_wrong_shape(x, W, out, match):
    # The compiled kernel read past arrays of the wrong size and returned garbage.
    with pytest.raises(ModelError, match=r"PolynomialBasis\.value_gradient: " + match):
        PolynomialBasis(2, [2, 4]).value_gradient(x, W, out)


@pytest.mark.parametrize("method", ["gradient", "__call__"])
@pytest.mark.parametrize(
    ("x", "shape"), [([1.0, 2.0], r"\(2,\)"), (np.ones((3, 2, 2)), r"\(3, 2, 2\)"), (1.0, r"\(\)")]
)
def test_gradient_and_values_refuse_points_of_the_wrong_dimension(method, x, shape):
    with pytest.raises(
        ModelError,
        match=rf"PolynomialBasis\.{method}: x must have shape \(n,\) = \(3,\) or "
        rf"\(n, N\) = \(3, N\), one column per point; got shape {shape}",
    ):
        getattr(PolynomialBasis(3), method)(x)


@pytest.mark.parametrize(
    ("n", "degrees", "match"),
    [
        (2, 2, r"degrees must be a sequence of integers >= 2, e\.g\. \[2\] or \[2, 4\]; got 2"),
        (2, None, r"degrees must be a sequence of integers >= 2.*got None"),
        (True, [2], r"n must be a positive integer; got True"),
        (30, [5], r"n = 30 and degrees \[5\] give 278256 monomials; at most 100000"),
    ],
)
def test_bad_n_and_degree_types_raise(n, degrees, match):
    with pytest.raises(ModelError, match=r"PolynomialBasis: " + match):
        PolynomialBasis(n, degrees)


@pytest.mark.parametrize("names", [["a"], ["a", "b", "c"], 5])
def test_labels_need_one_name_per_state(names):
    with pytest.raises(
        ModelError,
        match=r"PolynomialBasis\.labels: names must give one name per state \(2 in all\)",
    ):
        PolynomialBasis(2).labels(names)
    assert PolynomialBasis(2).labels(["p", "q"]) == ["p^2", "p q", "q^2"]
