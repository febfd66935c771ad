"""The observer SDP of :mod:`ofrl_drake.design`, built in cvxpy (second backend).

Same variables, constraints and objectives as the Drake backend (see the
:mod:`ofrl_drake.design` docstring), for both formulations: ``P = P^T >= I``;
``"paper"``: (lmi2) ``<= -margin I`` at every input vertex; ``"polytopic"``:
``A^T P + P A - C^T R^T - R C + 2 alpha P <= -margin I`` at every corner matrix
``A``; ``min ||R||_2`` (``+ ||[H K]||_F`` when ``H, K`` are free) by default.
The LMIs are written here directly in cvxpy expressions, independently of the
numpy assembly the Drake backend uses, so agreement of the two backends is a
check of both. Solvers: Clarabel and SCS, both shipped with cvxpy. The numbers
are certified in numpy exactly as for the Drake backend, and the same
:class:`ObserverDesign` is returned with ``backend="cvxpy"``.
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import cvxpy as cp
import numpy as np

from ofrl_drake.design import (
    DEFAULT_MARGIN,
    DesignError,
    LmiProblem,
    ObserverDesign,
    SdpSolution,
    design_observer,
)
from ofrl_drake.jacobian_bounds import JacobianBounds
from ofrl_drake.model import ControlAffineSystem

__all__ = ["CVXPY_SOLVERS", "design_observer_cvxpy", "solve_cvxpy"]

CVXPY_SOLVERS = {"clarabel": cp.CLARABEL, "scs": cp.SCS}
_SOLVER_OPTIONS: dict[str, dict[str, Any]] = {
    "clarabel": {},
    "scs": {"eps_abs": 1e-8, "eps_rel": 1e-8, "max_iters": 200_000},
}


def _sym(M: cp.Expression) -> cp.Expression:
    return 0.5 * (M + M.T)


def solve_cvxpy(problem: LmiProblem, solver: str) -> SdpSolution:
    """Build and solve ``problem`` in cvxpy.

    Parameters
    ----------
    problem : LmiProblem
        The SDP data (from :mod:`ofrl_drake.design`).
    solver : {"clarabel", "scs"}
        The cvxpy solver.

    Returns
    -------
    SdpSolution
        Numbers (None if the solver returned none) and the cvxpy status.

    Raises
    ------
    DesignError
        For a solver other than Clarabel or SCS, or one cvxpy cannot find.
    """
    if solver not in CVXPY_SOLVERS:
        raise DesignError(
            f"the cvxpy backend supports solvers {sorted(CVXPY_SOLVERS)}; got "
            f"{solver!r}. Use backend='drake' for 'csdp' or 'mosek'."
        )
    if CVXPY_SOLVERS[solver] not in cp.installed_solvers():
        raise DesignError(f"cvxpy cannot find the solver {solver!r}; install it.")
    start = time.perf_counter()
    n, q, C = problem.n, problem.q, problem.C
    eye = np.eye(n)
    P = cp.Variable((n, n), symmetric=True, name="P")
    R = cp.Variable((n, q), name="R") if problem.L is None else P @ problem.L
    if problem.HK is None:
        H = cp.Variable((n, q), name="H")
        K = cp.Variable((n, q), name="K")
    else:
        H, K = problem.HK
    constraints = [P - eye >> 0]
    if problem.formulation == "paper":
        for _, A, Jf21, Jg21 in problem.vertices:
            J21 = Jf21 @ (eye - H @ C) + Jg21 @ (eye - K @ C)
            M11 = A.T @ P + P @ A - C.T @ R.T - R @ C + 2.0 * problem.alpha * P
            M21 = P - J21
            M = cp.bmat([[M11, M21.T], [M21, -2.0 * eye]])
            constraints.append(_sym(-M) - problem.margin * np.eye(2 * n) >> 0)
    else:
        for A in problem.corners:
            M = A.T @ P + P @ A - C.T @ R.T - R @ C + 2.0 * problem.alpha * P
            constraints.append(_sym(-M) - problem.margin * eye >> 0)
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
    with warnings.catch_warnings():
        # "Solution may be inaccurate": the numpy certificate decides.
        warnings.simplefilter("ignore", UserWarning)
        try:
            prob.solve(solver=CVXPY_SOLVERS[solver], **_SOLVER_OPTIONS[solver])
        except cp.error.SolverError as err:
            elapsed = time.perf_counter() - start
            return SdpSolution(None, None, None, None, f"solver_error: {err}", False, elapsed)
    elapsed = time.perf_counter() - start
    status = str(prob.status)
    infeasible = status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE)
    if infeasible or P.value is None:
        return SdpSolution(None, None, None, None, status, infeasible, elapsed)
    Pv = np.asarray(P.value, dtype=float)
    Rv = np.asarray(R.value, dtype=float) if problem.L is None else Pv @ problem.L
    if problem.HK is None:
        Hv = np.asarray(H.value, dtype=float)
        Kv = np.asarray(K.value, dtype=float)
    else:
        Hv, Kv = problem.HK
    return SdpSolution(Pv, Rv, Hv, Kv, status, False, elapsed)


def design_observer_cvxpy(
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
    sector: str = "sign_correct",
    formulation: str = "polytopic",
    injection_gains: bool = True,
) -> ObserverDesign:
    """:func:`ofrl_drake.design.design_observer` with ``backend="cvxpy"``.

    Parameters and exceptions are those of
    :func:`ofrl_drake.design.design_observer`; ``solver`` is "clarabel" or
    "scs".

    Returns
    -------
    ObserverDesign
        Certified, with ``backend == "cvxpy"``.
    """
    return design_observer(
        system,
        box,
        input_bound,
        alpha,
        bounds=bounds,
        jacobian_method=jacobian_method,
        solver=solver,
        margin=margin,
        objective=objective,
        max_gain=max_gain,
        backend="cvxpy",
        sector=sector,
        formulation=formulation,
        injection_gains=injection_gains,
    )
