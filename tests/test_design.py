"""Observer design: certificates, backends, persistence, infeasibility, errors."""

import json

import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ofrl_drake.design import (
    DesignError,
    ObserverDesign,
    ObserverDesignInfeasible,
    design_observer,
    max_decay_rate,
)
from ofrl_drake.design_cvxpy import design_observer_cvxpy
from ofrl_drake.errors import OfrlError
from ofrl_drake.examples import make_system
from ofrl_drake.jacobian_bounds import BoxError, jacobian_bounds
from ofrl_drake.lmi import certificate, lmi_matrix
from ofrl_drake.model import ControlAffineSystem

BOX2 = ([-2.0, -2.0], [2.0, 2.0])
BOX4 = ([-2.0] * 4, [2.0] * 4)


@pytest.fixture(scope="module")
def two_state():
    return make_system("two_state")


@pytest.fixture(scope="module")
def bounds2(two_state):
    return jacobian_bounds(two_state, BOX2)


@pytest.fixture(scope="module")
def design2(two_state, bounds2):
    return design_observer(two_state, BOX2, 3.0, 2.0, bounds=bounds2)


def _recomputed(design, system):
    """The certificate from the JSON numbers alone, through the pure-numpy module."""
    d = json.loads(json.dumps(design.to_dict()))
    return certificate(
        d["P"], d["L"], d["H"], d["K"], system.output_matrix, d["jacobian_bounds"],
        d["input_bound"], d["alpha"],
    )  # fmt: skip


# ------------------------------------------------------------- certificates
def test_two_state_certifies_at_alpha_2(two_state, design2):
    d = design2
    assert d.is_certified
    assert d.backend == "drake" and d.solver == "clarabel"
    cert = d.certificate()
    assert [u.tolist() for u, _ in cert] == [[-3.0], [0.0], [3.0]]
    # Every vertex has the strict margin the SDP asked for (1e-3), up to solver accuracy.
    for _, lam in cert:
        assert lam <= -0.5e-3
    assert d.condition_number < 1e3
    assert np.all(np.linalg.eigvalsh(d.P) >= 1.0 - 1e-6)  # P >= I
    np.testing.assert_allclose(d.R, d.P @ d.L, rtol=1e-9, atol=1e-9)
    again = _recomputed(d, two_state)
    for (u1, lam1), (u2, lam2) in zip(cert, again, strict=True):
        np.testing.assert_array_equal(u1, u2)
        assert lam1 == pytest.approx(lam2, rel=1e-9, abs=1e-12)


def test_mimo_coupled_two_state_certifies_at_all_nine_vertices():
    system = make_system("coupled_two_state")
    d = design_observer(system, BOX4, 3.0, 1.0)
    assert d.L.shape == (4, 2) and d.H.shape == (4, 2) and d.K.shape == (4, 2)
    cert = d.certificate()
    assert len(cert) == 9
    assert all(lam < 0 for _, lam in cert)
    assert d.is_certified and d.condition_number < 1e3
    again = _recomputed(d, system)
    assert max(lam for _, lam in again) < 0


def test_min_gain_beats_feasibility_on_gain(two_state, bounds2):
    small = design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2)
    plain = design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2, objective="feasibility")
    assert plain.is_certified and small.is_certified
    assert small.gain_norm < plain.gain_norm


def test_max_gain_caps_the_gain(two_state, bounds2):
    d = design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2, max_gain=200.0)
    assert d.gain_norm <= 200.0 * (1 + 1e-6)
    with pytest.raises(ObserverDesignInfeasible, match="a larger max_gain"):
        design_observer(two_state, BOX2, 3.0, 2.0, bounds=bounds2, max_gain=50.0)


# ------------------------------------------------------------------ sign gap
def test_paper_sector_fails_at_negative_input_where_sign_correct_certifies(two_state, design2):
    C = two_state.output_matrix
    d = design2
    args = (d.P, d.L, d.H, d.K, C, d.bounds)
    assert np.linalg.eigvalsh(lmi_matrix(*args, [-3.0], 2.0))[-1] < 0
    # Same numbers, the paper's literal sector (M_g1 u, M_g2 u): fails at u = -3 ...
    assert np.linalg.eigvalsh(lmi_matrix(*args, [-3.0], 2.0, sector="paper"))[-1] > 1.0
    # ... and agrees at u >= 0, where the two sectors coincide.
    for u in (0.0, 3.0):
        a = lmi_matrix(*args, [u], 2.0)
        b = lmi_matrix(*args, [u], 2.0, sector="paper")
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_paper_sector_design_is_infeasible_at_alpha_2(two_state, bounds2):
    with pytest.raises(ObserverDesignInfeasible, match="smaller alpha") as err:
        design_observer(two_state, BOX2, 3.0, 2.0, bounds=bounds2, sector="paper")
    assert "Infeasible" in err.value.status


# ------------------------------------------------------------------ backends
@pytest.mark.parametrize(
    ("half", "alpha"),
    [(0.5, 0.5), (0.5, 2.0), (0.5, 50.0), (2.0, 0.5), (2.0, 2.0), (2.0, 50.0), (50.0, 0.5)],
)
def test_backends_agree_on_feasibility(two_state, half, alpha):
    box = ([-half, -half], [half, half])
    bounds = jacobian_bounds(two_state, box)
    outcomes = []
    for backend in ("drake", "cvxpy"):
        try:
            d = design_observer(two_state, box, 3.0, alpha, bounds=bounds, backend=backend)
        except ObserverDesignInfeasible:
            outcomes.append(False)
        else:
            assert d.is_certified and d.backend == backend
            outcomes.append(True)
    assert outcomes[0] == outcomes[1]
    assert outcomes[0] == (alpha < 50.0 or half == 50.0)


def test_backends_find_the_same_optimum(two_state, bounds2, design2):
    other = design_observer_cvxpy(two_state, BOX2, 3.0, 2.0, bounds=bounds2)
    assert other.backend == "cvxpy" and other.is_certified
    # Same convex program, same objective: the same minimal ||R||_2.
    assert np.linalg.norm(other.R, 2) == pytest.approx(np.linalg.norm(design2.R, 2), rel=1e-3)


def test_csdp_through_drake(two_state, bounds2):
    d = design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2, solver="csdp")
    assert d.is_certified and d.solver == "csdp"


# ------------------------------------------------------------- infeasibility
def test_infeasible_rate_raises_with_one_line_advice(two_state, bounds2):
    with pytest.raises(ObserverDesignInfeasible, match=r"alpha=50.*try a smaller alpha") as err:
        design_observer(two_state, BOX2, 3.0, 50.0, bounds=bounds2)
    e = err.value
    assert "\n" not in str(e)
    assert e.alpha == 50.0 and e.input_bound == 3.0
    assert e.box.lower.tolist() == [-2.0, -2.0]
    assert e.status
    assert isinstance(e, OfrlError)


# ------------------------------------------------------------- persistence
def test_to_dict_keys_and_json_round_trip(two_state, design2, tmp_path):
    d = design2.to_dict()
    required = {
        "P", "L", "H", "K", "alpha", "input_bound", "box", "jacobian_bounds",
        "certificate", "solver", "solve_time",
    }  # fmt: skip
    assert required <= set(d)
    assert set(d["box"]) == {"lower", "upper"}
    assert set(d["jacobian_bounds"]) == {"Mf1", "Mf2", "Mg1", "Mg2"}
    assert [set(c) for c in d["certificate"]] == [{"input", "max_eigenvalue"}] * 3
    assert isinstance(d["P"][0][0], float) and isinstance(d["L"][1][0], float)
    path = tmp_path / "design.json"
    design2.to_json(path)
    back = ObserverDesign.from_json(path)
    for key in ("P", "L", "H", "K", "R", "C"):
        np.testing.assert_array_equal(getattr(back, key), getattr(design2, key))
    assert back.alpha == design2.alpha and back.box == design2.box
    assert back.is_certified
    assert [lam for _, lam in back.certificate()] == [lam for _, lam in design2.certificate()]
    # Without "C", the system supplies it.
    del d["C"]
    assert ObserverDesign.from_dict(d, system=two_state).is_certified
    with pytest.raises(DesignError, match="no 'C'"):
        ObserverDesign.from_dict(d)
    with pytest.raises(DesignError, match=r"missing keys \['P'\]"):
        ObserverDesign.from_dict({k: v for k, v in d.items() if k != "P"}, system=two_state)


def test_from_gains_finds_p_or_reports_honestly(two_state, bounds2, design2):
    d = design2
    pinned = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 2.0, d.L, d.H, d.K, P=d.P, bounds=bounds2
    )
    assert pinned.is_certified and pinned.solver == "none"
    found = ObserverDesign.from_gains(two_state, BOX2, 3.0, 2.0, d.L, d.H, d.K, bounds=bounds2)
    assert found.is_certified
    assert found.condition_number <= d.condition_number * (1 + 1e-3)  # it minimizes lambda_max
    # Arbitrary gains with P = I: the certificate says no, honestly.
    bad = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 2.0, [1.0, 1.0], [0.0, 0.0], [0.0, 0.0], P=np.eye(2),
        bounds=bounds2,
    )  # fmt: skip
    assert not bad.is_certified and bad.max_eigenvalue > 0
    with pytest.raises(ObserverDesignInfeasible, match="smaller alpha"):
        ObserverDesign.from_gains(
            two_state, BOX2, 3.0, 2.0, [1.0, 1.0], [0.0, 0.0], [0.0, 0.0], bounds=bounds2
        )


# ------------------------------------------------------------ max decay rate
def test_max_decay_rate_brackets_the_boundary(two_state, bounds2):
    best = max_decay_rate(
        two_state, BOX2, 3.0, alpha_max=8.0, tol=0.1, bounds=bounds2, max_gain=200.0
    )
    assert best.is_certified and best.gain_norm <= 200.0 * (1 + 1e-6)
    assert 0.0 < best.alpha < 8.0
    with pytest.raises(ObserverDesignInfeasible):
        design_observer(two_state, BOX2, 3.0, best.alpha + 0.1, bounds=bounds2, max_gain=200.0)
    # Without a cap the rate is higher.
    free = max_decay_rate(two_state, BOX2, 3.0, alpha_max=8.0, tol=0.1, bounds=bounds2)
    assert free.alpha > best.alpha


# ------------------------------------------------------------------- errors
def test_argument_errors(two_state, bounds2):
    with pytest.raises(DesignError, match="solver must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, solver="gurobi")
    with pytest.raises(DesignError, match="backend must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, backend="matlab")
    with pytest.raises(DesignError, match="objective must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, objective="max_gain")
    with pytest.raises(DesignError, match="cvxpy backend supports solvers"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, backend="cvxpy", solver="csdp")
    with pytest.raises(DesignError, match="alpha must be a finite number >= 0"):
        design_observer(two_state, BOX2, 3.0, -1.0, bounds=bounds2)
    with pytest.raises(BoxError, match=r"lower\[1\] = 2 is not below upper\[1\] = 1"):
        design_observer(two_state, ([-1.0, 2.0], [1.0, 1.0]), 3.0, 1.0)
    with pytest.raises(DesignError, match="does not contain the design box"):
        design_observer(two_state, ([-3.0, -3.0], [3.0, 3.0]), 3.0, 1.0, bounds=bounds2)
    with pytest.raises(OfrlError, match="method must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, jacobian_method="exact")


def test_mosek_needs_a_licence(two_state, bounds2):
    from pydrake.solvers import MosekSolver

    if MosekSolver().available() and MosekSolver().enabled():
        pytest.skip("MOSEK is licensed here")
    with pytest.raises(DesignError, match=r"'mosek' is not usable here.*licence"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, solver="mosek")


# --------------------------------------------- linear systems: real decay
def _linear_system(A, B, C):
    return ControlAffineSystem(
        f=lambda x: A @ x,
        g=lambda x: np.multiply.outer(B, 1 + 0 * x[0]),
        C=C,
    )


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow],
)
@given(
    data=st.data(),
    n=st.sampled_from([2, 3]),
    q=st.sampled_from([1, 2]),
    alpha=st.floats(0.1, 2.0),
)
def test_linear_certificate_implies_decay(data, n, q, alpha):
    A = data.draw(arrays(np.float64, (n, n), elements=st.floats(-3, 3)))
    B = data.draw(arrays(np.float64, (n, 1), elements=st.floats(-2, 2)))
    C = data.draw(arrays(np.float64, (q, n), elements=st.floats(-2, 2)))
    assume(np.linalg.matrix_rank(C) == q)
    system = _linear_system(A, B, C)
    box = ([-1.0] * n, [1.0] * n)
    try:
        d = design_observer(system, box, 1.0, alpha)
    except ObserverDesignInfeasible:
        assume(False)
        return
    # f = A x: the bounds are exact, and g is constant.
    np.testing.assert_allclose(d.bounds.Mf1, A, rtol=0, atol=1e-12)
    np.testing.assert_allclose(d.bounds.Mf2, A, rtol=0, atol=1e-12)
    np.testing.assert_allclose(d.bounds.Mg2 - d.bounds.Mg1, 0.0, rtol=0, atol=1e-12)
    Acl = A - d.L @ C
    assert np.max(np.linalg.eigvals(Acl).real) < -alpha + 1e-6
    # e' = (A - L C) e exactly; V = e^T P e must decay at least like exp(-2 alpha t).
    rng = np.random.default_rng(0)
    for e0 in rng.normal(size=(4, n)):
        V0 = e0 @ d.P @ e0
        for t in np.linspace(0.0, 3.0 / alpha, 13)[1:]:
            e = scipy.linalg.expm(Acl * t) @ e0
            assert e @ d.P @ e <= np.exp(-2 * alpha * t) * V0 * (1 + 1e-6) + 1e-12
