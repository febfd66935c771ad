"""The (lmi2) matrix, the polytopic decay certificate and their checks: pure numpy."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ofrl_drake import lmi
from ofrl_drake.errors import OfrlError
from ofrl_drake.lmi import (
    MAX_CORNERS,
    LmiError,
    bounds_arrays,
    box_corners,
    certificate,
    corner_count,
    corner_matrices,
    decay_certificate,
    is_certified,
    is_decay_certified,
    lmi_matrix,
    polytopic_lmi,
    thin_perturbation,
    vertex_data,
)
from ofrl_drake.sector import input_sector

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
    # With M22 = -2 I < 0, M < 0 iff S = M11 + M21^T M21 / 2 < 0 (Schur complement).
    # S is built from the design variables by the (lmi2) formula (ofrl_drake/lmi.py's
    # module docstring), not from M's blocks: for a linear plant (M_f1 = M_f2 = A,
    # M_g = 0) J21 = 0, so M11 = A_cl^T P + P A_cl + 2 alpha P with A_cl = A - L C
    # (R = P L) and M21 = P. A wrong M11 or M21 in lmi_matrix breaks the identities.
    Z = np.zeros((2, 2, 1))
    P = np.array([[3.0, -0.5], [-0.5, 1.5]])
    M = lmi_matrix(P, L, np.zeros((2, 1)), np.zeros((2, 1)), C2, (A, A, Z, Z), [0.0], alpha)
    Acl = A - L @ C2
    S = Acl.T @ P + P @ Acl + 2 * alpha * P + P.T @ P / 2
    # det M = det(M22) det S = 4 det S (n = 2), to rounding of 4x4 determinants.
    scale = (1.0 + np.abs(M).max()) ** 4
    np.testing.assert_allclose(
        np.linalg.det(M), 4.0 * np.linalg.det(S), rtol=1e-9, atol=1e-12 * scale
    )
    lam_M = np.linalg.eigvalsh(M)
    lam_S = np.linalg.eigvalsh(S)
    if np.all(np.abs(lam_S) > 1e-9 * (1 + np.abs(S).max())):
        # Haynsworth: M has the n negative eigenvalues of M22 and the inertia of S,
        # so as many positive eigenvalues as S, and M < 0 iff S < 0.
        assert np.sum(lam_M > 0) == np.sum(lam_S > 0)
        assert (lam_M[-1] < 0) == (lam_S[-1] < 0)


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


# ------------------------------------------------ polytopic decay certificate
# A 2x2 case by hand: f has one uncertain entry d f_2 / d x_1 in [-1, 1], g one
# entry d g_2 / d x_1 in [-1, 1]; with |u| <= 1 the sum a = M_f[1, 0] + M_gu[1, 0]
# lies in [-2, 2] at u = +-1 and in [-1, 1] at u = 0.
HAND = (
    np.array([[-1.0, 0.0], [-1.0, -2.0]]),
    np.array([[-1.0, 0.0], [1.0, -2.0]]),
    np.array([[[0.0], [0.0]], [[-1.0], [0.0]]]),
    np.array([[[0.0], [0.0]], [[1.0], [0.0]]]),
)


def test_decay_certificate_by_hand():
    zeros = np.zeros((2, 1))
    # P = I, L = 0, alpha = 1/2: S = A + A^T + I = [[-1, a], [a, -3]],
    # lambda_max = -2 + sqrt(1 + a^2), largest at |a| = 2 (u = +-1), 1 (u = 0).
    cert = decay_certificate(np.eye(2), zeros, zeros, zeros, C2, HAND, 1.0, 0.5)
    assert [u.tolist() for u, _ in cert] == [[-1.0], [0.0], [1.0]]
    want = [-2 + np.sqrt(5.0), -2 + np.sqrt(2.0), -2 + np.sqrt(5.0)]
    np.testing.assert_allclose([ev for _, ev in cert], want, rtol=0, atol=1e-12)
    assert not is_decay_certified(np.eye(2), zeros, zeros, zeros, C2, HAND, 1.0, 0.5)
    # L = [0, 1]^T moves A_cl[1, 1] to -3: S = [[-1, a], [a, -5]],
    # lambda_max = -3 + sqrt(4 + a^2).
    L = np.array([[0.0], [1.0]])
    cert = decay_certificate(np.eye(2), L, zeros, zeros, C2, HAND, 1.0, 0.5)
    want = [-3 + np.sqrt(8.0), -3 + np.sqrt(5.0), -3 + np.sqrt(8.0)]
    np.testing.assert_allclose([ev for _, ev in cert], want, rtol=0, atol=1e-12)
    assert is_decay_certified(np.eye(2), L, zeros, zeros, C2, HAND, 1.0, 0.5)
    # A P that is not positive definite never certifies.
    assert not is_decay_certified(-np.eye(2), L, zeros, zeros, C2, HAND, 1.0, 0.5)


def test_box_corners_vary_only_the_uncertain_entries():
    lo = np.array([[0.0, 1.0], [2.0, -1.0]])
    hi = np.array([[3.0, 1.0], [2.0, 4.0]])
    corners = box_corners(lo, hi)
    assert corners.shape == (4, 2, 2)
    got = {tuple(c.ravel()) for c in corners}
    assert got == {(a, 1.0, 2.0, b) for a in (0.0, 3.0) for b in (-1.0, 4.0)}
    np.testing.assert_array_equal(box_corners(lo, lo), lo[None])
    with pytest.raises(
        LmiError, match=r"entry \[0, 0\]: lower = 3, upper = 0; the lower bound exceeds"
    ):
        box_corners(hi, lo)
    with pytest.raises(LmiError, match=r"17 uncertain entries, 131072 corners, more than"):
        box_corners(np.zeros(17), np.ones(17))


def _brute_force_decay(P, L, H, K, C, bounds, input_bound, alpha):
    """Max eigenvalue per input vertex over every corner of M_f and of each G_k."""
    Mf1, Mf2, Mg1, Mg2 = bounds
    n, m = Mf1.shape[0], Mg1.shape[2]
    eye = np.eye(n)
    f_free = [tuple(i) for i in np.argwhere(Mf1 != Mf2)]
    g_free = [tuple(i) for i in np.argwhere(Mg1 != Mg2)]
    out = []
    for u in itertools.product((-input_bound, 0.0, input_bound), repeat=m):
        u = np.array(u)
        Mug1 = sum(np.minimum(Mg1[:, :, k] * u[k], Mg2[:, :, k] * u[k]) for k in range(m))
        worst = -np.inf
        for f_bits in itertools.product((0, 1), repeat=len(f_free)):
            Mf = Mf1.copy()
            for idx, bit in zip(f_free, f_bits, strict=True):
                Mf[idx] = (Mf1, Mf2)[bit][idx]
            for g_bits in itertools.product((0, 1), repeat=len(g_free)):
                G = Mg1.copy()
                for idx, bit in zip(g_free, g_bits, strict=True):
                    G[idx] = (Mg1, Mg2)[bit][idx]
                Mgu = sum(G[:, :, k] * u[k] for k in range(m))
                Acl = Mf @ (eye - H @ C) + Mgu @ (eye - K @ C) - (L - Mf1 @ H - Mug1 @ K) @ C
                S = Acl.T @ P + P @ Acl + 2 * alpha * P
                worst = max(worst, np.linalg.eigvalsh(S)[-1])
        out.append((u, worst))
    return out


def _random_case(seed, n=3, q=2, m=2):
    rng = np.random.default_rng(seed)
    Mf1 = rng.normal(size=(n, n))
    Mf2 = Mf1 + rng.uniform(0, 2, size=(n, n)) * (rng.random((n, n)) < 0.5)
    Mg1 = rng.normal(size=(n, n, m))
    Mg2 = Mg1 + rng.uniform(0, 1, size=(n, n, m)) * (rng.random((n, n, m)) < 0.25)
    P0 = rng.normal(size=(n, n))
    P = P0 @ P0.T + np.eye(n)
    L, H, K = (rng.normal(size=(n, q)) for _ in range(3))
    C = rng.normal(size=(q, n))
    return (Mf1, Mf2, Mg1, Mg2), P, L, H, K, C


@pytest.mark.parametrize("injection", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_decay_certificate_equals_brute_force_over_every_g_corner(seed, injection):
    bounds, P, L, H, K, C = _random_case(seed)
    if not injection:
        H, K = np.zeros_like(H), np.zeros_like(K)
    got = decay_certificate(P, L, H, K, C, bounds, 1.5, 0.3)
    want = _brute_force_decay(P, L, H, K, C, bounds, 1.5, 0.3)
    assert len(got) == 9
    for (u1, ev1), (u2, ev2) in zip(got, want, strict=True):
        np.testing.assert_array_equal(u1, u2)
        assert ev1 == pytest.approx(ev2, rel=1e-10, abs=1e-10)


@pytest.mark.parametrize("seed", [3, 4])
def test_decay_certificate_bounds_every_sampled_jacobian_and_input(seed):
    # The convexity argument: any M_f, G_k in their boxes and any |u_k| <= bound
    # give a lambda_max no larger than the certificate's worst vertex value.
    bounds, P, L, H, K, C = _random_case(seed)
    Mf1, Mf2, Mg1, Mg2 = bounds
    worst = max(ev for _, ev in decay_certificate(P, L, H, K, C, bounds, 1.5, 0.3))
    rng = np.random.default_rng(seed + 100)
    eye = np.eye(3)
    for _ in range(300):
        Mf = Mf1 + rng.random(Mf1.shape) * (Mf2 - Mf1)
        G = Mg1 + rng.random(Mg1.shape) * (Mg2 - Mg1)
        u = rng.uniform(-1.5, 1.5, size=2)
        Mug1, _ = input_sector(Mg1, Mg2, u)
        Acl = Mf @ (eye - H @ C) + (G * u).sum(-1) @ (eye - K @ C) - (L - Mf1 @ H - Mug1 @ K) @ C
        S = Acl.T @ P + P @ Acl + 0.6 * P
        assert np.linalg.eigvalsh(S)[-1] <= worst + 1e-10 * (1 + abs(worst))


def test_corner_matrices_without_injection_use_the_summed_box():
    # H = K = 0: the corners of [Mf1 + Mug1(u), Mf2 + Mug2(u)]; at u = +-1 the
    # entry [1, 0] ranges over [-2, 2], at u = 0 over [-1, 1].
    for u, lo, hi in (([1.0], -2.0, 2.0), ([0.0], -1.0, 1.0), ([-1.0], -2.0, 2.0)):
        A = corner_matrices(HAND, u)
        assert A.shape == (2, 2, 2) and corner_count(HAND, u) == 2
        assert sorted(A[:, 1, 0].tolist()) == [lo, hi]
        np.testing.assert_array_equal(A[:, 0, 0], [-1.0, -1.0])
        np.testing.assert_array_equal(A[:, 1, 1], [-2.0, -2.0])
    # With injection, M_f and M_gu corners are taken separately: 2 x 2 at u = 1.
    H = np.array([[0.5], [0.0]])
    assert corner_matrices(HAND, [1.0], H, np.zeros((2, 1)), C2).shape == (4, 2, 2)
    assert corner_count(HAND, [1.0], H, np.zeros((2, 1)), C2) == 4


def test_polytopic_lmi_is_the_decay_matrix_with_r_equal_p_l():
    bounds, P, L, _, _, C = _random_case(5)
    zeros = np.zeros_like(L)
    A = corner_matrices(bounds, [1.0, -1.0])
    got = polytopic_lmi(P, P @ L, A, C, 0.7)
    for Ai, Mi in zip(A, got, strict=True):
        Acl = Ai - L @ C
        np.testing.assert_allclose(Mi, Acl.T @ P + P @ Acl + 1.4 * P, rtol=1e-12, atol=1e-11)
    cert = decay_certificate(P, L, zeros, zeros, C, bounds, 1.0, 0.7)
    assert cert[2 * 3 + 0][1] == pytest.approx(np.linalg.eigvalsh(got)[:, -1].max(), rel=1e-12)


def test_linear_plant_decay_certificate_is_the_lyapunov_inequality():
    # Mf1 = Mf2 = A, g constant: one corner, S = (A - LC)^T P + P (A - LC) + 2 alpha P.
    A = np.array([[0.0, 1.0], [-2.0, -0.5]])
    Z = np.zeros((2, 2, 1))
    P = np.array([[2.0, 0.3], [0.3, 1.0]])
    L = np.array([[1.0], [2.0]])
    Acl = A - L @ C2
    want = np.linalg.eigvalsh(Acl.T @ P + P @ Acl + 0.6 * P)[-1]
    cert = decay_certificate(P, L, 5 * L, -L, C2, (A, A, Z, Z), 2.0, 0.3)
    for _, ev in cert:
        assert ev == pytest.approx(want, rel=1e-12, abs=1e-12)


def test_decay_certificate_errors_name_the_problem():
    eye = np.eye(2)
    g = np.zeros((2, 1))
    with pytest.raises(LmiError, match="input_bound must be finite"):
        decay_certificate(eye, g, g, g, C2, HAND, -1.0, 1.0)
    with pytest.raises(LmiError, match="alpha must be finite"):
        decay_certificate(eye, g, g, g, C2, HAND, 1.0, np.nan)
    with pytest.raises(LmiError, match=r"P must have shape \(2, 2\)"):
        decay_certificate(np.eye(3), g, g, g, C2, HAND, 1.0, 1.0)
    with pytest.raises(LmiError, match=r"u must have shape \(1,\)"):
        corner_matrices(HAND, [1.0, 2.0])
    with pytest.raises(LmiError, match="give H, K and C together"):
        corner_matrices(HAND, [1.0], H=g)
    # 5 x 5 with every f entry uncertain: 2**25 corners at each of 3 vertices.
    n = 5
    wide = (-np.ones((n, n)), np.ones((n, n)), np.zeros((n, n, 1)), np.zeros((n, n, 1)))
    gn = np.zeros((n, 1))
    Cn = np.eye(1, n)
    with pytest.raises(LmiError, match=f"more than MAX_CORNERS = {MAX_CORNERS}"):
        decay_certificate(np.eye(n), gn, gn, gn, Cn, wide, 1.0, 1.0)


def _widen_by_ulps(M, ulps=1):
    lo, hi = M.copy(), M.copy()
    for _ in range(ulps):
        lo, hi = np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)
    return lo, hi


def test_entries_one_ulp_wide_add_no_corners():
    # An enclosure widens the constant entries of the two-state Jacobian by an
    # ulp; they must not multiply the corners (4 wide entries, 16 corners).
    Mf1, Mf2 = MF1.copy(), MF2.copy()
    constant = Mf1 == Mf2
    lo, hi = _widen_by_ulps(Mf1)
    Mf1[constant], Mf2[constant] = lo[constant], hi[constant]
    bounds = (Mf1, Mf2, MG1, MG2)
    H = K = np.array([[0.3], [0.1]])
    assert corner_count(bounds, [3.0], H, K, C2) == corner_count(TWO_STATE, [3.0], H, K, C2)
    assert 0 < thin_perturbation(bounds, [3.0], H, K, C2) < 1e-14
    assert thin_perturbation(TWO_STATE, [3.0], H, K, C2) == 0.0


@pytest.mark.parametrize("injection", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 5])
def test_thin_entries_stay_sound_through_the_perturbation_bound(monkeypatch, seed, injection):
    # Make "thin" coarse enough (5%) that the perturbation term is measurable:
    # the certificate must still bound every corner of the full box (brute
    # force), and must differ from a midpoint-only evaluation.
    monkeypatch.setattr(lmi, "THIN_RTOL", 0.05)
    bounds, P, L, H, K, C = _random_case(seed)
    if not injection:
        H, K = np.zeros_like(H), np.zeros_like(K)
    Mf1, Mf2, Mg1, Mg2 = bounds
    rng = np.random.default_rng(seed + 7)
    thin_f = rng.random(Mf1.shape) < 0.4
    Mf2 = np.where(thin_f, Mf1 + 0.02, Mf2)
    bounds = (Mf1, Mf2, Mg1, Mg2)
    got = decay_certificate(P, L, H, K, C, bounds, 1.5, 0.3)
    want = _brute_force_decay(P, L, H, K, C, bounds, 1.5, 0.3)
    assert any(thin_perturbation(bounds, u, H, K, C) > 0 for u, _ in got)
    for (u, ev), (_, brute) in zip(got, want, strict=True):
        assert ev >= brute - 1e-12 * (1 + abs(brute))
        # ... and not by an absurd margin: within the perturbation term.
        slack = 2 * np.linalg.norm(P, 2) * thin_perturbation(bounds, u, H, K, C)
        assert ev <= brute + slack + 1e-9


@pytest.mark.parametrize(
    "check", [certificate, decay_certificate, is_certified, is_decay_certified]
)
def test_a_gain_that_is_not_finite_is_named(check):
    # Before: certificate raised numpy's LinAlgError ("Eigenvalues did not converge")
    # and decay_certificate returned NaN values; now one check, lmi.gain_matrix, names L.
    g = np.zeros((2, 1))
    nan = np.array([[np.nan], [0.0]])
    with pytest.raises(LmiError, match=r"L must be finite; got \[\[nan\], \[0\.0\]\]"):
        check(np.eye(2), nan, g, g, C2, TWO_STATE, 1.0, 0.5)


def test_gain_matrix_reads_a_column_and_names_the_shape():
    np.testing.assert_array_equal(lmi.gain_matrix("L", [1.0, 2.0], 2, 1), [[1.0], [2.0]])
    with pytest.raises(LmiError, match=r"K must have shape \(n, q\) = \(2, 2\); got \(2,\)"):
        lmi.gain_matrix("K", [1.0, 2.0], 2, 2)
    with pytest.raises(OfrlError, match=r"L must be numeric; got 'x'") as caught:
        lmi.gain_matrix("L", "x", 2, 1, error=OfrlError)
    assert type(caught.value) is OfrlError
    g = np.zeros((2, 1))
    with pytest.raises(LmiError, match=r"H must be finite; got \[\[inf\], \[0\.0\]\]"):
        corner_matrices(TWO_STATE, [1.0], np.array([[np.inf], [0.0]]), g, C2)


def test_certifies_judges_p_on_its_symmetric_part():
    negative = lambda: [(np.zeros(1), -1.0)]  # noqa: E731
    skew = np.array([[0.0, 10.0], [-10.0, 0.0]])
    assert lmi.certifies(np.eye(2) + skew, negative)  # lower triangle alone: indefinite
    assert not lmi.certifies(-np.eye(2) + skew, negative)
    assert not lmi.certifies(np.eye(2), lambda: [(np.zeros(1), -1.0), (np.ones(1), 0.0)])

    def never():
        raise AssertionError("the certificate of a P that is not positive definite")

    assert not lmi.certifies(np.full((2, 2), np.nan), never)
    assert not lmi.certifies(np.diag([1.0, 0.0]), never)


def test_vertex_corners_are_corner_matrices_per_vertex_within_max_corners():
    H = K = np.array([[0.3], [0.1]])
    got = list(lmi.vertex_corners(TWO_STATE, 3.0, H, K, C2))
    assert [u.tolist() for u, _ in got] == [[-3.0], [0.0], [3.0]]
    for u, corners in got:
        np.testing.assert_array_equal(corners, corner_matrices(TWO_STATE, u, H, K, C2))
    n = 5
    wide = (-np.ones((n, n)), np.ones((n, n)), np.zeros((n, n, 1)), np.zeros((n, n, 1)))
    with pytest.raises(
        LmiError,
        match=r"needs 100663296 corner matrices over 3 input vertices, more than MAX_CORNERS = "
        r"65536; tighten the Jacobian bounds, use a smaller box or formulation='paper'\.$",
    ):
        lmi.vertex_corners(wide, 1.0, hint="formulation='paper'")
    with pytest.raises(LmiError, match=r"tighten the Jacobian bounds or use a smaller box\.$"):
        lmi.vertex_corners(wide, 1.0)
