"""The cvxpy backend: the observer SDP built in cvxpy (the second modelling layer).

Same variables, constraints and objectives as the Drake backend (see
:mod:`ofrl_drake.design.sdp`), for every formulation: ``P = P^T >= I``; the
formulation's LMI ``<= -margin I`` at every vertex or corner
(:meth:`ofrl_drake.design.formulations.Formulation.cvxpy_blocks`, written in
cvxpy expressions directly, independently of the numpy assembly the Drake
backend uses, so agreement of the two backends is a check of both);
``min ||R||_2`` (``+ ||[H K]||_F`` when ``H, K`` are free) by default. The
structured formulations' multipliers ``tau`` are cvxpy variables too, one
vector per structured LMI.
Solvers: Clarabel and SCS, both shipped with cvxpy. cvxpy is imported on the
first solve, so the Drake backend does not pay its import time.
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np

from ofrl_drake.design.errors import DesignError
from ofrl_drake.design.formulations import FORMULATIONS
from ofrl_drake.design.sdp import (
    TIME_LIMIT_OPTIONS,
    LmiProblem,
    SdpBackend,
    SdpSolution,
    solver_time_limit,
)

__all__ = ["CVXPY_SOLVERS", "CvxpyBackend"]

#: The solvers of this backend: our name -> cvxpy's (``cvxpy.CLARABEL``, ``cvxpy.SCS``).
CVXPY_SOLVERS = {"clarabel": "CLARABEL", "scs": "SCS"}
_SOLVER_OPTIONS: dict[str, dict[str, Any]] = {
    "clarabel": {},
    "scs": {"eps_abs": 1e-8, "eps_rel": 1e-8, "max_iters": 200_000},
}


class CvxpyBackend(SdpBackend):
    """The SDP as a ``cvxpy.Problem``, solved by Clarabel or SCS."""

    name = "cvxpy"
    solvers = tuple(CVXPY_SOLVERS)

    def solve(
        self, problem: LmiProblem, solver: str, time_limit: float | None = None
    ) -> SdpSolution:
        """Build and solve ``problem`` in cvxpy.

        Parameters
        ----------
        problem : LmiProblem
            The SDP data.
        solver : {"clarabel", "scs"}
            The cvxpy solver.
        time_limit : float, optional
            Seconds for building and solving, through the solver's own
            time-limit option (:data:`~ofrl_drake.design.sdp.TIME_LIMIT_OPTIONS`).

        Returns
        -------
        SdpSolution
            Numbers (None if the solver returned none) and the cvxpy status.

        Raises
        ------
        DesignError
            For a solver other than Clarabel or SCS, or one cvxpy cannot find.
        """
        import cvxpy as cp

        if solver not in CVXPY_SOLVERS:
            raise DesignError(
                f"the cvxpy backend supports solvers {sorted(CVXPY_SOLVERS)}; got "
                f"{solver!r}. Use backend='drake' for 'csdp' or 'mosek'."
            )
        if CVXPY_SOLVERS[solver] not in cp.installed_solvers():
            raise DesignError(f"cvxpy cannot find the solver {solver!r}; install it.")
        start = time.perf_counter()
        n, q = problem.n, problem.q
        eye = np.eye(n)
        P = cp.Variable((n, n), symmetric=True, name="P")
        R = cp.Variable((n, q), name="R") if problem.L is None else P @ problem.L
        H: Any  # a cp.Variable to solve for, or the pinned gains (ndarray)
        K: Any
        if problem.HK is None:
            H = cp.Variable((n, q), name="H")
            K = cp.Variable((n, q), name="K")
        else:
            H, K = problem.HK
        tau = [cp.Variable(r, name=f"tau{i}") for i, r in enumerate(problem.multiplier_counts)]
        constraints = [P - eye >> 0]
        form = FORMULATIONS[problem.formulation]
        for block in form.cvxpy_blocks(problem, P, R, H, K, tau if tau else None):
            constraints.append(block >> 0)
        if problem.max_gain is not None:
            constraints.append(cp.sigma_max(R) <= float(problem.max_gain))
        if problem.objective == "min_gain":
            cost = cp.sigma_max(R)
            if problem.HK is None:
                cost = cost + cp.norm(cp.hstack([cp.vec(H, order="F"), cp.vec(K, order="F")]))
            objective = cp.Minimize(cost)
        elif problem.objective == "min_condition":
            objective = cp.Minimize(cp.lambda_max(P))
        else:
            objective = cp.Minimize(0)
        prob = cp.Problem(objective, constraints)
        options = dict(_SOLVER_OPTIONS[solver])
        limit = solver_time_limit(solver, time_limit, time.perf_counter() - start)
        if limit is not None:
            options[TIME_LIMIT_OPTIONS[solver]] = limit
        with warnings.catch_warnings():
            # "Solution may be inaccurate": the numpy certificate decides.
            warnings.simplefilter("ignore", UserWarning)
            try:
                prob.solve(solver=CVXPY_SOLVERS[solver], **options)
            except cp.error.SolverError as err:
                elapsed = time.perf_counter() - start
                return SdpSolution(None, None, None, None, f"solver_error: {err}", False, elapsed)
        elapsed = time.perf_counter() - start
        status = str(prob.status)
        # cvxpy reports a solver's time limit as "user_limit" (no numbers) or,
        # with numbers, as "optimal_inaccurate".
        timed_out = time_limit is not None and (
            status == cp.USER_LIMIT or (status != cp.OPTIMAL and elapsed >= time_limit)
        )
        infeasible = status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE)
        if infeasible or P.value is None:
            return SdpSolution(
                None, None, None, None, status, infeasible, elapsed, timed_out=timed_out
            )
        Pv = np.asarray(P.value, dtype=float)
        Rv = np.asarray(R.value, dtype=float) if problem.L is None else Pv @ problem.L
        if problem.HK is None:
            Hv = np.asarray(H.value, dtype=float)
            Kv = np.asarray(K.value, dtype=float)
        else:
            Hv, Kv = problem.HK
        tau_v = [np.asarray(t.value, dtype=float).ravel() for t in tau] if tau else None
        return SdpSolution(Pv, Rv, Hv, Kv, status, False, elapsed, tau_v, timed_out)
