"""Control-affine dynamics extracted from Drake systems and multibody models.

Two routes turn a Drake model into ``f`` and ``g`` of ``x' = f(x) + g(x) u``
as ``pydrake.symbolic`` expressions
(:class:`~ofrl_drake.expression_function.ExpressionFunction`), so they evaluate
over ``(n, N)`` batches, differentiate symbolically and admit certified
Jacobian bounds:

* :func:`extract_drake_system`: any Drake ``System`` with one continuous state
  vector and a vector input that supports the symbolic scalar type
  (``ToSymbolic``). ``f(x) = xdot(x, u = 0)`` and ``g(x) = d xdot / d u`` come
  from the symbolic ``EvalTimeDerivatives``.
* :func:`extract_multibody`: a model file, a ``package://`` URL or a finalized
  continuous ``MultibodyPlant``. ``f = [v; M^-1 (tau_g + tau_app - C(q, v) v)]``
  and ``g = [0; M^-1 B]`` are assembled from ``CalcMassMatrix``,
  ``CalcBiasTerm``, ``CalcGravityGeneralizedForces``, the joint damping and
  ``MakeActuationMatrix`` on the symbolic plant.

Both return a :class:`DrakeDynamics`, which keeps where the equations came from
in ``source`` (:class:`DrakeSystemSource` or :class:`MultibodySource`) so blocks
can use the Drake model itself, e.g. to draw it.
:meth:`ControlAffineSystem.from_drake <ofrl_drake.model.ControlAffineSystem.from_drake>`
and :meth:`~ofrl_drake.model.ControlAffineSystem.from_multibody` call these and
add the output matrix; this module does not import :mod:`ofrl_drake.model`
(the import runs one way, model -> drake_models).

>>> from pydrake.examples import PendulumPlant
>>> pendulum = extract_drake_system(PendulumPlant())
>>> (pendulum.n, pendulum.m, pendulum.name)
(2, 1, 'PendulumPlant')
>>> cart_pole = extract_multibody(
...     "package://drake/examples/multibody/cart_pole/cart_pole.sdf")
>>> (cart_pole.n, cart_pole.m, cart_pole.default_C.shape)
(4, 1, (2, 4))
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydrake.symbolic import Expression, Jacobian, MakeVectorVariable, Variable
from pydrake.systems.framework import InputPort, PortDataType, System

from ofrl_drake.checks import integer_at_least
from ofrl_drake.drake_typing import input_port_names
from ofrl_drake.errors import ModelError
from ofrl_drake.expression_function import ExpressionFunction
from ofrl_drake.multibody_bounds import MultibodyStructure, _symbolic_state, multibody_structure

__all__ = [
    "AFFINITY_POINTS",
    "AFFINITY_RTOL",
    "EXPAND_MAX_CHARS",
    "DrakeDynamics",
    "DrakeSystemSource",
    "MultibodySource",
    "extract_drake_system",
    "extract_multibody",
]

#: Random (x, u) points (standard normal, seeded) of the numerical checks: an
#: entry of ``d xdot / d u`` that still names ``u`` after expansion is compared
#: at ``u = 0`` and at ``u``, and ``f + g u`` is compared with the system's own
#: double-precision ``EvalTimeDerivatives``.
AFFINITY_POINTS = 20
#: Relative tolerance of both comparisons, ``|a - b| <= rtol (1 + |b|)``: of
#: ``d xdot / d u`` at ``u`` (``a``) and at ``u = 0`` (``b``), and of
#: ``f + g u`` (``a``) and ``xdot`` (``b``).
AFFINITY_RTOL = 1e-8
#: Largest printed size (characters) of an entry of ``d xdot / d u`` that is
#: expanded symbolically to see whether ``u`` cancels; larger entries that name
#: ``u`` are only checked numerically.
EXPAND_MAX_CHARS = 20_000


@dataclass(frozen=True, eq=False)
class DrakeSystemSource:
    """The Drake system :func:`extract_drake_system` extracted a model from.

    Attributes
    ----------
    system : System
        The system as given (double scalar type).
    input_port : str
        Name of its input port that is ``u``.
    fixed_inputs : dict of str to ndarray
        Every other vector input port, by name, with the value it was held at
        while extracting ``f`` and ``g`` (zeros); a block that runs ``system``
        must feed these ports the same values.
    state_size : int
        ``n``.
    """

    system: System
    input_port: str
    fixed_inputs: dict[str, np.ndarray] = field(default_factory=dict)
    state_size: int = 0

    @property
    def multibody_plant(self) -> None:
        """None: a Drake system is not a multibody plant (see :class:`MultibodySource`)."""
        return None


@dataclass(frozen=True, eq=False)
class MultibodySource:
    """The multibody model :func:`extract_multibody` built a model from.

    Attributes
    ----------
    plant : MultibodyPlant
        The finalized double plant the equations come from.
    model : str or None
        The file path or ``package://`` URL it was parsed from, or None when a
        plant was given; re-parse it next to a ``SceneGraph`` to draw the model.
    position_names, velocity_names, actuator_names : tuple of str
        Names of the entries of ``q``, ``v`` and ``u``, in order.
    structure : MultibodyStructure or None
        ``qdot``, ``M``, ``tau`` and ``B`` as symbolic parts (see
        :func:`ofrl_drake.multibody_bounds.multibody_structure`), for certified
        Jacobian bounds.
    """

    plant: Any
    model: str | None
    position_names: tuple[str, ...] = ()
    velocity_names: tuple[str, ...] = ()
    actuator_names: tuple[str, ...] = ()
    structure: MultibodyStructure | None = None

    @property
    def multibody_plant(self) -> Any:
        """:attr:`plant`: what a model's source gives when asked for its ``MultibodyPlant``.

        Every source answers (:class:`DrakeSystemSource` with None), so a
        caller asks ``ControlAffineSystem.multibody_plant`` instead of testing
        the source's class.
        """
        return self.plant


@dataclass(frozen=True, eq=False)
class DrakeDynamics:
    """``f`` and ``g`` extracted from a Drake model, and where they came from.

    Built by :func:`extract_drake_system` and :func:`extract_multibody`;
    :meth:`~ofrl_drake.model.ControlAffineSystem.from_drake` and
    :meth:`~ofrl_drake.model.ControlAffineSystem.from_multibody` turn it into a
    :class:`~ofrl_drake.model.ControlAffineSystem` with an output matrix.

    Attributes
    ----------
    name : str
        The model's name (given, or the system's name, class or file stem).
    f : ExpressionFunction
        Drift, shape ``(n,)``, in the state variables.
    g : ExpressionFunction
        Input matrix, shape ``(n, m)``, in the same variables (no ``u``).
    source : DrakeSystemSource or MultibodySource
        The Drake model the equations came from.
    default_C : ndarray of shape (q, n), or None
        The output matrix used when none is given: the positions ``y = q`` of a
        multibody plant; None for a Drake system (``C`` is then required).
    state_units, input_units : tuple of str, or None
        The units of ``x`` and ``u`` where the model knows them (a multibody
        plant's joint types); None otherwise.
    """

    name: str
    f: ExpressionFunction
    g: ExpressionFunction
    source: DrakeSystemSource | MultibodySource
    default_C: np.ndarray | None = None
    state_units: tuple[str, ...] | None = None
    input_units: tuple[str, ...] | None = None

    @property
    def n(self) -> int:
        """Number of states."""
        return self.f.shape[0]

    @property
    def m(self) -> int:
        """Number of inputs."""
        return self.g.shape[1]


# ------------------------------------------------------------- Drake systems
def _resolve_input_port(system: System, input_port: int | str) -> InputPort:
    names = input_port_names(system)
    if not names:
        raise ModelError(
            f"{system.get_name() or type(system).__name__} has no input port; "
            "from_drake needs a vector input u."
        )
    if isinstance(input_port, str):
        if not system.HasInputPort(input_port):
            raise ModelError(
                f"input_port {input_port!r} is not an input port of the system; "
                f"choose one of {names}."
            )
        port = system.GetInputPort(input_port)
    else:
        if int(input_port) != input_port or not 0 <= input_port < len(names):
            raise ModelError(
                f"input_port {input_port!r} is out of range; the system has input "
                f"ports {names} (index 0..{len(names) - 1}, or give the name)."
            )
        port = system.get_input_port(int(input_port))
    if port.get_data_type() != PortDataType.kVectorValued:
        raise ModelError(
            f"input_port {port.get_name()!r} is abstract-valued; u must be a vector port."
        )
    return port


def _system_label(system: System) -> str:
    return system.get_name() or type(system).__name__


def _check_points(label: str, check_points: int) -> None:
    """The numerical checks need at least one point; with none they would pass unseen."""
    integral = isinstance(check_points, int | np.integer) and not isinstance(check_points, bool)
    if not integral or check_points < 1:
        raise ModelError(
            f"{label}: check_points must be a positive integer; got {check_points!r} "
            f"(the default is {AFFINITY_POINTS})."
        )


def extract_drake_system(
    system: System,
    input_port: int | str = 0,
    *,
    name: str | None = None,
    check_points: int = AFFINITY_POINTS,
    seed: int = 0,
) -> DrakeDynamics:
    """Control-affine dynamics of a Drake system, extracted symbolically.

    The system is converted with ``ToSymbolic()``; its default context (so
    its default parameters) gets symbolic state ``x``, input ``u`` and time
    ``t``, every other vector input port is held at zero, and
    ``EvalTimeDerivatives`` gives ``xdot(x, u)``. Then
    ``f(x) = xdot(x, 0)`` and ``g(x) = d xdot / d u`` at ``u = 0``.

    The dynamics are affine in ``u`` exactly when ``d xdot / d u`` does not
    depend on ``u``; which variables an expression names is not enough (Drake
    leaves terms such as ``u * (0 / d(x))`` in the derivative of a solved mass
    matrix, as in ``AcrobotPlant`` and ``QuadrotorPlant``). Each entry of
    ``d xdot / d u`` that names ``u`` is decided

    1. symbolically: expanded (``Expression.Expand``, for entries of at most
       :data:`EXPAND_MAX_CHARS` printed characters), it is affine if ``u``
       cancels;
    2. otherwise numerically: at ``check_points`` (default
       :data:`AFFINITY_POINTS` = 20) random ``(x, u)``, standard normal and
       seeded with ``seed``, the entry at ``u`` must equal the entry at
       ``u = 0`` to ``|a - b| <= rtol (1 + |b|)`` with ``rtol =``
       :data:`AFFINITY_RTOL` (1e-8).

    Finally ``f(x) + g(x) u`` is compared with the system's own
    double-precision ``EvalTimeDerivatives`` at the same ``(x, u)`` and
    tolerance (which catches a system whose symbolic and double paths differ);
    a point where ``EvalTimeDerivatives`` raises a ``RuntimeError`` (such as
    the gimbal-lock guard of ``QuadrotorPlant``'s roll-pitch-yaw angles) is
    left out of this comparison.

    Parameters
    ----------
    system : pydrake.systems.framework.System
        One continuous state vector (no discrete or abstract state), a vector
        input, and support for the symbolic scalar type; for example
        ``pydrake.examples.PendulumPlant()``.
    input_port : int or str
        The input port that is ``u``, by index or name.
    name : str, optional
        The model's name; defaults to the system's name or class name.
    check_points : int
        Random points of the numerical checks (at least 1).
    seed : int
        Seed of those points.

    Returns
    -------
    DrakeDynamics
        With ``source`` a :class:`DrakeSystemSource` and no ``default_C``.

    Raises
    ------
    ModelError
        If ``check_points`` is not a positive integer or ``seed`` not an
        integer >= 0, the system does not support symbolic scalars, has other
        kinds of state, time-varying dynamics, no such vector input port (in
        the system, or by name in its ``ToSymbolic()`` version), or
        dynamics that are not affine in ``u`` (the message names the state
        rows, the tolerance and the number of points).
    """
    if not isinstance(system, System):
        if isinstance(system, type) and issubclass(system, System):
            raise ModelError(
                f"from_drake needs a Drake System; got the class {system.__name__}: pass an "
                f"instance, {system.__name__}(...)."
            )
        raise ModelError(f"from_drake needs a Drake System; got {type(system).__name__}.")
    label = name or _system_label(system)
    _check_points(label, check_points)
    integer_at_least(f"{label}: seed", seed)
    try:
        symbolic = system.ToSymbolic()
    except Exception as err:
        raise ModelError(
            f"{label}: the system does not support the symbolic scalar type "
            f"({type(err).__name__}: {str(err).splitlines()[0]}); from_drake needs "
            "ToSymbolic(). Write f and g in numpy and use ControlAffineSystem(f, g, C) "
            "instead."
        ) from err
    port = _resolve_input_port(system, input_port)
    context = symbolic.CreateDefaultContext()
    n = context.num_continuous_states()
    if n == 0 or context.num_discrete_state_groups() or context.num_abstract_states():
        raise ModelError(
            f"{label}: from_drake needs exactly one continuous state vector and no "
            f"discrete or abstract state; the system has {n} continuous states, "
            f"{context.num_discrete_state_groups()} discrete groups and "
            f"{context.num_abstract_states()} abstract states."
        )
    m = port.size()
    x = MakeVectorVariable(n, "x")
    u = MakeVectorVariable(m, "u")
    t = Variable("t")
    context.SetTime(Expression(t))
    context.SetContinuousState([Expression(v) for v in x])  # type: ignore[arg-type]  # pydrake array stub
    # By name: the converted system need not declare its ports in the same order.
    if not symbolic.HasInputPort(port.get_name()):
        converted = input_port_names(symbolic)
        raise ModelError(
            f"{label}: the system's symbolic version (ToSymbolic()) has no input port "
            f"{port.get_name()!r}, only {converted}; its scalar conversion must keep the "
            "names of the input ports."
        )
    sym_port = symbolic.GetInputPort(port.get_name())
    sym_port.FixValue(context, [Expression(v) for v in u])
    fixed: dict[str, np.ndarray] = {}
    for i in range(symbolic.num_input_ports()):
        other = symbolic.get_input_port(i)
        if other.get_name() == port.get_name() or (
            other.get_data_type() != PortDataType.kVectorValued
        ):
            continue
        fixed[other.get_name()] = np.zeros(other.size())
        other.FixValue(context, np.zeros(other.size()))
    try:
        xdot = np.asarray(symbolic.EvalTimeDerivatives(context).CopyToVector(), dtype=object)
    except Exception as err:
        raise ModelError(
            f"{label}: symbolic EvalTimeDerivatives failed ({type(err).__name__}: "
            f"{str(err).splitlines()[0]}); the system must compute its derivatives "
            "from the state and the vector inputs with symbolic scalars."
        ) from err
    xdot = np.array([Expression(e) if not isinstance(e, Expression) else e for e in xdot])
    timed = [i for i, e in enumerate(xdot) if e.GetVariables().include(t)]
    if timed:
        raise ModelError(
            f"{label}: the dynamics depend on time in state rows {timed}; ofrl_drake "
            "needs a time-invariant plant x' = f(x) + g(x) u."
        )
    try:
        B = Jacobian(xdot, list(u))  # type: ignore[call-overload]  # pydrake array stub
    except RuntimeError as err:
        raise ModelError(
            f"{label}: d xdot / d u cannot be taken symbolically ({err}); the "
            "dynamics must be differentiable in u (and affine: x' = f(x) + g(x) u)."
        ) from err
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, check_points))
    U = rng.standard_normal((m, check_points))
    zero_u = {v: Expression(0.0) for v in u}
    g_expr = _input_matrix(label, B, x, u, zero_u, X, U)
    f_expr = np.array([e.Substitute(zero_u) for e in xdot], dtype=object)
    f = ExpressionFunction(f_expr, x)
    g = ExpressionFunction(g_expr, x)
    source = DrakeSystemSource(system, port.get_name(), fixed, n)
    _check_against_double(label, system, port, fixed, f, g, X, U)
    return DrakeDynamics(label, f, g, source)


def _names_any(expression: Expression, variables: Collection[Variable]) -> bool:
    names = expression.GetVariables()
    return any(names.include(v) for v in variables)


def _input_matrix(
    label: str,
    B: np.ndarray,
    x: Collection[Variable],
    u: Collection[Variable],
    zero_u: dict[Variable, Expression],
    X: np.ndarray,
    U: np.ndarray,
) -> np.ndarray:
    """``g(x)``: ``B = d xdot / d u`` at ``u = 0``, once ``B`` is shown not to depend on ``u``.

    Entries that name ``u`` are expanded (if at most :data:`EXPAND_MAX_CHARS`
    long) and, if ``u`` does not cancel, compared at ``u = 0`` and ``u = U[:, k]``
    for each column of ``X``; entries that do not name ``u`` are kept as they are.
    """
    g_expr = np.array(B, dtype=object)
    undecided: list[tuple[int, int]] = []
    for (i, k), entry in np.ndenumerate(B):
        if not _names_any(entry, u):
            continue
        if len(entry.to_string()) <= EXPAND_MAX_CHARS and not _names_any(entry.Expand(), u):
            g_expr[i, k] = entry.Substitute(zero_u)
        else:
            undecided.append((i, k))
    bad: dict[int, str] = {}
    points = X.shape[1]
    for i, k in undecided:
        entry = B[i, k]
        for p in range(points):
            env = {v: float(value) for v, value in zip(x, X[:, p], strict=True)}
            at_zero = entry.Evaluate({**env, **{v: 0.0 for v in u}})
            at_u = entry.Evaluate({**env, **{v: float(w) for v, w in zip(u, U[:, p], strict=True)}})
            same = (
                at_u == at_zero
                or abs(at_u - at_zero) <= AFFINITY_RTOL * (1.0 + abs(at_zero))
                or (np.isnan(at_u) and np.isnan(at_zero))
            )
            if not same:
                bad.setdefault(
                    i,
                    f"d xdot[{i}] / d u[{k}] = {entry} is {at_zero:.6g} at u = 0 but "
                    f"{at_u:.6g} at u = {U[:, p].tolist()} (x = {X[:, p].tolist()})",
                )
                break
        else:
            g_expr[i, k] = entry.Substitute(zero_u)
    if bad:
        rows = sorted(bad)
        raise ModelError(
            f"{label}: the dynamics are not affine in u: d xdot / d u depends on u in "
            f"state rows {rows} (e.g. {bad[rows[0]]}; compared at u = 0 and at u for "
            f"{points} random (x, u), standard normal, to a relative {AFFINITY_RTOL:g}); "
            "ofrl_drake needs x' = f(x) + g(x) u."
        )
    return g_expr


def _check_against_double(
    label: str,
    system: System,
    port: InputPort,
    fixed: dict[str, np.ndarray],
    f: ExpressionFunction,
    g: ExpressionFunction,
    X: np.ndarray,
    U: np.ndarray,
) -> None:
    """Compare f + g u with the double system's derivatives at the columns of X, U.

    Points where the double system raises are skipped; all of them raising is an error.
    """
    points = X.shape[1]
    context = system.CreateDefaultContext()
    for name, value in fixed.items():
        system.GetInputPort(name).FixValue(context, value)
    fX, gX = f(X), g(X)
    bad_rows: set[int] = set()
    worst: tuple[float, int, int | None] = (0.0, -1, None)
    refused: list[tuple[int, Exception]] = []
    for k in range(points):
        context.SetContinuousState(X[:, k])  # type: ignore[arg-type]  # pydrake array stub
        port.FixValue(context, U[:, k])
        try:
            xdot = system.EvalTimeDerivatives(context).CopyToVector()
        except RuntimeError as err:  # e.g. the gimbal-lock guard of roll-pitch-yaw
            refused.append((k, err))
            continue
        model = fX[:, k] + gX[:, :, k] @ U[:, k]
        gap = np.abs(xdot - model)
        rows = np.flatnonzero(~(gap <= AFFINITY_RTOL * (1.0 + np.abs(xdot))))
        bad_rows.update(int(i) for i in rows)
        gap = np.where(np.isnan(gap), np.inf, gap)  # a NaN row is the worst
        if rows.size and (worst[1] < 0 or gap[rows].max() > worst[0]):
            worst = (float(gap[rows].max()), k, int(rows[np.argmax(gap[rows])]))
    if refused and len(refused) == points:
        k, first = refused[0]
        raise ModelError(
            f"{label}: the system's own EvalTimeDerivatives failed at all {points} random "
            f"(x, u) of the check (e.g. at x = {X[:, k].tolist()}: "
            f"{str(first).splitlines()[0]}); it must evaluate at standard normal states."
        )
    if bad_rows:
        _, k, row = worst
        raise ModelError(
            f"{label}: the dynamics are not affine in u: xdot differs from "
            f"f(x) + g(x) u in state rows {sorted(bad_rows)} (row {row} by {worst[0]:.3g} "
            f"at x = {X[:, k].tolist()}, u = {U[:, k].tolist()}; compared at {points} "
            f"random (x, u) to a relative {AFFINITY_RTOL:g}); ofrl_drake needs "
            "x' = f(x) + g(x) u."
        )


# ---------------------------------------------------------- multibody models
def _load_plant(model: Any) -> tuple[Any, str | None, str]:
    """The finalized double plant, the model path/URL (or None) and a name."""
    from pathlib import Path

    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    if isinstance(model, MultibodyPlant):
        if not model.is_finalized():
            raise ModelError(
                "from_multibody: the MultibodyPlant is not finalized; call plant.Finalize() first."
            )
        return model, None, model.get_name() or "multibody_plant"
    if not isinstance(model, str | Path):
        raise ModelError(
            f"from_multibody: model must be a file path, a package:// URL or a "
            f"MultibodyPlant; got {type(model).__name__}."
        )
    text = str(model)
    plant = MultibodyPlant(time_step=0.0)
    parser = Parser(plant)
    try:
        if "://" in text:
            parser.AddModels(url=text)  # type: ignore[call-arg]  # pydrake stub lacks url=
        else:
            if not Path(text).is_file():  # a stat, not an open: a FIFO would block
                what = (
                    "is a directory, not a model file"
                    if Path(text).is_dir()
                    else "is not a regular file"
                    if Path(text).exists()
                    else "does not exist"
                )
                raise ModelError(
                    f"from_multibody: model file {text!r} {what}; give an SDF, URDF or MJCF "
                    "file or a package:// URL."
                )
            parser.AddModels(file_name=Path(text))
        plant.Finalize()
    except ModelError:
        raise
    except Exception as err:
        raise ModelError(
            f"from_multibody: cannot load {text!r}: {str(err).splitlines()[0]}"
        ) from err
    stem = text.rstrip("/").rsplit("/", 1)[-1].split(".", 1)[0]
    return plant, text, stem or "multibody_plant"


def _solve_spd(M: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``M^-1 R`` for a symbolic symmetric positive definite ``M`` (LDL^T, no pivoting).

    A mass matrix has positive pivots everywhere, so no pivoting is needed and
    the result is one expression per entry, without square roots.
    """
    k = M.shape[0]
    L = np.empty((k, k), dtype=object)
    D = np.empty(k, dtype=object)
    for j in range(k):
        D[j] = M[j, j] - sum((L[j, i] * L[j, i] * D[i] for i in range(j)), Expression(0.0))
        for r in range(j + 1, k):
            s = M[r, j] - sum((L[r, i] * L[j, i] * D[i] for i in range(j)), Expression(0.0))
            L[r, j] = s / D[j]
    Y = np.empty(R.shape, dtype=object)
    for r in range(k):
        Y[r] = R[r] - sum((L[r, i] * Y[i] for i in range(r)), Expression(0.0) * R[r])
    X = np.empty(R.shape, dtype=object)
    for r in reversed(range(k)):
        X[r] = Y[r] / D[r] - sum((L[i, r] * X[i] for i in range(r + 1, k)), Expression(0.0) * R[r])
    return X


def extract_multibody(
    model: Any,
    *,
    name: str | None = None,
    check_points: int = AFFINITY_POINTS,
    seed: int = 0,
) -> DrakeDynamics:
    """Control-affine dynamics of a continuous multibody plant.

    With state ``x = [q; v]`` and input ``u`` the actuation,

        f(x) = [N(q) v; M(q)^-1 (tau_app(q, v) - C(q, v) v)],
        g(x) = [0; M(q)^-1 B],

    where ``N`` is ``MapVelocityToQDot`` (the identity for revolute and
    prismatic joints), ``M`` is ``CalcMassMatrix``, ``C(q, v) v`` is
    ``CalcBiasTerm``, ``B`` is ``MakeActuationMatrix`` and ``tau_app`` is every
    force the plant's force elements apply: gravity
    (``CalcGravityGeneralizedForces``) plus the generalized forces of
    ``CalcForceElementsContribution`` (joint damping) when gravity is the only
    force element; otherwise ``-CalcInverseDynamics`` at zero acceleration
    with all the force elements' forces (which covers body forces such as
    springs between bodies). ``M^-1`` is applied by a symbolic ``LDL^T`` solve.

    Not modelled: contact forces, effort limits (a plant with finite effort
    limits is refused: Drake clamps the actuation to them) and any force
    Drake applies outside position limits: the model holds inside them.
    The equations are compared with the plant's own double-precision
    ``EvalTimeDerivatives`` at ``check_points`` random ``(x, u)`` to a
    relative :data:`AFFINITY_RTOL`.

    Parameters
    ----------
    model : str, pathlib.Path or MultibodyPlant
        An SDF/URDF/MJCF file, a ``package://`` URL (parsed into a continuous
        plant without geometry), or a finalized continuous plant.
    name : str, optional
        Defaults to the file's stem or the plant's name.
    check_points : int
        Random points of the check against ``EvalTimeDerivatives``.
    seed : int
        Their seed.

    Returns
    -------
    DrakeDynamics
        With ``source`` a :class:`MultibodySource` and ``default_C`` measuring
        the positions, ``[I 0]`` of shape ``(nq, nq + nv)``.

    Raises
    ------
    ModelError
        If ``check_points`` is not a positive integer or ``seed`` not an
        integer >= 0, the model file does not exist or is a directory (or
        another kind of non-regular file, named as such), the model cannot be
        loaded, the plant is discrete or not finalized, has quaternion
        (floating) joints, effort limits, no actuators, or the equations
        disagree with ``EvalTimeDerivatives``.
    """
    plant, path, stem = _load_plant(model)
    label = name or stem
    _check_points(label, check_points)
    integer_at_least(f"{label}: seed", seed)
    if plant.time_step() != 0.0:
        raise ModelError(
            f"{label}: the plant is discrete (time_step = {plant.time_step()}); "
            "from_multibody needs a continuous plant, MultibodyPlant(time_step=0)."
        )
    nq, nv, nu = plant.num_positions(), plant.num_velocities(), plant.num_actuators()
    if nq != nv:
        raise ModelError(
            f"{label}: the plant has {nq} positions but {nv} velocities (a quaternion "
            "floating body or ball joint); from_multibody needs qdot = N(q) v with as "
            "many positions as velocities: weld the floating body or use RPY joints."
        )
    if nu == 0:
        raise ModelError(f"{label}: the plant has no actuators, so no input u.")
    finite = np.flatnonzero(
        np.isfinite(plant.GetEffortLowerLimits()) | np.isfinite(plant.GetEffortUpperLimits())
    )
    if finite.size:
        raise ModelError(
            f"{label}: the plant has finite effort limits (actuator {int(finite[0])}); the "
            "saturation they imply is not control-affine. Remove them from the model and "
            "bound the input with the scenario's input_bound instead."
        )
    # numpy's object loops flag "invalid value" on Drake expressions; harmless.
    with np.errstate(invalid="ignore"):
        f, g = _multibody_equations(plant, nq, nv, nu)
    source = MultibodySource(
        plant,
        path,
        tuple(plant.GetPositionNames(False)),
        tuple(plant.GetVelocityNames(False)),
        tuple(plant.GetActuatorNames(False)),
        multibody_structure(plant),
    )
    _check_multibody(label, plant, f, g, nq + nv, nu, check_points, seed)
    positions = np.hstack([np.eye(nq), np.zeros((nq, nv))])
    state_units, input_units = _multibody_units(plant)
    return DrakeDynamics(label, f, g, source, positions, state_units, input_units)


#: Units of a joint's positions by its Drake type name; velocities add "/s".
_JOINT_UNITS = {"revolute": ("rad",), "prismatic": ("m",), "planar": ("m", "m", "rad")}
#: Units of an actuator's effort by the type of the joint it drives.
_EFFORT_UNITS = {"revolute": "N·m", "prismatic": "N"}


def _multibody_units(plant: Any) -> tuple[tuple[str, ...] | None, tuple[str, ...] | None]:
    """The units of ``x = [q; v]`` and of ``u`` from the joint types, or None if unknown."""
    from pydrake.multibody.tree import JointActuatorIndex, JointIndex

    positions: list[str | None] = [None] * plant.num_positions()
    velocities: list[str | None] = [None] * plant.num_velocities()
    for i in range(plant.num_joints()):
        joint = plant.get_joint(JointIndex(i))
        kinds = _JOINT_UNITS.get(joint.type_name())
        if kinds is not None and len(kinds) == joint.num_positions() == joint.num_velocities():
            start = joint.position_start()
            positions[start : start + len(kinds)] = kinds
            start = joint.velocity_start()
            velocities[start : start + len(kinds)] = [f"{u}/s" for u in kinds]
    efforts = [
        _EFFORT_UNITS.get(plant.get_joint_actuator(JointActuatorIndex(k)).joint().type_name())
        for k in range(plant.num_actuators())
    ]
    return _known(positions + velocities), _known(efforts)


def _known(units: list[str | None]) -> tuple[str, ...] | None:
    """``units`` as a tuple, or None if one of them is unknown (None)."""
    known = tuple(unit for unit in units if unit is not None)
    return known if len(known) == len(units) else None


def _multibody_equations(
    plant: Any, nq: int, nv: int, nu: int
) -> tuple[ExpressionFunction, ExpressionFunction]:
    """``f`` and ``g`` of :func:`extract_multibody` from the symbolic plant."""
    symbolic, context, q, v, qdot, forces = _symbolic_state(plant)
    M = np.asarray(symbolic.CalcMassMatrix(context))
    if plant.num_force_elements() == 1:  # the gravity field only
        tau = (
            np.asarray(symbolic.CalcGravityGeneralizedForces(context))
            + np.asarray(forces.generalized_forces())
            - np.asarray(symbolic.CalcBiasTerm(context))
        )
    else:
        zero = [Expression(0.0)] * nv
        tau = -np.asarray(symbolic.CalcInverseDynamics(context, zero, forces))
    B = np.asarray(plant.MakeActuationMatrix(), dtype=float)
    rhs = np.concatenate([tau.reshape(nv, 1), B.astype(object) + Expression(0.0)], axis=1)
    solved = _solve_spd(M, rhs)
    f_expr = np.concatenate([qdot, solved[:, 0]])
    g_expr = np.concatenate([np.full((nq, nu), Expression(0.0), dtype=object), solved[:, 1:]])
    x = np.concatenate([q, v])
    return ExpressionFunction(f_expr, x), ExpressionFunction(g_expr, x)


def _check_multibody(
    label: str,
    plant: Any,
    f: ExpressionFunction,
    g: ExpressionFunction,
    n: int,
    m: int,
    points: int,
    seed: int,
) -> None:
    context = plant.CreateDefaultContext()
    port = plant.get_actuation_input_port()
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, points))
    U = rng.standard_normal((m, points))
    # Inside the position limits, where the limits' penalty forces vanish.
    lo, hi = plant.GetPositionLowerLimits(), plant.GetPositionUpperLimits()
    both = np.isfinite(lo) & np.isfinite(hi)
    nq = lo.size
    X[:nq][both] = lo[both, None] + rng.random((int(both.sum()), points)) * (hi - lo)[both, None]
    X[:nq] = np.clip(X[:nq], lo[:, None], hi[:, None])
    fX, gX = f(X), g(X)
    for k in range(points):
        plant.SetPositionsAndVelocities(context, X[:, k])
        port.FixValue(context, U[:, k])
        xdot = plant.EvalTimeDerivatives(context).CopyToVector()
        err = np.abs(xdot - (fX[:, k] + gX[:, :, k] @ U[:, k]))
        rows = np.flatnonzero(~(err <= AFFINITY_RTOL * (1.0 + np.abs(xdot))))
        if rows.size:
            raise ModelError(
                f"{label}: the assembled equations differ from the plant's "
                f"EvalTimeDerivatives in state rows {rows.tolist()} (by up to "
                f"{err[rows].max():.3g} at x = {X[:, k].tolist()}, u = {U[:, k].tolist()}); "
                "the plant applies a force from_multibody does not model (contact?)."
            )
