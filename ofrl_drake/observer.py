"""The three-gain extended-Luenberger observer (eq:observerdynamics_x).

With ``ytil = y - C xhat`` the observer simplifies exactly to (NOTES.md)::

    xhat' = f(xhat + H ytil) + g(xhat + K ytil) u + (L - M_f1 H - M_ug1(u) K) ytil

where ``M_ug1(u)`` is the sign-correct lower input sector
(:func:`ofrl_drake.sector.input_sector`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.sector import input_sector

__all__ = ["ObserverGains", "observer_rhs"]


def _matrix(name: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise ValueError(f"observer gain {name} must have shape {shape}; got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"observer gain {name} must be finite; got {arr.tolist()}.")
    return arr


@dataclass(frozen=True)
class ObserverGains:
    """Everything the observer's right-hand side needs besides f, g and C.

    Attributes
    ----------
    L, H, K : ndarray, shape (n, q)
        Linear correction and the two nonlinear injection gains.
    Mf1 : ndarray, shape (n, n)
        Lower Jacobian bound of f.
    Mg1, Mg2 : ndarray, shape (n, n, m)
        Lower and upper Jacobian bounds of g.
    """

    L: np.ndarray
    H: np.ndarray
    K: np.ndarray
    Mf1: np.ndarray
    Mg1: np.ndarray
    Mg2: np.ndarray

    @classmethod
    def from_arrays(
        cls,
        system: ControlAffineSystem,
        L: Any,
        H: Any,
        K: Any,
        Mf1: Any,
        Mg1: Any,
        Mg2: Any,
    ) -> ObserverGains:
        """Check shapes against ``system`` and build the gains."""
        n, m, q = system.n, system.m, system.q
        return cls(
            L=_matrix("L", L, (n, q)),
            H=_matrix("H", H, (n, q)),
            K=_matrix("K", K, (n, q)),
            Mf1=_matrix("Mf1", Mf1, (n, n)),
            Mg1=_matrix("Mg1", Mg1, (n, n, m)),
            Mg2=_matrix("Mg2", Mg2, (n, n, m)),
        )

    @classmethod
    def from_design(cls, system: ControlAffineSystem, design: Any) -> ObserverGains:
        """Take L, H, K and the Jacobian bounds from an ``ObserverDesign``."""
        b = design.bounds
        return cls.from_arrays(system, design.L, design.H, design.K, b.Mf1, b.Mg1, b.Mg2)


def observer_rhs(
    system: ControlAffineSystem,
    gains: ObserverGains,
    xhat: np.ndarray,
    y: np.ndarray,
    u: np.ndarray,
) -> np.ndarray:
    """``xhat'`` of the three-gain observer at one time."""
    ytil = y - system.output_matrix @ xhat
    Mug1, _ = input_sector(gains.Mg1, gains.Mg2, u)
    correction = gains.L - gains.Mf1 @ gains.H - Mug1 @ gains.K
    return (
        np.asarray(system.f(xhat + gains.H @ ytil), dtype=float)
        + np.asarray(system.g(xhat + gains.K @ ytil), dtype=float) @ u
        + correction @ ytil
    )
