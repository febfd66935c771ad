"""The optimal-control yardstick ``J*`` for one initial state.

For an initial state ``x0`` the closed loop's cost ``J = int_0^T Q(x) + U(u) dt``
is compared with the smallest cost any input with ``|u_k| <= lambda_bar`` can
reach over the same horizon ``T``:

    J* = min_u  int_0^T Q(x) + U(u) dt,   x' = f(x) + g(x) u,  x(0) = x0.

It is solved by direct collocation (Drake's ``DirectCollocation``: cubic
Hermite states, first-order-hold inputs, collocation at interval midpoints) with
SNOPT, which the Drake wheel ships. IPOPT is the fallback when SNOPT is not
available, but Drake gives IPOPT no Hessian and its quasi-Newton iterations
stall on this problem.

Two choices make the numbers accurate and the problem well posed:

* **The input bound.** ``U(u)`` contains ``atanh(u_k / lambda_bar)``: its value
  is finite at the bound (``U -> r lambda_bar^2 2 ln 2``) but its derivative is
  not, and ``atanh(1)`` itself is infinite. The collocation therefore bounds
  ``|u_k| <= lambda_bar (1 - input_margin)`` with ``input_margin = 1e-6``, where
  ``U`` and its gradient are finite (``atanh(1 - 1e-6) = 7.25``). The stage cost
  is continuous at the bound, so excluding the last ``1e-6`` of the input range
  changes ``J*`` by a negligible amount. (The tempting alternative, ``u =
  lambda_bar tanh(v)`` with a free ``v``, was tried and rejected: where ``tanh``
  saturates the gradient in ``v`` vanishes, and SNOPT stopped there, at costs
  up to 8 % above the optimum.) ``atanh(s)`` is written ``(1/2) ln((1 + s) /
  (1 - s))`` since Drake's symbolic library has no ``atanh``.
* **The cost integral.** ``J`` is appended as a state, ``J' = Q(x) + U(u)``,
  ``J(0) = 0``, and the final cost is ``J(T)``. The cost is then integrated
  by the same Hermite-Simpson collocation as the dynamics, not by a separate
  trapezoid rule.

The time grid is fixed (not optimized, so the solver cannot exploit the
discretization error): steps start at ``Mesh.initial_step`` and grow
geometrically by ``Mesh.growth`` up to ``Mesh.max_step``, fine where the
trajectory moves and coarse where it has settled. A grid is only as good as
the plant is slow, so every ``J*`` is checked against its grid: it is solved
again on a grid twice as fine (warm-started from the last), until two grids
in a row agree to ``Mesh.rtol``, and the finer one's ``J*`` is the result. On
the paper's example (``x0 = (-1, 1)``, ``T = 30`` s) the default grid has 108
intervals and gives ``3.751106``, the check 216 intervals and ``3.751103``
(moved by 9e-7); on an oscillator at 20 rad/s the first grid alone
overstates ``J*`` by 2 %, and the check settles two grids later.

A run that does not converge is reported with its solver status and a NaN
cost, never a made-up number; so is a solve whose iterates leave the domain
of ``f`` or ``g`` (``sqrt`` of a negative number...), with that domain error
in its status. The solver is warm-started from a closed-loop
trajectory when one is given (the learned controller's, in
:func:`ofrl_drake.ablation.ablate`); if that fails, it is retried from default
guesses (``x`` decaying to zero with time constants 1, 0.5 and 2 s, ``u = 0``),
since SNOPT occasionally stops on numerical difficulties from one guess and
converges from another.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import reprlib
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from pydrake.planning import DirectCollocation
from pydrake.solvers import IpoptSolver, SnoptSolver, SolverOptions
from pydrake.symbolic import Expression, MakeVectorVariable, if_then_else, log
from pydrake.systems.primitives import SymbolicVectorSystem
from pydrake.trajectories import PiecewisePolynomial

from ofrl_drake.atomic import atomic_file
from ofrl_drake.checks import (
    deadline_or_none,
    is_real_number,
    nonnegative_matrix,
    number_to_json,
    positive_number,
    positive_vector,
)
from ofrl_drake.errors import (
    ModelError,
    OfrlError,
    WallTimeExceeded,
    is_domain_error,
    one_line,
)
from ofrl_drake.model import ControlAffineSystem, SymbolicDynamics
from ofrl_drake.plants import resolve_system
from ofrl_drake.scenario import Scenario, validate_scenario

__all__ = [
    "SERIES_BELOW",
    "SMALL_COST",
    "SOLVERS",
    "Mesh",
    "OptimalControlResult",
    "OptimalCostCache",
    "Trajectory",
    "checked_mesh",
    "cost_augmented_plant",
    "optimal_control",
    "problem_key",
    "require_traceable",
    "saturation_cost",
    "solve_optimal_control",
    "solver_name",
    "solving",
]

#: Nonlinear-programming solvers tried, by name.
SOLVERS = ("snopt", "ipopt")

#: A ``J*`` below this can be limited by the solver's tolerances rather than by
#: the grid: from the paper's example at ``x0 = (1e-4, 0)`` (``J* = 2.3e-8``)
#: SNOPT's grids solve to values 50 % apart, where IPOPT's settle.
SMALL_COST = 1e-4


@dataclass(frozen=True)
class Mesh:
    """A fixed, geometrically graded time grid for the collocation, and its check.

    ``J*`` is solved on this grid, then again on grids twice as fine (each
    warm-started from the last) until two in a row agree to ``rtol``; the
    finer one's ``J*`` is the result. At most ``refinements`` finer grids are
    solved: if ``J*`` has not settled by then, the result is not converged.

    Attributes
    ----------
    initial_step : float
        Length of the first interval [s].
    growth : float
        Ratio of consecutive intervals (>= 1).
    max_step : float
        Longest interval [s].
    rtol : float
        Accept ``J*`` when it moves by at most ``rtol`` (relative) from the
        grid half as fine.
    refinements : int
        The most grids twice as fine to solve (0: no check, ``J*`` of this
        grid alone).
    """

    initial_step: float = 0.05
    growth: float = 1.03
    max_step: float = 0.5
    rtol: float = 1e-3
    refinements: int = 3

    def __post_init__(self) -> None:
        ok = (
            all(
                is_real_number(v) and math.isfinite(v)
                for v in (self.initial_step, self.growth, self.max_step, self.rtol)
            )
            and self.initial_step > 0
            and self.growth >= 1
            and self.max_step >= self.initial_step
            and self.rtol > 0
            and isinstance(self.refinements, int)
            and not isinstance(self.refinements, bool)
            and 0 <= self.refinements <= 6
        )
        if not ok:
            raise OfrlError(
                "mesh: need initial_step > 0, growth >= 1, max_step >= initial_step and "
                "rtol > 0, all numbers, and refinements an integer from 0 to 6; "
                f"got {self}."
            )

    def steps(self, duration: float) -> np.ndarray:
        """Interval lengths covering ``[0, duration]`` exactly, shape ``(N,)``.

        The geometric sequence is cut where it first reaches ``duration`` and
        then scaled by at most one step's worth to end exactly there.
        """
        if not (math.isfinite(duration) and duration > 0):
            raise OfrlError(f"mesh: the horizon must be a positive number; got {duration!r}.")
        steps, h, total = [], self.initial_step, 0.0
        while total < duration * (1 - 1e-12):
            steps.append(h)
            total += h
            h = min(self.max_step, h * self.growth)
        out = np.asarray(steps, dtype=float)
        return out * (duration / out.sum())

    def refined(self) -> Mesh:
        """The grid twice as fine: steps halved, growth per step its square root."""
        return dataclasses.replace(
            self,
            initial_step=self.initial_step / 2,
            growth=math.sqrt(self.growth),
            max_step=self.max_step / 2,
        )


def checked_mesh(mesh: Any) -> Mesh:
    """``mesh``, or the default :class:`Mesh` for None.

    Raises
    ------
    OfrlError
        If ``mesh`` is neither None nor a :class:`Mesh`.
    """
    if mesh is None:
        return Mesh()
    if not isinstance(mesh, Mesh):
        raise OfrlError(
            f"optimal control: mesh must be a Mesh(initial_step, growth, max_step) or None "
            f"(the default {Mesh()}); got {reprlib.repr(mesh)}."
        )
    return mesh


@dataclass(frozen=True)
class Trajectory:
    """A sampled trajectory: a warm start, or the optimum itself.

    Attributes
    ----------
    t : ndarray, shape (T,)
    x : ndarray, shape (T, n)
    u : ndarray, shape (T, m)
    cost : ndarray, shape (T,)
        Accumulated cost ``int_0^t Q(x) + U(u)``.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    cost: np.ndarray

    @classmethod
    def from_result(cls, result: Any) -> Trajectory:
        """Take ``t, x, u, cost`` from a :class:`~ofrl_drake.SimulationResult`."""
        return cls(
            t=np.asarray(result.t, dtype=float),
            x=np.asarray(result.x, dtype=float),
            u=np.asarray(result.u, dtype=float),
            cost=np.asarray(result.cost, dtype=float),
        )


@dataclass(frozen=True)
class OptimalControlResult:
    """``J*`` for one initial state, or why there is none.

    Attributes
    ----------
    x0 : tuple of float
        The initial state.
    cost : float
        ``J*``; NaN unless :attr:`converged`.
    converged : bool
        True if the solver reported an optimal solution.
    status : str
        ``"ok"`` or the solver's status for every attempt, on one line.
    duration : float
        The horizon T [s].
    solver : str
        Which solver produced the result.
    solve_time : float
        Wall-clock seconds of all attempts.
    warm_started : bool
        True if the solve on the first grid started from the given warm start
        (the finer grids start from the grid before them).
    intervals : int
        The number of intervals of the grid whose ``J*`` was accepted (0 if
        not converged).
    mesh_change : float
        ``|J* - J*_half| / J*``: how far ``J*`` moved from the grid half as
        fine, the check's estimate of the grid's error; for a ``J*`` that did
        not settle, the last grid's change. NaN when ``Mesh.refinements`` is 0,
        when no grid converged, or when a finer grid did not.
    trajectory : Trajectory or None
        The optimal trajectory at the accepted grid's knots (None if not converged).
    """

    x0: tuple[float, ...]
    cost: float
    converged: bool
    status: str
    duration: float
    solver: str
    solve_time: float
    warm_started: bool = False
    intervals: int = 0
    mesh_change: float = math.nan
    trajectory: Trajectory | None = field(default=None, compare=False)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (without the trajectory)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "trajectory"}
        out["x0"] = list(self.x0)
        out["cost"] = number_to_json(self.cost)
        out["mesh_change"] = number_to_json(self.mesh_change)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OptimalControlResult:
        """Inverse of :meth:`to_dict`."""
        cost = data["cost"]
        change = data.get("mesh_change")
        return cls(
            x0=tuple(float(v) for v in data["x0"]),
            cost=float("nan") if cost is None else float(cost),
            converged=bool(data["converged"]),
            status=str(data["status"]),
            duration=float(data["duration"]),
            solver=str(data["solver"]),
            solve_time=float(data["solve_time"]),
            warm_started=bool(data.get("warm_started", False)),
            intervals=int(data.get("intervals", 0)),
            mesh_change=math.nan if change is None else float(change),
        )


#: Below this ``s^2``, :func:`saturation_cost` is its Taylor series: ``|s| < 0.088``.
#: Drake differentiates the switch as NaN where ``s^2`` equals it exactly, which
#: no double ``s`` near 2^-3.5 makes likely (0.01 would be ``u = lbar / 10``).
SERIES_BELOW = 2.0**-7

#: The series' coefficients ``1 / ((2k - 1) 2k)``, k = 1 ... 8.
_SERIES = tuple(1.0 / ((2 * k - 1) * (2 * k)) for k in range(1, 9))


def saturation_cost(s: Expression) -> Expression:
    """``s atanh(s) + (1/2) ln(1 - s^2)``, accurate to round-off for every ``|s| < 1``.

    It is ``U(u) / (2 r lbar^2)`` at ``s = u / lbar``, and equals
    ``sum_k s^(2k) / ((2k - 1) 2k)``. The closed form cancels for small ``s``
    (``ln(1 - s^2)`` loses ``s^2``'s low digits): with ``lbar = 1e6`` and
    ``u`` near 1 it made ``U`` a staircase that SNOPT could not solve. Below
    ``s^2 =`` :data:`SERIES_BELOW` the series' first eight terms are used
    (the rest is below 1e-18 of the sum); Drake's expressions have no
    ``log1p``.
    """
    s2 = s * s
    series = Expression(_SERIES[-1])
    for c in reversed(_SERIES[:-1]):
        series = c + s2 * series
    closed = 0.5 * s * log((1.0 + s) / (1.0 - s)) + 0.5 * log(1.0 - s2)
    return if_then_else(s2 < SERIES_BELOW, s2 * series, closed)


def cost_augmented_plant(
    system: ControlAffineSystem, Q: np.ndarray, r: np.ndarray, input_bound: float
) -> SymbolicVectorSystem:
    """The plant with the running cost appended as a state.

    State ``(x, J)``, input ``u`` (size m)::

        x' = f(x) + g(x) u
        J' = x^T Q x + sum_k 2 r_k lbar (u_k atanh(u_k / lbar)
                                         + (lbar / 2) ln(1 - u_k^2 / lbar^2))

    defined for ``|u_k| < lbar`` (``atanh(s) = (1/2) ln((1 + s) / (1 - s))``),
    written as :func:`saturation_cost` of ``u_k / lbar``.

    Raises
    ------
    ModelError
        If Drake cannot trace ``f`` or ``g`` on symbolic states (they branch on
        the state, call scipy...): ``J*`` needs them symbolic.
    """
    dynamics = _traced(system)
    m = system.m
    Q = np.asarray(Q, dtype=float)
    r = np.asarray(r, dtype=float)
    x = dynamics.x
    J = MakeVectorVariable(1, "J")
    u = MakeVectorVariable(m, "u")
    # numpy's object loops flag "invalid value" on Drake symbolic values; harmless.
    with np.errstate(invalid="ignore"):
        xdot = dynamics.f + dynamics.g @ u
        running = x @ Q @ x
    for k in range(m):
        running += 2.0 * r[k] * input_bound**2 * saturation_cost(u[k] / input_bound)
    return SymbolicVectorSystem(
        state=np.concatenate([x, J]), input=u, dynamics=np.concatenate([xdot, [running]])
    )


def require_traceable(system: ControlAffineSystem) -> None:
    """Refuse a system whose ``f`` and ``g`` Drake cannot trace: ``J*`` needs them.

    For a command that solves ``J*`` after other work, to refuse before it.

    Raises
    ------
    ModelError
        If Drake cannot trace ``f`` or ``g`` on symbolic states.
    """
    _traced(system)


def _traced(system: ControlAffineSystem) -> SymbolicDynamics:
    """``f`` and ``g`` traced by Drake; refused if they cannot be: the collocation needs them."""
    try:
        return system.symbolic()
    except ModelError as err:
        cause = err.__cause__ or err
        text = one_line(cause, 200)
        raise ModelError(
            f"optimal control: J* (run --optimal, montecarlo, ablate) needs f and g that Drake "
            f"can trace on symbolic states, and those of the model {system.name!r} cannot be "
            f"({type(cause).__name__}: {text}). Write f and g with numpy functions (np.cos, "
            "np.exp, **) and no branches on the state; without them J* is not available."
        ) from err


def _domain_failure(err: RuntimeError | ValueError) -> str | None:
    """Why a solve stopped, if ``err`` is ``f`` or ``g`` evaluated outside its domain; else None.

    IPOPT passes on the ``ValueError`` of Drake's symbolic math (``sqrt(-0.01)``,
    ``log(-1)``); SNOPT wraps its message in a ``RuntimeError``.
    """
    if not is_domain_error(err):
        return None
    text = one_line(err)
    quoted = re.search(r"'(.*)'", text)  # SNOPT quotes the math error inside its own
    cause = quoted.group(1).strip() if quoted else text
    return f"f or g evaluated outside its domain ({cause[:200]})"


def _solver(name: str | None) -> Any:
    if name is None:
        name = "snopt" if SnoptSolver().available() and SnoptSolver().enabled() else "ipopt"
    makers = {"snopt": SnoptSolver, "ipopt": IpoptSolver}
    if not isinstance(name, str) or name not in makers:
        raise OfrlError(
            f"optimal control: solver must be one of {SOLVERS}; got {reprlib.repr(name)}."
        )
    solver = makers[name]()
    if not (solver.available() and solver.enabled()):
        raise OfrlError(f"optimal control: solver {name!r} is not available in this Drake.")
    return name, solver


def solving(mesh: Mesh | None, solver: str | None) -> dict[str, Any]:
    """How ``J*`` is solved, as a sweep's plan records it: the mesh and the solver's name.

    Raises
    ------
    OfrlError
        If ``mesh`` is not a :class:`Mesh` or ``solver`` not an available solver.
    """
    return {"mesh": asdict(checked_mesh(mesh)), "solver": solver_name(solver)}


def solver_name(solver: str | None) -> str:
    """The solver ``solver`` names (None: SNOPT if available, else IPOPT).

    Raises
    ------
    OfrlError
        If ``solver`` is not one of :data:`SOLVERS` or is not available in this Drake.
    """
    name: str = _solver(solver)[0]
    return name


def _check_warm_start(warm_start: Any, n: int, m: int) -> None:
    """Refuse a warm start that is not a :class:`Trajectory` of ``n`` states and ``m`` inputs."""
    if warm_start is None:
        return
    if not isinstance(warm_start, Trajectory):
        raise OfrlError(
            "optimal control: warm_start must be a Trajectory (e.g. "
            f"Trajectory.from_result(simulate(...))) or None; got {reprlib.repr(warm_start)}."
        )
    try:
        t, x, u, cost = (
            np.asarray(getattr(warm_start, k), dtype=float) for k in ("t", "x", "u", "cost")
        )
    except (TypeError, ValueError):
        raise OfrlError(
            "optimal control: warm_start must hold numeric arrays t, x, u and cost; got "
            f"{reprlib.repr(warm_start)}."
        ) from None
    T = t.shape[0] if t.ndim == 1 else -1
    ok = T >= 2 and x.shape == (T, n) and (u.size == 0 or u.shape == (T, m)) and cost.shape == (T,)
    if not ok:
        raise OfrlError(
            f"optimal control: warm_start must have t of shape (T,) with T >= 2, x (T, {n}), "
            f"u (T, {m}) and cost (T,); got t {t.shape}, x {x.shape}, u {u.shape}, "
            f"cost {cost.shape}."
        )


def _default_guess(x0: np.ndarray, duration: float, time_constant: float) -> Trajectory:
    """x decaying from x0 with the given time constant, u = 0."""
    t = np.linspace(0.0, duration, 200)
    x = np.exp(-t / time_constant)[:, None] * x0[None, :]
    return Trajectory(t=t, x=x, u=np.zeros((t.size, 0)), cost=np.zeros(t.size))


def _initial_trajectories(
    guess: Trajectory, x0: np.ndarray, m: int, u_max: float, duration: float
) -> tuple[PiecewisePolynomial, PiecewisePolynomial]:
    t = np.asarray(guess.t, dtype=float)
    keep = np.concatenate([[True], np.diff(t) > 1e-12]) & (t <= duration + 1e-9)
    t = t[keep]
    x = np.asarray(guess.x, dtype=float)[keep]
    J = np.asarray(guess.cost, dtype=float)[keep]
    if guess.u.size:
        u = np.clip(np.asarray(guess.u, dtype=float)[keep], -u_max, u_max)
    else:
        u = np.zeros((t.size, m))
    x[0] = x0
    states = np.hstack([x, J[:, None]])
    return (
        PiecewisePolynomial.FirstOrderHold(t, u.T),
        PiecewisePolynomial.FirstOrderHold(t, states.T),
    )


def solve_optimal_control(
    system: ControlAffineSystem,
    x0: np.ndarray,
    Q: np.ndarray,
    r: np.ndarray,
    input_bound: float,
    duration: float,
    *,
    warm_start: Trajectory | None = None,
    mesh: Mesh | None = None,
    solver: str | None = None,
    input_margin: float = 1e-6,
    deadline: float | None = None,
) -> OptimalControlResult:
    """Minimize ``int_0^T Q(x) + U(u) dt`` over inputs with ``|u_k| <= lambda_bar``.

    Parameters
    ----------
    system : ControlAffineSystem
    x0 : array_like, shape (n,)
        Initial state.
    Q : array_like, shape (n, n)
        State weight.
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lambda_bar.
    duration : float
        Horizon T [s].
    warm_start : Trajectory, optional
        Initial guess (e.g. the learned closed loop from ``x0``). If the solve
        from it fails, a default guess is tried too.
    mesh : Mesh, optional
        The time grid (default :class:`Mesh`).
    solver : {"snopt", "ipopt"}, optional
        Default: SNOPT if available.
    input_margin : float
        Inputs are bounded by ``|u_k| <= lambda_bar (1 - input_margin)``, where
        the gradient of ``U`` is finite (see the module docstring).
    deadline : float, optional
        A ``time.monotonic()`` reading after which no solve starts (a solve
        under way is not interrupted: neither SNOPT nor IPOPT can be stopped
        from Python). None: no limit.

    Returns
    -------
    OptimalControlResult
        With ``cost = NaN`` and the solver status if no attempt converged.

    Raises
    ------
    OfrlError
        For bad arguments: ``x0``, a ``mesh`` that is not a :class:`Mesh`, a
        ``warm_start`` that is not a :class:`Trajectory` of the system's
        dimensions, an unknown or unavailable solver, ``input_margin``.
    ModelError
        If ``Q`` is not a finite symmetric positive semidefinite ``n x n``
        matrix, ``r`` not ``m`` finite entries > 0, or ``input_bound`` or
        ``duration`` not a finite number > 0; or if Drake cannot trace the
        system's ``f`` or ``g`` on symbolic states (:func:`cost_augmented_plant`).
    WallTimeExceeded
        If ``deadline`` passed before ``J*`` was found and checked (step ``"J*"``).

    Notes
    -----
    An attempt whose iterates leave the domain of ``f`` or ``g`` (``sqrt`` or
    ``log`` of a negative number) is a failed attempt, not an error: if no
    attempt converges, the result's status names the domain error.
    """
    mesh = checked_mesh(mesh)
    name, nlp = _solver(solver)
    n, m = system.n, system.m
    try:
        x0 = np.asarray(x0, dtype=float)
    except (TypeError, ValueError):
        raise OfrlError(
            f"optimal control: x0 must be {n} finite numbers; got {reprlib.repr(x0)}."
        ) from None
    if x0.shape != (n,) or not np.all(np.isfinite(x0)):
        raise OfrlError(f"optimal control: x0 must be {n} finite numbers; got {x0}.")
    Q = nonnegative_matrix("optimal control: Q", Q, n)
    r = positive_vector("optimal control: r", r, m)
    input_bound = positive_number("optimal control: input_bound", input_bound)
    duration = positive_number("optimal control: duration", duration)
    _check_warm_start(warm_start, n, m)
    mesh.steps(duration)  # refuses a horizon the grid cannot cover, before any solve
    plant = cost_augmented_plant(system, Q, r, input_bound)

    if not (is_real_number(input_margin) and 0 < input_margin < 1):
        raise OfrlError(f"optimal control: input_margin must be in (0, 1); got {input_margin!r}.")
    deadline = deadline_or_none("optimal control: deadline", deadline, error=OfrlError)
    problem = _Problem(
        plant,
        x0,
        n,
        m,
        input_bound * (1.0 - input_margin),
        duration,
        name,
        nlp,
        deadline,
        time.monotonic(),
    )
    defaults = [
        (f"default guess ({tc:g} s)", _default_guess(x0, duration, tc)) for tc in (1.0, 0.5, 2.0)
    ]
    start = time.perf_counter()
    first = problem.solve(
        mesh, ([("warm start", warm_start)] if warm_start is not None else []) + defaults
    )

    found: _Solved | None
    if isinstance(first, _Failed):
        found, status, change = None, _unsolved(first, system.name), math.nan
    else:
        found, status, change = _settle(problem, mesh, first, defaults)
    return OptimalControlResult(
        x0=tuple(float(a) for a in x0),
        cost=math.nan if found is None else found.cost,
        converged=found is not None,
        status=status,
        duration=float(duration),
        solver=name,
        solve_time=time.perf_counter() - start,
        warm_started=isinstance(first, _Solved) and first.label == "warm start",
        intervals=0 if found is None else found.intervals,
        mesh_change=change,
        trajectory=None if found is None else found.trajectory,
    )


def _unsolved(first: _Failed, model: str) -> str:
    """The status of a ``J*`` whose first grid did not converge from any starting guess."""
    status = "not converged (" + "; ".join(first.statuses) + ")"
    if first.domain_failed:
        status += (
            f"; the solver's iterates left the region where f and g of the model "
            f"{model!r} are defined: define them on every state (e.g. clip the "
            "argument of sqrt or log) or start x0 farther from the edge of their domain"
        )
    return status


def _settle(
    problem: _Problem, mesh: Mesh, first: _Solved, defaults: list[tuple[str, Trajectory]]
) -> tuple[_Solved | None, str, float]:
    """Check ``first`` on grids twice as fine until two agree to ``mesh.rtol``.

    Returns the accepted grid's solve (None if ``J*`` did not settle or a
    finer grid did not converge), the status and the last relative change.
    """
    accepted, grid, change = first, mesh, math.nan
    settled = [(first.cost, first.intervals)]
    for _ in range(mesh.refinements):
        grid = grid.refined()
        guess = (f"from the grid of {accepted.intervals} intervals", accepted.trajectory)
        finer = problem.solve(grid, [guess, *defaults])
        if isinstance(finer, _Failed):
            return (
                None,
                f"not converged (J* = {accepted.cost:.7g} on {accepted.intervals} intervals, "
                "but the check on a grid twice as fine did not converge: "
                f"{'; '.join(finer.statuses)}; pass a finer Mesh, or Mesh(refinements=0) "
                "to accept an unchecked J*)",
                math.nan,
            )
        change = _relative_change(finer.cost, accepted.cost)
        accepted = finer
        settled.append((finer.cost, finer.intervals))
        if change <= mesh.rtol:
            return accepted, "ok", change
    if mesh.refinements == 0:
        return accepted, "ok", math.nan
    values = ", ".join(f"{cost:.7g} on {k}" for cost, k in settled)
    other = next(s for s in SOLVERS if s != problem.name)
    small = (
        f"; a J* below {SMALL_COST:g} may be limited by {problem.name}'s tolerances "
        f"instead, which no grid improves: try solver={other!r} (--solver {other}), or start "
        "farther from the equilibrium"
        if max(cost for cost, _ in settled) < SMALL_COST
        else ""
    )
    return (
        None,
        f"not converged (J* did not settle to rtol {mesh.rtol:g} in {mesh.refinements} "
        f"refinement{'s' if mesh.refinements > 1 else ''}, each grid twice as fine as the "
        f"last: {values} intervals; pass a finer Mesh, more refinements or a larger rtol "
        f"(mesh= in Python; the command line uses the default){small})",
        change,
    )


def _relative_change(new: float, old: float) -> float:
    """``|new - old| / new``: 0 when they are equal, inf when only ``new`` is 0."""
    if new == old:
        return 0.0
    return abs(new - old) / new if new > 0 else math.inf


@dataclass(frozen=True)
class _Solved:
    """The optimum on one grid: the attempt that converged, and its trajectory."""

    label: str
    intervals: int
    trajectory: Trajectory

    @property
    def cost(self) -> float:
        """``J*`` on this grid."""
        return float(self.trajectory.cost[-1])


@dataclass(frozen=True)
class _Failed:
    """Why no attempt on one grid converged: each attempt's status."""

    statuses: list[str]
    domain_failed: bool


@dataclass(frozen=True)
class _Problem:
    """One optimal-control problem, solved by direct collocation on any grid."""

    plant: SymbolicVectorSystem
    x0: np.ndarray
    n: int
    m: int
    u_max: float
    duration: float
    name: str
    nlp: Any
    deadline: float | None
    started: float

    def solve(self, mesh: Mesh, attempts: list[tuple[str, Trajectory]]) -> _Solved | _Failed:
        """The first attempt (a label and a starting guess) that converges on ``mesh``."""
        steps = mesh.steps(self.duration)
        n, m, plant = self.n, self.m, self.plant
        statuses: list[str] = []
        domain_failed = False
        for label, guess in attempts:
            now = time.monotonic()
            if self.deadline is not None and now >= self.deadline:
                raise WallTimeExceeded(
                    f"J* ran out of wall time {now - self.started:.3g} s into its solves, "
                    f"before its attempt {label!r} on a grid of {steps.size} intervals"
                    + "".join(f", after {status}" for status in statuses[-1:]),
                    step="J*",
                )
            dircol = DirectCollocation(
                plant,
                plant.CreateDefaultContext(),
                num_time_samples=steps.size + 1,
                minimum_time_step=float(steps.min()) * (1 - 1e-9),
                maximum_time_step=float(steps.max()) * (1 + 1e-9),
            )
            prog = dircol.prog()
            for i, h in enumerate(steps):
                prog.AddBoundingBoxConstraint(h, h, dircol.time_step(i))
            start_state = np.concatenate([self.x0, [0.0]])
            prog.AddBoundingBoxConstraint(start_state, start_state, dircol.initial_state())  # type: ignore[arg-type]  # pydrake array stub
            for k in range(steps.size + 1):
                prog.AddBoundingBoxConstraint(-self.u_max, self.u_max, dircol.input(k))
            dircol.AddFinalCost(dircol.final_state()[n])
            dircol.SetInitialTrajectory(
                *_initial_trajectories(guess, self.x0, m, self.u_max, self.duration)
            )
            try:
                result = self.nlp.Solve(prog, None, _options(self.name, self.nlp))
            except (RuntimeError, ValueError) as err:
                why = _domain_failure(err)
                if why is None:
                    raise
                statuses.append(f"{label}: {self.name} stopped, {why}")
                domain_failed = True
                continue
            code = result.get_solution_result()
            states = dircol.GetStateSamples(result)
            cost = float(states[n, -1])
            if result.is_success() and math.isfinite(cost) and cost >= 0:
                trajectory = Trajectory(
                    t=np.asarray(dircol.GetSampleTimes(result), dtype=float),
                    x=states[:n].T.copy(),
                    u=np.asarray(dircol.GetInputSamples(result), dtype=float).T.copy(),
                    cost=states[n].copy(),
                )
                return _Solved(label, steps.size, trajectory)
            info = getattr(result.get_solver_details(), "info", None)
            detail = f" (info {info})" if info is not None else ""
            if result.is_success():  # the solver's optimum, but no cost
                detail += f", but its J* = {cost:.3g} is not a number >= 0"
            statuses.append(f"{label}: {self.name} {code.name}{detail}")
        return _Failed(statuses, domain_failed)


def _options(name: str, nlp: Any) -> SolverOptions:
    """Quiet IPOPT; SNOPT without its gradient check.

    SNOPT's default check (``Verify level`` 0) steps every variable by a
    finite difference at the starting point, and an input started on its
    bound is stepped past it, where ``U``'s logarithm is undefined: a
    warm start from a saturated optimum then failed with a domain error.
    Drake's gradients are exact, so the check is off.
    """
    options = SolverOptions()
    if name == "ipopt":
        options.SetOption(nlp.solver_id(), "print_level", 0)
    else:
        options.SetOption(nlp.solver_id(), "Verify level", -1)
    return options


def optimal_control(
    scenario: Scenario,
    x0: ArrayLike | None = None,
    *,
    warm_start: Trajectory | None = None,
    mesh: Mesh | None = None,
    solver: str | None = None,
    deadline: float | None = None,
) -> OptimalControlResult:
    """``J*`` of ``scenario`` from ``x0`` (default: the scenario's own) over its horizon.

    The scenario is validated first (:func:`~ofrl_drake.scenario.validate_scenario`);
    the rest is :func:`solve_optimal_control`'s.

    Raises
    ------
    ScenarioError
        If a value of ``scenario`` is bad (e.g. ``cost.R`` not ``m`` entries > 0,
        a non-finite ``cost.Q`` or ``input_bound``), named in the message.
    OfrlError
        For bad ``x0``, ``warm_start``, ``mesh`` or ``solver``
        (:func:`solve_optimal_control`).
    ModelError
        If Drake cannot trace the system's ``f`` or ``g`` on symbolic states
        (they branch on the state, for instance): ``J*`` needs them symbolic.
    WallTimeExceeded
        If ``deadline`` (a ``time.monotonic()`` reading) passed before ``J*``
        was found and checked.
    """
    validate_scenario(scenario)
    system = resolve_system(scenario)
    return solve_optimal_control(
        system,
        np.asarray(scenario.x0 if x0 is None else x0, dtype=float),
        np.asarray(scenario.cost.Q, dtype=float),
        np.asarray(scenario.cost.R, dtype=float),
        scenario.input_bound,
        scenario.simulation.duration,
        warm_start=warm_start,
        mesh=mesh,
        solver=solver,
        deadline=deadline,
    )


def problem_key(
    scenario: Scenario, x0: np.ndarray, mesh: Mesh | None = None, solver: str | None = None
) -> str:
    """A hash of everything ``J*`` depends on: the scenario's problem data and ``x0``.

    The problem data are the system (``system``, or ``plant`` and ``equilibrium``
    when given, and the dynamics' :meth:`~ofrl_drake.model.ControlAffineSystem.fingerprint`,
    so an edited plant module is not served its old ``J*``), ``Q``, ``R``,
    ``lambda_bar`` and the horizon; the key also covers the mesh and the
    solver, so a change to either is not served from a stale cache.

    Raises
    ------
    OfrlError
        If ``mesh`` is not a :class:`Mesh` or ``solver`` not an available solver.
    ScenarioError
        If the scenario's system cannot be built (its fingerprint is part of the key).
    """
    mesh = checked_mesh(mesh)
    payload = {
        "system": scenario.system,
        "dynamics": resolve_system(scenario).fingerprint(),
        "Q": np.asarray(scenario.cost.Q, dtype=float).tolist(),
        "R": np.asarray(scenario.cost.R, dtype=float).tolist(),
        "input_bound": float(scenario.input_bound),
        "duration": float(scenario.simulation.duration),
        "mesh": asdict(mesh),
        "solver": _solver(solver)[0],
        "x0": [float(a).hex() for a in np.asarray(x0, dtype=float)],
    }
    for name in ("plant", "equilibrium"):  # a Drake plant, an operating point
        if getattr(scenario, name, None) is not None:
            payload[name] = asdict(getattr(scenario, name))
    text = json.dumps(payload, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


class OptimalCostCache:
    """Converged ``J*`` values on disk, one JSON file per problem key.

    Parameters
    ----------
    directory : str or Path
        Where the files live (created on first write).
    mesh : Mesh, optional
    solver : str, optional
        Part of the key (see :func:`problem_key`).

    Raises
    ------
    OfrlError
        If ``mesh`` is not a :class:`Mesh` or ``solver`` not an available solver.

    Notes
    -----
    Only converged results are stored, so a failure is retried next time.
    Files are written to a temporary name and renamed, so a reader never sees
    half a file.
    """

    def __init__(
        self, directory: str | os.PathLike[str], mesh: Mesh | None = None, solver: str | None = None
    ) -> None:
        checked_mesh(mesh)
        if solver is not None:
            solver_name(solver)
        self.directory = directory
        self.mesh = mesh
        self.solver = solver
        self._dir = Path(directory)

    def path(self, scenario: Scenario, x0: np.ndarray) -> Path:
        """The file holding ``J*`` of ``scenario`` from ``x0``."""
        return self._dir / f"{problem_key(scenario, x0, self.mesh, self.solver)}.json"

    def get(self, scenario: Scenario, x0: np.ndarray) -> OptimalControlResult | None:
        """The cached result (with its trajectory when stored), or None."""
        path = self.path(scenario, x0)
        if not path.is_file():
            return None
        try:
            result = OptimalControlResult.from_dict(json.loads(path.read_text()))
        except (ValueError, KeyError, TypeError):
            return None  # a damaged file is recomputed
        npz = path.with_suffix(".npz")
        if npz.is_file():
            with np.load(npz) as data:
                trajectory = Trajectory(t=data["t"], x=data["x"], u=data["u"], cost=data["cost"])
            result = dataclasses.replace(result, trajectory=trajectory)
        return result

    def put(self, scenario: Scenario, result: OptimalControlResult) -> None:
        """Store ``result`` (and its trajectory, as ``.npz``) if it converged."""
        if not result.converged:
            return
        path = self.path(scenario, np.asarray(result.x0))
        self._dir.mkdir(parents=True, exist_ok=True)
        if result.trajectory is not None:
            with atomic_file(path.with_suffix(".npz"), "wb") as fh:
                np.savez(fh, **asdict(result.trajectory))
        with atomic_file(path, "w") as fh:
            json.dump({**result.to_dict(), "scenario": scenario.name}, fh, indent=2)
            fh.write("\n")
