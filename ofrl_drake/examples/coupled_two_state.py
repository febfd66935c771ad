"""A MIMO example: two copies of the paper's system, weakly coupled.

Rows 1 and 3 are coupled by ``0.1 (x3 - x1)`` and ``0.1 (x1 - x3)``; the two
inputs enter rows 2 and 4; x2 and x4 are measured (n = 4, m = 2, q = 2).
"""

from __future__ import annotations

import numpy as np

from ofrl_drake.examples.two_state import f as paper_drift
from ofrl_drake.model import ControlAffineSystem


def f(x: np.ndarray) -> np.ndarray:
    """Two copies of the paper's drift plus the coupling in rows 1 and 3."""
    a = paper_drift(x[0:2])
    b = paper_drift(x[2:4])
    coupling = 0.1 * (x[2] - x[0])
    return np.array([a[0] + coupling, a[1], b[0] - coupling, b[1]])


def g(x: np.ndarray) -> np.ndarray:
    """Input 1 drives row 2 and input 2 drives row 4; shape (4, 2)."""
    zero = 0 * x[0]
    return np.array(
        [
            [zero, zero],
            [np.cos(2 * x[0]) + 2, zero],
            [zero, zero],
            [zero, np.cos(2 * x[2]) + 2],
        ]
    )


def coupled_two_state() -> ControlAffineSystem:
    """n = 4, m = 2, q = 2; C measures x2 and x4."""
    C = [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    return ControlAffineSystem(f, g, C, name="coupled_two_state")
