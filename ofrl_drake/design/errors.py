"""What a design raises: a bad argument, or no certified gains (infeasible or inaccurate)."""

from __future__ import annotations

from ofrl_drake.errors import OfrlError
from ofrl_drake.jacobian_bounds import Box

__all__ = ["DesignError", "ObserverDesignInaccurate", "ObserverDesignInfeasible"]


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
