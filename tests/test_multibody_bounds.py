"""Certified Jacobian bounds of multibody models, from their M(q), tau(q, v), B structure.

Soundness is checked against finite differences of the models' own f and g
(which tests/test_drake_models.py checks against Drake's EvalTimeDerivatives)
at thousands of random states and every corner of the box.
"""

import time
from pathlib import Path

import numpy as np
import pytest
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant

from ofrl_drake.branch_and_bound import refine
from ofrl_drake.errors import WallTimeExceeded
from ofrl_drake.jacobian_bounds import (
    MULTIBODY_RTOL,
    BoundsError,
    Box,
    UncertifiedBoundsError,
    jacobian_bounds,
)
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.multibody_bounds import (
    MultibodyJacobianEncloser,
    MultibodyStructure,
    multibody_structure,
)

ROOT = Path(__file__).resolve().parents[1]
ACROBOT = "package://drake/examples/acrobot/Acrobot.urdf"
CART_POLE = "package://drake/examples/multibody/cart_pole/cart_pole.sdf"
CART_DOUBLE_PENDULUM = str(ROOT / "diagrams" / "models" / "cart_double_pendulum.urdf")

#: name -> (model, upright equilibrium, box around it in shifted coordinates)
PLANTS = {
    "acrobot": (ACROBOT, [np.pi, 0.0, 0.0, 0.0], ([-0.3, -0.3, -2.0, -2.0], [0.3, 0.3, 2.0, 2.0])),
    "cart_pole": (
        CART_POLE,
        [0.0, np.pi, 0.0, 0.0],
        ([-2.0, -0.4, -1.5, -1.5], [2.0, 0.4, 1.5, 1.5]),
    ),
    "cart_double_pendulum": (
        CART_DOUBLE_PENDULUM,
        [0.0, np.pi, 0.0, 0.0, 0.0, 0.0],
        ([-0.5, -0.2, -0.2, -1.0, -1.0, -1.0], [0.5, 0.2, 0.2, 1.0, 1.0, 1.0]),
    ),
}


@pytest.fixture(scope="module")
def upright():
    return {
        name: ControlAffineSystem.from_multibody(model).shifted(x_eq)
        for name, (model, x_eq, _) in PLANTS.items()
    }


@pytest.fixture(scope="module")
def bounds(upright):
    """(sampled, certified) bounds of each plant on its box, with the default tolerances."""
    return {
        name: (
            jacobian_bounds(system, PLANTS[name][2], "sampled"),
            jacobian_bounds(system, PLANTS[name][2], "certified"),
        )
        for name, system in upright.items()
    }


def _fd_jacobians(system, X, h=1e-6):
    """Central differences of f and g: (n, n, N) and (n, n, m, N), indexed [i, j, (k,) point]."""
    E = np.eye(system.n)
    Jf = np.stack(
        [(system.f_batch(X + h * E[:, [j]]) - system.f_batch(X - h * E[:, [j]])) / (2 * h)
         for j in range(system.n)],
        axis=1,
    )  # fmt: skip
    Jg = np.stack(
        [(system.g_batch(X + h * E[:, [j]]) - system.g_batch(X - h * E[:, [j]])) / (2 * h)
         for j in range(system.n)],
        axis=1,
    )  # fmt: skip
    return Jf, Jg


def _states(box, count, seed):
    """Every corner of the box plus ``count`` uniform states (columns), kept inside by h."""
    lo, hi = np.asarray(box[0], float), np.asarray(box[1], float)
    n = lo.size
    bits = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1
    corners = np.where(bits == 1, hi, lo).T
    inside = lo[:, None] + np.random.default_rng(seed).random((n, count)) * (hi - lo)[:, None]
    X = np.concatenate([corners, inside], axis=1)
    return np.clip(X, lo[:, None] + 1e-6, hi[:, None] - 1e-6)  # the differences stay in the box


# ------------------------------------------------------------------ soundness
@pytest.mark.parametrize("name", list(PLANTS))
def test_certified_bounds_contain_finite_difference_jacobians(name, upright, bounds):
    system = upright[name]
    _, certified = bounds[name]
    assert certified.method == "certified" and certified.excess.converged
    X = _states(PLANTS[name][2], 5000, seed=11)
    Jf, Jg = _fd_jacobians(system, X)
    # Central differences with h = 1e-6 are accurate to ~1e-8 (J up to ~100): 1e-6 of slack.
    for lo, hi, J in ((certified.Mf1, certified.Mf2, Jf), (certified.Mg1, certified.Mg2, Jg)):
        slack = 1e-6 * (1.0 + np.abs(J))
        below = lo[..., None] - slack > J
        above = J > hi[..., None] + slack
        assert not below.any(), f"{name}: a Jacobian below its bound at {np.argwhere(below)[0]}"
        assert not above.any(), f"{name}: a Jacobian above its bound at {np.argwhere(above)[0]}"


@pytest.mark.parametrize("name", list(PLANTS))
def test_certified_bounds_are_within_the_tolerance_of_sampled_ones(name, bounds):
    sampled, certified = bounds[name]
    assert certified.contains(sampled)
    for c_lo, c_hi, s_lo, s_hi in (
        (certified.Mf1, certified.Mf2, sampled.Mf1, sampled.Mf2),
        (certified.Mg1, certified.Mg2, sampled.Mg1, sampled.Mg2),
    ):
        width = s_hi - s_lo
        # Each end within max(tol, rtol * width) of the (inner) estimate, which the
        # centres visited may widen beyond the samples by at most their own spread.
        allowed = np.maximum(1e-3, MULTIBODY_RTOL * width) + 1e-9
        assert np.all(s_lo - c_lo <= allowed + 0.02 * width)
        assert np.all(c_hi - s_hi <= allowed + 0.02 * width)
        # Entries that are exactly constant (qdot = v, the unactuated g rows,
        # d g / d v) stay exact up to rounding: no spurious width.
        exact = width == 0
        assert np.all(c_hi[exact] - c_lo[exact] <= 1e-12 * (1 + np.abs(c_hi[exact])))


def test_a_nonzero_input_offset_enters_the_drift_jacobian():
    # Not an equilibrium: f~(z) = f(z + x*) + g(z + x*) u*, so d f~ / dz has d g / dx u*.
    system = ControlAffineSystem.from_multibody(ACROBOT).shifted(
        [np.pi, 0.0, 0.0, 0.0], [3.0], tol=1e9
    )
    box = ([-0.2, -0.2, -1.0, -1.0], [0.2, 0.2, 1.0, 1.0])
    certified = jacobian_bounds(system, box, "certified")
    X = _states(box, 3000, seed=5)
    Jf, _ = _fd_jacobians(system, X)
    slack = 1e-6 * (1.0 + np.abs(Jf))
    assert np.all(certified.Mf1[..., None] - slack <= Jf)
    assert np.all(Jf <= certified.Mf2[..., None] + slack)
    base = jacobian_bounds(system.base.shifted([np.pi, 0.0, 0.0, 0.0]), box, "certified")
    assert not np.allclose(base.Mf1, certified.Mf1)  # u* = 3 moved the bounds


# ------------------------------------------------------------------ structure
@pytest.mark.parametrize("model", [ACROBOT, CART_POLE, CART_DOUBLE_PENDULUM])
def test_the_structure_gives_the_models_f_and_g(model):
    system = ControlAffineSystem.from_multibody(model)
    structure = system.multibody_structure()
    assert isinstance(structure, MultibodyStructure)
    assert (structure.n, structure.m) == (system.n, system.m)
    X = np.random.default_rng(2).uniform(-3, 3, size=(system.n, 200))
    f, g = structure.dynamics(X)
    np.testing.assert_allclose(f, system.f_batch(X), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(g, system.g_batch(X), rtol=1e-10, atol=1e-10)
    shifted = system.shifted(X[:, 0], [0.7], tol=1e9)
    f, g = shifted.multibody_structure().dynamics(X)
    np.testing.assert_allclose(f, shifted.f_batch(X), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(g, shifted.g_batch(X), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("model", [ACROBOT, CART_POLE, CART_DOUBLE_PENDULUM])
def test_the_structure_gives_the_models_jacobians(model):
    from ofrl_drake.interval import ExpressionEvaluator
    from ofrl_drake.jacobian_bounds import symbolic_jacobians

    system = ControlAffineSystem.from_multibody(model)
    shifted = system.shifted(np.zeros(system.n), [0.7], tol=1e9)  # u* enters the drift's
    X = np.random.default_rng(3).uniform(-1.0, 1.0, size=(system.n, 100))
    Jf, Jg = shifted.multibody_structure().jacobians(X)
    x, Sf, Sg = symbolic_jacobians(shifted)
    want_f, want_g = ExpressionEvaluator(Sf, x)(X), ExpressionEvaluator(Sg, x)(X)
    scale = 1.0 + np.abs(want_f).max()
    np.testing.assert_allclose(Jf, want_f, rtol=0, atol=1e-11 * scale)
    np.testing.assert_allclose(Jg, want_g, rtol=0, atol=1e-11 * scale)
    assert set(shifted.multibody_structure().used_states()) <= set(range(system.n))


def test_large_expressions_take_their_samples_from_the_structure(monkeypatch, upright, bounds):
    # Past SYMBOLIC_MAX_CHARS the symbolic Jacobians of f and g are never formed.
    from ofrl_drake import jacobian_bounds as jb

    def refuse(system):
        raise AssertionError("symbolic_jacobians called")

    monkeypatch.setattr(jb, "SYMBOLIC_MAX_CHARS", 0)
    monkeypatch.setattr(jb, "symbolic_jacobians", refuse)
    system, box = upright["acrobot"], PLANTS["acrobot"][2]
    sampled = bounds["acrobot"][0]
    from_structure = jacobian_bounds(system, box, "sampled")
    # Other points (one grid over the states M and tau depend on): close, not equal.
    for a, b in zip(from_structure.arrays(), sampled.arrays(), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=0.02 * (1 + np.abs(b).max()))
    again = jacobian_bounds(system, box, "certified")
    assert again.excess.converged and again.contains(from_structure)
    X = _states(box, 200, seed=4)
    Jf, Jg = _fd_jacobians(system, X)
    assert np.all((again.Mf1[..., None] - 1e-5 <= Jf) & (Jf <= again.Mf2[..., None] + 1e-5))
    assert np.all((again.Mg1[..., None] - 1e-5 <= Jg) & (Jg <= again.Mg2[..., None] + 1e-5))


def test_mass_matrix_and_bias_do_not_depend_on_a_root_joint():
    # The structure evaluates M and C(q, v) v with the acrobot's shoulder (a
    # revolute joint on the world) at zero; the double plant's own, at the true
    # angle, must agree: the invariance the structure relies on.
    from pydrake.multibody.tree import MultibodyForces

    from ofrl_drake.interval import ExpressionEvaluator

    plant = MultibodyPlant(time_step=0.0)
    Parser(plant).AddModels(url=ACROBOT)
    plant.Finalize()
    structure = multibody_structure(plant)
    parts = ExpressionEvaluator([*structure.M.ravel(), *structure.tau], structure.x)
    assert all(0 not in used for used in parts.variables_used()[:4])  # M is free of q0
    context = plant.CreateDefaultContext()
    forces = MultibodyForces(plant)
    rng = np.random.default_rng(9)
    for _ in range(20):
        x = rng.uniform(-4, 4, size=4)
        plant.SetPositionsAndVelocities(context, x)
        values = parts(x)
        np.testing.assert_allclose(
            values[:4].reshape(2, 2), plant.CalcMassMatrix(context), rtol=1e-12, atol=1e-12
        )
        plant.CalcForceElementsContribution(context, forces)
        tau = plant.CalcGeneralizedForces(context, forces) - plant.CalcBiasTerm(context)
        np.testing.assert_allclose(values[4:], tau, rtol=1e-12, atol=1e-12)


def test_plain_models_have_no_structure_and_a_wrong_one_is_caught(upright):
    acrobot = upright["acrobot"]
    plain = ControlAffineSystem(acrobot.f, acrobot.g, acrobot.C)
    assert plain.multibody_structure() is None
    # The unshifted structure does not describe the shifted f: refused, not used.
    lying = ControlAffineSystem(acrobot.f, acrobot.g, acrobot.C, source=acrobot.base.source)
    with pytest.raises(BoundsError, match=r"multibody structure \(M, tau, B\) gives a f"):
        jacobian_bounds(lying, PLANTS["acrobot"][2], "certified")


# --------------------------------------------------------------- the budget
def test_a_bound_that_cannot_be_certified_names_the_entry_and_the_box(upright):
    # On the whole box [M] of the cart double pendulum cannot be inverted; with
    # one box of budget every velocity row is infinite.
    system = upright["cart_double_pendulum"]
    box = PLANTS["cart_double_pendulum"][2]
    with pytest.raises(
        UncertifiedBoundsError,
        match=r"certified bound of d f\[3\] / d x\[1\] over Box\(lower=\[-0\.5, .*\]\) is "
        r"\[-inf, inf\]: not finite \(1 boxes in .* s, stopped by max_boxes\)",
    ):
        jacobian_bounds(system, box, "certified", max_boxes=1)
    # With no time at all, even the symbolic Jacobians are not formed.
    with pytest.raises(WallTimeExceeded, match=r"f\[0\] was next.*allow more wall time"):
        jacobian_bounds(system, box, "certified", max_wall_time=1e-9)


def test_boxes_where_m_is_not_proven_invertible_are_cut_along_their_widest_side(upright):
    """Where [M] cannot be inverted every share is infinite; the tie went to x[0], the
    acrobot's shoulder angle, which M does not depend on: 134,000 of 141,000 cuts, and
    the box |q| <= 0.8 was refused after 151,081 boxes (by hand, 4 slices along q[1]
    certified it). Now it certifies, and is sound at sampled states."""
    system = upright["acrobot"]
    box = ([-0.8, -0.8, -2.0, -2.0], [0.8, 0.8, 2.0, 2.0])
    certified = jacobian_bounds(system, box, "certified")
    assert certified.excess.converged
    assert certified.contains(jacobian_bounds(system, box, "sampled"))
    X = _states(box, 400, seed=3)
    Jf, _ = _fd_jacobians(system, X)
    lower, upper = certified.Mf1[:, :, None], certified.Mf2[:, :, None]
    assert np.all(Jf >= lower - 1e-5) and np.all(Jf <= upper + 1e-5)


def test_the_multibody_derivatives_stop_at_the_deadline(upright):
    """Before: the third-order derivatives of M and tau took 31 s of a 10 s budget on a
    three-link robot, and the design ran on."""
    structure = upright["acrobot"].multibody_structure()
    with pytest.raises(
        WallTimeExceeded,
        match=r"^the multibody Taylor derivatives of M\(q\) and the bias were not done by the "
        r"deadline \(max_wall_time, --max-wall\): d/dx\d was next; allow more wall time",
    ):
        MultibodyJacobianEncloser(structure, deadline=time.monotonic() - 1.0)
    assert MultibodyJacobianEncloser(structure, deadline=None).deadline is None


def test_a_budget_stops_early_with_sound_bounds(upright, bounds):
    system = upright["acrobot"]
    box = PLANTS["acrobot"][2]
    sampled, converged = bounds["acrobot"]
    rough = jacobian_bounds(system, box, "certified", max_boxes=200)
    assert not rough.excess.converged
    assert rough.contains(converged) and rough.contains(sampled)
    assert rough.excess.max > converged.excess.max


def test_refine_stopped_by_the_clock_is_sound(upright):
    system = upright["cart_double_pendulum"]
    box = Box(*PLANTS["cart_double_pendulum"][2])
    encloser = MultibodyJacobianEncloser(system.multibody_structure())
    E = encloser.n_entries
    inner = np.zeros(E)
    calls = []
    enclose = encloser.enclose

    def slow(lo, hi):  # the clock runs out after the second batch of boxes
        calls.append(lo.shape[1])
        return enclose(lo, hi)

    encloser.enclose = slow
    import time

    deadline = time.monotonic() + 3600.0
    full = refine(encloser, box.lower, box.upper, inner, inner, tol=1e-3, rtol=0.1,
                  max_boxes=10**6, deadline=deadline)  # fmt: skip
    assert full.converged and full.stop == "converged"
    calls.clear()
    encloser.chunk = 8  # several batches per level, so the clock can stop one midway
    stopped = refine(encloser, box.lower, box.upper, inner, inner, tol=1e-3, rtol=0.1,
                     max_boxes=10**6, deadline=time.monotonic() + 0.5)  # fmt: skip
    assert stopped.stop == "max_wall_time" and not stopped.converged
    assert np.all(stopped.lo <= full.lo) and np.all(full.hi <= stopped.hi)


def test_the_benchmark_script_runs_and_reports_ratios(capsys):
    from benchmarks.multibody_bounds import main

    assert main(["--plants", "cart_pole", "--methods", "certified", "--timeout", "120"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| cart_pole | certified"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[5] == "True"  # converged
    assert 1.0 <= float(cells[6]) <= 1.0 + 2 * MULTIBODY_RTOL + 1e-6  # max width ratio


def test_the_design_gives_the_bounds_the_runs_wall_time(monkeypatch):
    """--max-wall sets simulation.max_wall_time, which bounds the bounds' refinement."""
    import dataclasses

    import ofrl_drake.jacobian_bounds as jb
    from ofrl_drake.scenario import load_scenario
    from ofrl_drake.variants import design_for

    seen = []

    class Stop(Exception):
        """Raised by the spy: the test stops before the LMI."""

    def spy(*args, **kwargs):
        seen.append(kwargs.get("max_wall_time"))
        raise Stop

    monkeypatch.setattr(jb, "jacobian_bounds", spy)
    scenario = load_scenario(ROOT / "diagrams" / "cart_pole.yaml")
    timed = dataclasses.replace(
        scenario, simulation=dataclasses.replace(scenario.simulation, max_wall_time=7.5)
    )
    for s, expected in ((scenario, None), (timed, 7.5)):
        with pytest.raises(Stop):
            design_for(s)
        assert seen[-1] == expected
