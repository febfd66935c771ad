"""The largest certified decay rate: :func:`max_decay_rate` and its :class:`DecayRateBracket`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ofrl_drake.design.driver import design_observer
from ofrl_drake.design.errors import DesignError, ObserverDesignInaccurate, ObserverDesignInfeasible
from ofrl_drake.design.result import ObserverDesign
from ofrl_drake.jacobian_bounds import Box, jacobian_bounds
from ofrl_drake.model import ControlAffineSystem

__all__ = ["DecayRateBracket", "max_decay_rate"]


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
