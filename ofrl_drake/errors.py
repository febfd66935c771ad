"""Exceptions raised by ofrl_drake.

Every error names the offending value and how to fix it. All of them derive
from :class:`ValueError`, so callers that only care about "bad input" can catch
that one type; the command-line tool prints them on one line and exits 2.
"""

from __future__ import annotations

__all__ = ["ModelError", "OfrlError", "OutputError", "ScenarioError", "SwapError"]


class OfrlError(ValueError):
    """Base class for every input error raised by ofrl_drake."""


class ModelError(OfrlError):
    """A model, basis, gain or point set has the wrong shape or non-finite values."""


class ScenarioError(OfrlError):
    """A scenario file or scenario object holds a missing, unknown or bad key."""


class SwapError(OfrlError):
    """A block swapped into the closed loop does not have the expected ports."""


class OutputError(OfrlError):
    """An output path cannot be written safely (a file in the way, a foreign folder...)."""
