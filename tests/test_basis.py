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
