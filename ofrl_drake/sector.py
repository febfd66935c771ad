"""The sign-correct input sector of ``d(g(x) u)/dx`` (docs/paper_notes.md, "input sector").

For Jacobian bounds ``M_g1 <= d g[i, k] / d x_j <= M_g2`` (arrays of shape
``(n, n, m)``, indexed ``[i, j, k]``) and an input ``u``, the element-wise sector
of ``d(sum_k g_k(x) u_k)/dx`` is

    M_ug1(u)[i, j] = sum_k min(M_g1[i, j, k] u_k, M_g2[i, j, k] u_k)
    M_ug2(u)[i, j] = sum_k max(M_g1[i, j, k] u_k, M_g2[i, j, k] u_k)

The paper's (aug_jac_g) writes ``[0, (M_g2 - M_g1) u]``, which holds only for
``u_k >= 0``; :func:`paper_input_sector` keeps that literal form so tests can
document the gap.
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["input_sector", "input_vertices", "paper_input_sector"]


def input_sector(Mg1: np.ndarray, Mg2: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(M_ug1(u), M_ug2(u))``, each of shape ``(n, n)``.

    Parameters
    ----------
    Mg1, Mg2 : ndarray, shape (n, n, m)
        Element-wise lower and upper bounds of ``d g[i, k] / d x_j``.
    u : array_like, shape (m,)
        The input.
    """
    lo = Mg1 * u  # broadcasts over the last axis k
    hi = Mg2 * u
    return np.minimum(lo, hi).sum(axis=-1), np.maximum(lo, hi).sum(axis=-1)


def paper_input_sector(
    Mg1: np.ndarray, Mg2: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's literal sector ``(M_g1 u, M_g2 u)``: valid only for ``u >= 0``."""
    return (Mg1 * u).sum(axis=-1), (Mg2 * u).sum(axis=-1)


def input_vertices(input_bound: float, m: int) -> np.ndarray:
    """All ``3**m`` inputs with entries in ``{-bound, 0, +bound}``, shape (3**m, m).

    The LMI is affine in the sector on each orthant, with breaks only at
    ``u_k = 0``, so certifying these vertices certifies every ``|u_k| <= bound``.
    """
    levels = (-input_bound, 0.0, input_bound)
    return np.array(list(itertools.product(levels, repeat=m)), dtype=float)
