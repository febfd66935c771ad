"""The structured (norm-bounded) observer certificate.

Layers: the numpy assembly and its re-checks against the polytopic corners of
:mod:`ofrl_drake.lmi` (no solver); then designs solved with Drake/Clarabel on
the shipped scenarios and the synthetic plants of
benchmarks/structured_certificate.py, each re-checked at every vertex of the
Jacobian box (k <= 12) and by the falsifier on the true dynamics.
"""

import doctest
import itertools
import json

import numpy as np
import pytest

from benchmarks.structured_certificate import max_rate, synthetic_system, uncertain_entries
from ofrl_drake import lmi, structured_lmi
from ofrl_drake.design import (
    FORMULATIONS,
    DesignError,
    ObserverDesign,
    ObserverDesignInfeasible,
    design_observer,
)
from ofrl_drake.jacobian_bounds import jacobian_bounds
from ofrl_drake.lmi import LmiError, corner_matrices, decay_certificate, thin_perturbation
from ofrl_drake.structured_lmi import (
    delta_check,
    structured_certificate,
    structured_lmi_blocks,
    vertex_model,
)
from ofrl_drake.structured_lmi import structured_lmi as build
from ofrl_drake.verification import verify_observer

from .conftest import ROOT

# The two-state example's bounds on [-2, 2]^2 (as in tests/test_lmi.py).
MF1 = np.array([[-1.0, 1.0], [-9.8074, 0.0]])
MF2 = np.array([[-1.0, 1.0], [7.8074, 4.0]])
MG1 = np.array([[[0.0], [0.0]], [[-2.0], [0.0]]])
MG2 = np.array([[[0.0], [0.0]], [[2.0], [0.0]]])
TWO_STATE = (MF1, MF2, MG1, MG2)
C2 = np.array([[0.0, 1.0]])


def _random_bounds(seed, n=3, m=2, fixed=0.5):
    """Bounds with about ``fixed`` of the entries exact (lower == upper)."""
    rng = np.random.default_rng(seed)
    Mf1 = rng.normal(size=(n, n))
    Mf2 = Mf1 + rng.uniform(0, 1, size=(n, n)) * (rng.uniform(size=(n, n)) > fixed)
    Mg1 = rng.normal(size=(n, n, m))
    Mg2 = Mg1 + rng.uniform(0, 1, size=(n, n, m)) * (rng.uniform(size=(n, n, m)) > 0.8)
    return Mf1, Mf2, Mg1, Mg2


def _all_signs(k):
    return np.array(list(itertools.product((-1.0, 1.0), repeat=k))).reshape(-1, k)


def _same_set(A, B, atol):
    """Every matrix of A is within atol of one of B, and conversely."""
    d = np.abs(A[:, None] - B[None]).max(axis=(2, 3))
    return d.min(axis=1).max() <= atol and d.min(axis=0).max() <= atol


# ------------------------------------------------------------- numpy layer
def test_vertex_model_by_hand():
    # u = 3: the sector adds [-6, 6] to entry (1, 0); entries (1, 0) and (1, 1) vary.
    model = vertex_model(TWO_STATE, [3.0])
    np.testing.assert_allclose(model.A0, [[-1.0, 1.0], [-1.0, 2.0]], rtol=0, atol=1e-14)
    assert model.rows.tolist() == [1, 1] and model.cols.tolist() == [0, 1]
    np.testing.assert_allclose(model.widths, [14.8074, 2.0], rtol=1e-15)
    np.testing.assert_array_equal(model.F, np.eye(2))
    assert model.thin == 0.0
    assert vertex_model(TWO_STATE, [0.0]).widths[0] == pytest.approx(8.8074, rel=1e-15)


@pytest.mark.parametrize("injection", [False, True])
@pytest.mark.parametrize("seed", range(4))
def test_the_delta_box_has_the_polytopic_corners(seed, injection):
    bounds = _random_bounds(seed)
    rng = np.random.default_rng(100 + seed)
    C = rng.normal(size=(2, 3))
    H, K = (0.3 * rng.normal(size=(3, 2)) for _ in range(2)) if injection else (None, None)
    for u in ([1.5, -0.7], [0.0, 2.0]):
        model = vertex_model(bounds, u, H, K, C if injection else None)
        corners = corner_matrices(bounds, u, H, K, C if injection else None)
        assert 2**model.k == corners.shape[0]
        assert _same_set(model.matrices(_all_signs(model.k)), corners, atol=1e-12)


def test_half_widths_cover_the_box_despite_rounding():
    rng = np.random.default_rng(7)
    lo = rng.normal(size=(6, 6)) * 10.0 ** rng.integers(-3, 4, size=(6, 6))
    hi = lo + np.abs(rng.normal(size=(6, 6))) * 10.0 ** rng.integers(-3, 4, size=(6, 6))
    Z = np.zeros((6, 6, 1))
    model = vertex_model((lo, hi, Z, Z), [0.0])
    i, j = model.rows, model.cols
    assert np.all(model.A0[i, j] - model.widths <= lo[i, j])
    assert np.all(model.A0[i, j] + model.widths >= hi[i, j])


def test_thin_entries_are_fixed_and_bounded_as_in_the_polytopic_certificate():
    Mf1 = np.array([[-1.1, 1.0], [-2.0, 0.0]])
    Mf2 = Mf1 + np.array([[0.0, 0.0], [1.0, 0.0]])
    Mf2[0, 0] = np.nextafter(-1.1, 0.0)  # an enclosure's one-ulp widening
    Z = np.zeros((2, 2, 1))
    model = vertex_model((Mf1, Mf2, Z, Z), [0.0])
    assert model.k == 1 and model.rows.tolist() == [1]
    assert model.thin == thin_perturbation((Mf1, Mf2, Z, Z), [0.0]) > 0


def test_input_vertices_with_the_same_model_are_merged():
    Z = np.zeros((2, 2, 1))
    problem = build(C2, (MF1, MF2, Z, Z), 3.0, 0.5, margin=1e-3)
    assert len(problem.models) == 1 and problem.sizes == [4]
    problem = build(C2, TWO_STATE, 3.0, 0.5, margin=1e-3, grouping="row")
    assert len(problem.models) == 2 and problem.sizes == [3, 3]  # u = +-3 alike, u = 0


@pytest.mark.parametrize("seed", range(3))
def test_row_grouping_is_entry_grouping_with_tied_multipliers(seed):
    # Schur complements agree for tau_l = tau_i s_i / w_l (module docstring).
    rng = np.random.default_rng(seed)
    bounds = _random_bounds(seed, fixed=0.3)
    C = rng.normal(size=(2, 3))
    entry = build(C, bounds, 1.0, 0.4, margin=0.0, grouping="entry")
    row = build(C, bounds, 1.0, 0.4, margin=0.0, grouping="row")
    P0 = rng.normal(size=(3, 3))
    P, R = P0 @ P0.T + np.eye(3), rng.normal(size=(3, 2))
    for me, mr in zip(entry.models, row.models, strict=True):
        groups = np.unique(mr.rows)
        tau_row = rng.uniform(0.5, 2.0, groups.size)
        s = {i: mr.widths[mr.rows == i].sum() for i in groups}
        tau_entry = np.array(
            [
                tau_row[list(groups).index(i)] * s[i] / w
                for i, w in zip(me.rows, me.widths, strict=True)
            ]
        )

        def schur(problem, model, tau):
            one = type(problem)(problem.C, (model,), problem.grouping, 0.4, 0.0)
            M = structured_lmi_blocks(one, P, R, [tau])[0]
            n = 3
            return M[:n, :n] - M[:n, n:] @ np.linalg.solve(M[n:, n:], M[n:, :n])

        np.testing.assert_allclose(
            schur(entry, me, tau_entry), schur(row, mr, tau_row), rtol=1e-10, atol=1e-10
        )


@pytest.mark.parametrize("grouping", ["entry", "row"])
@pytest.mark.parametrize("injection", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_a_negative_lmi_bounds_the_lyapunov_matrix_at_every_corner(seed, injection, grouping):
    # The S-procedure in numbers: lambda_max(S) at every corner <= lambda_max(M) < 0.
    rng = np.random.default_rng(seed)
    n, q, m = 3, 2, 1
    A = -4.0 * np.eye(n) + 0.5 * rng.normal(size=(n, n))
    mask_f = rng.uniform(size=(n, n)) < 0.5  # about 4 uncertain entries of f, 2 of g
    mask_g = rng.uniform(size=(n, n, m)) < 0.25
    Mf1 = A - 0.4 * rng.uniform(size=(n, n)) * mask_f
    Mf2 = A + 0.4 * rng.uniform(size=(n, n)) * mask_f
    Mg1 = -0.2 * rng.uniform(size=(n, n, m)) * mask_g
    Mg2 = 0.2 * rng.uniform(size=(n, n, m)) * mask_g
    bounds = (Mf1, Mf2, Mg1, Mg2)
    C = rng.normal(size=(q, n))
    H, K = (0.1 * rng.normal(size=(n, q)) for _ in range(2)) if injection else (None, None)
    problem = build(C, bounds, 1.0, 0.5, margin=0.0, grouping=grouping, H=H, K=K)
    P = np.eye(n) + 0.1 * np.diag(rng.uniform(size=n))
    L = 0.1 * rng.normal(size=(n, q))
    tau = [np.full(r, 2.0) for r in problem.multiplier_counts]
    cert = structured_certificate(problem, P, L, tau)
    assert problem.uncertain_entries >= 3  # several signals: the S-procedure is not trivial
    assert max(v for _, v in cert) < 0  # the case is built to certify
    for u, mu in cert:
        corners = corner_matrices(bounds, u, H, K, C if injection else None) - L @ C
        S = lmi.decay_matrices(P, corners, 0.5)
        assert np.linalg.eigvalsh(S)[:, -1].max() <= mu + 1e-12


@pytest.mark.parametrize("seed", range(4))
def test_exhaustive_delta_check_is_the_polytopic_decay_certificate(seed):
    rng = np.random.default_rng(seed)
    bounds = _random_bounds(seed, n=3, m=1)
    C = rng.normal(size=(2, 3))
    P0 = rng.normal(size=(3, 3))
    P, L = P0 @ P0.T + np.eye(3), rng.normal(size=(3, 2))
    problem = build(C, bounds, 0.8, 0.3, margin=0.0)
    checks = delta_check(problem, P, L)
    poly = {tuple(u): v for u, v in decay_certificate(P, L, 0 * L, 0 * L, C, bounds, 0.8, 0.3)}
    for check, model in zip(checks, problem.models, strict=True):
        assert check.exhaustive and check.points == 2**model.k
        assert check.worst == pytest.approx(poly[tuple(check.u)], rel=1e-9, abs=1e-9)


def test_sampled_delta_check_never_exceeds_the_exhaustive_one():
    bounds = _random_bounds(5, n=3, m=1, fixed=0.0)
    rng = np.random.default_rng(5)
    C = rng.normal(size=(1, 3))
    problem = build(C, bounds, 1.0, 0.2, margin=0.0)
    P, L = np.eye(3), rng.normal(size=(3, 1))
    full = delta_check(problem, P, L)
    sampled = delta_check(problem, P, L, samples=50, seed=1, max_vertices=4)
    for a, b in zip(full, sampled, strict=True):
        assert a.exhaustive and not b.exhaustive and b.points == 100
        assert b.worst <= a.worst + 1e-12


def test_structured_certificate_by_hand():
    # n = 1: A in [-2, 0], A0 = -1, w = 1; P = 1, L = 1, alpha = 0.5, tau = 1:
    # S0 = 2 (-1) - 2 + 1 = -3, M = [[-3 + 1, 1], [1, -1]], lambda_max = (-3 + sqrt 5) / 2.
    Z = np.zeros((1, 1, 1))
    problem = build([[1.0]], ([[-2.0]], [[0.0]], Z, Z), 1.0, 0.5, margin=0.0)
    [(_, value)] = structured_certificate(problem, [[1.0]], [[1.0]], [[1.0]])
    assert value == pytest.approx((-3.0 + np.sqrt(5.0)) / 2.0, rel=1e-12)


def test_numpy_errors_name_the_problem():
    Z = np.zeros((2, 2, 1))
    with pytest.raises(LmiError, match=r"grouping must be one of \('entry', 'row'\); got 'col'"):
        build(C2, TWO_STATE, 1.0, 0.5, margin=0.0, grouping="col")
    with pytest.raises(LmiError, match=r"alpha must be a finite number >= 0; got -1"):
        build(C2, TWO_STATE, 1.0, -1.0, margin=0.0)
    crossed = (MF2, MF1, Z, Z)
    with pytest.raises(LmiError, match=r"Mf bounds at entry \[1, 0\]: lower = 7.8074"):
        vertex_model(crossed, [0.0])
    nan = (np.where(MF1 == 0.0, np.nan, MF1), MF2, Z, Z)
    with pytest.raises(LmiError, match=r"must be finite with lower <= upper"):
        vertex_model(nan, [0.0])
    with pytest.raises(LmiError, match=r"u must be a finite array of shape \(1,\)"):
        vertex_model(TWO_STATE, [1.0, 2.0])
    problem = build(C2, TWO_STATE, 1.0, 0.5, margin=0.0)
    with pytest.raises(LmiError, match=r"tau must hold \[2, 2\] multipliers"):
        structured_certificate(problem, np.eye(2), [[1.0], [1.0]], [[1.0]])
    with pytest.raises(LmiError, match=r"P must be \(2, 2\) and L \(2, 1\); got \(3, 3\)"):
        structured_certificate(problem, np.eye(3), [[1.0], [1.0]], [[1.0, 1.0]] * 2)
    with pytest.raises(LmiError, match=r"samples must be a positive integer; got 0"):
        delta_check(problem, np.eye(2), [[1.0], [1.0]], samples=0)
    with pytest.raises(LmiError, match=r"delta must have 2 columns"):
        problem.models[0].matrices(np.zeros((1, 3)))


def test_docstring_examples_run():
    result = doctest.testmod(structured_lmi, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0


# -------------------------------------------------- designs (Drake, Clarabel)
def _structured(system, bounds, input_bound, alpha, *, grouping="entry", **kwargs):
    """``design_observer`` with the structured formulation of ``grouping`` on ``bounds``."""
    formulation = "structured" if grouping == "entry" else "structured_row"
    return design_observer(
        system, bounds.box, input_bound, alpha, bounds=bounds, formulation=formulation, **kwargs
    )


def _scenario(name):
    from ofrl_drake.plants import resolve_system
    from ofrl_drake.scenario import load_scenario

    scenario = load_scenario(ROOT / "diagrams" / f"{name}.yaml")
    system = resolve_system(scenario)
    o = scenario.observer
    box = (np.asarray(o.box.lower, float), np.asarray(o.box.upper, float))
    return scenario, system, box, jacobian_bounds(system, box, o.jacobian_method)


def _assert_sound(design, bounds):
    """Certified by the structured LMI, and at every vertex of the Jacobian box."""
    assert design.is_certified and design.max_eigenvalue < 0
    poly = decay_certificate(
        design.P,
        design.L,
        design.H,
        design.K,
        design.C,
        bounds,
        design.input_bound,
        design.alpha,
    )
    assert max(v for _, v in poly) < 0
    checks = design.delta_check()
    assert all(c.exhaustive for c in checks) and max(c.worst for c in checks) < 0


# (scenario, alpha, LMI sizes per distinct input vertex for "entry" and "row")
SCENARIOS = [
    ("two_state_paper", 0.9, [4, 4], [3, 3]),  # k = 2 in one row
    ("pendulum_upright", 2.0, [3], [3]),  # k = 1, no input in the Jacobian
    ("cart_pole", 2.0, [8, 8, 8], [6, 6, 6]),  # k = 4 in two rows
]


@pytest.mark.parametrize(("name", "alpha", "entry_sizes", "row_sizes"), SCENARIOS)
@pytest.mark.parametrize("grouping", ["entry", "row"])
def test_shipped_scenarios_get_sound_structured_designs(
    name, alpha, entry_sizes, row_sizes, grouping
):
    scenario, system, box, bounds = _scenario(name)
    design = _structured(system, bounds, scenario.input_bound, alpha, grouping=grouping)
    _assert_sound(design, bounds)
    assert design.lmi_sizes == (entry_sizes if grouping == "entry" else row_sizes)
    # The polytopic design at the same rate exists too (the structured claim implies it).
    design_observer(system, box, scenario.input_bound, alpha, bounds=bounds)


def test_two_state_rate_one_is_not_certified():
    # No quadratic V certifies alpha >= 1 on the two-state example (docs/paper_notes.md),
    # and the structured LMI implies the polytopic one.
    scenario, system, _, bounds = _scenario("two_state_paper")
    with pytest.raises(ObserverDesignInfeasible, match=r"formulation=structured, alpha=1"):
        _structured(system, bounds, scenario.input_bound, 1.0)


def test_the_falsifier_finds_no_counterexample():
    scenario, system, _, bounds = _scenario("two_state_paper")
    design = _structured(system, bounds, scenario.input_bound, 0.9)
    report = verify_observer(design, system, samples=2000, seed=3)
    assert not report.falsified


@pytest.mark.parametrize(("n", "k"), [(2, 2), (4, 8), (6, 10), (8, 12)])
def test_synthetic_designs_are_sound_at_every_vertex(n, k):
    system, box = synthetic_system(n, k)
    bounds = jacobian_bounds(system, box, "certified")
    assert uncertain_entries(bounds, 1.0) == [k, k, k]  # u = -1, 0, +1
    for grouping in ("entry", "row"):
        design = _structured(system, bounds, 1.0, 0.5, grouping=grouping)
        _assert_sound(design, bounds)
        sizes = n + (
            k if grouping == "entry" else np.unique(design.structured_lmi().models[0].rows).size
        )
        assert design.lmi_sizes == [sizes] * 3


def test_synthetic_design_survives_the_falsifier():
    system, box = synthetic_system(4, 8)
    bounds = jacobian_bounds(system, box, "certified")
    design = _structured(system, bounds, 1.0, 0.5)
    report = verify_observer(design, system, samples=1000, seed=0, starts=4)
    assert not report.falsified


def test_many_uncertain_entries_make_one_lmi_per_input_vertex():
    system, box = synthetic_system(8, 24, scale=0.5)
    bounds = jacobian_bounds(system, box, "certified")
    entry = _structured(system, bounds, 1.0, 0.5)
    row = _structured(system, bounds, 1.0, 0.5, grouping="row")
    assert entry.lmi_sizes == [8 + 24] * 3 and row.lmi_sizes == [8 + 8] * 3  # all 8 rows
    for design in (entry, row):
        assert design.is_certified
        checks = design.delta_check(samples=500)
        assert not any(c.exhaustive for c in checks) and max(c.worst for c in checks) < 0


def test_one_uncertain_entry_loses_nothing():
    # The S-procedure with one signal is lossless. a' = -a + b, b' = d a - b, y = b, with d in
    # [-2, 1] of both signs: as on the two-state plant no quadratic V certifies rate 1, and
    # the polytopic supremum is 1; the structured one must reach it too.
    from ofrl_drake.jacobian_bounds import Box, JacobianBounds
    from ofrl_drake.model import ControlAffineSystem

    system = ControlAffineSystem(
        lambda x: np.array([-x[0] + x[1], -x[0] - x[1]]),
        lambda x: np.array([[0 * x[0]], [1 + 0 * x[0]]]),
        [[0.0, 1.0]],
    )
    box = (-np.ones(2), np.ones(2))
    Mf1, Mf2 = np.array([[-1.0, 1.0], [-2.0, -1.0]]), np.array([[-1.0, 1.0], [1.0, -1.0]])
    Z = np.zeros((2, 2, 1))
    bounds = JacobianBounds("given", Box.coerce(box), Mf1, Mf2, Z, Z)

    def poly(a):
        return design_observer(system, box, 1.0, a, bounds=bounds)

    def entry(a):
        return _structured(system, bounds, 1.0, a)

    top_poly, top_entry = max_rate(poly, 8.0, 0.002), max_rate(entry, 8.0, 0.002)
    assert top_poly[1] is not None and top_poly[0] == pytest.approx(1.0, abs=0.005)
    assert top_entry[0] == pytest.approx(top_poly[0], abs=0.002)


def test_row_feasible_implies_entry_feasible():
    system, box = synthetic_system(6, 8)
    bounds = jacobian_bounds(system, box, "certified")
    both = 0
    for alpha in (0.5, 1.5, 3.0):
        try:
            _structured(system, bounds, 1.0, alpha, grouping="row")
        except ObserverDesignInfeasible:
            continue
        _structured(system, bounds, 1.0, alpha, grouping="entry")
        both += 1
    assert both >= 1


def test_pinned_gains():
    system, box = synthetic_system(4, 6)
    bounds = jacobian_bounds(system, box, "certified")
    free = _structured(system, bounds, 1.0, 0.5)
    zero = np.zeros((4, 2))
    pinned = ObserverDesign.from_gains(
        system, box, 1.0, 0.5, free.L, zero, zero, bounds=bounds, formulation="structured"
    )
    np.testing.assert_array_equal(pinned.L, free.L)
    assert pinned.objective == "min_condition" and pinned.is_certified
    # Injection gains pinned: the F rows carry I - H C and I - K C; still sound.
    rng = np.random.default_rng(0)
    H, K = (0.05 * rng.normal(size=(4, 2)) for _ in range(2))
    inj = ObserverDesign.from_gains(
        system, box, 1.0, 0.5, free.L, H, K, bounds=bounds, formulation="structured"
    )
    np.testing.assert_array_equal(inj.H, H)
    _assert_sound(inj, bounds)


def test_a_skew_part_of_p_changes_nothing():
    # V = e^T P e sees (P + P^T) / 2 only, and so does the structured certificate.
    # Before: is_certified tested eigvalsh(P) on the raw P (its lower triangle), so a
    # skew part made a certified design look uncertified with the same certificate.
    import dataclasses

    system, box = synthetic_system(4, 6)
    bounds = jacobian_bounds(system, box, "certified")
    design = _structured(system, bounds, 1.0, 0.5)
    upper = np.triu(np.ones((4, 4)), 1)
    skew = 5.0 * np.linalg.norm(design.P) * (upper - upper.T)
    given = dataclasses.replace(design, P=design.P + skew)
    want = [v for _, v in design.certificate()]
    assert [v for _, v in given.certificate()] == pytest.approx(want, rel=1e-9)
    assert given.is_certified and given.is_decay_certified


@pytest.mark.parametrize("backend", ["drake", "cvxpy"])
def test_json_round_trip_rechecks_the_multipliers(tmp_path, backend):
    scenario, system, _, bounds = _scenario("pendulum_upright")
    design = _structured(system, bounds, scenario.input_bound, 2.0, backend=backend)
    design.to_json(tmp_path / "d.json")
    data = json.loads((tmp_path / "d.json").read_text())
    assert data["formulation"] == "structured" and data["is_certified"] is True
    assert data["is_decay_certified"] is True and design.lmi_sizes == [3]
    assert len(data["tau"]) == 1 and data["tau"][0][0] > 0
    loaded = ObserverDesign.from_json(tmp_path / "d.json")
    assert loaded.is_decay_certified and loaded.lmi_sizes == [3]
    assert loaded.max_eigenvalue == pytest.approx(design.max_eigenvalue, rel=1e-12)
    # The certificate is recomputed from the stored multipliers, not trusted:
    # multipliers far off make it fail, and none at all are refused by name.
    data["tau"] = [[1e6 * t for t in taus] for taus in data["tau"]]
    assert not ObserverDesign.from_dict(data).is_decay_certified
    del data["tau"]
    with pytest.raises(DesignError, match=r"formulation='structured' needs the S-procedure"):
        ObserverDesign.from_dict(data)


def test_both_backends_agree():
    scenario, system, _, bounds = _scenario("cart_pole")
    drake = _structured(system, bounds, scenario.input_bound, 2.0)
    cvx = _structured(system, bounds, scenario.input_bound, 2.0, backend="cvxpy")
    assert cvx.backend == "cvxpy" and cvx.is_decay_certified
    assert cvx.gain_norm == pytest.approx(drake.gain_norm, rel=1e-3)


def test_design_errors_name_the_problem():
    _, system, box, bounds = _scenario("two_state_paper")
    assert {"structured", "structured_row"} <= set(FORMULATIONS)
    with pytest.raises(DesignError, match=r"formulation must be one of .*'structured'.*got 'x'"):
        design_observer(system, box, 3.0, 0.5, bounds=bounds, formulation="x")
    with pytest.raises(DesignError, match=r"sector='paper' applies to formulation='paper' only"):
        _structured(system, bounds, 3.0, 0.5, sector="paper")
    with pytest.raises(DesignError, match=r"needs the S-procedure multipliers tau"):
        ObserverDesign.from_gains(
            system,
            box,
            3.0,
            0.5,
            [1.0, 1.0],
            [0.0, 0.0],
            [0.0, 0.0],
            P=np.eye(2),
            bounds=bounds,
            formulation="structured",
        )
    with pytest.raises(ObserverDesignInfeasible, match=r"a larger max_gain"):
        _structured(system, bounds, 3.0, 0.5, max_gain=1.0)


def test_past_max_corners_is_decay_certified():
    # n = 8 with 24 uncertain entries: 3 * 2^24 corners, far beyond MAX_CORNERS, so the
    # polytopic formulation refuses; the structured one is certified and says so.
    system, box = synthetic_system(8, 24, scale=0.5)
    bounds = jacobian_bounds(system, box, "certified")
    with pytest.raises(DesignError, match=r"more than MAX_CORNERS = 65536"):
        design_observer(system, box, 1.0, 0.5, bounds=bounds)
    design = _structured(system, bounds, 1.0, 0.5)
    assert design.is_certified and design.is_decay_certified
    assert design.to_dict()["decay_certificate"] is None
    checks = design.delta_check(samples=300)
    assert not any(c.exhaustive for c in checks) and max(c.worst for c in checks) < 0
    report = verify_observer(design, system, samples=300, seed=0, starts=2)
    assert not report.falsified


def test_the_scaling_benchmark_reports_both_formulations():
    from benchmarks.structured_certificate import format_report, scaling

    rows = scaling(cases={2: (2,)})
    assert [r["formulation"] for r in rows] == ["polytopic", "entry", "row"]
    assert all(r["feasible"] and r["k"] == 2 for r in rows)
    assert [(r["blocks"], r["block_size"]) for r in rows] == [(12, 2), (3, 4), (3, 4)]
    assert rows[1]["polytopic_recheck"] < 0 and rows[1]["delta_exhaustive"]
    table = format_report({"scaling": rows})
    assert table.count("\n| 2 | 2 |") == 3
