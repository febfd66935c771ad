"""The observer SDP as data, what a backend returns, and what a backend is.

The semidefinite program, in either backend (:mod:`ofrl_drake.design.backend_drake`,
:mod:`ofrl_drake.design.backend_cvxpy`):

* ``P = P^T >= I`` (normalizes the scale of the homogeneous LMI, so that
  ``lambda_max(P)`` is a bound on ``cond(P)`` and ``||L|| <= ||R||``);
* the formulation's LMI ``<= -margin I`` at every vertex (and corner)
  (:mod:`ofrl_drake.design.formulations`): a strict margin, so the numbers the
  solver returns still certify after rounding;
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
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ofrl_drake.design.errors import DesignError
from ofrl_drake.structured_lmi import StructuredLmi

__all__ = [
    "DEFAULT_MARGIN",
    "OBJECTIVES",
    "TIME_LIMIT_OPTIONS",
    "LmiProblem",
    "SdpBackend",
    "SdpSolution",
    "solver_time_limit",
]

OBJECTIVES = ("min_gain", "min_condition", "feasibility")
DEFAULT_MARGIN = 1e-3
#: Each solver's own wall-time option (seconds), the same name in Drake's
#: ``SetSolverOption`` and in cvxpy's ``solve(**options)``. CSDP has none.
TIME_LIMIT_OPTIONS = {
    "clarabel": "time_limit",
    "scs": "time_limit_secs",
    "mosek": "MSK_DPAR_OPTIMIZER_MAX_TIME",
}
#: The least time a solver is given (its option must be positive): a build
#: that used the whole limit leaves the solver this, and it reports running out.
_MIN_SOLVER_TIME = 1e-6


def solver_time_limit(solver: str, time_limit: float | None, elapsed: float) -> float | None:
    """The seconds left to ``solver`` after a build of ``elapsed`` seconds (None: no limit).

    Raises
    ------
    DesignError
        If ``time_limit`` is given for a solver without a time-limit option
        (CSDP).
    """
    if time_limit is None:
        return None
    if solver not in TIME_LIMIT_OPTIONS:
        raise DesignError(
            f"solver {solver!r} has no time limit, so max_wall_time (--max-wall) = "
            f"{time_limit:g} s cannot bound the LMI solve; use solver 'clarabel' or "
            "'scs', or drop the limit."
        )
    return max(float(time_limit) - elapsed, _MIN_SOLVER_TIME)


@dataclass(frozen=True, eq=False)
class LmiProblem:
    """The numeric data of one observer SDP, shared by both backends.

    Attributes
    ----------
    formulation : str
        The name of its formulation, a key of
        :data:`ofrl_drake.design.formulations.FORMULATIONS` (``"polytopic"`` or
        ``"paper"``), which built it and owns its LMI blocks.
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
        only: ``"polytopic"`` and ``"structured"`` always pin them).
    structured : StructuredLmi or None
        ``"structured"``: the norm-bounded model of the Jacobian box at each
        distinct input vertex (:func:`ofrl_drake.structured_lmi.structured_lmi`);
        its S-procedure multipliers ``tau`` are decision variables too
        (``multiplier_counts`` of them per model). None otherwise.
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
    structured: StructuredLmi | None = None

    @property
    def multiplier_counts(self) -> list[int]:
        """How many S-procedure multipliers each structured LMI has (empty if none)."""
        return [] if self.structured is None else self.structured.multiplier_counts

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
    tau : list of ndarray or None
        The S-procedure multipliers of each structured LMI (``"structured"``
        formulations only; None otherwise or without a solution).
    timed_out : bool
        True if the solve stopped at its ``time_limit`` (the numbers, if any,
        are not to be trusted).
    """

    P: np.ndarray | None
    R: np.ndarray | None
    H: np.ndarray | None
    K: np.ndarray | None
    status: str
    infeasible: bool
    solve_time: float
    tau: list[np.ndarray] | None = None
    timed_out: bool = False


class SdpBackend(ABC):
    """A modelling layer that builds an :class:`LmiProblem` and solves it.

    Attributes
    ----------
    name : str
        What ``design_observer(backend=...)`` calls it.
    solvers : tuple of str
        The solver names it accepts.
    """

    name: ClassVar[str]
    solvers: ClassVar[tuple[str, ...]]

    @abstractmethod
    def solve(
        self, problem: LmiProblem, solver: str, time_limit: float | None = None
    ) -> SdpSolution:
        """Build and solve ``problem`` with ``solver``.

        Parameters
        ----------
        problem : LmiProblem
            The SDP data.
        solver : str
            One of :attr:`solvers`.
        time_limit : float, optional
            Wall-clock seconds for building and solving together: the solver
            gets what the build leaves (its own time-limit option), and
            :attr:`SdpSolution.timed_out` says whether it ran out. Default: no
            limit.

        Returns
        -------
        SdpSolution
            Numbers (None if the solver returned none) and the solver's status.

        Raises
        ------
        DesignError
            For a solver this backend does not offer, or one not usable here,
            or a ``time_limit`` for a solver that has no time limit (CSDP).
        """
