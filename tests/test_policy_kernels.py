"""The controller block's math at numpy level, without Drake.

``SaturatedController._calc_u`` is one call of :func:`ofrl_drake.policy.policy_kernel`:
:func:`ofrl_drake.basis.value_gradient_kernel` (``grad V = grad sigma(x)^T W``)
and then :func:`ofrl_drake.policy.saturate` (``u = -lbar tanh(s * g^T grad V)``,
``s_k = 1 / (2 lbar r_k)``). Both kernels are compared here, over random states,
weights, input matrices and bases, with the numpy entry points
(:meth:`PolynomialBasis.value_gradient`, :func:`~ofrl_drake.policy.saturated_policy`)
and with the law written out in plain numpy from the exponents
(``d x^e / d x_j = e_j x^(e - 1_j)``), so a slip in the gradient tables or in
the kernels' loops shows up without a diagram.

Tolerances: the kernels sum in another order than numpy's matrix products, so
the gradients agree to ``RTOL`` relative, plus ``RTOL`` times the sum of the
magnitudes of the terms (``|W|^T |grad sigma|``) absolute, which covers
cancellation; ``u`` to the same error carried through ``tanh`` (slope <= 1).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ofrl_drake.basis import PolynomialBasis, value_gradient_kernel
from ofrl_drake.policy import policy_kernel, policy_scale, saturated_policy

#: Relative tolerance of a kernel against numpy (a few hundred units in the last place).
RTOL = 1e-12


def _numpy_gradient(basis, x):
    """``d sigma / d x`` (shape ``(L, n)``) from the exponents, in plain numpy."""
    exponents = basis.exponents
    grad = np.zeros(exponents.shape, dtype=float)
    for j in range(basis.n):
        has = exponents[:, j] > 0
        lowered = exponents.copy()
        lowered[has, j] -= 1
        grad[:, j] = np.where(has, exponents[:, j] * np.prod(x**lowered, axis=1), 0.0)
    return grad


def _numpy_policy(grad_V, g, r, input_bound):
    """``u = -lbar tanh(g^T grad V / (2 lbar r))``, in plain numpy."""
    return -input_bound * np.tanh((g.T @ grad_V) / (2.0 * input_bound * r))


@st.composite
def problems(draw):
    """A basis, a state, weights, an input matrix, ``r`` and ``lbar`` (from a seed)."""
    n = draw(st.integers(1, 4))
    m = draw(st.integers(1, 3))
    degrees = draw(st.lists(st.integers(2, 4), min_size=1, max_size=3, unique=True))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    basis = PolynomialBasis(n, degrees)
    x = rng.uniform(-2.0, 2.0, n)
    W = rng.normal(0.0, draw(st.sampled_from([0.1, 1.0, 10.0])), basis.size)
    g = rng.uniform(-3.0, 3.0, (n, m))
    r = rng.uniform(0.1, 10.0, m)
    input_bound = float(rng.uniform(0.1, 10.0))
    return basis, x, W, g, r, input_bound


def _magnitudes(basis, x, W):
    """``sum_l |W_l| |d sigma_l / d x_j|`` (shape ``(n,)``): the size of the terms of ``grad V``."""
    return np.abs(W) @ np.abs(_numpy_gradient(basis, x))


def _gradient_atol(basis, x, W):
    return RTOL * float(np.max(_magnitudes(basis, x, W)))


def _policy_atol(basis, x, W, g, r, input_bound):
    """An error ``RTOL |terms|`` in ``grad V`` moves ``D_k`` by ``s_k |g_k|^T`` that, and
    ``u_k`` by ``lbar`` times that at most (tanh has slope <= 1); plus tanh's rounding."""
    shift = policy_scale(r, input_bound) * (np.abs(g).T @ _magnitudes(basis, x, W))
    return RTOL * input_bound * (float(np.max(shift)) + 1.0)


def _kernel_gradient(basis, x, W):
    out = np.empty(basis.n)
    value_gradient_kernel(x, W, *basis.gradient_tables, out)
    return out


def _kernel_policy(basis, x, W, g, r, input_bound):
    return policy_kernel(
        x, np.ascontiguousarray(g), W, *basis.gradient_tables, policy_scale(r, input_bound),
        input_bound,
    )  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(problems())
def test_value_gradient_kernel_is_the_numpy_gradient_of_the_value(problem):
    basis, x, W, _, _, _ = problem
    kernel = _kernel_gradient(basis, x, W)
    # The method is the kernel behind its checks: the same numbers, bit for bit.
    np.testing.assert_array_equal(basis.value_gradient(x, W), kernel)
    atol = _gradient_atol(basis, x, W)
    np.testing.assert_allclose(kernel, _numpy_gradient(basis, x).T @ W, rtol=RTOL, atol=atol)
    np.testing.assert_allclose(kernel, W @ basis.gradient(x), rtol=RTOL, atol=atol)


@settings(max_examples=60, deadline=None)
@given(problems())
def test_policy_kernel_is_the_saturated_policy(problem):
    basis, x, W, g, r, input_bound = problem
    kernel = _kernel_policy(basis, x, W, g, r, input_bound)
    assert kernel.shape == (g.shape[1],)
    assert np.all(np.abs(kernel) <= input_bound)
    atol = _policy_atol(basis, x, W, g, r, input_bound)
    reference = saturated_policy(basis.gradient(x), g, W, r, input_bound)
    np.testing.assert_allclose(kernel, reference, rtol=RTOL, atol=atol)
    plain = _numpy_policy(_numpy_gradient(basis, x).T @ W, g, r, input_bound)
    np.testing.assert_allclose(kernel, plain, rtol=RTOL, atol=atol)


def test_kernels_on_the_papers_basis_by_hand():
    """``V = x1^2 + x1 x2 + x2^2`` at ``x = (1, 2)``: ``grad V = (2 x1 + x2, x1 + 2 x2)``."""
    basis = PolynomialBasis(2)
    x, W = np.array([1.0, 2.0]), np.array([1.0, 1.0, 1.0])
    np.testing.assert_allclose(_kernel_gradient(basis, x, W), [4.0, 5.0], rtol=0, atol=1e-15)
    g, r, input_bound = np.array([[0.0], [3.0]]), np.array([1.0]), 3.0
    # D = s (g^T grad V) = 15 / (2 * 3 * 1) = 2.5
    u = _kernel_policy(basis, x, W, g, r, input_bound)
    np.testing.assert_allclose(u, [-3.0 * np.tanh(2.5)], rtol=1e-15, atol=0)


@pytest.mark.parametrize("size", [1e3, 1e8])
def test_policy_kernel_saturates_at_the_bound_without_overflow(size):
    """Huge weights give ``u = -lbar sign(D)`` exactly, never nan or beyond the bound."""
    basis = PolynomialBasis(3, (2, 4))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.0, 1.0, 3)
    W = size * np.abs(rng.normal(size=basis.size))
    g, r, input_bound = rng.normal(size=(3, 2)), np.array([0.5, 2.0]), 1.5
    u = _kernel_policy(basis, x, W, g, r, input_bound)
    D = (g.T @ (W @ basis.gradient(x))) / (2.0 * input_bound * r)
    assert np.all(np.abs(D) > 20.0)  # far in tanh's flat part
    np.testing.assert_array_equal(u, -input_bound * np.sign(D))


def test_kernels_vanish_at_the_origin():
    """Every monomial has degree >= 2, so ``grad V(0) = 0`` and ``u(0) = 0`` for any W."""
    basis = PolynomialBasis(3, (2, 3))
    W = np.random.default_rng(1).normal(size=basis.size)
    np.testing.assert_array_equal(_kernel_gradient(basis, np.zeros(3), W), np.zeros(3))
    g = np.ones((3, 2))
    u = _kernel_policy(basis, np.zeros(3), W, g, np.ones(2), 2.0)
    np.testing.assert_array_equal(u, np.zeros(2))
