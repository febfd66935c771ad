"""The Drake backend: the observer SDP as a ``pydrake.solvers.MathematicalProgram``.

Every LMI goes to ``AddLinearMatrixInequalityConstraint`` as its numeric
coefficient matrices ``F_0 + sum_i z_i F_i``, read off the pure-numpy LMI
blocks of the formulation (:meth:`ofrl_drake.design.formulations.Formulation.lmi_blocks`,
assembled by :mod:`ofrl_drake.lmi`), which are affine in the decision variables
``z``, so no symbolic matrix arithmetic is needed. Solvers: Clarabel, SCS,
CSDP and MOSEK (with a licence).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
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

from ofrl_drake.design.errors import DesignError
from ofrl_drake.design.formulations import FORMULATIONS
from ofrl_drake.design.sdp import (
    TIME_LIMIT_OPTIONS,
    LmiProblem,
    SdpBackend,
    SdpSolution,
    solver_time_limit,
)
from ofrl_drake.lmi import block_matrix

__all__ = ["DrakeBackend"]

#: The solvers of this backend, by the names ``design_observer(solver=...)`` takes.
_MAKERS = {
    "clarabel": ClarabelSolver,
    "scs": ScsSolver,
    "csdp": CsdpSolver,
    "mosek": MosekSolver,
}
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
#: :func:`_coefficients` reads the unit vectors in stacks of at most this many
#: block entries (floats) in all: 160 MB.
_COEFFICIENT_ENTRIES = 20_000_000
# SCS (first order) needs tight tolerances to return numbers that certify.
_DRAKE_OPTIONS: dict[str, dict[str, float | int]] = {
    "scs": {"eps_abs": 1e-8, "eps_rel": 1e-8, "max_iters": 200_000},
}


def _drake_solver(name: str) -> Any:
    if name not in _MAKERS:
        raise DesignError(f"solver must be one of {tuple(_MAKERS)}; got {name!r}.")
    solver = _MAKERS[name]()
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

    ``z = [vech(P), vec(R), tau, vec(H), vec(K), t, s]``, each part present
    only when it is a variable: ``R`` unless ``L`` is pinned, ``tau`` (the
    S-procedure multipliers of every structured LMI, concatenated) for a
    structured formulation, ``H, K`` unless pinned, ``t`` for ``min_gain``,
    ``s`` for ``min_gain`` with free ``H, K`` and for ``min_condition``.
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
        if problem.structured is not None:
            names.append(("tau", sum(problem.multiplier_counts)))
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
        """``P, R, H, K`` (and ``tau``, ``t, s`` if present) from ``z``; affine in ``z``.

        ``z`` of shape ``(size,)`` gives matrices; a stack ``(B, size)`` gives
        stacks ``(B, n, n)``, ``(B, n, q)``, ``(B, r)`` and ``(B,)`` (pinned
        ``H, K`` stay unstacked and broadcast).
        """
        n, q, p = self.problem.n, self.problem.q, self.problem
        lead = z.shape[:-1]
        parts: dict[str, Any] = {}
        pos = 0
        for name, k in self.names:
            parts[name] = z[..., pos : pos + k]
            pos += k
        P = np.zeros((*lead, n, n))
        rows, cols = np.triu_indices(n)
        P[..., rows, cols] = parts["P"]
        P[..., cols, rows] = parts["P"]
        out: dict[str, Any] = {"P": P}
        out["R"] = parts["R"].reshape(*lead, n, q) if p.L is None else P @ p.L
        if p.HK is None:
            out["H"] = parts["H"].reshape(*lead, n, q)
            out["K"] = parts["K"].reshape(*lead, n, q)
        else:
            out["H"], out["K"] = p.HK
        out["tau"] = None
        if "tau" in parts:
            out["tau"] = np.split(parts["tau"], np.cumsum(p.multiplier_counts)[:-1], axis=-1)
        for name in ("t", "s"):
            if name in parts:
                out[name] = parts[name][..., 0] if lead else float(parts[name][0])
        return out


def _psd_blocks(problem: LmiProblem, v: dict[str, Any]) -> list[np.ndarray]:
    """Every matrix the SDP asks to be positive semidefinite, at the numbers ``v``.

    Affine in the decision vector (see :class:`_Layout`), so the Drake backend
    reads the coefficient matrices ``F_i`` off it. ``v`` may hold stacks (from
    a stack of decision vectors, :meth:`_Layout.unpack`); every block is then
    a stack ``(B, size, size)``.
    """
    n, q = problem.n, problem.q
    P, R, H, K = v["P"], v["R"], v["H"], v["K"]
    eye = np.eye(n)
    blocks = [P - eye]
    blocks += FORMULATIONS[problem.formulation].lmi_blocks(problem, P, R, H, K, v["tau"])
    Rt = np.swapaxes(R, -1, -2)
    if problem.max_gain is not None:
        g = float(problem.max_gain)
        blocks.append(block_matrix([[g * eye, R], [Rt, g * np.eye(q)]]))
    if problem.objective == "min_gain":
        t = np.asarray(v["t"])[..., None, None]
        blocks.append(block_matrix([[t * eye, R], [Rt, t * np.eye(q)]]))
        if problem.HK is None:
            s = np.asarray(v["s"])[..., None, None]
            lead = np.shape(v["s"])
            w = np.concatenate([H.reshape(*lead, -1), K.reshape(*lead, -1)], axis=-1)[..., :, None]
            blocks.append(block_matrix([[s, np.swapaxes(w, -1, -2)], [w, s * np.eye(w.shape[-2])]]))
    elif problem.objective == "min_condition":
        blocks.append(np.asarray(v["s"])[..., None, None] * eye - P)
    return [0.5 * (B + np.swapaxes(B, -1, -2)) for B in blocks]


def _coefficients(problem: LmiProblem, layout: _Layout) -> list[tuple[np.ndarray, list[int]]]:
    """Each PSD block's coefficient matrices ``[F_0, F_i, ...]`` and the ``i`` that appear.

    ``F_0`` is :func:`_psd_blocks` at ``z = 0`` and ``F_i`` its change at the
    unit vector ``e_i`` (exact for an affine map). The unit vectors are
    evaluated in stacks of up to :data:`_COEFFICIENT_ENTRIES` block entries in
    all, with one call of the (vectorized) block assembly per stack, and only
    the ``F_i`` that are not zero are kept: a structured LMI's multiplier
    appears in its own block only.
    """
    N = layout.size
    F0 = _psd_blocks(problem, layout.unpack(np.zeros(N)))
    entries = sum(B.size for B in F0)
    chunk = int(max(1, min(N, _COEFFICIENT_ENTRIES // max(entries, 1))))
    out: list[tuple[list[np.ndarray], list[int]]] = [([B0], []) for B0 in F0]
    for start in range(0, N, chunk):
        stop = min(N, start + chunk)
        Z = np.zeros((stop - start, N))
        Z[np.arange(stop - start), np.arange(start, stop)] = 1.0
        for (matrices, used), B, B0 in zip(
            out, _psd_blocks(problem, layout.unpack(Z)), F0, strict=True
        ):
            D = B - B0
            for i in np.flatnonzero(np.any(D != 0, axis=(-2, -1))):
                matrices.append(D[i])
                used.append(start + int(i))
    return [(np.asarray(m), u) for m, u in out]


def _drake_program(problem: LmiProblem) -> tuple[MathematicalProgram, np.ndarray, _Layout]:
    """The SDP as a ``MathematicalProgram``; returns it, ``z`` and its layout.

    Each LMI ``F_0 + sum_i z_i F_i >= 0`` is added with its numeric ``F_i``
    (:func:`_coefficients`), keeping only the variables that appear in that
    block.
    """
    layout = _Layout.of(problem)
    prog = MathematicalProgram()
    z = np.concatenate([prog.NewContinuousVariables(k, name) for name, k in layout.names])
    N = layout.size
    for matrices, used in _coefficients(problem, layout):
        prog.AddLinearMatrixInequalityConstraint(list(matrices), z[used])
    if problem.objective in ("min_gain", "min_condition"):
        cost = np.zeros(N)
        pos = 0
        for name, k in layout.names:
            if name in ("t", "s"):
                cost[pos] = 1.0
            pos += k
        prog.AddLinearCost(cost, 0.0, z)  # type: ignore[arg-type]  # pydrake array stub
    return prog, z, layout


class DrakeBackend(SdpBackend):
    """The SDP as a Drake ``MathematicalProgram``, solved by a Drake solver."""

    name = "drake"
    solvers = tuple(_MAKERS)

    def solve(
        self, problem: LmiProblem, solver: str, time_limit: float | None = None
    ) -> SdpSolution:
        """Build and solve ``problem`` with ``pydrake.solvers.MathematicalProgram``.

        ``time_limit`` (seconds, building included) goes to the solver's own
        time-limit option (:data:`~ofrl_drake.design.sdp.TIME_LIMIT_OPTIONS`).

        Raises
        ------
        DesignError
            For an unknown solver, one not usable here (MOSEK without licence),
            or a ``time_limit`` for CSDP, which has none.
        """
        drake_solver = _drake_solver(solver)
        solver_time_limit(solver, time_limit, 0.0)  # refuse CSDP before the build
        start = time.perf_counter()
        prog, z, layout = _drake_program(problem)
        for key, value in _DRAKE_OPTIONS.get(solver, {}).items():
            prog.SetSolverOption(drake_solver.solver_id(), key, value)
        limit = solver_time_limit(solver, time_limit, time.perf_counter() - start)
        if limit is not None:
            prog.SetSolverOption(drake_solver.solver_id(), TIME_LIMIT_OPTIONS[solver], limit)
        result = drake_solver.Solve(prog)
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
        clean = code == SolutionResult.kSolutionFound and (scs is None or int(scs) == 1)
        # Clarabel says "MaxTime"; SCS and MOSEK return what they have, inaccurate.
        timed_out = time_limit is not None and (
            "MaxTime" in status or (not clean and elapsed >= time_limit)
        )
        infeasible = code in (
            SolutionResult.kInfeasibleConstraints,
            SolutionResult.kInfeasibleOrUnbounded,
        )
        if infeasible:
            return SdpSolution(None, None, None, None, status, True, elapsed)
        v = layout.unpack(np.asarray(result.GetSolution(z), dtype=float))
        return SdpSolution(
            v["P"], v["R"], v["H"], v["K"], status, False, elapsed, v["tau"], timed_out
        )
