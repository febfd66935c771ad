"""Exceptions raised by ofrl_drake.

Every error names the offending value and how to fix it. All of them derive
from :class:`ValueError`, so callers that only care about "bad input" can catch
that one type; the command-line tool prints them on one line and exits 2.
"""

from __future__ import annotations

import time

__all__ = [
    "SMOOTH_FORMS",
    "InitialPolicyWarning",
    "ModelError",
    "OfrlError",
    "OutputError",
    "RunFolderError",
    "ScenarioError",
    "ScenarioTypeError",
    "SwapError",
    "TargetWarning",
    "WallTimeExceeded",
    "is_domain_error",
    "lmi_time_left",
    "one_line",
    "status_line",
]


class OfrlError(ValueError):
    """Base class for every input error raised by ofrl_drake."""


class ModelError(OfrlError):
    """A model, basis, gain or point set has the wrong shape or non-finite values."""


class ScenarioError(OfrlError):
    """A scenario file or scenario object holds a missing, unknown or bad key."""


class ScenarioTypeError(ScenarioError, TypeError):
    """What was given as a scenario is not one (a path, a dict...): also a ``TypeError``."""


class SwapError(OfrlError):
    """A block swapped into the closed loop does not have the expected ports."""


class OutputError(OfrlError):
    """An output path cannot be written safely (a file in the way, a foreign folder...)."""


class RunFolderError(OfrlError):
    """A run folder cannot be read back: a file missing, damaged, or not fitting the others.

    Raised by :meth:`ofrl_drake.SimulationResult.load` and ``ofrl-drake plot``
    for the folder ``ofrl-drake run`` (or :meth:`~ofrl_drake.SimulationResult.save`)
    writes; the message names the file and how to get a good one.
    """


class WallTimeExceeded(OfrlError):
    """A step ran out of its wall-time budget (``max_wall_time``, ``--max-wall``).

    Raised by the steps of an observer design that cannot return a sound
    partial result: the symbolic Jacobians and the LMI solve. The message names
    the step, the budget and how to allow more.

    Attributes
    ----------
    step : str
        What was running when the budget ran out.
    """

    def __init__(self, message: str, *, step: str) -> None:
        super().__init__(message)
        self.step = step


def lmi_time_left(budget: float | None, start: float, budget_name: str, fix: str) -> float | None:
    """Seconds of an observer design's ``budget`` the Jacobian bounds left for its LMI.

    Parameters
    ----------
    budget : float or None
        The whole design's seconds (None: no limit, and None is returned).
    start : float
        ``time.monotonic()`` when the bounds began.
    budget_name, fix : str
        How the message names the budget (``"time_limit"``, ``"max_wall_time
        (--max-wall)"``) and what it suggests.

    Raises
    ------
    WallTimeExceeded
        If the bounds used the whole budget (step ``"Jacobian bounds"``).
    """
    if budget is None:
        return None
    used = time.monotonic() - start
    if used >= budget:
        raise WallTimeExceeded(
            f"the observer design's Jacobian bounds took {used:.3g} s of {budget_name} = "
            f"{budget:g} s, leaving nothing for the LMI; {fix}.",
            step="Jacobian bounds",
        )
    return budget - used


def is_domain_error(err: BaseException) -> bool:
    """True for Drake's symbolic math refusing an argument, e.g. ``log(nan)`` or ``sqrt(-1)``.

    Drake raises it as a ``ValueError`` from a diagram's evaluation, and a
    solver such as SNOPT passes its text on inside a ``RuntimeError``.
    """
    return "out of domain" in str(err)


def one_line(value: object, limit: int | None = None) -> str:
    """``str(value)`` (an error, a message) on one line: every run of whitespace one space.

    ``limit`` keeps the first so many characters (None: all).
    """
    text = " ".join(str(value).split())
    return text if limit is None else text[:limit]


def status_line(err: BaseException) -> str:
    """An error as the one-line status of a run in a sweep.

    ``"timeout: <message>"`` for :class:`WallTimeExceeded`, like a run the
    guard stopped; ``"<ExceptionType>: <message>"`` otherwise (the type alone
    for an empty message, as plants' import errors always read).
    """
    head = "timeout" if isinstance(err, WallTimeExceeded) else type(err).__name__
    text = one_line(err)
    return f"{head}: {text}" if text else head


#: How to write a branch of ``f`` or ``g`` (``|x|``, ``sign``, ``max``) in the smooth form
#: the symbolic Jacobians and the certified bounds need.
SMOOTH_FORMS = (
    "Write them in a smooth form, with a small eps > 0: np.sqrt(x**2 + eps) for |x|, "
    "np.tanh(x / eps) for sign(x), (a + b + np.sqrt((a - b)**2 + eps)) / 2 for max(a, b)"
)


class InitialPolicyWarning(UserWarning):
    """Policy iteration starts from a policy its acceptance test would refuse (``critic.W0``)."""


class TargetWarning(UserWarning):
    """The target (the origin of the model's coordinates) is not an equilibrium of ``f``."""
