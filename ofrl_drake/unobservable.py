"""Equilibria at which the plant's linearization loses observability.

At an equilibrium ``f(x*) + g(x*) u* = 0`` with the input held at ``u*``, the
error of the three-gain observer linearizes (``e -> 0``) to ``e' = A_e e`` with

    A_e = A - (Df H + Dg_u K + L - M_f1 H - M_ug1(u*) K) C,
    A = Df(x*) + sum_k u*_k Dg_k(x*),

so every gain enters through ``C``: an eigenvalue ``lambda`` of ``A`` that is
unobservable (``[A - lambda I; C]`` loses rank, the PBH test) is an eigenvalue of
``A_e`` **whatever the gains**. No design can make the error decay faster than
``-Re(lambda)`` there, whatever rate it claims.

:func:`unobservable_equilibria` finds these points by root finding on ``f`` and
``g`` themselves (Jacobians from ``pydrake.symbolic``): ``n + 1`` equations,
``f(x) + g(x) u = 0`` and ``det O(A(x, u), C) = 0`` with ``O`` the observability
matrix, in the ``n + 1`` unknowns ``(x, u)``, hence for one input and one
output. On the paper's two-state example they are ``x1 = x2 = +-1.647...``,
``u* = +-1.609...``, where ``d(f2 + g2 u)/dx1 = 0`` and the mode -1 of ``x1`` is
unobservable from ``y = x2``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import root

from ofrl_drake.errors import ModelError
from ofrl_drake.jacobian_bounds import Box
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.verification import plant_jacobians

__all__ = [
    "UnobservableEquilibrium",
    "linearization",
    "unobservable_equilibria",
    "unobservable_modes",
]


@dataclass(frozen=True, eq=False)
class UnobservableEquilibrium:
    """An equilibrium whose linearization is not observable.

    Attributes
    ----------
    x : ndarray, shape (n,)
        The state ``x*``.
    u : ndarray, shape (m,)
        The input ``u*`` that holds it.
    A : ndarray, shape (n, n)
        ``Df(x*) + sum_k u*_k Dg_k(x*)``.
    modes : ndarray
        The unobservable eigenvalues of ``A`` (complex dtype): eigenvalues of
        every observer's linearized error there, whatever its gains.
    residual : float
        ``max |f(x*) + g(x*) u*|``.
    """

    x: np.ndarray
    u: np.ndarray
    A: np.ndarray
    modes: np.ndarray
    residual: float


def linearization(system: ControlAffineSystem, x: Any, u: Any) -> np.ndarray:
    """``A = d(f + g u)/dx`` at ``(x, u)``, shape ``(n, n)``."""
    Jf, Jg = plant_jacobians(system, np.asarray(x, dtype=float)[:, None])
    return Jf[..., 0] + np.einsum("ijk,k->ij", Jg[..., 0], np.asarray(u, dtype=float))


def _observability(A: np.ndarray, C: np.ndarray) -> np.ndarray:
    blocks, M = [], C
    for _ in range(A.shape[0]):
        blocks.append(M)
        M = M @ A
    return np.vstack(blocks)


def unobservable_modes(A: np.ndarray, C: np.ndarray, tol: float) -> np.ndarray:
    """The eigenvalues ``lambda`` of ``A`` for which ``[A - lambda I; C]`` loses rank (PBH).

    Rank is lost when its smallest singular value is at most ``tol max(1, max |A_ij|)``.
    """
    n = A.shape[0]
    modes = []
    for lam in np.linalg.eigvals(A):
        pbh = np.vstack([A - lam * np.eye(n), C])
        if np.linalg.svd(pbh, compute_uv=False)[-1] <= tol * max(1.0, np.abs(A).max()):
            modes.append(lam)
    return np.asarray(modes, dtype=complex)


def unobservable_equilibria(
    system: ControlAffineSystem,
    box: Any,
    input_bound: float,
    *,
    starts: int = 64,
    seed: int = 0,
    tol: float = 1e-9,
) -> list[UnobservableEquilibrium]:
    """Equilibria in ``box`` with ``|u| <= input_bound`` where ``(A, C)`` is unobservable.

    Parameters
    ----------
    system : ControlAffineSystem
        One input and one output (``m = q = 1``), so that the equations are square.
    box : Box or (lower, upper)
        Where to look for ``x*``.
    input_bound : float
        Largest ``|u*|``.
    starts : int
        Seeded random starts of the root finder (scipy ``root``, ``hybr``) in
        the box and the input range.
    seed : int
        Seed of the starts.
    tol : float
        Roots closer than ``1e3 tol`` (relative to the box) are one; a residual
        above ``tol`` is no root.

    Returns
    -------
    list of UnobservableEquilibrium
        Sorted by ``x``; empty if none was found.

    Raises
    ------
    ModelError
        If the system does not have one input and one output.
    """
    if system.m != 1 or system.q != 1:
        raise ModelError(
            f"unobservable_equilibria solves n + 1 equations in the n + 1 unknowns (x, u), so "
            f"it needs one input and one output; {system.name} has m = {system.m}, "
            f"q = {system.q}."
        )
    box = Box.coerce(box, system.n)
    n, C = system.n, system.output_matrix
    scale = float(np.max(box.width))

    def equations(z: np.ndarray) -> np.ndarray:
        x, u = z[:n], z[n:]
        A = linearization(system, x, u)
        rhs = np.asarray(system.dynamics(x, u), dtype=float)
        return np.append(rhs, np.linalg.det(_observability(A, C)))

    rng = np.random.default_rng(seed)
    lower = np.append(box.lower, -input_bound)
    upper = np.append(box.upper, input_bound)
    found: list[UnobservableEquilibrium] = []
    for z0 in lower + rng.random((starts, n + 1)) * (upper - lower):
        sol = root(equations, z0, method="hybr")
        z = sol.x
        x, u = z[:n], z[n:]
        residual = float(np.max(np.abs(system.dynamics(x, u))))
        inside = np.all(box.lower - tol <= x) and np.all(x <= box.upper + tol)
        if not (sol.success and residual <= tol and inside and abs(u[0]) <= input_bound):
            continue
        if any(np.max(np.abs(np.append(e.x, e.u) - z)) < 1e3 * tol * scale for e in found):
            continue
        A = linearization(system, x, u)
        modes = unobservable_modes(A, C, 1e-6)
        if modes.size:
            found.append(UnobservableEquilibrium(x.copy(), u.copy(), A, modes, residual))
    return sorted(found, key=lambda e: tuple(e.x))
