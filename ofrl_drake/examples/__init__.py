"""A registry of example systems, so scenario files can name them.

>>> from ofrl_drake.examples import make_system
>>> make_system("two_state").n
2
"""

from __future__ import annotations

from collections.abc import Callable

from ofrl_drake.errors import ScenarioError
from ofrl_drake.examples.coupled_two_state import coupled_two_state
from ofrl_drake.examples.two_state import two_state
from ofrl_drake.model import ControlAffineSystem

__all__ = ["EXAMPLES", "coupled_two_state", "make_system", "register", "two_state"]

EXAMPLES: dict[str, Callable[[], ControlAffineSystem]] = {
    "two_state": two_state,
    "coupled_two_state": coupled_two_state,
}


def register(name: str, factory: Callable[[], ControlAffineSystem]) -> None:
    """Add ``factory`` to the registry under ``name`` (for user systems)."""
    EXAMPLES[name] = factory


def make_system(name: str) -> ControlAffineSystem:
    """Build the registered example ``name``."""
    try:
        factory = EXAMPLES[name]
    except KeyError:
        raise ScenarioError(
            f"system: unknown example {name!r}; choose one of {sorted(EXAMPLES)}, "
            "or name your own plant as 'module.path:callable' (a function of no arguments "
            "returning a ControlAffineSystem)."
        ) from None
    return factory()
