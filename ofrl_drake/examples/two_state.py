"""The two-state example of the paper's simulation section (eq. sim_dyn)."""

from __future__ import annotations

import numpy as np

from ofrl_drake.model import ControlAffineSystem


def f(x: np.ndarray) -> np.ndarray:
    """Drift of (sim_dyn)."""
    c = np.cos(2 * x[0]) + 2
    return np.array([-x[0] + x[1], -x[0] - 0.5 * x[1] * (1 - c**2)])


def g(x: np.ndarray) -> np.ndarray:
    """Input matrix of (sim_dyn), shape (2, 1)."""
    return np.array([[0 * x[0]], [np.cos(2 * x[0]) + 2]])


def two_state() -> ControlAffineSystem:
    """The paper's system: n = 2, m = 1, q = 1, measuring x2 (C = [0 1])."""
    return ControlAffineSystem(f, g, [[0.0, 1.0]], name="two_state")
