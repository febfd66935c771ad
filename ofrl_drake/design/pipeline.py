"""The steps every observer design takes, from checked inputs to a certified design.

Check the numbers, the box and the Jacobian bounds; build the SDP of the
formulation (:mod:`ofrl_drake.design.formulations`); solve it with a backend
(:mod:`ofrl_drake.design.backends`); and keep the numbers only if they certify.
Whatever the solver reports, the returned numbers are accepted only if the
certificate of the formulation, recomputed in numpy from ``P, L, H, K, C`` and
the bounds alone, is negative at every vertex; otherwise
:class:`~ofrl_drake.design.ObserverDesignInfeasible` (or its subclass
:class:`~ofrl_drake.design.ObserverDesignInaccurate`) is raised.

Shared by :func:`ofrl_drake.design.design_observer` and
:meth:`ofrl_drake.design.ObserverDesign.from_gains`, which passes its own class.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from ofrl_drake.checks import is_real_number
from ofrl_drake.design.backends import SOLVERS, get_backend
from ofrl_drake.design.errors import DesignError, ObserverDesignInaccurate, ObserverDesignInfeasible
from ofrl_drake.design.formulations import get_formulation
from ofrl_drake.design.sdp import OBJECTIVES, LmiProblem, SdpSolution
from ofrl_drake.errors import WallTimeExceeded, lmi_time_left
from ofrl_drake.jacobian_bounds import Box, JacobianBounds, jacobian_bounds
from ofrl_drake.model import ControlAffineSystem, require_system

if TYPE_CHECKING:
    from ofrl_drake.design.result import ObserverDesign


def _check_request(
    solver: str,
    backend: str,
    formulation: str,
    sector: str,
    alpha: float,
    input_bound: float,
    margin: float,
    time_limit: float | None,
    max_gain: float | None = None,
    objective: str = "min_condition",
) -> tuple[float, float, float, float | None, float | None]:
    """Check a design request before anything slow (the Jacobian bounds) runs.

    The one argument check of :func:`~ofrl_drake.design.design_observer` and
    :meth:`~ofrl_drake.design.ObserverDesign.from_gains`, in this order:
    solver, backend, formulation and sector, ``alpha``, ``input_bound``,
    ``margin``, ``time_limit``, ``max_gain``, objective.

    Returns
    -------
    alpha, input_bound, margin : float
    time_limit, max_gain : float or None

    Raises
    ------
    DesignError
        Naming the first bad argument.
    """
    if solver not in SOLVERS:
        raise DesignError(f"solver must be one of {SOLVERS}; got {solver!r}.")
    get_backend(backend)
    get_formulation(formulation, sector)
    alpha, input_bound, margin = _check_numbers(alpha, input_bound, margin)
    time_limit = _check_time_limit(time_limit)
    max_gain = _check_max_gain(max_gain)
    _check_objective(objective)
    return alpha, input_bound, margin, time_limit, max_gain


def _check_objective(objective: str) -> None:
    if objective not in OBJECTIVES:
        raise DesignError(f"objective must be one of {OBJECTIVES}; got {objective!r}.")


def _check_numbers(alpha: float, input_bound: float, margin: float) -> tuple[float, float, float]:
    for name, value in (
        ("alpha", alpha),
        ("input_bound", input_bound),
        ("margin", margin),
    ):
        if not (is_real_number(value) and math.isfinite(value) and value >= 0):
            raise DesignError(f"{name} must be a finite number >= 0; got {value!r}.")
    return float(alpha), float(input_bound), float(margin)


def _box_and_bounds(
    system: ControlAffineSystem,
    box: Any,
    bounds: JacobianBounds | None,
    jacobian_method: str,
    time_limit: float | None = None,
) -> tuple[Box, JacobianBounds, float | None]:
    """The design box, its bounds (computed unless given) and the time left of ``time_limit``.

    Bounds computed here get ``time_limit`` as their ``max_wall_time`` (the
    refinement stops there with sound bounds); the LMI gets what they leave.

    Raises
    ------
    WallTimeExceeded
        If the bounds leave nothing of ``time_limit`` (or their symbolic
        Jacobians are not done by then).
    DesignError
        If ``system`` is not a :class:`~ofrl_drake.model.ControlAffineSystem`,
        or ``bounds`` are not :class:`JacobianBounds` of the system and box.
    """
    require_system(system, "the observer design's system", DesignError)
    box = Box.coerce(box, system.n)
    if bounds is None:
        start = time.monotonic()
        bounds = jacobian_bounds(system, box, jacobian_method, max_wall_time=time_limit)
        left = lmi_time_left(
            time_limit,
            start,
            "time_limit",
            "allow more time, shrink the box, or pass bounds computed beforehand",
        )
        return box, bounds, left
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
    return box, bounds, time_limit


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
    form = get_formulation(formulation, sector)
    _check_objective(objective)
    max_gain = _check_max_gain(max_gain)
    return form.problem(
        C, bounds, input_bound, alpha, margin, objective, max_gain, sector, L=L, HK=HK
    )


def _check_max_gain(max_gain: float | None) -> float | None:
    """``max_gain`` as a float (None: no bound), else a :class:`DesignError`."""
    if max_gain is None:
        return None
    if not (is_real_number(max_gain) and math.isfinite(max_gain) and max_gain > 0):
        raise DesignError(
            f"max_gain must be a positive number (a bound on ||L||_2) or None; got {max_gain!r}."
        )
    return float(max_gain)


def _relax_hint(max_gain: float | None, inaccurate: bool) -> str:
    hint = "try a smaller alpha, a smaller box, a smaller input bound"
    if max_gain is not None:
        hint += ", a larger max_gain"
    if inaccurate:
        hint += ", a larger margin or a more accurate solver ('clarabel')"
    return hint


def _smaller_lmi(formulation: str) -> str:
    hint = "a smaller box or fewer uncertain Jacobian entries"
    if not formulation.startswith("structured"):
        hint += ", or formulation 'structured', one LMI instead of one per corner"
    return hint


def _check_time_limit(time_limit: float | None) -> float | None:
    if time_limit is None:
        return None
    if not (is_real_number(time_limit) and math.isfinite(time_limit) and time_limit > 0):
        raise DesignError(
            f"time_limit must be a positive number of seconds or None; got {time_limit!r}."
        )
    return float(time_limit)


def _solve(problem: LmiProblem, solver: str, backend: str, time_limit: float | None) -> SdpSolution:
    return get_backend(backend).solve(problem, solver, time_limit)


def _finish(
    design_type: type[ObserverDesign],
    problem: LmiProblem,
    bounds: JacobianBounds,
    box: Box,
    input_bound: float,
    solver: str,
    backend: str,
    sector: str,
    max_gain: float | None,
    time_limit: float | None = None,
) -> ObserverDesign:
    """Solve ``problem`` and return the certified ``design_type`` (ObserverDesign or a subclass).

    ``time_limit`` bounds the solve (seconds, building included; None: no limit).

    Raises
    ------
    WallTimeExceeded
        If the solve ran out of ``time_limit``.
    ObserverDesignInfeasible
        If the solver reports infeasibility or returns no numbers.
    ObserverDesignInaccurate
        If the numbers are not finite, ``P`` is singular, or the numpy
        certificate of the formulation fails.
    """
    sol = _solve(problem, solver, backend, time_limit)
    if sol.timed_out:
        raise WallTimeExceeded(
            f"the observer LMI ({problem.formulation}, {solver}/{backend}) ran out of its "
            f"time limit of {time_limit:.3g} s (status {sol.status}; from a scenario, the "
            "time max_wall_time (--max-wall) leaves after the Jacobian bounds); allow more "
            f"wall time, or make the LMI smaller ({_smaller_lmi(problem.formulation)}).",
            step="LMI solve",
        )
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

    if sol.infeasible or sol.P is None or sol.R is None or sol.H is None or sol.K is None:
        raise fail(f"solver status {sol.status}", inaccurate=not sol.infeasible)
    if problem.structured is not None and sol.tau is None:
        raise fail(f"solver status {sol.status}, no multipliers returned")
    numbers = [sol.P, sol.R, sol.H, sol.K, *(sol.tau or [])]
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
        if not np.all(np.isfinite(L)):
            raise fail(
                f"solver status {sol.status}, P too close to singular for L = P^-1 R",
                kind=ObserverDesignInaccurate,
            )
    design = design_type(
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
        tau=tuple(sol.tau or ()),
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
