"""The SDP backends by name (``design_observer(backend=...)``) and the solvers they offer."""

from __future__ import annotations

from ofrl_drake.design.backend_cvxpy import CvxpyBackend
from ofrl_drake.design.backend_drake import DrakeBackend
from ofrl_drake.design.errors import DesignError
from ofrl_drake.design.sdp import SdpBackend

__all__ = ["BACKENDS", "SOLVERS", "get_backend"]

#: The backends by name; the first is the default.
BACKENDS: dict[str, SdpBackend] = {b.name: b for b in (DrakeBackend(), CvxpyBackend())}
#: Every solver some backend offers, in the backends' order.
SOLVERS = tuple(dict.fromkeys(s for b in BACKENDS.values() for s in b.solvers))


def get_backend(name: str) -> SdpBackend:
    """The backend called ``name``.

    Raises
    ------
    DesignError
        For an unknown backend.
    """
    if name not in BACKENDS:
        raise DesignError(f"backend must be one of {tuple(BACKENDS)}; got {name!r}.")
    return BACKENDS[name]
