"""ControlAffineSystem.shifted: the system seen from an equilibrium (x*, u*)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pydrake.autodiffutils import ExtractGradient, InitializeAutoDiff

from ofrl_drake.errors import ModelError
from ofrl_drake.interval import evaluate
from ofrl_drake.jacobian_bounds import jacobian_bounds, symbolic_jacobians
from ofrl_drake.model import ControlAffineSystem, ShiftedSystem


def _f(x):
    # A pendulum with a constant torque bias: equilibria need u* = -1 + sin(x1*).
    return np.array([x[1], -np.sin(x[0]) - 0.2 * x[1] + 1 + 0 * x[0]])


def _g(x):
    return np.array([[0 * x[0]], [2 + np.cos(x[0])]])


BASE = ControlAffineSystem(_f, _g, [[1.0, 0.0]], name="biased_pendulum")


def _u_eq(theta: float) -> np.ndarray:
    return np.array([(np.sin(theta) - 1) / (2 + np.cos(theta))])


finite = st.floats(-3, 3, allow_nan=False)


@given(theta=st.floats(-3, 3), z=arrays(float, 2, elements=finite), v=finite)
@settings(max_examples=50, deadline=None)
def test_shifted_dynamics_are_the_base_dynamics_moved(theta, z, v):
    x_eq, u_eq = np.array([theta, 0.0]), _u_eq(theta)
    s = BASE.shifted(x_eq, u_eq)
    lhs = s.f(z) + s.g(z) @ [v]
    rhs = BASE.f(z + x_eq) + BASE.g(z + x_eq) @ (np.array([v]) + u_eq)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(s.f(np.zeros(2)), 0.0, atol=1e-12)
    np.testing.assert_allclose(s.output(z), BASE.output(z + x_eq) - BASE.output(x_eq), atol=1e-12)


def test_shifted_keeps_the_point_and_the_base():
    x_eq, u_eq = [np.pi / 2, 0.0], [0.0]
    s = BASE.shifted(x_eq, u_eq)
    assert isinstance(s, ShiftedSystem)
    assert s.base is BASE and s.name == BASE.name and s.source is None
    assert (s.n, s.m, s.q) == (2, 1, 1)
    np.testing.assert_array_equal(s.x_eq, x_eq)
    np.testing.assert_array_equal(s.u_eq, u_eq)
    np.testing.assert_array_equal(s.output_matrix, BASE.output_matrix)
    np.testing.assert_allclose(s.residual, 0.0, atol=1e-15)
    Z = np.array([[0.1, -0.2], [0.3, 0.0]])
    np.testing.assert_allclose(s.to_original_state(Z.T), Z.T + x_eq)
    np.testing.assert_allclose(s.to_original_input([[0.5]]), [[0.5]])


def test_shifted_batch_matches_pointwise():
    s = BASE.shifted([0.3, 0.0], _u_eq(0.3))
    assert s.vectorized
    Z = np.random.default_rng(1).uniform(-1, 1, size=(2, 9))
    fZ, gZ = s.f_batch(Z), s.g_batch(Z)
    for k in range(Z.shape[1]):
        np.testing.assert_allclose(fZ[:, k], s.f(Z[:, k]), rtol=0, atol=1e-14)
        np.testing.assert_allclose(gZ[..., k], s.g(Z[:, k]), rtol=0, atol=1e-14)


def test_shifted_accepts_autodiff():
    s = BASE.shifted([0.3, 0.0], _u_eq(0.3))
    z = np.array([0.1, -0.4])
    fz = s.f(InitializeAutoDiff(z).ravel())
    J = ExtractGradient(fz)
    h = 1e-6
    J_fd = np.stack([(s.f(z + h * e) - s.f(z - h * e)) / (2 * h) for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(J, J_fd, atol=1e-8)


def test_shifted_symbolic_jacobian_is_the_base_jacobian_at_the_moved_point():
    x_eq, u_eq = np.array([0.3, 0.0]), _u_eq(0.3)
    s = BASE.shifted(x_eq, u_eq)
    z, Jf, Jg = symbolic_jacobians(s)
    x, Jf0, Jg0 = symbolic_jacobians(BASE)
    Z = np.random.default_rng(2).uniform(-1, 1, size=(2, 5))
    expected = (
        evaluate(Jf0, x, Z + x_eq[:, None]) + evaluate(Jg0, x, Z + x_eq[:, None])[:, :, 0] * u_eq[0]
    )
    np.testing.assert_allclose(evaluate(Jf, z, Z), expected, atol=1e-12)
    np.testing.assert_allclose(evaluate(Jg, z, Z), evaluate(Jg0, x, Z + x_eq[:, None]), atol=1e-12)


def test_certified_bounds_of_the_upright_pendulum():
    s = BASE.shifted([np.pi, 0.0], _u_eq(np.pi))
    box = ([-0.4, -1.0], [0.4, 1.0])
    b = jacobian_bounds(s, box, "certified", tol=1e-4)
    # d f2 / d z1 = -cos(pi + z1) + g' u* = cos(z1) + sin(z1) u*, u* = -1.
    z1 = np.linspace(-0.4, 0.4, 201)
    exact = np.cos(z1) + np.sin(z1) * _u_eq(np.pi)[0]
    assert b.Mf1[1, 0] <= exact.min() and exact.max() <= b.Mf2[1, 0]
    assert exact.min() - b.Mf1[1, 0] < 1e-3 and b.Mf2[1, 0] - exact.max() < 1e-3


def test_not_an_equilibrium_names_the_residual_and_the_fix():
    with pytest.raises(ModelError, match=r"not an equilibrium.*row 1 is 1 \(tolerance 1e-08\)"):
        BASE.shifted([0.0, 0.0], [0.0])
    with pytest.raises(ModelError, match="solve for u\\* given x\\*"):
        BASE.shifted([0.0, 0.0])
    # A looser tolerance accepts it.
    assert BASE.shifted([0.0, 0.0], [-0.4], tol=0.3).residual[1] == pytest.approx(-0.2)


@pytest.mark.parametrize(
    ("x_eq", "u_eq", "match"),
    [
        ([0.0], [0.0], r"equilibrium x must have length 2"),
        ([0.0, np.nan], [0.0], r"equilibrium x must be finite"),
        ([0.0, 0.0], [0.0, 1.0], r"equilibrium u must have length 1"),
        (["a", 0.0], [0.0], r"equilibrium x must be a list of 2 numbers"),
    ],
)
def test_bad_equilibrium_is_named(x_eq, u_eq, match):
    with pytest.raises(ModelError, match=match):
        BASE.shifted(x_eq, u_eq)


def test_shifted_stores_its_arguments_as_given_and_its_arrays_apart():
    # Before: x_eq and u_eq were replaced by float arrays (u_eq zeros for None).
    x_eq = np.array([np.pi / 2, 0.0])
    s = BASE.shifted(x_eq, tol=0.5)  # sin(pi/2) = 1 cancels the bias: u* = 0 (omitted)
    assert s.x_eq is x_eq and s.u_eq is None and s.tol == 0.5
    assert s.is_shifted is True
    x_star, u_star = s.equilibrium
    np.testing.assert_array_equal(x_star, [np.pi / 2, 0.0])
    np.testing.assert_array_equal(u_star, [0.0])
    assert not x_star.flags.writeable and not u_star.flags.writeable
    assert not s.residual.flags.writeable
    before = s.f(np.array([0.1, 0.2]))
    x_eq[0] = 0.0  # the caller's array changes; the model, built from a copy, does not
    np.testing.assert_array_equal(s.f(np.array([0.1, 0.2])), before)
    np.testing.assert_array_equal(s.equilibrium[0], [np.pi / 2, 0.0])
    np.testing.assert_array_equal(s.to_original_state(np.zeros(2)), [np.pi / 2, 0.0])
    assert "x_eq=[1.5707963267948966, 0.0]" in repr(s)
