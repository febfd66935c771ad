"""The local certificate of a Luenberger gain on the linearization (pure numpy/scipy)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from ofrl_drake.baselines import (
    linearized_observer_certificate,
    luenberger_gain,
    luenberger_poles,
)
from ofrl_drake.errors import ModelError

A = np.array([[-1.0, 1.0], [-0.5, 0.0]])  # the paper's linearization at the origin
C = np.array([[0.0, 1.0]])


def test_placed_gain_certifies_its_rate_and_the_certificate_rechecks():
    L = luenberger_gain(A, C, luenberger_poles(2.0, 2))
    cert = linearized_observer_certificate(A, C, L, 2.0)
    assert cert.is_certified
    Acl = A - L @ C
    M = Acl.T @ cert.P + cert.P @ Acl + 2.0 * 2.0 * cert.P
    assert cert.certificate() == pytest.approx(np.linalg.eigvalsh(M)[-1], rel=1e-12)
    # The Lyapunov equation holds: (Acl + alpha I)^T P + P (Acl + alpha I) = -I.
    S = Acl + 2.0 * np.eye(2)
    np.testing.assert_allclose(S.T @ cert.P + cert.P @ S, -np.eye(2), rtol=0, atol=1e-10)


def test_rate_beyond_the_slowest_pole_is_not_certified():
    L = luenberger_gain(A, C, luenberger_poles(2.0, 2))  # poles -4, -6
    assert linearized_observer_certificate(A, C, L, 3.9).is_certified
    assert not linearized_observer_certificate(A, C, L, 4.1).is_certified


def test_bad_alpha_and_shapes_raise():
    L = np.array([[1.0], [1.0]])
    with pytest.raises(ModelError, match=r"alpha must be a positive number; got -1.0"):
        linearized_observer_certificate(A, C, L, -1.0)
    with pytest.raises(ModelError, match=r"A must be \(n, n\) and C \(q, n\)"):
        linearized_observer_certificate(A, np.ones((1, 3)), L, 1.0)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.floats(-3, 3), min_size=3, max_size=3),
    st.floats(0.11, 3.0),
    st.sampled_from([-1.0, 1.0]),
    st.floats(0.2, 2.0),
)
def test_certified_gains_decay_at_the_rate_in_simulation(entries, coupling, sign, alpha):
    """If certified, V = e^T P e decays at least like exp(-2 alpha t) along e' = (A - LC) e."""
    # |A[1, 0]| > 0.1 keeps (A, C) well observable, so every example places poles.
    a00, a01, a11 = entries
    A_r = np.array([[a00, a01], [sign * coupling, a11]])
    L = luenberger_gain(A_r, C, luenberger_poles(alpha, 2))
    cert = linearized_observer_certificate(A_r, C, L, alpha)
    assert cert.is_certified
    Acl = A_r - L @ C
    e0 = np.array([1.0, -0.7])
    sol = solve_ivp(lambda t, e: Acl @ e, (0, 2.0), e0, rtol=1e-10, atol=1e-12, dense_output=True)
    V0 = e0 @ cert.P @ e0
    for t in np.linspace(0, 2.0, 9):
        e = sol.sol(t)
        assert e @ cert.P @ e <= V0 * np.exp(-2 * alpha * t) * (1 + 1e-6) + 1e-12
