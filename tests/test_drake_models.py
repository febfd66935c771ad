"""Control-affine models from Drake systems and multibody models."""

import os
import re

import numpy as np
import pydrake.math as pmath
import pytest
from pydrake.autodiffutils import ExtractGradient, InitializeAutoDiff
from pydrake.examples import AcrobotPlant, PendulumParams, PendulumPlant, QuadrotorPlant
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import LinearSpringDamper
from pydrake.symbolic import Expression, MakeVectorVariable
from pydrake.symbolic import sin as sym_sin
from pydrake.systems.framework import LeafSystem, LeafSystem_
from pydrake.systems.primitives import SymbolicVectorSystem
from pydrake.systems.scalar_conversion import TemplateSystem

from ofrl_drake import drake_models
from ofrl_drake.drake_models import (
    AFFINITY_POINTS,
    DrakeSystemSource,
    MultibodySource,
    extract_drake_system,
)
from ofrl_drake.errors import ModelError
from ofrl_drake.expression_function import ExpressionFunction
from ofrl_drake.jacobian_bounds import jacobian_bounds
from ofrl_drake.model import ControlAffineSystem

CART_POLE = "package://drake/examples/multibody/cart_pole/cart_pole.sdf"
ACROBOT = "package://drake/examples/acrobot/Acrobot.urdf"


# ------------------------------------------------------------------ from_drake
def _pendulum_closed_form():
    p = PendulumParams()
    inertia = p.mass() * p.length() ** 2

    def f(x):
        return np.array(
            [
                x[1],
                -(p.damping() * x[1] + p.mass() * p.gravity() * p.length() * np.sin(x[0]))
                / inertia,
            ]
        )

    def g(x):
        return np.array([[0 * x[0]], [1 / inertia + 0 * x[0]]])

    return f, g


def test_from_drake_pendulum_matches_closed_form():
    system = ControlAffineSystem.from_drake(PendulumPlant(), C=[[1.0, 0.0]])
    f, g = _pendulum_closed_form()
    assert (system.n, system.m, system.q) == (2, 1, 1)
    assert system.vectorized and system.name == "PendulumPlant"
    X = np.random.default_rng(0).uniform(-4, 4, size=(2, 50))
    np.testing.assert_allclose(system.f_batch(X), f(X), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(system.g_batch(X), g(X), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(system.f(X[:, 0]), f(X[:, 0]), rtol=1e-13, atol=1e-13)
    # Default parameters: m = 1, l = 0.5, b = 0.1, g = 9.81 -> 1 / (m l^2) = 4.
    np.testing.assert_allclose(system.g(np.zeros(2)), [[0.0], [4.0]], atol=1e-15)
    assert isinstance(system.source, DrakeSystemSource)
    assert system.source.input_port == "tau" and system.source.fixed_inputs == {}


def test_from_drake_input_port_by_name_and_errors():
    plant = PendulumPlant()
    assert ControlAffineSystem.from_drake(plant, [[1.0, 0.0]], input_port="tau").m == 1
    with pytest.raises(ModelError, match=r"input_port 'torque' is not an input port.*\['tau'\]"):
        ControlAffineSystem.from_drake(plant, [[1.0, 0.0]], input_port="torque")
    with pytest.raises(ModelError, match=r"input_port 3 is out of range"):
        ControlAffineSystem.from_drake(plant, [[1.0, 0.0]], input_port=3)
    with pytest.raises(ModelError, match=r"C has 3 columns but the system has n = 2 states"):
        ControlAffineSystem.from_drake(plant, [[1.0, 0.0, 0.0]])


def _affine_test_system(name, n, rhs):
    """The ``TemplateSystem`` ``name``: ``n`` states, one input port ``u``, ``x' = rhs(T, x, u)``.

    ``T`` is the scalar type, ``x`` the state and ``u`` the input, both as vectors.
    """

    def instantiate(T):
        class Impl(LeafSystem_[T]):
            def _construct(self, converter=None):
                LeafSystem_[T].__init__(self, converter)
                self.DeclareContinuousState(n)
                self._u = self.DeclareVectorInputPort("u", 1)

            def _construct_copy(self, other, converter=None):
                Impl._construct(self, converter=converter)

            def DoCalcTimeDerivatives(self, context, derivatives):
                x = context.get_continuous_state_vector().CopyToVector()
                xdot = rhs(T, x, self._u.Eval(context))
                derivatives.get_mutable_vector().SetFromVector(xdot)

        return Impl

    return TemplateSystem.define(name)(instantiate)


# x0' = x1, x1' = u**2 - x0: not affine in u (row 1).
_Quadratic_ = _affine_test_system("_Quadratic_", 2, lambda T, x, u: [x[1], u[0] ** 2 - x[0]])


def test_from_drake_non_affine_leaf_system_names_its_row():
    with pytest.raises(ModelError, match=r"not affine in u.*state rows \[1\]"):
        ControlAffineSystem.from_drake(_Quadratic_[float](), C=[[1.0, 0.0]])


@TemplateSystem.define("_Reordered_")
def _Reordered_(T):
    class Impl(LeafSystem_[T]):
        """x' = -x + u + 2 d; the symbolic version declares its ports in another order."""

        def _construct(self, converter=None, renamed=False):
            LeafSystem_[T].__init__(self, converter)
            self._renamed = renamed
            self.DeclareContinuousState(1)
            symbolic = T == Expression
            u_name = "v" if renamed and symbolic else "u"
            names = (u_name, "d") if symbolic else ("d", u_name)
            ports = {name: self.DeclareVectorInputPort(name, 1) for name in names}
            self._u, self._d = ports[u_name], ports["d"]

        def _construct_copy(self, other, converter=None):
            Impl._construct(self, converter=converter, renamed=other._renamed)

        def DoCalcTimeDerivatives(self, context, derivatives):
            x = context.get_continuous_state_vector().CopyToVector()
            u, d = self._u.Eval(context), self._d.Eval(context)
            derivatives.get_mutable_vector().SetFromVector([-x[0] + u[0] + 2 * d[0]])

    return Impl


@pytest.mark.parametrize("input_port", ["u", 1])
def test_from_drake_finds_u_by_name_in_the_symbolic_system(input_port):
    # Before: the port's index was reused on ToSymbolic(), whose port 1 is d, not u.
    system = _Reordered_[float]()
    assert system.get_input_port(1).get_name() == "u"
    assert system.ToSymbolic().get_input_port(1).get_name() == "d"
    model = ControlAffineSystem.from_drake(system, C=[[1.0]], input_port=input_port)
    np.testing.assert_array_equal(model.g(np.array([0.3])), [[1.0]])
    np.testing.assert_array_equal(model.f(np.array([0.3])), [-0.3])
    assert model.source.input_port == "u"
    assert list(model.source.fixed_inputs) == ["d"]


def test_from_drake_refuses_a_symbolic_version_without_the_input_port():
    # Before: Drake's RuntimeError (no port 'v' on the double system) from deep inside.
    system = _Reordered_[float](renamed=True)
    with pytest.raises(
        ModelError,
        match=r"symbolic version \(ToSymbolic\(\)\) has no input port 'u', only \['v', 'd'\]; "
        r"its scalar conversion must keep the names of the input ports",
    ):
        ControlAffineSystem.from_drake(system, C=[[1.0]], input_port="u")


def test_a_model_s_source_gives_its_multibody_plant_or_none():
    # Before: callers tested isinstance(source, MultibodySource).
    pendulum = ControlAffineSystem.from_drake(PendulumPlant(), C=[[1.0, 0.0]])
    assert pendulum.source.multibody_plant is None and pendulum.multibody_plant is None
    cart_pole = ControlAffineSystem.from_multibody(CART_POLE)
    plant = cart_pole.source.plant
    assert cart_pole.source.multibody_plant is plant and cart_pole.multibody_plant is plant
    assert cart_pole.shifted([0.0, np.pi, 0.0, 0.0]).multibody_plant is plant


def _check_against_system(model, plant, X, U):
    """f(x) = xdot(x, 0) and f(x) + g(x) u = xdot(x, u), the system's own derivatives."""
    context = plant.CreateDefaultContext()
    port = plant.GetInputPort(model.source.input_port)  # the port that is u, by name
    fX, gX = model.f_batch(X), model.g_batch(X)
    for k in range(X.shape[1]):
        context.SetContinuousState(X[:, k])
        port.FixValue(context, np.zeros(model.m))
        drift = plant.EvalTimeDerivatives(context).CopyToVector()
        port.FixValue(context, U[:, k])
        xdot = plant.EvalTimeDerivatives(context).CopyToVector()
        np.testing.assert_allclose(fX[:, k], drift, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fX[:, k] + gX[:, :, k] @ U[:, k], xdot, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(model.f(X[:, k]) + model.g(X[:, k]) @ U[:, k], xdot, rtol=1e-9)


def _acrobot_points(rng, points):
    return rng.uniform(-np.pi, np.pi, (4, points)) * [[1], [1], [2], [2]]


def _quadrotor_points(rng, points):
    X = rng.uniform(-2.0, 2.0, (12, points))
    X[4] = rng.uniform(-1.2, 1.2, points)  # pitch away from gimbal lock (+-pi/2)
    return X


# d xdot / d u of these plants names u in terms such as u * (0 / det M(x)) (the
# derivative of a solved mass matrix), which do not depend on u: they used to be
# refused as "not affine in u".
DRAKE_EXAMPLES = [
    pytest.param(AcrobotPlant, 4, 1, _acrobot_points, id="AcrobotPlant"),
    pytest.param(QuadrotorPlant, 12, 4, _quadrotor_points, id="QuadrotorPlant"),
]


@pytest.mark.parametrize(("plant_class", "n", "m", "draw"), DRAKE_EXAMPLES)
def test_from_drake_accepts_plants_whose_input_matrix_names_u_in_vanishing_terms(
    plant_class, n, m, draw
):
    plant = plant_class()
    C = np.eye(n)[: n // 2]
    model = ControlAffineSystem.from_drake(plant, C)
    assert (model.n, model.m, model.q) == (n, m, n // 2)
    assert model.vectorized and model.name == plant_class.__name__
    rng = np.random.default_rng(11)
    _check_against_system(model, plant, draw(rng, 40), rng.uniform(-5.0, 5.0, (m, 40)))
    # g holds no u: it is d xdot / d u at u = 0, and evaluates at a state alone.
    assert all(
        v.get_name().startswith("x") for e in model.g.expressions.flat for v in e.GetVariables()
    )


@pytest.mark.parametrize(("plant_class", "n", "m", "draw"), DRAKE_EXAMPLES)
def test_from_drake_decides_affinity_numerically_when_expansion_is_skipped(
    plant_class, n, m, draw, monkeypatch
):
    # With no entry small enough to expand, every entry naming u is compared at
    # u = 0 and at random u: the same plants are accepted, with the same f + g u.
    monkeypatch.setattr(drake_models, "EXPAND_MAX_CHARS", 0)
    plant = plant_class()
    model = ControlAffineSystem.from_drake(plant, np.eye(n)[:1])
    rng = np.random.default_rng(12)
    _check_against_system(model, plant, draw(rng, 20), rng.uniform(-5.0, 5.0, (m, 20)))


def test_quadrotor_check_points_at_gimbal_lock_are_left_out():
    # With seed 0 one of the 20 check points has a pitch within 0.5 degree of
    # 90 degrees, where QuadrotorPlant's double EvalTimeDerivatives throws.
    rng = np.random.default_rng(0)
    X = rng.standard_normal((12, AFFINITY_POINTS))
    assert np.any(np.abs(np.abs(X[4]) - np.pi / 2) < np.radians(0.5))
    assert extract_drake_system(QuadrotorPlant(), seed=0).n == 12


def _one(u):
    """``sin^2 u + cos^2 u``: 1, which Expand does not see."""
    return pmath.sin(u) ** 2 + pmath.cos(u) ** 2


# x0' = sin(u) (not affine, row 0); x1' = u (sin^2 u + cos^2 u) - x0 (affine).
_SineAndIdentity_ = _affine_test_system(
    "_SineAndIdentity_", 2, lambda T, x, u: [pmath.sin(u[0]), u[0] * _one(u[0]) - x[0]]
)
# x0' = x1, x1' = u (sin^2 u + cos^2 u) - x0: affine, but u survives Expand.
_TrigIdentity_ = _affine_test_system(
    "_TrigIdentity_", 2, lambda T, x, u: [x[1], u[0] * _one(u[0]) - x[0]]
)


def test_from_drake_sin_u_is_refused_naming_its_row_the_tolerance_and_the_points():
    with pytest.raises(
        ModelError,
        match=r"_SineAndIdentity_.*not affine in u: d xdot / d u depends on u in state "
        r"rows \[0\] \(e\.g\. d xdot\[0\] / d u\[0\] = cos\(u\(0\)\) is 1 at u = 0 but "
        r".*compared at u = 0 and at u for 20 random \(x, u\), standard normal, to a "
        r"relative 1e-08\)",
    ):
        ControlAffineSystem.from_drake(_SineAndIdentity_[float](), C=[[1.0, 0.0]])
    with pytest.raises(ModelError, match=r"state rows \[0\].*for 5 random \(x, u\)"):
        ControlAffineSystem.from_drake(_SineAndIdentity_[float](), [[1.0, 0.0]], check_points=5)


def test_from_drake_accepts_an_input_matrix_that_is_constant_only_numerically():
    # d xdot[1] / d u = sin^2 u + cos^2 u + u (2 sin u cos u - 2 cos u sin u) keeps u
    # after expansion; at u = 0 and at random u it is 1.
    model = ControlAffineSystem.from_drake(_TrigIdentity_[float](), C=[[1.0, 0.0]])
    X = np.random.default_rng(2).standard_normal((2, 10))
    np.testing.assert_allclose(model.g_batch(X), np.broadcast_to([[[0.0]], [[1.0]]], (2, 1, 10)))
    np.testing.assert_allclose(model.f_batch(X), [X[1], -X[0]], rtol=0, atol=0)


def _double_fails(T, x, u):
    """x' = -x + u symbolically; the double path always throws."""
    if T is float:
        raise RuntimeError("no double derivatives here")
    return [-x[0] + u[0]]


_DoubleFails_ = _affine_test_system("_DoubleFails_", 1, _double_fails)


@pytest.mark.parametrize("points", [0, -3, 2.5, True])
def test_check_points_must_be_a_positive_integer(points):
    with pytest.raises(
        ModelError, match=rf"PendulumPlant: check_points must be a positive integer; got {points!r}"
    ):
        ControlAffineSystem.from_drake(PendulumPlant(), [[1.0, 0.0]], check_points=points)
    with pytest.raises(ModelError, match=r"cart_pole: check_points must be a positive integer"):
        ControlAffineSystem.from_multibody(CART_POLE, check_points=points)


@pytest.mark.parametrize("seed", [-1, 1.5, "0", None])
def test_seed_must_be_a_nonnegative_integer(seed):
    # numpy's "expected non-negative integer" (or a TypeError) came from deep inside.
    with pytest.raises(
        ModelError, match=rf"PendulumPlant: seed must be an integer >= 0; got {seed!r}\."
    ):
        ControlAffineSystem.from_drake(PendulumPlant(), [[1.0, 0.0]], seed=seed)
    with pytest.raises(ModelError, match=r"cart_pole: seed must be an integer >= 0"):
        ControlAffineSystem.from_multibody(CART_POLE, seed=seed)


def test_from_drake_refuses_a_system_whose_double_derivatives_always_fail():
    with pytest.raises(
        ModelError,
        match=r"EvalTimeDerivatives failed at all 20 random \(x, u\).*no double derivatives here",
    ):
        ControlAffineSystem.from_drake(_DoubleFails_[float](), C=[[1.0]])


def test_drake_models_sits_below_model_in_the_import_graph():
    # No circle, lazy imports included: model builds on drake_models' DrakeDynamics.
    from .test_import_graph import GRAPH

    assert "model" not in GRAPH["drake_models"]
    assert "drake_models" in GRAPH["model"]


def _two_faced(T, x, u):
    """Affine for symbolic scalars, but u**3 in row 1 in double precision."""
    push = u[0] ** 3 if T is float else u[0]
    return [x[1], push - x[0]]


_TwoFaced_ = _affine_test_system("_TwoFaced_", 2, _two_faced)


def test_from_drake_numerical_check_compares_with_the_double_system():
    # The symbolic check passes (the symbolic path is affine); only the comparison
    # with the double-precision derivatives can catch the u**3.
    with pytest.raises(
        ModelError, match=r"xdot differs from f\(x\) \+ g\(x\) u in state rows \[1\]"
    ):
        ControlAffineSystem.from_drake(_TwoFaced_[float](), C=[[1.0, 0.0]])


def test_from_drake_refuses_time_varying_and_non_symbolic_systems():
    x = MakeVectorVariable(1, "x")
    u = MakeVectorVariable(1, "u")
    from pydrake.symbolic import Variable

    t = Variable("t")
    timed = SymbolicVectorSystem(time=t, state=x, input=u, dynamics=[-x[0] + sym_sin(t) * u[0]])
    with pytest.raises(ModelError, match=r"depend on time in state rows \[0\]"):
        ControlAffineSystem.from_drake(timed, C=[[1.0]])

    class DoubleOnly(LeafSystem):
        def __init__(self):
            super().__init__()
            self.DeclareContinuousState(1)
            self.DeclareVectorInputPort("u", 1)

    with pytest.raises(ModelError, match=r"does not support the symbolic scalar type"):
        ControlAffineSystem.from_drake(DoubleOnly(), C=[[1.0]])


def test_from_drake_holds_other_inputs_at_zero():
    x = MakeVectorVariable(2, "x")
    u = MakeVectorVariable(2, "u")
    sys = SymbolicVectorSystem(state=x, input=u, dynamics=[x[1] + u[1], -x[0] + u[0]])
    model = ControlAffineSystem.from_drake(sys, C=[[1.0, 0.0]])
    assert model.m == 2  # one vector input port of size 2
    np.testing.assert_allclose(model.g(np.zeros(2)), [[0.0, 1.0], [1.0, 0.0]])


def test_certified_bounds_on_pendulum_contain_sampled_jacobians():
    system = ControlAffineSystem.from_drake(PendulumPlant(), C=[[1.0, 0.0]])
    box = ([-1.0, -2.0], [2.0, 2.0])
    b = jacobian_bounds(system, box, "certified", tol=1e-6)
    assert b.excess.converged
    X = np.random.default_rng(3).uniform(box[0], box[1], size=(5000, 2)).T
    p = PendulumParams()
    d21 = -p.gravity() / p.length() * np.cos(X[0])  # d f2 / d theta
    assert b.Mf1[1, 0] <= d21.min() and d21.max() <= b.Mf2[1, 0]
    np.testing.assert_allclose(b.Mf1[0], [0.0, 1.0])
    np.testing.assert_allclose(b.Mf2[0], [0.0, 1.0])
    np.testing.assert_allclose(
        [b.Mf1[1, 1], b.Mf2[1, 1]], -p.damping() / (p.mass() * p.length() ** 2)
    )
    np.testing.assert_array_equal(b.Mg1, 0.0)
    np.testing.assert_array_equal(b.Mg2, 0.0)
    # Bounds are tight: the exact range of -g/l cos over [-1, 2] is [-19.62, 8.165...].
    assert b.Mf1[1, 0] == pytest.approx(-p.gravity() / p.length(), abs=1e-5)
    assert b.Mf2[1, 0] == pytest.approx(-p.gravity() / p.length() * np.cos(2.0), abs=1e-5)


# ------------------------------------------------------------ ExpressionFunction
def test_expression_function_types():
    x = MakeVectorVariable(2, "x")
    F = ExpressionFunction([[x[0] * x[1]], [sym_sin(x[0]) + 2.0]], x)
    assert F.shape == (2, 1)
    z = np.array([0.4, -1.3])
    J = ExtractGradient(F(InitializeAutoDiff(z).ravel()).ravel())
    np.testing.assert_allclose(J, [[z[1], z[0]], [np.cos(z[0]), 0.0]], atol=1e-15)
    y = MakeVectorVariable(2, "y")
    sym = F(np.array([Expression(y[0]) + 1.0, Expression(y[1])]))
    assert sym[0, 0].EqualTo((y[0] + 1.0) * y[1])
    with pytest.raises(ModelError, match=r"shape \(2,\) or \(2, N\)"):
        F(np.zeros(3))


# --------------------------------------------------------------- from_multibody
def _plant(url):
    plant = MultibodyPlant(time_step=0.0)
    Parser(plant).AddModels(url=url)
    return plant


def _check_against_plant(system, plant, points=100, seed=7):
    context = plant.CreateDefaultContext()
    rng = np.random.default_rng(seed)
    X = rng.uniform(-np.pi, np.pi, size=(system.n, points))
    U = rng.uniform(-5, 5, size=(system.m, points))
    fX, gX = system.f_batch(X), system.g_batch(X)
    for k in range(points):
        plant.SetPositionsAndVelocities(context, X[:, k])
        plant.get_actuation_input_port().FixValue(context, U[:, k])
        xdot = plant.EvalTimeDerivatives(context).CopyToVector()
        np.testing.assert_allclose(fX[:, k] + gX[:, :, k] @ U[:, k], xdot, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("url", [CART_POLE, ACROBOT])
def test_from_multibody_matches_eval_time_derivatives(url):
    system = ControlAffineSystem.from_multibody(url)
    plant = _plant(url)
    plant.Finalize()
    assert (system.n, system.m, system.q) == (4, 1, 2)
    np.testing.assert_array_equal(system.output_matrix, np.hstack([np.eye(2), np.zeros((2, 2))]))
    _check_against_plant(system, plant)
    assert isinstance(system.source, MultibodySource) and system.source.model == url
    assert len(system.source.position_names) == 2 and len(system.source.actuator_names) == 1


def test_from_multibody_cart_pole_structure():
    system = ControlAffineSystem.from_multibody(CART_POLE, C=[[1, 0, 0, 0], [0, 1, 0, 0]])
    assert system.name == "cart_pole"
    assert system.source.position_names == ("CartSlider_x", "PolePin_q")
    x = np.array([0.3, 1.1, -0.4, 0.8])
    np.testing.assert_allclose(system.f(x)[:2], x[2:], atol=0)
    np.testing.assert_allclose(system.g(x)[:2], 0.0, atol=0)
    # The upright is an equilibrium; the shifted system has f(0) = 0.
    upright = system.shifted([0.0, np.pi, 0.0, 0.0], [0.0])
    np.testing.assert_allclose(upright.f(np.zeros(4)), 0.0, atol=1e-14)


def test_from_multibody_with_a_spring_between_bodies_and_a_given_plant():
    plant = _plant(ACROBOT)
    link1, link2 = plant.GetBodyByName("upper_link"), plant.GetBodyByName("lower_link")
    plant.AddForceElement(
        LinearSpringDamper(link1, [0.0, 0.0, -0.5], link2, [0.0, 0.0, -1.0], 0.5, 30.0, 2.0)
    )
    plant.Finalize()
    system = ControlAffineSystem.from_multibody(plant)
    assert system.source.model is None and system.source.plant is plant
    _check_against_plant(system, plant, points=50)


def test_from_multibody_errors(tmp_path):
    with pytest.raises(ModelError, match=r"model file '.*nothing.sdf' does not exist"):
        ControlAffineSystem.from_multibody(str(tmp_path / "nothing.sdf"))
    with pytest.raises(ModelError, match=r"model must be a file path.*got int"):
        ControlAffineSystem.from_multibody(3)
    with pytest.raises(ModelError, match=r"cannot load 'package://drake/nope.sdf'"):
        ControlAffineSystem.from_multibody("package://drake/nope.sdf")
    unfinished = _plant(CART_POLE)
    with pytest.raises(ModelError, match=r"not finalized; call plant.Finalize\(\)"):
        ControlAffineSystem.from_multibody(unfinished)
    discrete = MultibodyPlant(time_step=0.01)
    Parser(discrete).AddModels(url=CART_POLE)
    discrete.Finalize()
    with pytest.raises(ModelError, match=r"discrete \(time_step = 0.01\)"):
        ControlAffineSystem.from_multibody(discrete)
    floating = MultibodyPlant(time_step=0.0)
    from pydrake.multibody.tree import SpatialInertia

    floating.AddRigidBody("ball", SpatialInertia.SolidSphereWithMass(1.0, 0.1))
    floating.Finalize()
    with pytest.raises(ModelError, match=r"7 positions but 6 velocities \(a quaternion"):
        ControlAffineSystem.from_multibody(floating)


def test_a_directory_as_a_model_file_is_named_a_directory(tmp_path):
    with pytest.raises(
        ModelError,
        match=rf"model file '{re.escape(str(tmp_path))}' is a directory, not a model file; "
        r"give an SDF, URDF or MJCF file",
    ):
        ControlAffineSystem.from_multibody(str(tmp_path))
    fifo = tmp_path / "cart_pole.sdf"
    os.mkfifo(fifo)  # never opened: it would block
    with pytest.raises(ModelError, match=r"cart_pole\.sdf' is not a regular file; give an SDF"):
        ControlAffineSystem.from_multibody(str(fifo))


_LIMITED_URDF = """<?xml version="1.0"?>
<robot name="limited">
  <link name="base"/>
  <link name="arm">
    <inertial><origin xyz="0 0 -0.5"/><mass value="1"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
  </link>
  <joint name="base_weld" type="fixed"><parent link="world"/><child link="base"/></joint>
  <joint name="pin" type="revolute">
    <parent link="base"/><child link="arm"/><axis xyz="0 1 0"/>
    <limit lower="-1" upper="1" EFFORT/>
    <dynamics damping="0.2"/>
  </joint>
  <transmission type="SimpleTransmission" name="t">
    <actuator name="motor"/><joint name="pin"/><mechanicalReduction>1</mechanicalReduction>
  </transmission>
</robot>
"""


def test_from_multibody_position_limits_are_fine_effort_limits_are_refused(tmp_path):
    free = tmp_path / "limited.urdf"
    free.write_text(_LIMITED_URDF.replace(" EFFORT", ""))
    system = ControlAffineSystem.from_multibody(free)
    assert (system.n, system.m, system.q) == (2, 1, 1) and system.name == "limited"
    # Closed form: I = m l^2 + I_yy = 0.26, damping 0.2, m g l = 4.905.
    x = np.array([0.7, -1.2])
    np.testing.assert_allclose(
        system.f(x), [x[1], (-0.2 * x[1] - 4.905 * np.sin(x[0])) / 0.26], rtol=1e-12
    )
    np.testing.assert_allclose(system.g(x), [[0.0], [1 / 0.26]], rtol=1e-12)
    clamped = tmp_path / "clamped.urdf"
    clamped.write_text(_LIMITED_URDF.replace("EFFORT", 'effort="5"'))
    with pytest.raises(ModelError, match=r"clamped: the plant has finite effort limits"):
        ControlAffineSystem.from_multibody(clamped)


def test_a_class_where_a_drake_system_is_wanted_says_to_make_an_instance():
    from pydrake.examples import PendulumPlant

    from ofrl_drake import ControlAffineSystem
    from ofrl_drake.errors import ModelError

    with pytest.raises(
        ModelError,
        match=r"got the class PendulumPlant: pass an instance, PendulumPlant\(\.\.\.\)\.$",
    ):
        ControlAffineSystem.from_drake(PendulumPlant, C=[[1.0, 0.0]])
