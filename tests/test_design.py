"""Observer design: both formulations, soundness, backends, persistence, errors."""

import dataclasses
import json
import time
import warnings

import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ofrl_drake.design import (
    DesignError,
    ObserverDesign,
    ObserverDesignInaccurate,
    ObserverDesignInfeasible,
    design_observer,
    max_decay_rate,
)
from ofrl_drake.errors import OfrlError, WallTimeExceeded
from ofrl_drake.examples import make_system
from ofrl_drake.jacobian_bounds import BoxError, JacobianBounds, jacobian_bounds
from ofrl_drake.lmi import certificate, decay_certificate, is_decay_certified, lmi_matrix
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.observer import ObserverGains, observer_rhs

BOX2 = ([-2.0, -2.0], [2.0, 2.0])
BOX4 = ([-2.0] * 4, [2.0] * 4)
# Where d f_2 / d x_1 = -1 + 4 (cos 2x1 + 2) sin 2x1 peaks on x2 = -2 (about +7.81).
X_PEAK = np.array([0.5 * np.arccos((np.sqrt(3.0) - 1.0) / 2.0), -2.0])


@pytest.fixture(scope="module")
def two_state():
    return make_system("two_state")


@pytest.fixture(scope="module")
def bounds2(two_state):
    return jacobian_bounds(two_state, BOX2)


@pytest.fixture(scope="module")
def certified2(two_state):
    """Guaranteed enclosures: the soundness tests must not rest on sampled bounds."""
    return jacobian_bounds(two_state, BOX2, "certified")


@pytest.fixture(scope="module")
def paper2(two_state, bounds2):
    return design_observer(two_state, BOX2, 3.0, 2.0, bounds=bounds2, formulation="paper")


@pytest.fixture(scope="module")
def poly2(two_state, certified2):
    return design_observer(two_state, BOX2, 3.0, 0.9, bounds=certified2)


def _recomputed(design, system, which="certificate"):
    """A certificate from the JSON numbers alone, through the pure-numpy module."""
    d = json.loads(json.dumps(design.to_dict()))
    check = {"certificate": certificate, "decay": decay_certificate}[which]
    return check(
        d["P"], d["L"], d["H"], d["K"], system.output_matrix, d["jacobian_bounds"],
        d["input_bound"], d["alpha"],
    )  # fmt: skip


def _vdot_over_v(system, design, x, xhat, u):
    """``dV/dt / V`` for ``V = e^T P e`` from the true plant and the real observer."""
    gains = ObserverGains.from_design(system, design)
    C = system.output_matrix
    u = np.atleast_1d(np.asarray(u, dtype=float))
    x_dot = system.f(x) + system.g(x) @ u
    xhat_dot = observer_rhs(system, gains, xhat, C @ x, u)
    e = x - xhat
    return 2.0 * e @ design.P @ (x_dot - xhat_dot) / (e @ design.P @ e)


# ------------------------------------------- the paper's (lmi2) formulation
def test_paper_formulation_certifies_lmi2_but_not_decay(two_state, paper2):
    d = paper2
    assert d.formulation == "paper" and d.is_certified
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
    # ... but the sound check of the same numbers fails, by far, at every vertex.
    assert not d.is_decay_certified
    decay = d.decay_certificate()
    assert [u.tolist() for u, _ in decay] == [[-3.0], [0.0], [3.0]]
    assert min(lam for _, lam in decay) > 1.0


def test_paper_design_has_a_growing_error_where_the_polytopic_one_decays(two_state, paper2, poly2):
    # The gap between (lmi2) and decay: at x = (0.598, -2), xhat = x - (1e-4, 0),
    # u = 0 the output error is zero, so no gain acts, and the true
    # dV/dt = 2 e1^T P A_cl e1 = 2 eps^2 (-P11 + P12 a21) is about +39 V.
    xhat = X_PEAK - np.array([1e-4, 0.0])
    rate = _vdot_over_v(two_state, paper2, X_PEAK, xhat, [0.0])
    assert rate > -2.0 * paper2.alpha
    assert rate > 30.0  # documents the size of the gap: the error grows
    # The polytopic design's bound holds at the same point.
    assert _vdot_over_v(two_state, poly2, X_PEAK, xhat, [0.0]) <= -2.0 * poly2.alpha


def test_paper_without_injection_gains_pins_h_and_k(two_state, bounds2):
    d = design_observer(
        two_state, BOX2, 3.0, 0.5, bounds=bounds2, formulation="paper", injection_gains=False
    )
    assert d.is_certified and d.formulation == "paper"
    np.testing.assert_array_equal(d.H, 0.0)
    np.testing.assert_array_equal(d.K, 0.0)


# ------------------------------------------------ the polytopic formulation
def test_polytopic_is_the_default_and_certifies_decay(two_state, poly2):
    d = poly2
    assert d.formulation == "polytopic"
    assert d.is_certified and d.is_decay_certified
    np.testing.assert_array_equal(d.H, 0.0)
    np.testing.assert_array_equal(d.K, 0.0)
    cert = d.certificate()
    assert [u.tolist() for u, _ in cert] == [[-3.0], [0.0], [3.0]]
    assert all(lam <= -0.5e-3 for _, lam in cert)
    # For this formulation the two certificates are the same check.
    for (u1, lam1), (u2, lam2) in zip(cert, d.decay_certificate(), strict=True):
        np.testing.assert_array_equal(u1, u2)
        assert lam1 == lam2
    for (_, lam1), (_, lam2) in zip(cert, _recomputed(d, two_state, "decay"), strict=True):
        assert lam1 == pytest.approx(lam2, rel=1e-9, abs=1e-12)
    assert np.all(np.linalg.eigvalsh(d.P) >= 1.0 - 1e-6)
    assert d.condition_number < 1e3


def test_polytopic_max_decay_rate_brackets_one_and_does_not_attain_it(two_state, bounds2):
    # Along e = eps e1 no quadratic V certifies alpha >= 1 (a21 takes both signs).
    found = max_decay_rate(two_state, BOX2, 3.0, bounds=bounds2)
    assert found.tol == 1e-3
    assert 1.0 - 1e-3 <= found.certified < 1.0 <= found.infeasible <= found.certified + 1e-3
    assert found.infeasible_status.startswith("kInfeasible")
    best = found.design
    assert best.alpha == found.certified == found.alpha
    assert best.formulation == "polytopic" and best.is_decay_certified
    assert found.condition_number == best.condition_number
    assert found.gain_norm == best.gain_norm
    data = found.to_dict()
    assert data["certified"] == found.certified and data["infeasible"] == found.infeasible
    with pytest.raises(ObserverDesignInfeasible, match=r"formulation=polytopic, alpha=1,"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2)
    # Not attained: cond(P) and ||L|| grow as alpha -> 1 (about 1 / sqrt(1 - alpha)).
    sizes = [design_observer(two_state, BOX2, 3.0, a, bounds=bounds2) for a in (0.9, 0.99, 0.999)]
    conds = [d.condition_number for d in sizes]
    gains = [d.gain_norm for d in sizes]
    assert conds[0] * 2 < conds[1] and conds[1] * 2 < conds[2] < found.condition_number
    assert gains[0] * 2 < gains[1] and gains[1] * 2 < gains[2] < found.gain_norm


def test_max_decay_rate_returns_alpha_max_when_it_certifies(two_state, bounds2):
    found = max_decay_rate(two_state, BOX2, 3.0, bounds=bounds2, alpha_max=0.5)
    assert found.certified == 0.5 and found.infeasible is None and found.attempts == 1
    assert "alpha_max = 0.5 certified" in str(found)


def _error_pairs(rng, count):
    """Random ``(x, xhat, u)`` in the box, errors from 1e-5 to the box size, and
    structured worst cases: the error along e1 (no output error) at x2 = +-2."""
    pairs = []
    for _ in range(count):
        x = rng.uniform(-2.0, 2.0, 2)
        step = rng.normal(size=2) * 10.0 ** rng.uniform(-5.0, 0.6)
        xhat = np.clip(x - step, -2.0, 2.0)
        pairs.append((x, xhat, rng.uniform(-3.0, 3.0, 1)))
    for x1 in [*np.linspace(-2.0, 2.0, 9).tolist(), X_PEAK[0], -X_PEAK[0]]:
        for x2 in (-2.0, 2.0):
            for u in (-3.0, 0.0, 3.0):
                x = np.array([x1, x2])
                for eps in (1e-4, 0.5):
                    xhat = np.array([np.clip(x1 - eps, -2.0, 2.0), x2])
                    pairs.append((x, xhat, np.array([u])))
    return [(x, xh, u) for x, xh, u in pairs if np.abs(x - xh).max() >= 1e-5]


def test_polytopic_design_decays_along_the_true_nonlinear_error_dynamics(two_state, poly2):
    # The soundness check: dV/dt <= -2 alpha V with the real plant f, g and the
    # real observer equations, for x, xhat anywhere in the box and |u| <= 3.
    pairs = _error_pairs(np.random.default_rng(20240611), 200)
    assert len(pairs) > 250
    alpha = poly2.alpha
    rates = np.array([_vdot_over_v(two_state, poly2, x, xh, u) for x, xh, u in pairs])
    assert np.all(rates <= -2.0 * alpha * (1 - 1e-9))


def test_paper_design_breaks_its_claim_on_the_same_pairs(two_state, paper2):
    pairs = _error_pairs(np.random.default_rng(20240611), 200)
    rates = np.array([_vdot_over_v(two_state, paper2, x, xh, u) for x, xh, u in pairs])
    assert np.any(rates > -2.0 * paper2.alpha)


def test_mimo_coupled_two_state_polytopic_certifies_at_all_nine_vertices():
    system = make_system("coupled_two_state")
    d = design_observer(system, BOX4, 3.0, 0.9)
    assert d.L.shape == (4, 2) and d.H.shape == (4, 2) and d.K.shape == (4, 2)
    np.testing.assert_array_equal(d.H, 0.0)
    cert = d.certificate()
    assert len(cert) == 9
    assert all(lam <= -0.5e-3 for _, lam in cert)
    assert d.is_certified and d.is_decay_certified and d.condition_number < 1e3
    assert max(lam for _, lam in _recomputed(d, system, "decay")) < 0
    with pytest.raises(ObserverDesignInfeasible, match="formulation=polytopic"):
        design_observer(system, BOX4, 3.0, 1.1)


def test_mimo_coupled_two_state_paper_certifies_lmi2_only():
    system = make_system("coupled_two_state")
    d = design_observer(system, BOX4, 3.0, 1.0, formulation="paper")
    cert = d.certificate()
    assert len(cert) == 9 and all(lam < 0 for _, lam in cert)
    assert d.is_certified and d.condition_number < 1e3
    assert max(lam for _, lam in _recomputed(d, system)) < 0
    assert not d.is_decay_certified


# ------------------------------------------------------------- objectives
@pytest.mark.parametrize("formulation", ["polytopic", "paper"])
def test_min_gain_beats_feasibility_on_gain(two_state, bounds2, formulation):
    kw = {"bounds": bounds2, "formulation": formulation}
    small = design_observer(two_state, BOX2, 3.0, 0.5, **kw)
    plain = design_observer(two_state, BOX2, 3.0, 0.5, objective="feasibility", **kw)
    assert plain.is_certified and small.is_certified
    assert small.gain_norm < plain.gain_norm


@pytest.mark.parametrize(
    ("formulation", "alpha_ok", "alpha_bad", "cap"),
    [("polytopic", 0.5, 0.9, 20.0), ("paper", 0.5, 2.0, 200.0)],
)
def test_max_gain_caps_the_gain(two_state, bounds2, formulation, alpha_ok, alpha_bad, cap):
    kw = {"bounds": bounds2, "formulation": formulation, "max_gain": cap}
    d = design_observer(two_state, BOX2, 3.0, alpha_ok, **kw)
    assert d.gain_norm <= cap * (1 + 1e-6)
    with pytest.raises(ObserverDesignInfeasible, match="a larger max_gain"):
        design_observer(two_state, BOX2, 3.0, alpha_bad, **{**kw, "max_gain": cap / 4})


# ------------------------------------------------------------------ sign gap
def test_paper_sector_fails_at_negative_input_where_sign_correct_certifies(two_state, paper2):
    C = two_state.output_matrix
    d = paper2
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
        design_observer(
            two_state, BOX2, 3.0, 2.0, bounds=bounds2, formulation="paper", sector="paper"
        )
    assert "Infeasible" in err.value.status


# ------------------------------------------------------------------ backends
def _feasible_in_both_backends(system, formulation, half, alpha, solver):
    """[drake, cvxpy]: whether each certified a design on ``[-half, half]^2``."""
    box = ([-half, -half], [half, half])
    bounds = jacobian_bounds(system, box)
    outcomes = []
    for backend in ("drake", "cvxpy"):
        try:
            d = design_observer(
                system,
                box,
                3.0,
                alpha,
                bounds=bounds,
                backend=backend,
                formulation=formulation,
                solver=solver,
            )
        except ObserverDesignInfeasible:
            outcomes.append(False)
        else:
            assert d.is_certified and d.backend == backend and d.formulation == formulation
            assert d.solver == solver
            if solver == "scs" and backend == "drake":  # SCS's own exit status, too
                assert "(SCS: solved" in d.status, d.status
            outcomes.append(True)
    return outcomes


@pytest.mark.parametrize(
    ("formulation", "half", "alpha", "feasible"),
    [
        ("paper", 0.5, 0.5, True),
        ("paper", 0.5, 2.0, True),
        ("paper", 0.5, 50.0, False),
        ("paper", 2.0, 2.0, True),
        ("paper", 2.0, 50.0, False),
        ("paper", 50.0, 0.5, True),
        ("polytopic", 0.5, 0.5, True),
        ("polytopic", 0.5, 5.0, False),
        ("polytopic", 2.0, 0.9, True),
        ("polytopic", 2.0, 1.0, False),
        ("polytopic", 2.0, 2.0, False),
        ("polytopic", 50.0, 0.5, True),
    ],
)
def test_backends_agree_on_feasibility(two_state, formulation, half, alpha, feasible):
    outcomes = _feasible_in_both_backends(two_state, formulation, half, alpha, "clarabel")
    assert outcomes == [feasible, feasible]


@pytest.mark.parametrize(("formulation", "alpha"), [("paper", 2.0), ("polytopic", 0.9)])
def test_backends_find_the_same_optimum(two_state, bounds2, formulation, alpha):
    kw = {"bounds": bounds2, "formulation": formulation}
    drake = design_observer(two_state, BOX2, 3.0, alpha, **kw)
    other = design_observer(two_state, BOX2, 3.0, alpha, backend="cvxpy", **kw)
    assert other.backend == "cvxpy" and other.is_certified
    # Same convex program, same objective: the same minimal ||R||_2.
    assert np.linalg.norm(other.R, 2) == pytest.approx(np.linalg.norm(drake.R, 2), rel=1e-3)


@pytest.mark.parametrize(
    ("formulation", "objective", "max_gain", "pinned"),
    [
        ("polytopic", "min_gain", None, None),
        ("polytopic", "min_condition", 50.0, "L"),
        ("paper", "min_gain", None, None),
        ("paper", "feasibility", 3.0, "HK"),
        ("structured", "min_gain", 100.0, None),
        ("structured_row", "min_condition", None, None),
    ],
)
@pytest.mark.parametrize("entries", [50, None])
def test_drake_coefficients_are_the_blocks_change_at_each_unit_vector(
    monkeypatch, two_state, bounds2, formulation, objective, max_gain, pinned, entries
):
    from ofrl_drake.design import backend_drake
    from ofrl_drake.design.pipeline import _problem

    if entries is not None:  # many small stacks of unit vectors instead of one
        monkeypatch.setattr(backend_drake, "_COEFFICIENT_ENTRIES", entries)
    C = np.atleast_2d(np.asarray(two_state.C, dtype=float))
    kw = {}
    if pinned == "L":
        kw["L"] = np.array([[1.0], [2.0]])
    elif pinned == "HK":
        kw["HK"] = (np.array([[0.1], [0.2]]), np.array([[0.3], [0.0]]))
    problem = _problem(
        C, bounds2, 1.0, 0.5, 1e-3, objective, max_gain, "sign_correct", formulation, **kw
    )
    layout = backend_drake._Layout.of(problem)
    N = layout.size
    F0 = backend_drake._psd_blocks(problem, layout.unpack(np.zeros(N)))
    one_at_a_time = [backend_drake._psd_blocks(problem, layout.unpack(e)) for e in np.eye(N)]
    got = backend_drake._coefficients(problem, layout)
    assert len(got) == len(F0)
    for j, (matrices, used) in enumerate(got):
        expected_used = [i for i in range(N) if np.any(one_at_a_time[i][j] != F0[j])]
        assert used == expected_used
        np.testing.assert_array_equal(matrices[0], F0[j])
        for F, i in zip(matrices[1:], used, strict=True):
            np.testing.assert_array_equal(F, one_at_a_time[i][j] - F0[j])


def test_csdp_through_drake(two_state, bounds2):
    for formulation in ("polytopic", "paper"):
        d = design_observer(
            two_state, BOX2, 3.0, 0.5, bounds=bounds2, solver="csdp", formulation=formulation
        )
        assert d.is_certified and d.solver == "csdp"


def test_drake_backend_raises_no_runtime_warning(two_state, bounds2):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for formulation in ("polytopic", "paper"):
            d = design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2, formulation=formulation)
            assert d.is_certified


# ------------------------------------------------------------- infeasibility
@pytest.mark.parametrize("formulation", ["polytopic", "paper"])
def test_infeasible_rate_raises_with_one_line_advice(two_state, bounds2, formulation):
    with pytest.raises(ObserverDesignInfeasible, match=r"alpha=50.*try a smaller alpha") as err:
        design_observer(two_state, BOX2, 3.0, 50.0, bounds=bounds2, formulation=formulation)
    e = err.value
    assert "\n" not in str(e)
    assert f"formulation={formulation}" in str(e)
    assert e.alpha == 50.0 and e.input_bound == 3.0 and e.formulation == formulation
    assert e.box.lower.tolist() == [-2.0, -2.0]
    assert e.status
    assert isinstance(e, OfrlError)


# ------------------------------------------------------------- persistence
@pytest.mark.parametrize("which", ["paper2", "poly2"])
def test_to_dict_keys_and_json_round_trip(two_state, which, request, tmp_path):
    design = request.getfixturevalue(which)
    d = design.to_dict()
    required = {
        "P", "L", "H", "K", "alpha", "input_bound", "box", "jacobian_bounds",
        "certificate", "solver", "solve_time", "formulation", "decay_certificate",
        "is_decay_certified",
    }  # fmt: skip
    assert required <= set(d)
    assert set(d["box"]) == {"lower", "upper"}
    assert set(d["jacobian_bounds"]) == {"Mf1", "Mf2", "Mg1", "Mg2"}
    assert [set(c) for c in d["certificate"]] == [{"input", "max_eigenvalue"}] * 3
    assert [set(c) for c in d["decay_certificate"]] == [{"input", "max_eigenvalue"}] * 3
    assert d["formulation"] == design.formulation
    assert d["is_decay_certified"] is (which == "poly2")
    assert isinstance(d["P"][0][0], float) and isinstance(d["L"][1][0], float)
    path = tmp_path / "design.json"
    design.to_json(path)
    back = ObserverDesign.from_json(path)
    for key in ("P", "L", "H", "K", "R", "C"):
        np.testing.assert_array_equal(getattr(back, key), getattr(design, key))
    assert back.alpha == design.alpha and back.box == design.box
    assert back.formulation == design.formulation
    assert back.is_certified
    assert back.is_decay_certified is design.is_decay_certified
    assert [lam for _, lam in back.certificate()] == [lam for _, lam in design.certificate()]
    # Without "C", the system supplies it.
    del d["C"]
    assert ObserverDesign.from_dict(d, system=two_state).is_certified
    with pytest.raises(DesignError, match="no 'C'"):
        ObserverDesign.from_dict(d)
    with pytest.raises(DesignError, match=r"missing keys \['P'\]"):
        ObserverDesign.from_dict({k: v for k, v in d.items() if k != "P"}, system=two_state)
    # Files written before the formulation key existed hold (lmi2) designs.
    del d["formulation"]
    assert ObserverDesign.from_dict(d, system=two_state).formulation == "paper"


def test_from_gains_finds_p_or_reports_honestly(two_state, bounds2, paper2):
    d = paper2
    pinned = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 2.0, d.L, d.H, d.K, P=d.P, bounds=bounds2, formulation="paper"
    )
    assert pinned.is_certified and pinned.solver == "none" and not pinned.is_decay_certified
    found = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 2.0, d.L, d.H, d.K, bounds=bounds2, formulation="paper"
    )
    assert found.is_certified
    assert found.condition_number <= d.condition_number * (1 + 1e-3)  # it minimizes lambda_max
    # The same pinned numbers checked polytopically: honestly not certified ...
    poly = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 2.0, d.L, d.H, d.K, P=d.P, bounds=bounds2
    )
    assert poly.formulation == "polytopic" and not poly.is_certified and poly.max_eigenvalue > 1
    # ... and no P makes them certify decay at alpha = 2.
    with pytest.raises(ObserverDesignInfeasible, match="formulation=polytopic, alpha=2"):
        ObserverDesign.from_gains(two_state, BOX2, 3.0, 2.0, d.L, d.H, d.K, bounds=bounds2)
    # Arbitrary gains with P = I: the certificate says no, honestly.
    bad = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 2.0, [1.0, 1.0], [0.0, 0.0], [0.0, 0.0], P=np.eye(2),
        bounds=bounds2, formulation="paper",
    )  # fmt: skip
    assert not bad.is_certified and bad.max_eigenvalue > 0
    with pytest.raises(ObserverDesignInfeasible, match="smaller alpha"):
        ObserverDesign.from_gains(
            two_state, BOX2, 3.0, 2.0, [1.0, 1.0], [0.0, 0.0], [0.0, 0.0], bounds=bounds2,
            formulation="paper",
        )  # fmt: skip


def test_from_gains_polytopic_finds_p_for_pinned_gains(two_state, certified2, poly2):
    d = poly2
    found = ObserverDesign.from_gains(two_state, BOX2, 3.0, 0.9, d.L, d.H, d.K, bounds=certified2)
    assert found.is_certified and found.is_decay_certified
    np.testing.assert_array_equal(found.L, d.L)
    assert found.condition_number <= d.condition_number * (1 + 1e-3)
    # Nonzero injection gains are checked over every M_f x M_gu corner too.
    H = np.array([[0.0], [1e-3]])
    inj = ObserverDesign.from_gains(two_state, BOX2, 3.0, 0.5, d.L, H, -H, bounds=certified2)
    assert inj.is_decay_certified
    np.testing.assert_array_equal(inj.H, H)


# ------------------------------------------------------------ max decay rate
def test_max_decay_rate_brackets_the_boundary_paper(two_state, bounds2):
    kw = {"bounds": bounds2, "formulation": "paper"}
    best = max_decay_rate(two_state, BOX2, 3.0, alpha_max=8.0, tol=0.1, max_gain=200.0, **kw).design
    assert best.is_certified and best.gain_norm <= 200.0 * (1 + 1e-6)
    assert best.formulation == "paper"
    assert 0.0 < best.alpha < 8.0
    # Proven infeasible by the solver, not merely an inaccurate solve.
    proven = r"kInfeasibleConstraints.*a larger max_gain"
    with pytest.raises(ObserverDesignInfeasible, match=proven):
        design_observer(two_state, BOX2, 3.0, best.alpha + 0.1, max_gain=200.0, **kw)
    # Without a cap the rate is higher.
    free = max_decay_rate(two_state, BOX2, 3.0, alpha_max=8.0, tol=0.1, **kw).design
    assert free.alpha > best.alpha


def test_max_decay_rate_with_a_gain_cap_polytopic(two_state, bounds2):
    best = max_decay_rate(two_state, BOX2, 3.0, bounds=bounds2, max_gain=30.0).design
    assert best.is_decay_certified and best.gain_norm <= 30.0 * (1 + 1e-6)
    assert 0.5 < best.alpha < 0.9
    with pytest.raises(ObserverDesignInfeasible, match="a larger max_gain"):
        design_observer(two_state, BOX2, 3.0, best.alpha + 0.02, bounds=bounds2, max_gain=30.0)


# ------------------------------------------------------------------- errors
def test_argument_errors(two_state, bounds2):
    with pytest.raises(DesignError, match="solver must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, solver="gurobi")
    with pytest.raises(DesignError, match="backend must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, backend="matlab")
    with pytest.raises(DesignError, match="objective must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, objective="max_gain")
    with pytest.raises(DesignError, match="formulation must be one of"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, formulation="lmi3")
    with pytest.raises(DesignError, match="applies to formulation='paper' only"):
        design_observer(two_state, BOX2, 3.0, 1.0, bounds=bounds2, sector="paper")
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


# --------------------------------------------------------------- time limit
@pytest.mark.parametrize("backend", ["drake", "cvxpy"])
def test_a_time_limit_the_lmi_cannot_meet_raises_wall_time_exceeded(two_state, certified2, backend):
    with pytest.raises(
        WallTimeExceeded,
        match=rf"the observer LMI \(polytopic, clarabel/{backend}\) ran out of its time "
        r"limit of 1e-06 s .*allow more wall time",
    ) as caught:
        design_observer(
            two_state, BOX2, 3.0, 0.9, bounds=certified2, backend=backend, time_limit=1e-6
        )
    assert caught.value.step == "LMI solve"


def test_scs_and_pinned_gains_are_bounded_too(two_state, certified2, poly2):
    with pytest.raises(WallTimeExceeded, match=r"polytopic, scs/drake"):
        design_observer(two_state, BOX2, 3.0, 0.9, bounds=certified2, solver="scs", time_limit=1e-6)
    with pytest.raises(WallTimeExceeded, match=r"ran out of its time limit"):
        ObserverDesign.from_gains(
            two_state, BOX2, 3.0, 0.9, poly2.L, poly2.H, poly2.K, bounds=certified2,
            time_limit=1e-6,
        )  # fmt: skip


def test_a_time_limit_that_is_met_changes_nothing(two_state, certified2, poly2):
    timed = design_observer(two_state, BOX2, 3.0, 0.9, bounds=certified2, time_limit=600.0)
    np.testing.assert_array_equal(timed.P, poly2.P)
    np.testing.assert_array_equal(timed.L, poly2.L)


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "10"])
def test_time_limit_must_be_a_positive_number(two_state, bounds2, bad):
    with pytest.raises(DesignError, match=r"time_limit must be a positive number of seconds"):
        design_observer(two_state, BOX2, 3.0, 0.9, bounds=bounds2, time_limit=bad)


def test_csdp_has_no_time_limit_and_is_refused_with_one(two_state, bounds2):
    with pytest.raises(
        DesignError,
        match=r"solver 'csdp' has no time limit, so max_wall_time \(--max-wall\) = 5 s "
        r"cannot bound the LMI solve; use solver 'clarabel' or 'scs'",
    ):
        design_observer(two_state, BOX2, 3.0, 0.9, bounds=bounds2, solver="csdp", time_limit=5)


def test_a_time_limit_bounds_the_bounds_design_observer_computes(two_state, monkeypatch):
    import ofrl_drake.design.pipeline as pipeline

    budgets, solves = [], []
    bounds_of = pipeline.jacobian_bounds
    solve_with = pipeline._solve

    def bounds_spy(*args, **kwargs):
        budgets.append(kwargs["max_wall_time"])
        return bounds_of(*args, **kwargs)

    def solve_spy(problem, solver, backend, time_limit):
        solves.append(time_limit)
        return solve_with(problem, solver, backend, time_limit)

    monkeypatch.setattr(pipeline, "jacobian_bounds", bounds_spy)
    monkeypatch.setattr(pipeline, "_solve", solve_spy)
    assert design_observer(two_state, BOX2, 3.0, 0.9, time_limit=60.0).is_certified
    # The bounds stop at the budget; the LMI gets what they leave of it.
    assert budgets == [60.0] and 0.0 < solves[0] < 60.0
    pinned = design_observer(two_state, BOX2, 3.0, 0.9)
    assert budgets[-1] is None and solves[-1] is None  # no budget, no limit
    ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 0.9, pinned.L, pinned.H, pinned.K, time_limit=60.0
    )
    assert budgets[-1] == 60.0 and 0.0 < solves[-1] < 60.0

    def slow_bounds(*args, **kwargs):
        time.sleep(0.05)
        return bounds_of(*args, **kwargs)

    monkeypatch.setattr(pipeline, "jacobian_bounds", slow_bounds)
    with pytest.raises(
        WallTimeExceeded,
        match=r"the observer design's Jacobian bounds took .* s of time_limit = 0\.01 s, "
        r"leaving nothing for the LMI; allow more time",
    ) as caught:
        design_observer(two_state, BOX2, 3.0, 0.9, time_limit=0.01)
    assert caught.value.step == "Jacobian bounds"


def test_a_scenarios_max_wall_time_bounds_its_whole_design(paper_scenario, monkeypatch):
    import ofrl_drake.design as design_module
    from ofrl_drake.variants import design_for

    timed = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(paper_scenario.simulation, max_wall_time=30.0),
    )
    limits = []
    solve = design_module.design_observer

    def spy(*args, **kwargs):
        limits.append(kwargs["time_limit"])
        return solve(*args, **kwargs)

    monkeypatch.setattr(design_module, "design_observer", spy)
    assert design_for(timed).is_certified
    assert design_for(paper_scenario).is_certified
    # The LMI gets what the Jacobian bounds leave of the budget; no budget, no limit.
    assert 0.0 < limits[0] < 30.0 and limits[1] is None
    rushed = dataclasses.replace(
        paper_scenario,
        simulation=dataclasses.replace(paper_scenario.simulation, max_wall_time=1e-3),
    )
    with pytest.raises(
        WallTimeExceeded,
        match=r"the observer design's Jacobian bounds took .* s of max_wall_time "
        r"\(--max-wall\) = 0\.001 s, leaving nothing for the LMI",
    ):
        design_for(rushed)


def test_too_many_corners_is_a_design_error():
    n = 5
    A = -np.eye(n)
    system = _linear_system(A, np.ones((n, 1)), np.eye(1, n))
    box = ([-1.0] * n, [1.0] * n)
    z = np.zeros((n, n, 1))
    wide = JacobianBounds("given", box, A - 1.0, A + 1.0, z, z)  # 25 uncertain entries
    with pytest.raises(DesignError, match=r"formulation='polytopic'.*more than MAX_CORNERS"):
        design_observer(system, box, 1.0, 0.1, bounds=wide)


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


@pytest.mark.parametrize("formulation", ["polytopic", "paper"])
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
def test_linear_certificate_implies_decay(formulation, data, n, q, alpha):
    A = data.draw(arrays(np.float64, (n, n), elements=st.floats(-3, 3)))
    B = data.draw(arrays(np.float64, (n, 1), elements=st.floats(-2, 2)))
    C = data.draw(arrays(np.float64, (q, n), elements=st.floats(-2, 2)))
    assume(np.linalg.matrix_rank(C) == q)
    system = _linear_system(A, B, C)
    box = ([-1.0] * n, [1.0] * n)
    try:
        d = design_observer(system, box, 1.0, alpha, formulation=formulation)
    except ObserverDesignInfeasible:
        assume(False)
        return
    # f = A x: the bounds are exact, and g is constant.
    np.testing.assert_allclose(d.bounds.Mf1, A, rtol=0, atol=1e-12)
    np.testing.assert_allclose(d.bounds.Mf2, A, rtol=0, atol=1e-12)
    np.testing.assert_allclose(d.bounds.Mg2 - d.bounds.Mg1, 0.0, rtol=0, atol=1e-12)
    # For a linear plant either certificate is a decay certificate.
    assert d.is_certified and d.is_decay_certified
    Acl = A - d.L @ C
    assert np.max(np.linalg.eigvals(Acl).real) < -alpha + 1e-6
    # e' = (A - L C) e exactly; V = e^T P e must decay at least like exp(-2 alpha t).
    rng = np.random.default_rng(0)
    for e0 in rng.normal(size=(4, n)):
        V0 = e0 @ d.P @ e0
        for t in np.linspace(0.0, 3.0 / alpha, 13)[1:]:
            e = scipy.linalg.expm(Acl * t) @ e0
            assert e @ d.P @ e <= np.exp(-2 * alpha * t) * V0 * (1 + 1e-6) + 1e-12


@pytest.mark.parametrize(
    ("formulation", "half", "alpha", "feasible"),
    [
        ("paper", 0.5, 0.5, True),
        ("paper", 0.5, 50.0, False),
        ("polytopic", 0.5, 0.5, True),
        ("polytopic", 0.5, 5.0, False),
    ],
)
def test_backends_agree_on_feasibility_with_scs(two_state, formulation, half, alpha, feasible):
    outcomes = _feasible_in_both_backends(two_state, formulation, half, alpha, "scs")
    assert outcomes == [feasible, feasible]


def test_a_solution_that_fails_the_certificate_is_inaccurate_not_infeasible(
    two_state, bounds2, monkeypatch
):
    import ofrl_drake.design.pipeline as design_module

    real = design_module._solve

    def sloppy(problem, solver, backend, time_limit):  # returns R off by a factor 3
        sol = real(problem, solver, backend, time_limit)
        return dataclasses.replace(sol, R=3.0 * sol.R)

    monkeypatch.setattr(design_module, "_solve", sloppy)
    with pytest.raises(
        ObserverDesignInaccurate,
        match=r"fails the numpy certificate with max eigenvalue .*: the solver was not accurate "
        r"enough, which proves nothing about feasibility\); .*a more accurate solver",
    ):
        design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2, formulation="paper")


def test_pinned_gains_that_fail_say_so(two_state, bounds2):
    with pytest.raises(
        ObserverDesignInfeasible,
        match=r"the given gains L, H, K are not certified for formulation=paper, alpha=2.*"
        r"remove observer.L/H/K to let the LMI design the gains",
    ):
        ObserverDesign.from_gains(
            two_state,
            BOX2,
            3.0,
            2.0,
            L=[[1.0], [1.0]],
            H=[[0.0], [0.0]],
            K=[[0.0], [0.0]],
            bounds=bounds2,
            formulation="paper",
        )


@pytest.mark.parametrize(
    ("system", "got"),
    [
        (
            "two_state",
            r"got str 'two_state'; for the registered example, pass "
            r"ofrl_drake\.examples\.make_system\('two_state'\)\.",
        ),
        (None, r"got NoneType None\. Build a model with ControlAffineSystem\(f, g, C\)"),
    ],
)
def test_design_observer_argument_not_a_model_raises_design_error(system, got):
    # Before: AttributeError "'str' object has no attribute 'n'".
    with pytest.raises(
        DesignError, match=r"the observer design's system must be a ControlAffineSystem; " + got
    ):
        design_observer(system, BOX2, 3.0, 0.5)


@pytest.mark.parametrize("max_gain", ["5", True, 0.0, float("inf")])
def test_design_observer_max_gain_argument_raises_design_error(two_state, bounds2, max_gain):
    # Before: TypeError from math.isfinite("5"); True was taken as 1.
    with pytest.raises(
        DesignError,
        match=rf"max_gain must be a positive number \(a bound on \|\|L\|\|_2\) or None; "
        rf"got {max_gain!r}\.",
    ):
        design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2, max_gain=max_gain)


def test_from_gains_names_a_system_that_is_not_a_model(poly2):
    with pytest.raises(DesignError, match=r"system must be a ControlAffineSystem; got str"):
        ObserverDesign.from_gains("two_state", BOX2, 3.0, 0.9, poly2.L, poly2.H, poly2.K)


def test_from_gains_judges_p_on_its_symmetric_part(two_state, certified2, poly2):
    # V = e^T P e sees only (P + P^T) / 2, which every certificate uses. Before: the
    # design tested eigvalsh(P) on the raw P, which reads its lower triangle only, so
    # a skew part made a certified P look indefinite (is_decay_certified False while
    # lmi.is_decay_certified of the same numbers was True).
    d = poly2
    skew = 5.0 * np.linalg.norm(d.P) * np.array([[0.0, 1.0], [-1.0, 0.0]])
    given = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 0.9, d.L, d.H, d.K, P=d.P + skew, bounds=certified2
    )
    assert is_decay_certified(*given._numbers())
    assert given.is_decay_certified and given.is_certified
    assert given.to_dict()["is_decay_certified"] is True
    # A P whose symmetric part is not positive definite is refused whatever its skew part.
    flipped = ObserverDesign.from_gains(
        two_state, BOX2, 3.0, 0.9, d.L, d.H, d.K, P=-d.P + skew, bounds=certified2
    )
    assert not flipped.is_decay_certified and not flipped.is_certified


@pytest.mark.parametrize("P", [None, "given"])
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"alpha": -1.0}, r"alpha must be a finite number >= 0; got -1\.0"),
        ({"input_bound": float("nan")}, r"input_bound must be a finite number >= 0; got nan"),
        ({"margin": -1e-3}, r"margin must be a finite number >= 0; got -0\.001"),
        ({"backend": "matlab"}, r"backend must be one of \('drake', 'cvxpy'\); got 'matlab'"),
        ({"solver": "gurobi"}, r"solver must be one of .*; got 'gurobi'"),
    ],
)
def test_from_gains_refuses_bad_arguments_before_computing_bounds(
    two_state, poly2, monkeypatch, kwargs, match, P
):
    # Before: from_gains computed the Jacobian bounds (seconds on a large plant) and
    # only then checked alpha, input_bound and margin; the backend and solver were
    # checked only by the solve, never with P given.
    import ofrl_drake.design.pipeline as pipeline

    def no_bounds(*args, **kwargs):
        raise AssertionError("the Jacobian bounds were computed before the argument checks")

    monkeypatch.setattr(pipeline, "jacobian_bounds", no_bounds)
    args = {"input_bound": 3.0, "alpha": 0.9, "P": None if P is None else poly2.P} | kwargs
    with pytest.raises(DesignError, match=match):
        ObserverDesign.from_gains(two_state, BOX2, L=poly2.L, H=poly2.H, K=poly2.K, **args)


@pytest.mark.parametrize(
    ("P", "match"),
    [
        (np.full((2, 2), np.nan), r"P must be finite; got \[\[nan, nan\], \[nan, nan\]\]"),
        (np.eye(3), r"P must have shape \(2, 2\); got \(3, 3\)"),
    ],
)
def test_from_gains_checks_a_given_p_before_computing_bounds(
    two_state, poly2, monkeypatch, P, match
):
    import ofrl_drake.design.pipeline as pipeline

    def no_bounds(*args, **kwargs):
        raise AssertionError("the Jacobian bounds were computed before P was checked")

    monkeypatch.setattr(pipeline, "jacobian_bounds", no_bounds)
    with pytest.raises(DesignError, match=match):
        ObserverDesign.from_gains(two_state, BOX2, 3.0, 0.9, poly2.L, poly2.H, poly2.K, P=P)


@pytest.mark.parametrize("which", ["poly2", "paper2"])
@pytest.mark.parametrize("key", ["P", "L", "H"])
def test_a_design_with_a_value_that_is_not_finite_is_named(request, which, key):
    # Before: numpy's LinAlgError ("SVD did not converge", "Eigenvalues did not
    # converge") from deep in the certificate, or a NaN L read as merely uncertified.
    data = json.loads(json.dumps(request.getfixturevalue(which).to_dict()))
    data[key][0][0] = float("nan")
    with pytest.raises(DesignError, match=rf"the design's {key} must be finite; got \[\[nan"):
        ObserverDesign.from_dict(data)


def test_a_solution_whose_l_overflows_is_inaccurate(two_state, bounds2, monkeypatch):
    # P finite and invertible but so small that L = P^-1 R overflows. Before: the
    # design was built with an infinite L and its certificate failed inside numpy.
    import ofrl_drake.design.pipeline as design_module

    real = design_module._solve

    def tiny(problem, solver, backend, time_limit):
        sol = real(problem, solver, backend, time_limit)
        return dataclasses.replace(sol, P=1e-310 * np.eye(2), R=np.ones((2, 1)))

    monkeypatch.setattr(design_module, "_solve", tiny)
    with pytest.raises(ObserverDesignInaccurate, match=r"P too close to singular for L = P\^-1 R"):
        design_observer(two_state, BOX2, 3.0, 0.5, bounds=bounds2, formulation="paper")
