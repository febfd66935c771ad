"""The observer LMI (lmi2) at one input vertex, and its eigenvalue certificate.

Pure numpy: nothing here needs Drake or a solver.

With Jacobian bounds ``M_f1, M_f2`` (n x n) and ``M_g1, M_g2`` (n x n x m), an
input ``u`` and the sign-correct input sector (NOTES.md, "input sector")
``M_ug1(u), M_ug2(u)`` of :func:`ofrl_drake.sector.input_sector`, the paper's
(lmi2) reads

    A      = M_f1 + M_ug1(u)
    Jf21   = -(M_f2 - M_f1) / 2
    Jg21   = -(M_ug2(u) - M_ug1(u)) / 2
    J21    = Jf21 (I - H C) + Jg21 (I - K C)

    [[A^T P + P A - C^T R^T - R C + 2 alpha P,  P - J21^T],
     [P - J21,                                  -2 I     ]]  <=  0

with ``R = P L`` (the paper's substitution ``L = P^{-1} R``); the lower-right
block is ``-((J_f)_22 + (J_g)_22) = -2 I``. Given numbers ``P, L, H, K`` the
matrix is assembled with ``R = P L`` and its largest eigenvalue is computed with
``numpy.linalg.eigvalsh``: a negative value at every one of the ``3**m`` input
vertices of :func:`ofrl_drake.sector.input_vertices` (and ``P`` positive
definite) certifies ``dV/dt <= -2 alpha V`` for ``V = e^T P e`` for every input
with ``|u_k| <= input_bound`` (NOTES.md, "one set of gains").

``sector="paper"`` uses the paper's literal ``(M_g1 u, M_g2 u)`` instead, which
is valid only for ``u >= 0``; it is kept to document that gap.

Caveat: this module checks (lmi2) exactly as the paper states it. For linear
plants (``M_f1 = M_f2``, constant ``g``) the nonlinear terms vanish and a
negative certificate does give ``dV/dt <= -2 alpha V``. For nonlinear plants the
paper's step from element-wise Jacobian bounds to the quadratic sector condition
(quad_f) needs each row of ``(M_f2 - M_f1)(I - H C) e`` to bound ``phi_f`` from
both sides, which fails when a row has more than one uncertain entry; on the
two-state example a design certified at alpha = 2 on [-2, 2]^2 has
``dV/dt = +39 V`` at ``x = (0.598, -2)``, ``u = 0``, ``e = (eps, 0)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ofrl_drake.errors import OfrlError
from ofrl_drake.sector import input_sector, input_vertices, paper_input_sector

__all__ = [
    "SECTORS",
    "LmiError",
    "bounds_arrays",
    "certificate",
    "is_certified",
    "lmi_matrix",
    "vertex_data",
]

SECTORS = ("sign_correct", "paper")


class LmiError(OfrlError):
    """Malformed input to the LMI assembly (shapes, sector name, alpha)."""


def bounds_arrays(
    bounds: Any,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return ``(Mf1, Mf2, Mg1, Mg2)`` as float arrays, checking their shapes.

    Parameters
    ----------
    bounds : object, mapping or sequence
        Anything with attributes ``Mf1, Mf2, Mg1, Mg2`` (such as
        :class:`ofrl_drake.jacobian_bounds.JacobianBounds`), a mapping with those
        keys, or a 4-sequence ``(Mf1, Mf2, Mg1, Mg2)``.

    Raises
    ------
    LmiError
        If the arrays are missing or have inconsistent shapes.
    """
    keys = ("Mf1", "Mf2", "Mg1", "Mg2")
    if all(hasattr(bounds, k) for k in keys):
        raw = [getattr(bounds, k) for k in keys]
    elif isinstance(bounds, Mapping):
        missing = [k for k in keys if k not in bounds]
        if missing:
            raise LmiError(f"bounds mapping is missing keys {missing}.")
        raw = [bounds[k] for k in keys]
    else:
        try:
            raw = list(bounds)
        except TypeError:
            raw = []
        if len(raw) != 4:
            raise LmiError(
                "bounds must be a JacobianBounds, a mapping with keys Mf1, Mf2, "
                f"Mg1, Mg2, or a tuple of those four arrays; got {type(bounds)}."
            )
    Mf1, Mf2, Mg1, Mg2 = (np.asarray(a, dtype=float) for a in raw)
    if Mf1.ndim != 2 or Mf1.shape[0] != Mf1.shape[1] or Mf2.shape != Mf1.shape:
        raise LmiError(f"Mf1 and Mf2 must be square (n, n); got {Mf1.shape} and {Mf2.shape}.")
    n = Mf1.shape[0]
    if Mg1.ndim != 3 or Mg1.shape[:2] != (n, n) or Mg2.shape != Mg1.shape:
        raise LmiError(
            f"Mg1 and Mg2 must have shape ({n}, {n}, m); got {Mg1.shape} and {Mg2.shape}."
        )
    return Mf1, Mf2, Mg1, Mg2


def vertex_data(
    bounds: Any, u: np.ndarray, sector: str = "sign_correct"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The constant matrices of (lmi2) at input ``u``: ``(A, Jf21, Jg21)``.

    Parameters
    ----------
    bounds : JacobianBounds or mapping or (Mf1, Mf2, Mg1, Mg2)
        Jacobian bounds (see :func:`bounds_arrays`).
    u : array_like, shape (m,)
        The input.
    sector : {"sign_correct", "paper"}
        Which input sector to use.

    Returns
    -------
    A, Jf21, Jg21 : ndarray, shape (n, n)
        ``A = Mf1 + Mug1(u)``, ``Jf21 = -(Mf2 - Mf1)/2``,
        ``Jg21 = -(Mug2(u) - Mug1(u))/2``.
    """
    Mf1, Mf2, Mg1, Mg2 = bounds_arrays(bounds)
    u = np.atleast_1d(np.asarray(u, dtype=float))
    if u.shape != (Mg1.shape[2],):
        raise LmiError(f"u must have shape ({Mg1.shape[2]},); got {u.shape}.")
    if sector == "sign_correct":
        Mug1, Mug2 = input_sector(Mg1, Mg2, u)
    elif sector == "paper":
        Mug1, Mug2 = paper_input_sector(Mg1, Mg2, u)
    else:
        raise LmiError(f"sector must be one of {SECTORS}; got {sector!r}.")
    A = Mf1 + Mug1
    Jf21 = -(Mf2 - Mf1) / 2.0
    Jg21 = -(Mug2 - Mug1) / 2.0
    return A, Jf21, Jg21


def _gains(
    P: Any, L: Any, H: Any, K: Any, C: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    C = np.atleast_2d(np.asarray(C, dtype=float))
    q, n = C.shape
    P = np.asarray(P, dtype=float)
    if P.shape != (n, n):
        raise LmiError(f"P must have shape ({n}, {n}) to match C; got {P.shape}.")
    out = [P]
    for name, G in (("L", L), ("H", H), ("K", K)):
        G = np.asarray(G, dtype=float)
        if G.ndim == 1 and q == 1:
            G = G.reshape(-1, 1)
        if G.shape != (n, q):
            raise LmiError(f"{name} must have shape (n, q) = ({n}, {q}); got {G.shape}.")
        out.append(G)
    return out[0], out[1], out[2], out[3], C


def lmi_matrix(
    P: np.ndarray,
    L: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    bounds: Any,
    u: np.ndarray,
    alpha: float,
    sector: str = "sign_correct",
) -> np.ndarray:
    """The (lmi2) matrix at input ``u`` for given numbers; ``R = P L``.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        The Lyapunov matrix (symmetrized here).
    L, H, K : ndarray, shape (n, q)
        Observer gains.
    C : ndarray, shape (q, n)
        Output matrix.
    bounds : JacobianBounds or mapping or (Mf1, Mf2, Mg1, Mg2)
        Jacobian bounds over the box.
    u : array_like, shape (m,)
        The input.
    alpha : float
        Decay rate.
    sector : {"sign_correct", "paper"}
        Input sector (see module docstring).

    Returns
    -------
    ndarray, shape (2n, 2n)
        Symmetric; the certificate needs it negative definite.

    Examples
    --------
    >>> import numpy as np
    >>> Z = np.zeros((1, 1, 1))
    >>> M = lmi_matrix([[1.0]], [[3.0]], [[0.0]], [[0.0]], [[1.0]],
    ...                ([[-1.0]], [[-1.0]], Z, Z), [0.0], 0.5)
    >>> M.tolist()
    [[-7.0, 1.0], [1.0, -2.0]]
    """
    P, L, H, K, C = _gains(P, L, H, K, C)
    if not np.isfinite(alpha):
        raise LmiError(f"alpha must be finite; got {alpha!r}.")
    A, Jf21, Jg21 = vertex_data(bounds, u, sector)
    n = P.shape[0]
    if A.shape != (n, n):
        raise LmiError(f"bounds are for n = {A.shape[0]} but P is {n} x {n}.")
    P = 0.5 * (P + P.T)
    R = P @ L
    eye = np.eye(n)
    J21 = Jf21 @ (eye - H @ C) + Jg21 @ (eye - K @ C)
    M11 = A.T @ P + P @ A - C.T @ R.T - R @ C + 2.0 * alpha * P
    M21 = P - J21
    M = np.block([[M11, M21.T], [M21, -2.0 * eye]])
    return 0.5 * (M + M.T)


def certificate(
    P: np.ndarray,
    L: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    bounds: Any,
    input_bound: float,
    alpha: float,
    sector: str = "sign_correct",
) -> list[tuple[np.ndarray, float]]:
    """Largest eigenvalue of the (lmi2) matrix at each of the 3**m input vertices.

    Parameters
    ----------
    P, L, H, K, C, bounds, alpha, sector
        As in :func:`lmi_matrix`.
    input_bound : float
        ``lambda_bar``: the vertices have entries in ``{-b, 0, +b}``.

    Returns
    -------
    list of (ndarray, float)
        ``(u, max eigenvalue)`` per vertex; all negative (and ``P`` positive
        definite) means certified.
    """
    if not (np.isfinite(input_bound) and input_bound >= 0):
        raise LmiError(f"input_bound must be finite and >= 0; got {input_bound!r}.")
    m = bounds_arrays(bounds)[2].shape[2]
    out = []
    for u in input_vertices(float(input_bound), m):
        M = lmi_matrix(P, L, H, K, C, bounds, u, alpha, sector)
        out.append((u, float(np.linalg.eigvalsh(M)[-1])))
    return out


def is_certified(
    P: np.ndarray,
    L: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    bounds: Any,
    input_bound: float,
    alpha: float,
    sector: str = "sign_correct",
) -> bool:
    """True if ``P`` is positive definite and every vertex eigenvalue is < 0."""
    P = np.asarray(P, dtype=float)
    if not np.all(np.isfinite(P)):
        return False
    if np.linalg.eigvalsh(0.5 * (P + P.T))[0] <= 0:
        return False
    cert = certificate(P, L, H, K, C, bounds, input_bound, alpha, sector)
    return all(ev < 0 for _, ev in cert)
