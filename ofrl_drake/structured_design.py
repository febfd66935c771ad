"""Observer gains certified by the structured LMI, solved with Drake's MathematicalProgram.

The LMI and its re-checks are :mod:`ofrl_drake.structured_lmi` (pure numpy);
this module solves it and wraps the numbers in a :class:`StructuredDesign`.
The semidefinite program mirrors the polytopic design of
:mod:`ofrl_drake.design` so the two can be compared number for number:

* ``P = P^T >= I``;
* at each input vertex, ``M(P, R, tau) <= -margin I`` with its own multipliers
  ``tau`` (:func:`ofrl_drake.structured_lmi.structured_lmi_blocks`), ``R = P L``;
* ``objective="min_gain"`` (default): minimize ``t`` with ``[[t I, R], [R^T, t
  I]] >= 0`` (``||R||_2 <= t``); ``"min_condition"``: minimize ``s`` with ``P
  <= s I``; ``"feasibility"``: no objective;
* ``max_gain``: ``||R||_2 <= max_gain``, hence ``||L||_2 <= max_gain``.

``H = K = 0`` unless pinned (as the polytopic design). Each LMI is handed to
``AddLinearMatrixInequalityConstraint`` as its numeric coefficient matrices,
read off the affine numpy assembly at unit vectors. Whatever the solver
reports, the numbers are accepted only if
:func:`ofrl_drake.structured_lmi.structured_certificate`, recomputed from
``P``, ``L`` and ``tau``, is negative at every input vertex.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydrake.solvers import ClarabelSolver, MathematicalProgram, ScsSolver, SolutionResult

from ofrl_drake.design import DesignError, ObserverDesignInaccurate, ObserverDesignInfeasible
from ofrl_drake.jacobian_bounds import Box, JacobianBounds
from ofrl_drake.lmi import LmiError
from ofrl_drake.structured_lmi import (
    DeltaCheck,
    StructuredLmi,
    delta_check,
    structured_certificate,
    structured_lmi,
    structured_lmi_blocks,
)

__all__ = [
    "DEFAULT_MARGIN",
    "OBJECTIVES",
    "SOLVERS",
    "StructuredDesign",
    "design_structured",
]

#: Solvers offered (no MOSEK: it needs a licence).
SOLVERS = ("clarabel", "scs")
OBJECTIVES = ("min_gain", "min_condition", "feasibility")
#: The strict margin of :func:`ofrl_drake.design.design_observer`'s default, so
#: that the two formulations are compared at the same margin.
DEFAULT_MARGIN = 1e-3
# SCS (first order) needs tight tolerances to return numbers that certify.
_OPTIONS: dict[str, dict[str, float | int]] = {
    "scs": {"eps_abs": 1e-8, "eps_rel": 1e-8, "max_iters": 200_000},
}


def _solver(name: str) -> Any:
    makers = {"clarabel": ClarabelSolver, "scs": ScsSolver}
    if name not in makers:
        raise DesignError(f"solver must be one of {SOLVERS}; got {name!r}.")
    solver = makers[name]()
    if not (solver.available() and solver.enabled()):
        raise DesignError(
            f"solver {name!r} is not usable in this Drake build; use one of {SOLVERS}."
        )
    return solver


@dataclass(frozen=True)
class _Layout:
    """``z = [vech(P), vec(R), tau, t or s]``: where each unknown sits.

    ``R`` only when ``L`` is not pinned, ``t`` for ``min_gain``, ``s`` for
    ``min_condition``; ``tau`` concatenates the multipliers of every model.
    """

    n: int
    q: int
    counts: tuple[int, ...]
    L: np.ndarray | None
    objective: str

    @property
    def names(self) -> list[tuple[str, int]]:
        """``(name, length)`` of each part of ``z``."""
        out = [("P", self.n * (self.n + 1) // 2)]
        if self.L is None:
            out.append(("R", self.n * self.q))
        out.append(("tau", sum(self.counts)))
        if self.objective == "min_gain":
            out.append(("t", 1))
        elif self.objective == "min_condition":
            out.append(("s", 1))
        return out

    @property
    def size(self) -> int:
        """Length of ``z``."""
        return sum(k for _, k in self.names)

    def unpack(self, z: np.ndarray) -> dict[str, Any]:
        """``P, R, tau`` (and ``t`` or ``s``) from ``z``; affine in ``z``."""
        parts, pos = {}, 0
        for name, k in self.names:
            parts[name] = z[pos : pos + k]
            pos += k
        P = np.zeros((self.n, self.n))
        rows, cols = np.triu_indices(self.n)
        P[rows, cols] = parts["P"]
        P[cols, rows] = parts["P"]
        R = parts["R"].reshape(self.n, self.q) if self.L is None else P @ self.L
        tau = np.split(parts["tau"], np.cumsum(self.counts)[:-1])
        out: dict[str, Any] = {"P": P, "R": R, "tau": tau}
        for name in ("t", "s"):
            if name in parts:
                out[name] = float(parts[name][0])
        return out


def _psd_blocks(
    problem: StructuredLmi, layout: _Layout, v: dict[str, Any], max_gain: float | None
) -> list[np.ndarray]:
    """Every matrix the SDP asks to be positive semidefinite, at the numbers ``v``."""
    n, q = problem.n, problem.q
    P, R = v["P"], v["R"]
    eye = np.eye(n)
    blocks = [P - eye]
    for M in structured_lmi_blocks(problem, P, R, v["tau"]):
        blocks.append(-M - problem.margin * np.eye(M.shape[0]))
    if max_gain is not None:
        blocks.append(np.block([[max_gain * eye, R], [R.T, max_gain * np.eye(q)]]))
    if layout.objective == "min_gain":
        t = v["t"]
        blocks.append(np.block([[t * eye, R], [R.T, t * np.eye(q)]]))
    elif layout.objective == "min_condition":
        blocks.append(v["s"] * eye - P)
    return [0.5 * (B + B.T) for B in blocks]


@dataclass(frozen=True)
class _Solution:
    P: np.ndarray | None
    R: np.ndarray | None
    tau: list[np.ndarray] | None
    status: str
    infeasible: bool
    solve_time: float


def _solve(
    problem: StructuredLmi,
    solver_name: str,
    objective: str,
    L: np.ndarray | None,
    max_gain: float | None,
) -> _Solution:
    solver = _solver(solver_name)
    start = time.perf_counter()
    layout = _Layout(problem.n, problem.q, tuple(problem.multiplier_counts), L, objective)
    prog = MathematicalProgram()
    z = np.concatenate([prog.NewContinuousVariables(k, name) for name, k in layout.names])
    N = layout.size
    F0 = _psd_blocks(problem, layout, layout.unpack(np.zeros(N)), max_gain)
    Fi = []
    for e in np.eye(N):
        blocks = _psd_blocks(problem, layout, layout.unpack(e), max_gain)
        Fi.append([B - B0 for B, B0 in zip(blocks, F0, strict=True)])
    for j, B0 in enumerate(F0):
        used = [i for i in range(N) if np.any(Fi[i][j])]
        prog.AddLinearMatrixInequalityConstraint([B0] + [Fi[i][j] for i in used], z[used])
    if objective != "feasibility":
        prog.AddLinearCost(np.eye(N)[-1], 0.0, z)  # t or s, always last
    for key, value in _OPTIONS.get(solver_name, {}).items():
        prog.SetSolverOption(solver.solver_id(), key, value)
    result = solver.Solve(prog)
    elapsed = time.perf_counter() - start
    code = result.get_solution_result()
    status = code.name
    details = result.get_solver_details()
    if hasattr(details, "status") and isinstance(details.status, str):
        status = f"{status} ({details.status})"
    if code in (SolutionResult.kInfeasibleConstraints, SolutionResult.kInfeasibleOrUnbounded):
        return _Solution(None, None, None, status, True, elapsed)
    v = layout.unpack(np.asarray(result.GetSolution(z), dtype=float))
    return _Solution(v["P"], v["R"], v["tau"], status, False, elapsed)


def _array(a: Any) -> np.ndarray:
    arr = np.array(a, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class StructuredDesign:
    """Observer gains certified by the structured LMI, with what re-checks them.

    The certificate (:meth:`certificate`) is recomputed in numpy from ``P``,
    ``L``, ``tau`` and the LMI data, never taken from the solver.

    Attributes
    ----------
    problem : StructuredLmi
        The LMI data: output matrix, per-vertex models, grouping, alpha, margin.
    P : ndarray, shape (n, n)
        Lyapunov matrix of ``V_e = e^T P e``.
    L : ndarray, shape (n, q)
        Observer gain.
    R : ndarray, shape (n, q)
        ``P L`` as the solver returned it.
    tau : tuple of ndarray
        The S-procedure multipliers of each model.
    H, K : ndarray, shape (n, q)
        The pinned injection gains (zero unless given).
    bounds : JacobianBounds
        The Jacobian bounds; the claim holds on ``bounds.box``.
    input_bound : float
        ``lambda_bar``.
    objective, solver, status : str
        What was asked and what the solver said.
    solve_time : float
        Wall-clock seconds of building and solving the program.
    """

    problem: StructuredLmi
    P: np.ndarray
    L: np.ndarray
    R: np.ndarray
    tau: tuple[np.ndarray, ...]
    H: np.ndarray
    K: np.ndarray
    bounds: JacobianBounds
    input_bound: float
    objective: str
    solver: str
    status: str
    solve_time: float
    _cert: list = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        for key in ("P", "L", "R", "H", "K"):
            object.__setattr__(self, key, _array(getattr(self, key)))
        object.__setattr__(self, "tau", tuple(_array(t) for t in self.tau))
        cert = structured_certificate(self.problem, self.P, self.L, list(self.tau))
        object.__setattr__(self, "_cert", cert)

    @property
    def alpha(self) -> float:
        """The decay rate certified: ``dV_e/dt <= -2 alpha V_e`` if :attr:`is_certified`."""
        return self.problem.alpha

    @property
    def box(self) -> Box:
        """Where the claim holds: x and xhat (and xhat + H ytil, xhat + K ytil) inside."""
        return self.bounds.box

    @property
    def grouping(self) -> str:
        """``"entry"`` or ``"row"``."""
        return self.problem.grouping

    def certificate(self) -> list[tuple[np.ndarray, float]]:
        """``(u vertex, lambda_max(M) + 2 ||P|| thin)`` per distinct input vertex."""
        return [(u.copy(), v) for u, v in self._cert]

    @property
    def max_eigenvalue(self) -> float:
        """The largest :meth:`certificate` value (< 0 when certified)."""
        return max(v for _, v in self._cert)

    @property
    def is_certified(self) -> bool:
        """True if ``P`` is positive definite and every certificate value is < 0."""
        if not np.all(np.isfinite(self.P)) or np.linalg.eigvalsh(self.P)[0] <= 0:
            return False
        return all(v < 0 for _, v in self._cert)

    def delta_check(self, *, samples: int = 2000, seed: int = 0) -> list[DeltaCheck]:
        """:func:`ofrl_drake.structured_lmi.delta_check` on these numbers (no multipliers)."""
        return delta_check(self.problem, self.P, self.L, samples=samples, seed=seed)

    @property
    def condition_number(self) -> float:
        """``cond(P)`` (2-norm)."""
        return float(np.linalg.cond(self.P))

    @property
    def gain_norm(self) -> float:
        """``||L||_2``."""
        return float(np.linalg.norm(self.L, 2))

    @property
    def lmi_sizes(self) -> list[int]:
        """Size of each vertex LMI, ``n + r``."""
        return self.problem.sizes

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict: the numbers, the claim and the certificate."""
        return {
            "formulation": f"structured_{self.grouping}",
            "P": self.P.tolist(),
            "L": self.L.tolist(),
            "H": self.H.tolist(),
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "tau": [t.tolist() for t in self.tau],
            "alpha": self.alpha,
            "margin": self.problem.margin,
            "input_bound": self.input_bound,
            "box": self.box.to_dict(),
            "jacobian_bounds": self.bounds.to_dict(),
            "jacobian_method": self.bounds.method,
            "uncertain_entries": self.problem.uncertain_entries,
            "lmi_sizes": self.lmi_sizes,
            "certificate": [{"input": u.tolist(), "max_eigenvalue": v} for u, v in self._cert],
            "is_certified": self.is_certified,
            "condition_number": self.condition_number,
            "gain_norm": self.gain_norm,
            "objective": self.objective,
            "solver": self.solver,
            "status": self.status,
            "solve_time": self.solve_time,
        }


def _gain(name: str, G: Any, n: int, q: int) -> np.ndarray:
    if G is None:
        return np.zeros((n, q))
    G = np.asarray(G, dtype=float)
    if G.ndim == 1 and q == 1:
        G = G.reshape(-1, 1)
    if G.shape != (n, q) or not np.all(np.isfinite(G)):
        raise DesignError(f"{name} must be a finite ({n}, {q}) array; got {G.tolist()}.")
    return G


def design_structured(
    C: Any,
    bounds: JacobianBounds,
    input_bound: float,
    alpha: float,
    *,
    grouping: str = "entry",
    objective: str = "min_gain",
    margin: float = DEFAULT_MARGIN,
    max_gain: float | None = None,
    solver: str = "clarabel",
    L: Any = None,
    H: Any = None,
    K: Any = None,
) -> StructuredDesign:
    """Solve the structured LMI for ``P``, ``L`` and the multipliers; certify in numpy.

    Parameters
    ----------
    C : array_like, shape (q, n)
        Output matrix.
    bounds : JacobianBounds
        Jacobian bounds over the observer box (``jacobian_method="certified"``
        makes the certificate a proof).
    input_bound : float
        ``lambda_bar``: certified for every ``|u_k| <= input_bound``.
    alpha : float
        Decay rate: ``dV_e/dt <= -2 alpha V_e``.
    grouping : {"entry", "row"}
        One S-procedure multiplier per uncertain entry (default; never more
        conservative) or per uncertain row (a smaller LMI).
    objective : {"min_gain", "min_condition", "feasibility"}
        As for :func:`ofrl_drake.design.design_observer`.
    margin : float
        Strict margin: ``M <= -margin I``.
    max_gain : float, optional
        Enforce ``||L||_2 <= max_gain`` (through ``||R||_2 <= max_gain``).
    solver : {"clarabel", "scs"}
        SDP solver.
    L : array_like, shape (n, q), optional
        Pin ``L`` (then ``R = P L`` and only ``P`` and ``tau`` are solved for).
    H, K : array_like, shape (n, q), optional
        Pinned injection gains (default zero, as the polytopic design).

    Returns
    -------
    StructuredDesign
        With :attr:`StructuredDesign.is_certified` True.

    Raises
    ------
    ObserverDesignInfeasible
        If the solver reports infeasibility (a subclass,
        ``ObserverDesignInaccurate``, if its numbers fail the numpy certificate).
    DesignError
        For a bad solver, objective, grouping, gain or bounds.

    Examples
    --------
    >>> from ofrl_drake.examples import make_system
    >>> from ofrl_drake.jacobian_bounds import jacobian_bounds
    >>> system = make_system("two_state")
    >>> bounds = jacobian_bounds(system, ([-2, -2], [2, 2]), "certified")
    >>> d = design_structured(system.output_matrix, bounds, 3.0, 0.5)
    >>> d.is_certified, d.lmi_sizes
    (True, [4, 4])
    """
    if solver not in SOLVERS:
        raise DesignError(f"solver must be one of {SOLVERS}; got {solver!r}.")
    if objective not in OBJECTIVES:
        raise DesignError(f"objective must be one of {OBJECTIVES}; got {objective!r}.")
    if not isinstance(bounds, JacobianBounds):
        raise DesignError(f"bounds must be a JacobianBounds; got {type(bounds).__name__}.")
    if max_gain is not None and not (math.isfinite(max_gain) and max_gain > 0):
        raise DesignError(f"max_gain must be a positive number; got {max_gain!r}.")
    C = np.atleast_2d(np.asarray(C, dtype=float))
    q, n = C.shape
    if n != bounds.n:
        raise DesignError(f"C has {n} columns but the bounds are for n = {bounds.n}.")
    pinned_L = None if L is None else _gain("L", L, n, q)
    Hp, Kp = _gain("H", H, n, q), _gain("K", K, n, q)
    if pinned_L is not None and objective == "min_gain":
        objective = "min_condition"  # ||R|| is not a variable with L pinned
    try:
        problem = structured_lmi(
            C, bounds, input_bound, alpha, margin=margin, grouping=grouping, H=Hp, K=Kp
        )
    except LmiError as err:
        raise DesignError(f"formulation='structured': {err}") from err
    sol = _solve(problem, solver, objective, pinned_L, max_gain)
    where = (
        f"formulation=structured ({grouping}), alpha={alpha:g}, box "
        f"{bounds.box.lower.tolist()}..{bounds.box.upper.tolist()}, |u_k| <= {input_bound:g}"
    )
    hint = "try a smaller alpha, a smaller box, a smaller input bound"
    if max_gain is not None:
        hint += ", a larger max_gain"
    if grouping == "row":
        hint += ", grouping='entry'"

    def fail(reason: str, kind: type = ObserverDesignInfeasible) -> ObserverDesignInfeasible:
        return kind(
            f"no certified observer for {where} ({solver}: {reason}); {hint}.",
            alpha=float(alpha),
            box=bounds.box,
            input_bound=float(input_bound),
            status=sol.status,
            solver=solver,
            formulation=f"structured_{grouping}",
        )

    if sol.infeasible or sol.P is None or sol.R is None or sol.tau is None:
        raise fail(f"solver status {sol.status}", ObserverDesignInfeasible)
    if not all(np.all(np.isfinite(a)) for a in (sol.P, sol.R, *sol.tau)):
        raise fail(f"solver status {sol.status}, non-finite solution", ObserverDesignInaccurate)
    P = 0.5 * (sol.P + sol.P.T)
    if pinned_L is not None:
        gain = pinned_L
    else:
        try:
            gain = np.linalg.solve(P, sol.R)
        except np.linalg.LinAlgError:
            raise fail(
                f"solver status {sol.status}, singular P", ObserverDesignInaccurate
            ) from None
    design = StructuredDesign(
        problem=problem,
        P=P,
        L=gain,
        R=sol.R,
        tau=tuple(sol.tau),
        H=Hp,
        K=Kp,
        bounds=bounds,
        input_bound=float(input_bound),
        objective=objective,
        solver=solver,
        status=sol.status,
        solve_time=sol.solve_time,
    )
    if not design.is_certified:
        raise fail(
            f"solver status {sol.status}, but its solution fails the numpy certificate with "
            f"max eigenvalue {design.max_eigenvalue:.3g}: the solver was not accurate enough, "
            "which proves nothing about feasibility; try a larger margin"
            + (" or solver='clarabel'" if solver != "clarabel" else ""),
            ObserverDesignInaccurate,
        )
    if max_gain is not None and design.gain_norm > max_gain * (1 + 1e-6):
        raise fail(f"||L|| = {design.gain_norm:.4g} exceeds max_gain")
    return design
