"""Observer gain design: solve an LMI for ``P, L (, H, K)`` and certify it in numpy.

Two formulations (``formulation=``):

``"polytopic"`` (default): a sound decay certificate.
    ``H = K = 0`` are fixed; the error then obeys ``e' = (M_f + M_gu - L C) e``
    with ``M_f + M_gu`` in the element-wise box ``[M_f1 + M_ug1(u), M_f2 +
    M_ug2(u)]`` (the row-wise mean value theorem; :mod:`ofrl_drake.lmi`), and
    ``P A_cl`` is linear in ``P`` and ``R = P L``. One common ``(P, R)`` is asked
    to satisfy

        A^T P + P A - C^T R^T - R C + 2 alpha P <= -margin I

    at every corner ``A`` of that box and every input vertex
    ``u_k in {-input_bound, 0, +input_bound}``
    (:func:`ofrl_drake.lmi.corner_matrices`); by convexity this gives
    ``dV/dt <= -2 alpha V`` for ``V = e^T P e``, every ``x, xhat`` in the box and
    every ``|u_k| <= input_bound``. Feasible only for rates the plant allows: on
    the two-state example no quadratic ``V`` certifies ``alpha >= 1``.
``"paper"``: the paper's (lmi2), exactly as stated, with the sign-correct input
    sector, at the ``3**m`` input vertices (docs/paper_notes.md, "one set of gains"), linear
    in ``(P, R, H, K)``. It is the paper's method, kept for reproduction and
    comparison, but it is not a decay certificate for nonlinear plants (a design
    that satisfies it at alpha = 2 on the two-state example has ``dV/dt = +39 V``
    at some states; see :mod:`ofrl_drake.lmi`). ``injection_gains=False`` pins
    ``H = K = 0`` (a linear Luenberger observer certified by (lmi2)).

Every design also carries the polytopic decay certificate of its own numbers
(:meth:`ObserverDesign.decay_certificate`, :attr:`ObserverDesign.is_decay_certified`),
so a "paper" design says honestly whether it certifies decay.

The semidefinite program, in either backend (Drake ``MathematicalProgram``
here, cvxpy in :mod:`ofrl_drake.design_cvxpy`):

* ``P = P^T >= I`` (normalizes the scale of the homogeneous LMI, so that
  ``lambda_max(P)`` is a bound on ``cond(P)`` and ``||L|| <= ||R||``);
* the formulation's LMI ``<= -margin I`` at every vertex (and corner): a strict
  margin, so the numbers the solver returns still certify after rounding;
* ``objective="min_gain"`` (default): minimize ``||R||_2`` (plus ``||[H K]||_F``
  when ``H, K`` are free), with ``||R||_2 <= t`` as the LMI
  ``[[t I, R], [R^T, t I]] >= 0`` and ``||[H K]||_F <= s`` as
  ``[[s, v^T], [v, s I]] >= 0`` (``v = vec[H K]``).
  A bare feasibility solve can return a nearly singular ``P`` and a huge ``L``
  (docs/paper_notes.md, "conditioning"); a large ``L`` makes the observer stiff and costs
  simulation time, and since ``P >= I`` gives ``||L|| = ||P^{-1} R|| <= ||R||``,
  minimizing ``||R||_2`` minimizes a bound on the gain while also keeping ``P``
  from growing (``R = P L``). The ``||[H K]||_F`` term, weighted equally with
  ``||R||_2`` (objective ``t + s``), pins the directions
  of ``H`` and ``K`` that the LMI does not see (e.g. ``K`` entries multiplying
  a zero column of ``M_g2 - M_g1``) to zero instead of leaving them to the solver.
  ``"min_condition"`` minimizes ``lambda_max(P)`` (a bound on ``cond(P)``);
  ``"feasibility"`` has no objective.
* ``max_gain``: the constraint ``||R||_2 <= max_gain``, which implies
  ``||L||_2 <= max_gain`` because ``P >= I`` (sufficient, slightly conservative);
  ``||L||_2`` is then also checked in numpy.

The Drake backend passes every LMI to ``AddLinearMatrixInequalityConstraint`` as
its numeric coefficient matrices ``F_0 + sum_i z_i F_i``, read off the
pure-numpy LMI functions of :mod:`ofrl_drake.lmi` (which are affine in the
decision variables ``z``), so no symbolic matrix arithmetic is needed.

Whatever the solver reports, the returned numbers are accepted only if the
certificate of the formulation, recomputed in numpy from ``P, L, H, K, C`` and
the bounds alone, is negative at every vertex; otherwise
:class:`ObserverDesignInfeasible` is raised.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydrake.solvers import (
    ClarabelSolver,
    CsdpSolver,
    MathematicalProgram,
    MosekSolver,
    ScsSolver,
    SolutionResult,
)

from ofrl_drake.errors import OfrlError
from ofrl_drake.jacobian_bounds import Box, JacobianBounds, jacobian_bounds
from ofrl_drake.lmi import (
    MAX_CORNERS,
    SECTORS,
    LmiError,
    certificate,
    corner_count,
    corner_matrices,
    decay_certificate,
    is_certified,
    lmi2_blocks,
    polytopic_lmi,
    vertex_data,
)
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.sector import input_vertices

__all__ = [
    "BACKENDS",
    "FORMULATIONS",
    "OBJECTIVES",
    "SOLVERS",
    "DecayRateBracket",
    "DesignError",
    "ObserverDesign",
    "ObserverDesignInaccurate",
    "ObserverDesignInfeasible",
    "design_observer",
    "max_decay_rate",
]

SOLVERS = ("clarabel", "scs", "csdp", "mosek")
BACKENDS = ("drake", "cvxpy")
OBJECTIVES = ("min_gain", "min_condition", "feasibility")
FORMULATIONS = ("polytopic", "paper")
DEFAULT_MARGIN = 1e-3
#: SCS exit codes (scs.h) that Drake folds into its SolutionResult.
_SCS_STATUS = {
    1: "solved",
    2: "solved inaccurate",
    -1: "unbounded",
    -2: "infeasible",
    -3: "indeterminate",
    -4: "interrupted",
    -5: "signal",
    -6: "unbounded inaccurate",
    -7: "infeasible inaccurate",
}
# SCS (first order) needs tight tolerances to return numbers that certify.
_DRAKE_OPTIONS: dict[str, dict[str, float | int]] = {
    "scs": {"eps_abs": 1e-8, "eps_rel": 1e-8, "max_iters": 200_000},
}


class DesignError(OfrlError):
    """A design was asked for with a bad argument (solver, backend, bounds...)."""


class ObserverDesignInfeasible(OfrlError):
    """No observer gains were certified for the given rate, box and input bound.

    Attributes
    ----------
    alpha : float
        The decay rate asked for.
    box : Box
        The box of the Jacobian bounds.
    input_bound : float
        The input bound.
    status : str
        What the solver reported.
    solver : str
        Which solver.
    formulation : str
        Which LMI formulation.
    """

    def __init__(
        self,
        message: str,
        *,
        alpha: float,
        box: Box,
        input_bound: float,
        status: str,
        solver: str = "",
        formulation: str = "",
    ) -> None:
        super().__init__(message)
        self.alpha = alpha
        self.box = box
        self.input_bound = input_bound
        self.status = status
        self.solver = solver
        self.formulation = formulation


class ObserverDesignInaccurate(ObserverDesignInfeasible):
    """The solver reported a solution, but its numbers fail the numpy certificate.

    Not a proof of infeasibility: the solver (typically a first-order one such
    as SCS on a badly scaled LMI) was not accurate enough. A subclass of
    :class:`ObserverDesignInfeasible`, since no certified design came back
    either way; the message suggests a more accurate solver.
    """


# ----------------------------------------------------------- the SDP problem
@dataclass(frozen=True, eq=False)
class LmiProblem:
    """The numeric data of one observer SDP, shared by both backends.

    Attributes
    ----------
    formulation : str
        ``"polytopic"`` or ``"paper"`` (see the module docstring).
    C : ndarray, shape (q, n)
        Output matrix.
    vertices : list of (u, A, Jf21, Jg21)
        ``"paper"``: per input vertex, the constant matrices of (lmi2)
        (:func:`ofrl_drake.lmi.vertex_data`). Empty for ``"polytopic"``.
    corners : ndarray, shape (N, n, n)
        ``"polytopic"``: the distinct corner matrices ``A`` over all input
        vertices (:func:`ofrl_drake.lmi.corner_matrices`, built with the pinned
        ``H, K``), with ``A_cl = A - L C``. Empty for ``"paper"``.
    alpha, margin : float
        Decay rate and strict margin (``LMI <= -margin I``).
    objective : str
        One of :data:`OBJECTIVES`.
    max_gain : float or None
        Cap on ``||R||_2`` (hence on ``||L||_2``).
    L : ndarray or None
        If given, ``L`` is pinned and ``R = P L``; else ``R`` is a variable.
    HK : tuple of (H, K) or None
        If given, ``H, K`` are pinned; else they are variables (``"paper"``
        only: ``"polytopic"`` always pins them).
    """

    formulation: str
    C: np.ndarray
    vertices: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
    corners: np.ndarray
    alpha: float
    margin: float
    objective: str
    max_gain: float | None
    L: np.ndarray | None = None
    HK: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def n(self) -> int:
        """State dimension."""
        return int(self.C.shape[1])

    @property
    def q(self) -> int:
        """Output dimension."""
        return int(self.C.shape[0])


@dataclass(frozen=True, eq=False)
class SdpSolution:
    """What a backend returns: numbers (or None) and the solver's verdict.

    Attributes
    ----------
    P, R, H, K : ndarray or None
        The solution, None if the solver returned none.
    status : str
        The solver's status, as text.
    infeasible : bool
        True if the solver reported (primal) infeasibility.
    solve_time : float
        Wall-clock seconds spent in the backend (building and solving).
    """

    P: np.ndarray | None
    R: np.ndarray | None
    H: np.ndarray | None
    K: np.ndarray | None
    status: str
    infeasible: bool
    solve_time: float


def _drake_solver(name: str) -> Any:
    makers = {
        "clarabel": ClarabelSolver,
        "scs": ScsSolver,
        "csdp": CsdpSolver,
        "mosek": MosekSolver,
    }
    if name not in makers:
        raise DesignError(f"solver must be one of {SOLVERS}; got {name!r}.")
    solver = makers[name]()
    if not (solver.available() and solver.enabled()):
        hint = " (MOSEK needs a licence: set MOSEKLM_LICENSE_FILE)" * (name == "mosek")
        raise DesignError(
            f"solver {name!r} is not usable here: available()="
            f"{solver.available()}, enabled()={solver.enabled()}{hint}; use "
            "solver='clarabel' or 'scs'."
        )
    return solver


@dataclass(frozen=True)
class _Layout:
    """Where each unknown sits in the decision vector ``z`` of the Drake program.

    ``z = [vech(P), vec(R), vec(H), vec(K), t, s]``, each part present only
    when it is a variable: ``R`` unless ``L`` is pinned, ``H, K`` unless
    pinned, ``t`` for ``min_gain``, ``s`` for ``min_gain`` with free ``H, K``
    and for ``min_condition``.
    """

    problem: LmiProblem
    names: tuple[tuple[str, int], ...]

    @classmethod
    def of(cls, problem: LmiProblem) -> _Layout:
        """The layout of ``problem``'s unknowns."""
        n, q = problem.n, problem.q
        names = [("P", n * (n + 1) // 2)]
        if problem.L is None:
            names.append(("R", n * q))
        if problem.HK is None:
            names += [("H", n * q), ("K", n * q)]
        if problem.objective == "min_gain":
            names.append(("t", 1))
            if problem.HK is None:
                names.append(("s", 1))
        elif problem.objective == "min_condition":
            names.append(("s", 1))
        return cls(problem, tuple(names))

    @property
    def size(self) -> int:
        """Length of ``z``."""
        return sum(k for _, k in self.names)

    def unpack(self, z: np.ndarray) -> dict[str, Any]:
        """``P, R, H, K`` (and ``t, s`` if present) from ``z``; affine in ``z``."""
        n, q, p = self.problem.n, self.problem.q, self.problem
        parts: dict[str, Any] = {}
        pos = 0
        for name, k in self.names:
            parts[name] = z[pos : pos + k]
            pos += k
        P = np.zeros((n, n))
        rows, cols = np.triu_indices(n)
        P[rows, cols] = parts["P"]
        P[cols, rows] = parts["P"]
        out: dict[str, Any] = {"P": P}
        out["R"] = parts["R"].reshape(n, q) if p.L is None else P @ p.L
        if p.HK is None:
            out["H"] = parts["H"].reshape(n, q)
            out["K"] = parts["K"].reshape(n, q)
        else:
            out["H"], out["K"] = p.HK
        for name in ("t", "s"):
            if name in parts:
                out[name] = float(parts[name][0])
        return out


def _psd_blocks(problem: LmiProblem, v: dict[str, Any]) -> list[np.ndarray]:
    """Every matrix the SDP asks to be positive semidefinite, at the numbers ``v``.

    Affine in the decision vector (see :class:`_Layout`), so the Drake backend
    reads the coefficient matrices ``F_i`` off it.
    """
    n, q, C = problem.n, problem.q, problem.C
    P, R, H, K = v["P"], v["R"], v["H"], v["K"]
    eye = np.eye(n)
    blocks = [P - eye]
    if problem.formulation == "paper":
        for _, A, Jf21, Jg21 in problem.vertices:
            M = lmi2_blocks(P, R, H, K, C, A, Jf21, Jg21, problem.alpha)
            blocks.append(-M - problem.margin * np.eye(2 * n))
    else:
        M = polytopic_lmi(P, R, problem.corners, C, problem.alpha)
        blocks.extend(-M - problem.margin * eye)
    if problem.max_gain is not None:
        g = float(problem.max_gain)
        blocks.append(np.block([[g * eye, R], [R.T, g * np.eye(q)]]))
    if problem.objective == "min_gain":
        t = v["t"]
        blocks.append(np.block([[t * eye, R], [R.T, t * np.eye(q)]]))
        if problem.HK is None:
            s = v["s"]
            w = np.concatenate([H.ravel(), K.ravel()])[:, None]
            blocks.append(np.block([[np.array([[s]]), w.T], [w, s * np.eye(w.shape[0])]]))
    elif problem.objective == "min_condition":
        blocks.append(v["s"] * eye - P)
    return [0.5 * (B + B.T) for B in blocks]


def _drake_program(problem: LmiProblem) -> tuple[MathematicalProgram, np.ndarray, _Layout]:
    """The SDP as a ``MathematicalProgram``; returns it, ``z`` and its layout.

    Each LMI ``F_0 + sum_i z_i F_i >= 0`` is added with its numeric ``F_i``:
    ``F_0`` is :func:`_psd_blocks` at ``z = 0`` and ``F_i`` its change at the
    unit vector ``e_i`` (exact for an affine map), keeping only the variables
    that appear in that block.
    """
    layout = _Layout.of(problem)
    prog = MathematicalProgram()
    z = np.concatenate([prog.NewContinuousVariables(k, name) for name, k in layout.names])
    N = layout.size
    F0 = _psd_blocks(problem, layout.unpack(np.zeros(N)))
    Fi = [
        [B - B0 for B, B0 in zip(_psd_blocks(problem, layout.unpack(e)), F0, strict=True)]
        for e in np.eye(N)
    ]
    for j, B0 in enumerate(F0):
        used = [i for i in range(N) if np.any(Fi[i][j])]
        prog.AddLinearMatrixInequalityConstraint([B0] + [Fi[i][j] for i in used], z[used])
    if problem.objective in ("min_gain", "min_condition"):
        cost = np.zeros(N)
        pos = 0
        for name, k in layout.names:
            if name in ("t", "s"):
                cost[pos] = 1.0
            pos += k
        prog.AddLinearCost(cost, 0.0, z)
    return prog, z, layout


def _solve_drake(problem: LmiProblem, solver_name: str) -> SdpSolution:
    """Build and solve ``problem`` with ``pydrake.solvers.MathematicalProgram``."""
    solver = _drake_solver(solver_name)
    start = time.perf_counter()
    prog, z, layout = _drake_program(problem)
    for key, value in _DRAKE_OPTIONS.get(solver_name, {}).items():
        prog.SetSolverOption(solver.solver_id(), key, value)
    result = solver.Solve(prog)
    elapsed = time.perf_counter() - start
    code = result.get_solution_result()
    status = code.name
    details = result.get_solver_details()
    if hasattr(details, "status") and isinstance(details.status, str):
        status = f"{status} ({details.status})"
    scs = getattr(details, "scs_status", None)
    if scs is not None:
        # Drake reports SCS's "solved inaccurate" (2) as kSolutionFound; say which.
        name = _SCS_STATUS.get(int(scs), f"code {int(scs)}")
        status = f"{status} (SCS: {name}, {details.iter} iterations)"
    infeasible = code in (
        SolutionResult.kInfeasibleConstraints,
        SolutionResult.kInfeasibleOrUnbounded,
    )
    if infeasible:
        return SdpSolution(None, None, None, None, status, True, elapsed)
    v = layout.unpack(np.asarray(result.GetSolution(z), dtype=float))
    return SdpSolution(v["P"], v["R"], v["H"], v["K"], status, False, elapsed)


# ------------------------------------------------------------ the result type
def _array(a: Any) -> np.ndarray:
    arr = np.array(a, dtype=float)
    arr.setflags(write=False)
    return arr


def _cert_list(cert: list[tuple[np.ndarray, float]]) -> list[dict[str, Any]]:
    return [{"input": u.tolist(), "max_eigenvalue": ev} for u, ev in cert]


@dataclass(frozen=True, eq=False)
class ObserverDesign:
    """Certified observer gains and everything needed to re-check them.

    Two certificates are kept, both recomputed in numpy from ``P, L, H, K, C``
    and the bounds only (never taken from the solver):

    * :meth:`certificate`: the check of the formulation that was solved:
      the (lmi2) eigenvalues at the ``3**m`` input vertices for ``"paper"``,
      the decay certificate for ``"polytopic"``; :attr:`is_certified`.
    * :meth:`decay_certificate`: the sound polytopic check of ``dV/dt <= -2
      alpha V`` (:func:`ofrl_drake.lmi.decay_certificate`), whatever the
      formulation; :attr:`is_decay_certified`.

    Attributes
    ----------
    P : ndarray, shape (n, n)
        Lyapunov matrix of ``V_e = e^T P e``.
    L, H, K : ndarray, shape (n, q)
        Observer gains (eq:observerdynamics).
    R : ndarray, shape (n, q)
        ``P L``, the SDP variable.
    alpha : float
        The decay rate asked for: ``dV_e/dt <= -2 alpha V_e`` if
        :attr:`is_decay_certified`.
    box : Box
        Where the Jacobian bounds hold (x and x-hat must stay inside).
    input_bound : float
        ``lambda_bar``: certified for every ``|u_k| <= input_bound``.
    bounds : JacobianBounds
        The Jacobian bounds used.
    C : ndarray, shape (q, n)
        Output matrix.
    solver, backend : str
        Which solver and modelling layer produced the numbers.
    solve_time : float
        Wall-clock seconds of the solve (building included).
    status : str
        The solver's status.
    sector : str
        ``"sign_correct"`` (default) or ``"paper"`` (``"paper"`` formulation only).
    objective : str
        The objective used.
    margin : float
        The strict margin asked of the solver.
    formulation : str
        ``"polytopic"`` (default) or ``"paper"``.
    """

    P: np.ndarray
    L: np.ndarray
    H: np.ndarray
    K: np.ndarray
    R: np.ndarray
    alpha: float
    box: Box
    input_bound: float
    bounds: JacobianBounds
    C: np.ndarray
    solver: str
    solve_time: float
    status: str
    backend: str
    sector: str = "sign_correct"
    objective: str = "min_gain"
    margin: float = DEFAULT_MARGIN
    formulation: str = "polytopic"
    _cert: list = field(default_factory=list, init=False, repr=False)
    _decay: list = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        for key in ("P", "L", "H", "K", "R", "C"):
            object.__setattr__(self, key, _array(getattr(self, key)))
        object.__setattr__(self, "box", Box.coerce(self.box))
        object.__setattr__(self, "alpha", float(self.alpha))
        object.__setattr__(self, "input_bound", float(self.input_bound))
        object.__setattr__(self, "solve_time", float(self.solve_time))
        _check_formulation(self.formulation, self.sector)
        if self.formulation == "paper":
            cert = certificate(*self._numbers(), self.sector)
        else:
            cert = self.decay_certificate()
        object.__setattr__(self, "_cert", cert)

    def _numbers(self) -> tuple[Any, ...]:
        return (
            self.P,
            self.L,
            self.H,
            self.K,
            self.C,
            self.bounds,
            self.input_bound,
            self.alpha,
        )

    # ------------------------------------------------------------ certificate
    def certificate(self) -> list[tuple[np.ndarray, float]]:
        """``(u vertex, max eigenvalue)`` of the solved formulation's LMI.

        ``"paper"``: the largest eigenvalue of the (lmi2) matrix at each of the
        ``3**m`` input vertices. ``"polytopic"``: at each input vertex, the
        largest eigenvalue of ``A_cl^T P + P A_cl + 2 alpha P`` over every corner
        of the Jacobian bounds (the same as :meth:`decay_certificate`).
        Recomputed in numpy from ``P, L, H, K, C`` and the bounds only.
        """
        return [(u.copy(), ev) for u, ev in self._cert]

    def decay_certificate(self) -> list[tuple[np.ndarray, float]]:
        """``(u vertex, max eigenvalue over the corners)``: the sound decay check.

        :func:`ofrl_drake.lmi.decay_certificate` on this design's numbers; all
        negative (and ``P > 0``) means ``dV/dt <= -2 alpha V`` for every ``x``,
        ``xhat`` in the box (with ``xhat + H ytil``, ``xhat + K ytil`` in it too)
        and every ``|u_k| <= input_bound``.

        Raises
        ------
        LmiError
            If the corner enumeration exceeds :data:`ofrl_drake.lmi.MAX_CORNERS`.
        """
        if not self._decay:
            object.__setattr__(self, "_decay", decay_certificate(*self._numbers()))
        return [(u.copy(), ev) for u, ev in self._decay]

    @property
    def max_eigenvalue(self) -> float:
        """The largest eigenvalue of :meth:`certificate` (< 0 when certified)."""
        return max(ev for _, ev in self._cert)

    @property
    def is_certified(self) -> bool:
        """True if ``P`` is positive definite and every :meth:`certificate` value is < 0."""
        if self.formulation == "paper":
            return is_certified(*self._numbers(), self.sector)
        return self.is_decay_certified

    @property
    def is_decay_certified(self) -> bool:
        """True if ``P > 0`` and every :meth:`decay_certificate` value is < 0.

        False also when the corner enumeration is too large to check.
        """
        try:
            cert = self.decay_certificate()
        except LmiError:
            return False
        if not np.all(np.isfinite(self.P)) or np.linalg.eigvalsh(self.P)[0] <= 0:
            return False
        return all(ev < 0 for _, ev in cert)

    @property
    def bounds_are_guaranteed(self) -> bool:
        """True unless the Jacobian bounds are ``"sampled"`` (an inner estimate).

        A decay certificate proves ``V' <= -2 alpha V`` on the box only if the
        bounds enclose the Jacobians; ``"certified"`` bounds do, sampled ones
        usually but not provably do. ``"given"`` bounds are the caller's claim.
        """
        return self.bounds.method != "sampled"

    @property
    def condition_number(self) -> float:
        """``cond(P)`` (2-norm)."""
        return float(np.linalg.cond(self.P))

    @property
    def gain_norm(self) -> float:
        """``||L||_2``."""
        return float(np.linalg.norm(self.L, 2))

    # ----------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict.

        Keys: ``P, L, H, K`` (nested lists), ``alpha``, ``input_bound``,
        ``box`` ``{lower, upper}``, ``jacobian_bounds`` ``{Mf1, Mf2, Mg1, Mg2}``,
        ``certificate`` ``[{input, max_eigenvalue}, ...]``, ``solver``,
        ``solve_time``, ``formulation``, ``decay_certificate`` (same shape as
        ``certificate``; None if the corner enumeration is too large),
        ``is_decay_certified``; and also ``R, C, status, backend, sector,
        objective, margin, jacobian_method, condition_number, gain_norm,
        is_certified``.
        """
        try:
            decay: list[dict[str, Any]] | None = _cert_list(self.decay_certificate())
        except LmiError:
            decay = None
        return {
            "P": self.P.tolist(),
            "L": self.L.tolist(),
            "H": self.H.tolist(),
            "K": self.K.tolist(),
            "alpha": self.alpha,
            "input_bound": self.input_bound,
            "box": self.box.to_dict(),
            "jacobian_bounds": self.bounds.to_dict(),
            "certificate": _cert_list(self._cert),
            "solver": self.solver,
            "solve_time": self.solve_time,
            "formulation": self.formulation,
            "decay_certificate": decay,
            "is_decay_certified": self.is_decay_certified,
            "bounds_are_guaranteed": self.bounds_are_guaranteed,
            "R": self.R.tolist(),
            "C": self.C.tolist(),
            "status": self.status,
            "backend": self.backend,
            "sector": self.sector,
            "objective": self.objective,
            "margin": self.margin,
            "jacobian_method": self.bounds.method,
            "condition_number": self.condition_number,
            "gain_norm": self.gain_norm,
            "is_certified": self.is_certified,
        }

    def to_json(self, path: str | os.PathLike[str]) -> None:
        """Write :meth:`to_dict` to ``path`` as JSON."""
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh, indent=2)
            fh.write("\n")

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], system: ControlAffineSystem | None = None
    ) -> ObserverDesign:
        """Rebuild a design from :meth:`to_dict` output.

        The stored certificates are not trusted: they are recomputed from the
        numbers. Data without a ``formulation`` key were written before the
        polytopic formulation existed and are read as ``"paper"``.

        Parameters
        ----------
        data : dict
            As written by :meth:`to_dict`.
        system : ControlAffineSystem, optional
            Supplies ``C`` if ``data`` has no ``"C"`` key.

        Raises
        ------
        DesignError
            If a required key is missing or the formulation is unknown.
        """
        required = [
            "P",
            "L",
            "H",
            "K",
            "alpha",
            "input_bound",
            "box",
            "jacobian_bounds",
            "solver",
            "solve_time",
        ]
        missing = [k for k in required if k not in data]
        if missing:
            raise DesignError(f"observer design data is missing keys {missing}.")
        if "C" in data:
            C = np.asarray(data["C"], dtype=float)
        elif system is not None:
            C = system.output_matrix
        else:
            raise DesignError("observer design data has no 'C'; pass system= to supply it.")
        box = Box.coerce(data["box"])
        method = data.get("jacobian_method", "given")
        bounds = JacobianBounds.from_dict(data["jacobian_bounds"], box, method)
        P = np.asarray(data["P"], dtype=float)
        L = np.asarray(data["L"], dtype=float)
        R = np.asarray(data["R"], dtype=float) if "R" in data else P @ L
        return cls(
            P=P,
            L=L,
            H=data["H"],
            K=data["K"],
            R=R,
            alpha=data["alpha"],
            box=box,
            input_bound=data["input_bound"],
            bounds=bounds,
            C=C,
            solver=data["solver"],
            solve_time=data["solve_time"],
            status=data.get("status", "loaded"),
            backend=data.get("backend", "drake"),
            sector=data.get("sector", "sign_correct"),
            objective=data.get("objective", "min_gain"),
            margin=data.get("margin", DEFAULT_MARGIN),
            formulation=data.get("formulation", "paper"),
        )

    @classmethod
    def from_json(
        cls, path: str | os.PathLike[str], system: ControlAffineSystem | None = None
    ) -> ObserverDesign:
        """Read a design written by :meth:`to_json`."""
        with open(path, encoding="utf-8") as fh:
            return cls.from_dict(json.load(fh), system)

    @classmethod
    def from_gains(
        cls,
        system: ControlAffineSystem,
        box: Any,
        input_bound: float,
        alpha: float,
        L: Any,
        H: Any,
        K: Any,
        P: Any = None,
        bounds: JacobianBounds | None = None,
        *,
        solver: str = "clarabel",
        backend: str = "drake",
        jacobian_method: str = "certified",
        margin: float = DEFAULT_MARGIN,
        sector: str = "sign_correct",
        formulation: str = "polytopic",
    ) -> ObserverDesign:
        """A design from pinned gains ``L, H, K`` (and optionally ``P``).

        If ``P`` is given, nothing is solved and the design is returned as it
        is: :meth:`certificate` and :attr:`is_certified` report honestly whether
        it certifies. If ``P`` is None, a small SDP looks for ``P >= I`` with
        the formulation's LMI ``<= -margin I`` at every vertex (``"paper"``) or
        every corner and vertex (``"polytopic"``, where the corners are built
        with the given ``H, K``, so nonzero injection gains are checked
        soundly too), ``L, H, K`` fixed, minimizing ``lambda_max(P)``.

        Raises
        ------
        ObserverDesignInfeasible
            If ``P`` is None and no certifying ``P`` is found.
        DesignError
            For gains of the wrong shape or a bad formulation, solver or backend,
            or (``P`` None) too many corners for the polytopic formulation.
        LmiError
            If ``P`` is given and the polytopic corner enumeration is too large.
        """
        C = system.output_matrix
        n, q = system.n, system.q
        gains = []
        for name, G in (("L", L), ("H", H), ("K", K)):
            G = np.asarray(G, dtype=float)
            if G.ndim == 1 and q == 1:
                G = G.reshape(-1, 1)
            if G.shape != (n, q) or not np.all(np.isfinite(G)):
                raise DesignError(f"{name} must be a finite ({n}, {q}) array; got {G.tolist()}.")
            gains.append(G)
        _check_formulation(formulation, sector)
        box, bounds = _box_and_bounds(system, box, bounds, jacobian_method)
        alpha, input_bound, margin = _check_numbers(alpha, input_bound, margin)
        if P is not None:
            P = np.asarray(P, dtype=float)
            if P.shape != (n, n):
                raise DesignError(f"P must have shape ({n}, {n}); got {P.shape}.")
            return cls(
                P=P,
                L=gains[0],
                H=gains[1],
                K=gains[2],
                R=P @ gains[0],
                alpha=alpha,
                box=box,
                input_bound=input_bound,
                bounds=bounds,
                C=C,
                solver="none",
                solve_time=0.0,
                status="given",
                backend="none",
                sector=sector,
                objective="given",
                margin=margin,
                formulation=formulation,
            )
        problem = _problem(
            C,
            bounds,
            input_bound,
            alpha,
            margin,
            "min_condition",
            None,
            sector,
            formulation,
            L=gains[0],
            HK=(gains[1], gains[2]),
        )
        return _finish(problem, bounds, box, input_bound, solver, backend, sector, max_gain=None)


# ---------------------------------------------------------------- the driver
def _check_formulation(formulation: str, sector: str) -> None:
    if formulation not in FORMULATIONS:
        raise DesignError(f"formulation must be one of {FORMULATIONS}; got {formulation!r}.")
    if sector not in SECTORS:
        raise DesignError(f"sector must be one of {SECTORS}; got {sector!r}.")
    if formulation == "polytopic" and sector != "sign_correct":
        raise DesignError(
            f"sector={sector!r} applies to formulation='paper' only; the polytopic "
            "formulation always uses the sign-correct input sector."
        )


def _check_numbers(alpha: float, input_bound: float, margin: float) -> tuple[float, float, float]:
    for name, value in (
        ("alpha", alpha),
        ("input_bound", input_bound),
        ("margin", margin),
    ):
        if not isinstance(value, int | float | np.floating | np.integer) or not (
            math.isfinite(value) and value >= 0
        ):
            raise DesignError(f"{name} must be a finite number >= 0; got {value!r}.")
    return float(alpha), float(input_bound), float(margin)


def _box_and_bounds(
    system: ControlAffineSystem,
    box: Any,
    bounds: JacobianBounds | None,
    jacobian_method: str,
) -> tuple[Box, JacobianBounds]:
    box = Box.coerce(box, system.n)
    if bounds is None:
        return box, jacobian_bounds(system, box, jacobian_method)
    if not isinstance(bounds, JacobianBounds):
        raise DesignError(f"bounds must be a JacobianBounds; got {type(bounds).__name__}.")
    if bounds.Mg1.shape != (system.n, system.n, system.m):
        raise DesignError(
            f"bounds are for n = {bounds.n}, m = {bounds.m} but the system has "
            f"n = {system.n}, m = {system.m}."
        )
    inside = np.all(bounds.box.lower <= box.lower) and np.all(box.upper <= bounds.box.upper)
    if not inside:
        raise DesignError(
            f"bounds hold on {bounds.box!r}, which does not contain the design "
            f"box {box!r}; recompute them on the design box."
        )
    return box, bounds


def _problem(
    C: np.ndarray,
    bounds: JacobianBounds,
    input_bound: float,
    alpha: float,
    margin: float,
    objective: str,
    max_gain: float | None,
    sector: str,
    formulation: str,
    *,
    L: np.ndarray | None = None,
    HK: tuple[np.ndarray, np.ndarray] | None = None,
) -> LmiProblem:
    _check_formulation(formulation, sector)
    if objective not in OBJECTIVES:
        raise DesignError(f"objective must be one of {OBJECTIVES}; got {objective!r}.")
    if max_gain is not None and not (math.isfinite(max_gain) and max_gain > 0):
        raise DesignError(f"max_gain must be a positive number; got {max_gain!r}.")
    n, q = C.shape[1], C.shape[0]
    vertices = []
    corners = np.zeros((0, n, n))
    if formulation == "paper":
        for u in input_vertices(input_bound, bounds.m):
            A, Jf21, Jg21 = vertex_data(bounds, u, sector)
            vertices.append((u, A, Jf21, Jg21))
    else:
        if HK is None:
            HK = (np.zeros((n, q)), np.zeros((n, q)))
        us = input_vertices(input_bound, bounds.m)
        try:
            total = sum(corner_count(bounds, u, *HK, C) for u in us)
            if total > MAX_CORNERS:
                raise LmiError(
                    f"{total} corner matrices over {len(us)} input vertices, more than "
                    f"MAX_CORNERS = {MAX_CORNERS}; tighten the Jacobian bounds, use a "
                    "smaller box or formulation='paper'."
                )
            stacks = [corner_matrices(bounds, u, *HK, C) for u in us]
        except LmiError as err:
            raise DesignError(f"formulation='polytopic': {err}") from err
        corners = np.unique(np.concatenate(stacks), axis=0)
    return LmiProblem(formulation, C, vertices, corners, alpha, margin, objective, max_gain, L, HK)


def _relax_hint(max_gain: float | None, inaccurate: bool) -> str:
    hint = "try a smaller alpha, a smaller box, a smaller input bound"
    if max_gain is not None:
        hint += ", a larger max_gain"
    if inaccurate:
        hint += ", a larger margin or a more accurate solver ('clarabel')"
    return hint


def _solve(problem: LmiProblem, solver: str, backend: str) -> SdpSolution:
    if backend == "drake":
        return _solve_drake(problem, solver)
    if backend == "cvxpy":
        from ofrl_drake.design_cvxpy import solve_cvxpy

        return solve_cvxpy(problem, solver)
    raise DesignError(f"backend must be one of {BACKENDS}; got {backend!r}.")


def _finish(
    problem: LmiProblem,
    bounds: JacobianBounds,
    box: Box,
    input_bound: float,
    solver: str,
    backend: str,
    sector: str,
    max_gain: float | None,
) -> ObserverDesign:
    sol = _solve(problem, solver, backend)
    where = (
        f"formulation={problem.formulation}, alpha={problem.alpha:g}, box "
        f"{box.lower.tolist()}..{box.upper.tolist()}, |u_k| <= {input_bound:g}"
    )

    pinned = problem.L is not None

    def fail(
        reason: str, inaccurate: bool = True, kind: type = ObserverDesignInfeasible
    ) -> ObserverDesignInfeasible:
        if pinned:
            head = f"the given gains L, H, K are not certified for {where}: no P >= I found"
            hint = (
                "if they come from a scenario, remove observer.L/H/K to let the LMI design "
                f"the gains, or {_relax_hint(max_gain, inaccurate)}"
            )
        else:
            head, hint = f"no certified observer for {where}", _relax_hint(max_gain, inaccurate)
        return kind(
            f"{head} ({solver}/{backend}: {reason}); {hint}.",
            alpha=problem.alpha,
            box=box,
            input_bound=input_bound,
            status=sol.status,
            solver=solver,
            formulation=problem.formulation,
        )

    if sol.infeasible or sol.P is None:
        raise fail(f"solver status {sol.status}", inaccurate=not sol.infeasible)
    numbers = [sol.P, sol.R, sol.H, sol.K]
    if not all(np.all(np.isfinite(a)) for a in numbers):
        raise fail(
            f"solver status {sol.status}, non-finite solution", kind=ObserverDesignInaccurate
        )
    P = 0.5 * (sol.P + sol.P.T)
    if problem.L is not None:
        L = problem.L
    else:
        try:
            L = np.linalg.solve(P, sol.R)
        except np.linalg.LinAlgError:
            raise fail(
                f"solver status {sol.status}, singular P", kind=ObserverDesignInaccurate
            ) from None
    design = ObserverDesign(
        P=P,
        L=L,
        H=sol.H,
        K=sol.K,
        R=sol.R,
        alpha=problem.alpha,
        box=box,
        input_bound=input_bound,
        bounds=bounds,
        C=problem.C,
        solver=solver,
        solve_time=sol.solve_time,
        status=sol.status,
        backend=backend,
        sector=sector,
        objective=problem.objective,
        margin=problem.margin,
        formulation=problem.formulation,
    )
    if not design.is_certified:
        raise fail(
            f"solver status {sol.status}, but its solution fails the numpy certificate "
            f"with max eigenvalue {design.max_eigenvalue:.3g}: the solver was not accurate "
            "enough, which proves nothing about feasibility",
            kind=ObserverDesignInaccurate,
        )
    if max_gain is not None and design.gain_norm > max_gain * (1 + 1e-6):
        raise fail(f"||L|| = {design.gain_norm:.4g} exceeds max_gain", False)
    return design


def design_observer(
    system: ControlAffineSystem,
    box: Any,
    input_bound: float,
    alpha: float,
    *,
    bounds: JacobianBounds | None = None,
    jacobian_method: str = "certified",
    solver: str = "clarabel",
    margin: float = DEFAULT_MARGIN,
    objective: str = "min_gain",
    max_gain: float | None = None,
    backend: str = "drake",
    sector: str = "sign_correct",
    formulation: str = "polytopic",
    injection_gains: bool = True,
) -> ObserverDesign:
    """Design certified observer gains by solving an LMI (see the module docstring).

    Parameters
    ----------
    system : ControlAffineSystem
        The plant.
    box : Box or (lower, upper)
        Compact set where the Jacobian bounds hold; ``x`` and ``x-hat`` must
        stay in it for the certificate to apply.
    input_bound : float
        ``lambda_bar``; one common set of gains is certified at all 3**m
        vertices, hence for every ``|u_k| <= input_bound``.
    alpha : float
        Decay rate: ``dV_e/dt <= -2 alpha V_e``, ``V_e = e^T P e`` (for
        ``"paper"``, only in the sense of (lmi2); see the module docstring).
    bounds : JacobianBounds, optional
        Precomputed bounds on a box containing ``box``; default: computed with
        ``jacobian_method``.
    jacobian_method : {"certified", "sampled"}
        How to compute ``bounds`` when they are not given. ``"certified"``
        (default) gives guaranteed interval enclosures, so a decay certificate
        is a proof; ``"sampled"`` is an inner estimate, faster but not a
        guarantee (see :attr:`ObserverDesign.bounds_are_guaranteed`).
    solver : {"clarabel", "scs", "csdp", "mosek"}
        SDP solver (the cvxpy backend accepts "clarabel" and "scs").
    margin : float
        Strict margin: ``LMI <= -margin I`` at every vertex (and corner).
    objective : {"min_gain", "min_condition", "feasibility"}
        See the module docstring; "min_gain" minimizes ``||R||_2`` (plus
        ``||[H K]||_F`` when ``H, K`` are free).
    max_gain : float, optional
        Enforce ``||L||_2 <= max_gain`` (through ``||R||_2 <= max_gain``).
    backend : {"drake", "cvxpy"}
        Modelling layer.
    sector : {"sign_correct", "paper"}
        Input sector of the ``"paper"`` formulation; "paper" reproduces the
        paper's literal (aug_jac_g), valid only for ``u >= 0``.
    formulation : {"polytopic", "paper"}
        ``"polytopic"``: the sound decay certificate with ``H = K = 0``.
        ``"paper"``: the paper's (lmi2).
    injection_gains : bool
        ``"paper"`` only: False pins ``H = K = 0`` (a linear Luenberger observer
        checked against (lmi2)). The polytopic formulation always has ``H = K =
        0`` and ignores it.

    Returns
    -------
    ObserverDesign
        Certified: :attr:`ObserverDesign.is_certified` is True (and, for
        ``"polytopic"``, so is :attr:`ObserverDesign.is_decay_certified`).

    Raises
    ------
    ObserverDesignInfeasible
        If the solver reports infeasibility or the numbers do not certify.
    DesignError
        For an unknown solver, backend, objective, sector or formulation, a
        solver that is not usable here (MOSEK without licence), bounds that do
        not match, or too many corners for the polytopic formulation.

    Examples
    --------
    >>> from ofrl_drake.examples import make_system
    >>> d = design_observer(make_system("two_state"), ([-2, -2], [2, 2]), 3.0, 0.5)
    >>> d.is_certified, d.is_decay_certified, d.condition_number < 1e3
    (True, True, True)
    >>> p = design_observer(make_system("two_state"), ([-2, -2], [2, 2]), 3.0, 2.0,
    ...                     formulation="paper")
    >>> p.is_certified, p.is_decay_certified
    (True, False)
    """
    if solver not in SOLVERS:
        raise DesignError(f"solver must be one of {SOLVERS}; got {solver!r}.")
    if backend not in BACKENDS:
        raise DesignError(f"backend must be one of {BACKENDS}; got {backend!r}.")
    _check_formulation(formulation, sector)
    alpha, input_bound, margin = _check_numbers(alpha, input_bound, margin)
    box, bounds = _box_and_bounds(system, box, bounds, jacobian_method)
    n, q = system.n, system.q
    pinned = None if injection_gains else (np.zeros((n, q)), np.zeros((n, q)))
    problem = _problem(
        system.output_matrix,
        bounds,
        input_bound,
        alpha,
        margin,
        objective,
        max_gain,
        sector,
        formulation,
        HK=pinned,
    )
    return _finish(problem, bounds, box, input_bound, solver, backend, sector, max_gain)


@dataclass(frozen=True, eq=False)
class DecayRateBracket:
    """What :func:`max_decay_rate` found: the largest certified rate and what lies above.

    The supremum of the certifiable rates lies in ``[certified, infeasible]``
    (``[certified, alpha_max]`` untested above ``alpha_max``). It may not be
    attained: on the two-state example the polytopic supremum is 1, and
    ``cond(P)`` and ``||L||`` of the certified design grow without bound as
    the certified end approaches it, so read them before using the gains.

    Attributes
    ----------
    design : ObserverDesign
        The certified design at the lower end.
    infeasible : float or None
        The smallest rate found not certified (None if ``alpha_max`` certified).
    infeasible_status : str
        Why that rate failed: the solver's infeasibility verdict, or
        ``"inaccurate"`` when the solver returned numbers that failed the numpy
        certificate (no proof of infeasibility).
    tol : float
        The bisection stopped once ``infeasible - certified <= tol``.
    alpha_max : float
        The upper end of the search.
    attempts : int
        Designs solved.
    """

    design: ObserverDesign
    infeasible: float | None
    infeasible_status: str
    tol: float
    alpha_max: float
    attempts: int

    @property
    def certified(self) -> float:
        """The largest rate certified: ``design.alpha``."""
        return self.design.alpha

    @property
    def alpha(self) -> float:
        """Same as :attr:`certified`."""
        return self.design.alpha

    @property
    def condition_number(self) -> float:
        """``cond(P)`` at the certified end."""
        return self.design.condition_number

    @property
    def gain_norm(self) -> float:
        """``||L||_2`` at the certified end."""
        return self.design.gain_norm

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the bracket, cond(P) and ||L|| at the certified end."""
        return {
            "certified": self.certified,
            "infeasible": self.infeasible,
            "infeasible_status": self.infeasible_status,
            "tol": self.tol,
            "alpha_max": self.alpha_max,
            "attempts": self.attempts,
            "condition_number": self.condition_number,
            "gain_norm": self.gain_norm,
        }

    def __str__(self) -> str:
        upper = (
            f"not certified at {self.infeasible:.6g} ({self.infeasible_status})"
            if self.infeasible is not None
            else f"alpha_max = {self.alpha_max:g} certified"
        )
        return (
            f"certified at alpha = {self.certified:.6g} (cond(P) = {self.condition_number:.3g}, "
            f"||L|| = {self.gain_norm:.3g}); {upper}"
        )


def max_decay_rate(
    system: ControlAffineSystem,
    box: Any,
    input_bound: float,
    *,
    alpha_max: float = 10.0,
    tol: float = 1e-3,
    max_gain: float | None = None,
    **kw: Any,
) -> DecayRateBracket:
    """Bisect ``alpha`` for the largest certified rate; return the bracket found.

    Parameters
    ----------
    system, box, input_bound
        As in :func:`design_observer`.
    alpha_max : float
        Upper end of the search; returned directly if it certifies.
    tol : float
        Stop when the bracket ``[certified, not certified]`` is at most this wide.
    max_gain : float, optional
        Cap ``||L||_2 <= max_gain``, enforced as ``||R||_2 <= max_gain`` inside
        the SDP (sufficient since ``P >= I``) and re-checked in numpy.
    **kw
        Passed to :func:`design_observer` (``formulation``, ``solver``,
        ``backend``, ``bounds``, ``margin``, ``objective``, ...). The Jacobian
        bounds are computed once.

    Returns
    -------
    DecayRateBracket
        The certified design at the lower end (``.design``), the rate above it
        that failed (``.infeasible``), and ``cond(P)``, ``||L||`` at the
        certified end. The supremum lies between the two ends and need not be
        attained: ``cond(P)`` and ``||L||`` may blow up as the certified end
        approaches it (on the two-state example, polytopic: supremum 1).

    Raises
    ------
    ObserverDesignInfeasible
        If not even ``alpha = 0`` certifies.
    """
    if not (math.isfinite(alpha_max) and alpha_max > 0):
        raise DesignError(f"alpha_max must be a positive number; got {alpha_max!r}.")
    if not (math.isfinite(tol) and tol > 0):
        raise DesignError(f"tol must be a positive number; got {tol!r}.")
    if kw.get("bounds") is None:
        method = kw.pop("jacobian_method", "certified")
        kw["bounds"] = jacobian_bounds(system, Box.coerce(box, system.n), method)
    attempts = 0

    def attempt(alpha: float) -> ObserverDesign | str:
        nonlocal attempts
        attempts += 1
        try:
            return design_observer(system, box, input_bound, alpha, max_gain=max_gain, **kw)
        except ObserverDesignInaccurate:
            return "inaccurate"
        except ObserverDesignInfeasible as err:
            return err.status

    def bracket(design: ObserverDesign, hi: float | None, status: str) -> DecayRateBracket:
        return DecayRateBracket(design, hi, status, float(tol), float(alpha_max), attempts)

    top = attempt(alpha_max)
    if isinstance(top, ObserverDesign):
        return bracket(top, None, "")
    # Not caught: if even alpha = 0 fails, raise the real error, with its message and status.
    attempts += 1
    best = design_observer(system, box, input_bound, 0.0, max_gain=max_gain, **kw)
    lo, hi, status = 0.0, float(alpha_max), top
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        design = attempt(mid)
        if isinstance(design, ObserverDesign):
            lo, best = mid, design
        else:
            hi, status = mid, design
    return bracket(best, hi, status)
