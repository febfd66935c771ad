"""The (lmi2) matrix and its eigenvalue certificate: pure numpy, no Drake."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ofrl_drake.errors import OfrlError
from ofrl_drake.lmi import (
    LmiError,
    bounds_arrays,
    certificate,
    is_certified,
    lmi_matrix,
    vertex_data,
)

# The two-state example's sampled bounds on [-2, 2]^2 (rounded outward a little).
MF1 = np.array([[-1.0, 1.0], [-9.8074, 0.0]])
MF2 = np.array([[-1.0, 1.0], [7.8074, 4.0]])
MG1 = np.array([[[0.0], [0.0]], [[-2.0], [0.0]]])
MG2 = np.array([[[0.0], [0.0]], [[2.0], [0.0]]])
TWO_STATE = (MF1, MF2, MG1, MG2)
C2 = np.array([[0.0, 1.0]])


def test_scalar_matrix_by_hand():
    # n = q = 1, f = -x exactly, no input: A - LC = -1 - 3 = -4.
    Z = np.zeros((1, 1, 1))
    M = lmi_matrix(
        [[1.0]], [[3.0]], [[0.0]], [[0.0]], [[1.0]], ([[-1.0]], [[-1.0]], Z, Z), [0.0], 0.5
    )
    # M11 = 2 * (-1) * 1 - 2 * 3 + 2 * 0.5 = -7; M21 = P - 0 = 1; M22 = -2.
    np.testing.assert_allclose(M, [[-7.0, 1.0], [1.0, -2.0]], rtol=0, atol=1e-15)


def test_blocks_match_the_formula():
    rng = np.random.default_rng(3)
    n, q, m = 3, 2, 2
    Mf1 = rng.normal(size=(n, n))
    Mf2 = Mf1 + rng.uniform(0, 2, size=(n, n))
    Mg1 = rng.normal(size=(n, n, m))
    Mg2 = Mg1 + rng.uniform(0, 1, size=(n, n, m))
    P0 = rng.normal(size=(n, n))
    P = P0 @ P0.T + np.eye(n)
    L, H, K = (rng.normal(size=(n, q)) for _ in range(3))
    C = rng.normal(size=(q, n))
    u = np.array([-1.5, 0.7])
    alpha = 0.8
    M = lmi_matrix(P, L, H, K, C, (Mf1, Mf2, Mg1, Mg2), u, alpha)

    # Independent construction, entry by entry over k, of the sign-correct sector.
    Mug1 = np.zeros((n, n))
    Mug2 = np.zeros((n, n))
    for k in range(m):
        a, b = Mg1[:, :, k] * u[k], Mg2[:, :, k] * u[k]
        Mug1 += np.minimum(a, b)
        Mug2 += np.maximum(a, b)
    A = Mf1 + Mug1
    J21 = -(Mf2 - Mf1) / 2 @ (np.eye(n) - H @ C) - (Mug2 - Mug1) / 2 @ (np.eye(n) - K @ C)
    R = P @ L
    M11 = A.T @ P + P @ A - C.T @ R.T - R @ C + 2 * alpha * P
    np.testing.assert_allclose(M[:n, :n], M11, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(M[n:, :n], P - J21, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(M[:n, n:], (P - J21).T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(M[n:, n:], -2 * np.eye(n), rtol=0, atol=0)


def test_sectors_agree_for_nonnegative_inputs_and_differ_for_negative():
    for u in (0.0, 1.0, 3.0):
        for a, b in zip(
            vertex_data(TWO_STATE, [u], "sign_correct"),
            vertex_data(TWO_STATE, [u], "paper"),
            strict=True,
        ):
            np.testing.assert_allclose(a, b, rtol=0, atol=0)
    A_sc, _, Jg_sc = vertex_data(TWO_STATE, [-3.0], "sign_correct")
    A_p, _, Jg_p = vertex_data(TWO_STATE, [-3.0], "paper")
    # Sign-correct: dg2/dx1 * u in [-6, 6], so A[1, 0] = Mf1[1, 0] - 6, width 12.
    assert A_sc[1, 0] == pytest.approx(MF1[1, 0] - 6.0, abs=1e-12)
    assert Jg_sc[1, 0] == pytest.approx(-6.0, abs=1e-12)
    # The paper's literal form flips the sector: "lower" +6, "width" -12.
    assert A_p[1, 0] == pytest.approx(MF1[1, 0] + 6.0, abs=1e-12)
    assert Jg_p[1, 0] == pytest.approx(+6.0, abs=1e-12)


def test_linear_system_reduces_to_schur_form():
    # Mf1 = Mf2 = A and Mg = 0: J21 = 0 whatever H, K are.
    A = np.array([[0.0, 1.0], [-2.0, -0.5]])
    Z = np.zeros((2, 2, 1))
    P = np.array([[2.0, 0.3], [0.3, 1.0]])
    L = np.array([[1.0], [2.0]])
    H = np.array([[5.0], [-7.0]])
    M = lmi_matrix(P, L, H, 3 * H, C2, (A, A, Z, Z), [1.0], 0.3)
    Acl = A - L @ C2
    expected = np.block([[Acl.T @ P + P @ Acl + 0.6 * P, P], [P, -2 * np.eye(2)]])
    np.testing.assert_allclose(M, expected, rtol=1e-13, atol=1e-13)


@settings(max_examples=30, deadline=None)
@given(
    arrays(np.float64, (2, 2), elements=st.floats(-3, 3)),
    arrays(np.float64, (2, 1), elements=st.floats(-20, 20)),
    st.floats(0.0, 3.0),
)
def test_negative_lmi_iff_negative_schur_complement(A, L, alpha):
    # With M22 = -2 I < 0, M < 0 iff M11 + M21^T M21 / 2 < 0 (Schur complement).
    Z = np.zeros((2, 2, 1))
    P = np.array([[3.0, -0.5], [-0.5, 1.5]])
    M = lmi_matrix(P, L, np.zeros((2, 1)), np.zeros((2, 1)), C2, (A, A, Z, Z), [0.0], alpha)
    S = M[:2, :2] + M[2:, :2].T @ M[2:, :2] / 2
    lam_M = np.linalg.eigvalsh(M)[-1]
    lam_S = np.linalg.eigvalsh(S)[-1]
    if abs(lam_S) > 1e-9 * (1 + np.abs(S).max()):
        assert (lam_M < 0) == (lam_S < 0)


def test_certificate_lists_every_vertex_with_its_max_eigenvalue():
    rng = np.random.default_rng(0)
    n, q, m = 2, 1, 2
    Mf1 = -np.eye(n)
    Mg1 = rng.uniform(-1, 0, size=(n, n, m))
    bounds = {"Mf1": Mf1, "Mf2": Mf1 + 0.1, "Mg1": Mg1, "Mg2": -Mg1}
    P, L, H, K = np.eye(n), np.ones((n, q)), np.zeros((n, q)), np.zeros((n, q))
    cert = certificate(P, L, H, K, C2, bounds, 2.0, 0.1)
    assert len(cert) == 3**m
    inputs = {tuple(u) for u, _ in cert}
    assert inputs == {(a, b) for a in (-2.0, 0.0, 2.0) for b in (-2.0, 0.0, 2.0)}
    for u, lam in cert:
        M = lmi_matrix(P, L, H, K, C2, bounds, u, 0.1)
        assert lam == pytest.approx(np.linalg.eigvalsh(M)[-1], abs=1e-12)


def test_is_certified_needs_positive_definite_p_and_negative_vertices():
    A = np.array([[-1.0, 0.0], [0.0, -1.0]])
    Z = np.zeros((2, 2, 1))
    zeros = np.zeros((2, 1))
    # Stable diagonal plant, small P: M11 = -2 P + 2 alpha P, M21 = P.
    P = 0.1 * np.eye(2)
    assert is_certified(P, zeros, zeros, zeros, C2, (A, A, Z, Z), 1.0, 0.1)
    # Same numbers but alpha too large: the (1, 1) block turns positive.
    assert not is_certified(P, zeros, zeros, zeros, C2, (A, A, Z, Z), 1.0, 1.5)
    # An indefinite P never certifies, even if the LMI happens to be negative.
    assert not is_certified(-P, zeros, zeros, zeros, C2, (A, A, Z, Z), 1.0, 0.1)


def test_bounds_arrays_accepts_objects_mappings_and_tuples():
    class Obj:
        Mf1, Mf2, Mg1, Mg2 = TWO_STATE

    for b in (Obj(), dict(zip(("Mf1", "Mf2", "Mg1", "Mg2"), TWO_STATE, strict=True)), TWO_STATE):
        out = bounds_arrays(b)
        for got, want in zip(out, TWO_STATE, strict=True):
            np.testing.assert_array_equal(got, want)


def test_errors_name_the_problem():
    eye = np.eye(2)
    g = np.zeros((2, 1))
    with pytest.raises(LmiError, match="sector must be one of"):
        lmi_matrix(eye, g, g, g, C2, TWO_STATE, [1.0], 1.0, sector="negative")
    with pytest.raises(LmiError, match=r"L must have shape \(n, q\) = \(2, 1\)"):
        lmi_matrix(eye, np.zeros((2, 2)), g, g, C2, TWO_STATE, [1.0], 1.0)
    with pytest.raises(LmiError, match=r"u must have shape \(1,\)"):
        lmi_matrix(eye, g, g, g, C2, TWO_STATE, [1.0, 2.0], 1.0)
    with pytest.raises(LmiError, match="missing keys"):
        bounds_arrays({"Mf1": MF1})
    with pytest.raises(LmiError, match=r"Mg1 and Mg2 must have shape \(2, 2, m\)"):
        bounds_arrays((MF1, MF2, np.zeros((2, 2)), np.zeros((2, 2))))
    with pytest.raises(LmiError, match="input_bound must be finite"):
        certificate(eye, g, g, g, C2, TWO_STATE, np.inf, 1.0)
    assert issubclass(LmiError, OfrlError)
