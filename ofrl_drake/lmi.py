"""Observer LMIs and their eigenvalue certificates: pure numpy, no Drake or solver.

Two checks live here.

The paper's (lmi2), at one input vertex
-----------------------------------------
With Jacobian bounds ``M_f1, M_f2`` (n x n) and ``M_g1, M_g2`` (n x n x m), an
input ``u`` and the sign-correct input sector (docs/paper_notes.md, "input sector")
``M_ug1(u), M_ug2(u)`` of :func:`ofrl_drake.sector.input_sector`, the paper's
(lmi2) reads

    A      = M_f1 + M_ug1(u)
    Jf21   = -(M_f2 - M_f1) / 2
    Jg21   = -(M_ug2(u) - M_ug1(u)) / 2
    J21    = Jf21 (I - H C) + Jg21 (I - K C)

    [[A^T P + P A - C^T R^T - R C + 2 alpha P,  P - J21^T],
     [P - J21,                                  -2 I     ]]  <=  0

with ``R = P L`` (the paper's substitution ``L = P^{-1} R``); the lower-right
block is ``-((J_f)_22 + (J_g)_22) = -2 I``. :func:`lmi_matrix` assembles it from
numbers and :func:`certificate` lists its largest eigenvalue at each of the
``3**m`` input vertices of :func:`ofrl_drake.sector.input_vertices`.
``sector="paper"`` uses the paper's literal ``(M_g1 u, M_g2 u)`` instead, which
is valid only for ``u >= 0``; it is kept to document that gap.

(lmi2) is *not* a decay certificate for nonlinear plants. For linear plants
(``M_f1 = M_f2``, constant ``g``) the nonlinear terms vanish and a negative
(lmi2) does give ``dV/dt <= -2 alpha V``. For nonlinear plants the paper's step
from element-wise Jacobian bounds to the quadratic sector condition (quad_f)
needs each row of ``(M_f2 - M_f1)(I - H C) e`` to bound ``phi_f`` from both
sides, which fails when a row has more than one uncertain entry, and (lmi) adds
the f and g conditions with one ``phi`` and multiplier 1. On the two-state
example a design satisfying (lmi2) at alpha = 2 on [-2, 2]^2 with ``|u| <= 3``
has ``dV/dt = +39 V`` at ``x = (0.598, -2)``, ``u = 0``, ``e = (eps, 0)``.

The polytopic decay certificate
-------------------------------
:func:`decay_certificate` is a sound check of ``dV/dt <= -2 alpha V`` for
``V = e^T P e``, ``e = x - xhat``. With ``ytil = C e`` the observer
(:mod:`ofrl_drake.observer`)

    xhat' = f(xhat + H ytil) + g(xhat + K ytil) u + (L - M_f1 H - M_ug1(u) K) ytil

and the plant ``x' = f(x) + g(x) u`` give, exactly,

    e' = [f(x) - f(z_f)] + [g(x) - g(z_g)] u - (L - M_f1 H - M_ug1(u) K) C e,

    z_f = xhat + H C e,  x - z_f = (I - H C) e,
    z_g = xhat + K C e,  x - z_g = (I - K C) e.

By the mean value theorem applied to each row ``i`` separately (each row at its
own point of the segment, which stays in the box because the box is convex),
``f(x) - f(z_f) = M_f (I - H C) e`` with ``M_f`` in the element-wise box
``[M_f1, M_f2]``, and for each input ``k``, ``g_k(x) - g_k(z_g) = G_k (I - K C) e``
with ``G_k`` in ``[M_g1[:, :, k], M_g2[:, :, k]]``. So ``e' = A_cl e`` with

    A_cl = M_f (I - H C) + M_gu (I - K C) - (L - M_f1 H - M_ug1(u) K) C,
    M_gu = sum_k u_k G_k,

and ``dV/dt + 2 alpha V = e^T S e`` with ``S = A_cl^T P + P A_cl + 2 alpha P``.
``lambda_max(S)`` is a convex function of ``A_cl``, and:

* for fixed ``u``, ``A_cl`` is affine in ``(M_f, G_1, ..., G_m)``, so the largest
  ``lambda_max(S)`` over the product of boxes is attained at a corner;
* for fixed ``M_f, G``, ``A_cl`` is affine in ``u`` on each orthant (``M_ug1(u)``
  is linear there, with breaks only at ``u_k = 0``), so the largest value over
  ``|u_k| <= lambda_bar`` is attained at a vertex in ``{-lambda_bar, 0,
  lambda_bar}^m``.

Applying the two in turn, ``lambda_max(S) <= 0`` at every combination of corner
and input vertex implies ``dV/dt <= -2 alpha V`` for every ``x`` and ``xhat`` in
the box (and ``xhat + H ytil``, ``xhat + K ytil`` in it too when ``H, K != 0``) and
every ``|u_k| <= lambda_bar``. At a fixed vertex ``u`` the set of ``M_gu`` over the
corners of the ``G_k`` has the same corners as the element-wise box
``[M_ug1(u), M_ug2(u)]`` (a sum of boxes is a box), so those corners are
enumerated instead: far fewer when ``m > 1``, the same maximum. When ``H = K =
0``, ``A_cl = (M_f + M_gu) - L C`` depends on the sum only, which ranges over the
box ``[M_f1 + M_ug1(u), M_f2 + M_ug2(u)]``, and its corners are enumerated.
The argument needs the bounds to be true enclosures of the Jacobians on the box:
``jacobian_method="certified"`` guarantees that; ``"sampled"`` is an inner
estimate, usually tight but without a guarantee.
Only entries with lower != upper generate corners; more than
:data:`MAX_CORNERS` matrices in total raise :class:`LmiError`.

*Thin* entries, whose width is at most :data:`THIN_RTOL` ``* max(1, |bound|)``
(an interval enclosure widens a constant Jacobian entry such as ``-1.1`` by an
ulp each way), generate no corners: they are fixed at their midpoint and their
half-widths ``D`` enter as a norm-bounded perturbation instead. With ``A_cl =
A_mid + dA`` and ``|dA_ij| <= D_ij`` entry-wise on ``M_f`` and ``M_gu``,

    lambda_max(S) <= lambda_max(S_mid) + 2 ||P||_2 ||dA||_2,
    ||dA||_2 <= ||D_f||_F ||I - H C||_2 + ||D_gu||_F ||I - K C||_2

(:func:`thin_perturbation`), which :func:`decay_certificate` adds to every
value, so the certificate stays sound while a plant with ``k`` inexact
constants keeps ``2**k`` times fewer corners.

Along ``e = eps e_1`` on the two-state example (``C = [0 1]``, so ``ytil = 0``)
``dV/dt = 2 eps^2 (-P11 + P12 a21(x))`` with ``a21 = d f_2 / d x_1`` of both
signs on the box, so no quadratic ``V`` certifies ``alpha >= 1`` there, whatever
the gains; the polytopic certificate finds rates just below 1.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from ofrl_drake.checks import array_of_shape, finite_array
from ofrl_drake.errors import OfrlError
from ofrl_drake.sector import input_sector, input_vertices, paper_input_sector

__all__ = [
    "MAX_CORNERS",
    "SECTORS",
    "THIN_RTOL",
    "LmiError",
    "block_matrix",
    "bounds_arrays",
    "box_corners",
    "certificate",
    "certifies",
    "corner_count",
    "corner_matrices",
    "decay_certificate",
    "decay_matrices",
    "gain_matrix",
    "is_certified",
    "is_decay_certified",
    "lmi2_blocks",
    "lmi_matrix",
    "polytopic_lmi",
    "thin_perturbation",
    "vertex_corners",
    "vertex_data",
]

SECTORS = ("sign_correct", "paper")
#: The most corner matrices (over all input vertices) the polytopic checks enumerate.
MAX_CORNERS = 2**16
#: Entries of a Jacobian box at most this wide, relative to ``max(1, |bound|)``,
#: are fixed at their midpoint and bounded as a perturbation (module docstring).
THIN_RTOL = 1e-12


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


def gain_matrix(name: str, G: Any, n: int, q: int, error: type[OfrlError] = LmiError) -> np.ndarray:
    """``G`` as a finite ``(n, q)`` float array; a 1-D ``G`` is a column when ``q == 1``.

    Parameters
    ----------
    name : str
        The gain's name in the message (``"L"``, ``"H"``, ``"K"``).
    G : array_like
        The gain.
    n, q : int
        State and output dimensions.
    error : type of OfrlError
        What to raise (default :class:`LmiError`).

    Returns
    -------
    ndarray, shape (n, q)

    Raises
    ------
    OfrlError
        ``error``, if ``G`` is not numeric, has a NaN or infinite entry, or
        does not have shape ``(n, q)``.

    Examples
    --------
    >>> gain_matrix("L", [1.0, 2.0], 2, 1).tolist()
    [[1.0], [2.0]]
    """
    G = finite_array(name, G, error=error)
    if G.ndim == 1 and q == 1:
        G = G.reshape(-1, 1)
    return array_of_shape(name, G, (n, q), meaning="(n, q)", error=error)


def _gains(
    P: Any, L: Any, H: Any, K: Any, C: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    C = np.atleast_2d(np.asarray(C, dtype=float))
    q, n = C.shape
    P = np.asarray(P, dtype=float)
    if P.shape != (n, n):
        raise LmiError(f"P must have shape ({n}, {n}) to match C; got {P.shape}.")
    L, H, K = (gain_matrix(name, G, n, q) for name, G in (("L", L), ("H", H), ("K", K)))
    return P, L, H, K, C


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

    Raises
    ------
    LmiError
        For bad shapes, gains that are not finite (:func:`gain_matrix`), a
        ``sector`` not in :data:`SECTORS` or an ``alpha`` that is not finite.

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
    return lmi2_blocks(P, P @ L, H, K, C, A, Jf21, Jg21, alpha)


def lmi2_blocks(
    P: np.ndarray,
    R: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    A: np.ndarray,
    Jf21: np.ndarray,
    Jg21: np.ndarray,
    alpha: float,
) -> np.ndarray:
    """The (lmi2) matrix from its vertex data, in terms of ``R`` (no checks).

    Affine in ``(P, R, H, K)`` jointly, which is what makes (lmi2) an LMI; the
    Drake backend of :mod:`ofrl_drake.design` reads its coefficient matrices off
    this function.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
        Symmetric Lyapunov matrix (or a stack of them, for a backend that
        reads the coefficients of many decision variables at once).
    R : ndarray, shape (..., n, q)
        ``P L``.
    H, K : ndarray, shape (..., n, q)
        Injection gains.
    C : ndarray, shape (q, n)
        Output matrix.
    A, Jf21, Jg21 : ndarray, shape (n, n)
        From :func:`vertex_data`.
    alpha : float
        Decay rate.

    Returns
    -------
    ndarray, shape (..., 2n, 2n)
        The symmetrized (lmi2) matrix (one per stacked ``P, R, H, K``).
    """
    n = P.shape[-1]
    eye = np.eye(n)
    J21 = Jf21 @ (eye - H @ C) + Jg21 @ (eye - K @ C)
    M11 = A.T @ P + P @ A - C.T @ _t(R) - R @ C + 2.0 * alpha * P
    M21 = P - J21
    M = block_matrix([[M11, _t(M21)], [M21, -2.0 * eye]])
    return 0.5 * (M + _t(M))


def _t(M: np.ndarray) -> np.ndarray:
    """The transpose of the last two axes (of every matrix of a stack)."""
    return np.swapaxes(M, -1, -2)


def block_matrix(rows: list[list[np.ndarray]]) -> np.ndarray:
    """``np.block`` of 2-D blocks, or of stacks of them with broadcast leading axes.

    Parameters
    ----------
    rows : list of list of ndarray
        Each block of shape ``(..., r_i, c_j)``; the leading axes broadcast
        (a plain ``(r_i, c_j)`` block is repeated along them).

    Returns
    -------
    ndarray, shape (..., sum r_i, sum c_j)

    Examples
    --------
    >>> import numpy as np
    >>> stack = block_matrix([[np.ones((2, 1, 1)), np.zeros((1, 1))]])
    >>> stack.shape, stack[1].tolist()
    ((2, 1, 2), [[1.0, 0.0]])
    """
    arrays = [[np.asarray(b, dtype=float) for b in row] for row in rows]
    lead = np.broadcast_shapes(*(b.shape[:-2] for row in arrays for b in row))
    return np.concatenate(
        [
            np.concatenate([np.broadcast_to(b, (*lead, *b.shape[-2:])) for b in row], axis=-1)
            for row in arrays
        ],
        axis=-2,
    )


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

    Raises
    ------
    LmiError
        As :func:`lmi_matrix`, or for an ``input_bound`` that is not finite and >= 0.
    """
    if not (np.isfinite(input_bound) and input_bound >= 0):
        raise LmiError(f"input_bound must be finite and >= 0; got {input_bound!r}.")
    m = bounds_arrays(bounds)[2].shape[2]
    out = []
    for u in input_vertices(float(input_bound), m):
        M = lmi_matrix(P, L, H, K, C, bounds, u, alpha, sector)
        out.append((u, float(np.linalg.eigvalsh(M)[-1])))
    return out


def certifies(P: Any, cert: Callable[[], Iterable[tuple[Any, float]]]) -> bool:
    """True if ``P`` is finite and positive definite and every certificate value is < 0.

    The one test of every certificate here and in :mod:`ofrl_drake.design`:
    ``P`` is judged on its symmetric part ``(P + P^T) / 2``, the matrix of
    ``V = e^T P e`` (the certificates symmetrize it too).

    Parameters
    ----------
    P : array_like, shape (n, n)
        The Lyapunov matrix.
    cert : callable
        Returns the certificate, ``(u vertex, value)`` pairs; called only when
        ``P`` passes, so an unusable ``P`` never reaches it.

    Returns
    -------
    bool

    Examples
    --------
    >>> certifies([[1.0, 3.0], [-3.0, 1.0]], lambda: [(None, -1.0)])
    True
    >>> certifies([[1.0, 0.0], [0.0, 0.0]], lambda: [(None, -1.0)])
    False
    """
    P = np.asarray(P, dtype=float)
    if not np.all(np.isfinite(P)):
        return False
    if np.linalg.eigvalsh(0.5 * (P + P.T))[0] <= 0:
        return False
    return all(ev < 0 for _, ev in cert())


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
    """True if ``P`` is positive definite and every vertex eigenvalue is < 0 (:func:`certifies`)."""
    return certifies(P, lambda: certificate(P, L, H, K, C, bounds, input_bound, alpha, sector))


# ------------------------------------------------- polytopic decay certificate
def _thin(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Mask of the entries with ``0 < upper - lower <= THIN_RTOL * max(1, |bounds|)``."""
    scale = np.maximum(1.0, np.maximum(np.abs(lower), np.abs(upper)))
    return (upper != lower) & (upper - lower <= THIN_RTOL * scale)


def _collapse(lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lower', upper', D)``: thin entries fixed at their midpoint, D their half-widths.

    ``D >= max(upper - mid, mid - lower)``; both differences are exact in
    floating point (Sterbenz), so ``[lower, upper]`` lies within ``mid +- D``.
    """
    thin = _thin(lower, upper)
    if not np.any(thin):
        return lower, upper, np.zeros_like(lower)
    mid = np.where(thin, lower + 0.5 * (upper - lower), lower)
    D = np.where(thin, np.maximum(upper - mid, mid - lower), 0.0)
    return np.where(thin, mid, lower), np.where(thin, mid, upper), D


def _free_count(lower: np.ndarray, upper: np.ndarray) -> int:
    lower, upper, _ = _collapse(lower, upper)
    return int(np.count_nonzero(lower != upper))


def box_corners(lower: Any, upper: Any) -> np.ndarray:
    """All corners of the element-wise box ``lower <= M <= upper``.

    Only entries with ``lower != upper`` vary, so a box with ``k`` such entries
    has ``2**k`` corners.

    Parameters
    ----------
    lower, upper : array_like, same shape
        Element-wise bounds, ``lower <= upper``.

    Returns
    -------
    ndarray, shape (2**k, *lower.shape)
        Corner ``c`` takes ``upper`` at the free entries whose bit is set in
        ``c`` (the first free entry, in C order, is bit 0) and ``lower`` elsewhere.

    Raises
    ------
    LmiError
        If the shapes differ, an entry has ``lower > upper`` or is NaN or
        infinite (the message names the entry and the likely cause), or
        ``2**k`` exceeds :data:`MAX_CORNERS`.

    Examples
    --------
    >>> box_corners([[0.0, 1.0]], [[2.0, 1.0]]).tolist()
    [[[0.0, 1.0]], [[2.0, 1.0]]]
    """
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    if lo.shape != hi.shape:
        raise LmiError(f"box lower has shape {lo.shape} but upper has {hi.shape}.")
    bad = ~(np.isfinite(lo) & np.isfinite(hi) & (lo <= hi))
    if np.any(bad):
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        a, b = float(lo[where]), float(hi[where])
        if np.isnan(a) or np.isnan(b):
            cause = (
                "a bound is NaN: f or g is undefined somewhere on the box (a log or square "
                "root of a negative number, a division by zero)"
            )
        elif not (np.isfinite(a) and np.isfinite(b)):
            cause = (
                "a bound is infinite: the certified enclosure did not converge there, or a "
                "value overflows (an input_bound too large?)"
            )
        else:
            cause = "the lower bound exceeds the upper"
        raise LmiError(
            f"Jacobian bounds at entry {list(where)}: lower = {a:.6g}, upper = {b:.6g}; {cause}. "
            "Check f and g on the observer box, shrink observer.box, or use "
            "observer.jacobian_method: sampled."
        )
    free = np.flatnonzero(lo.ravel() != hi.ravel())
    k = free.size
    if 2**k > MAX_CORNERS:
        raise LmiError(
            f"the box has {k} uncertain entries, {2**k} corners, more than "
            f"MAX_CORNERS = {MAX_CORNERS}; tighten the Jacobian bounds or use a smaller box."
        )
    bits = (np.arange(2**k)[:, None] >> np.arange(k)[None, :]) & 1
    out = np.repeat(lo.ravel()[None, :], 2**k, axis=0)
    out[:, free] = np.where(bits == 1, hi.ravel()[free], lo.ravel()[free])
    return out.reshape((2**k, *lo.shape))


def _injection(H: Any, K: Any, C: Any, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(H, K, C)`` as arrays, or None when there is no injection (H = K = 0)."""
    if H is None and K is None:
        return None
    if H is None or K is None or C is None:
        raise LmiError("give H, K and C together (or neither, for H = K = 0).")
    C = np.atleast_2d(np.asarray(C, dtype=float))
    q = C.shape[0]
    if C.shape != (q, n):
        raise LmiError(f"C must have shape (q, n) = ({q}, {n}); got {C.shape}.")
    H, K = gain_matrix("H", H, n, q), gain_matrix("K", K, n, q)
    if not (np.any(H) or np.any(K)):
        return None
    return H, K, C


def corner_count(bounds: Any, u: Any, H: Any = None, K: Any = None, C: Any = None) -> int:
    """How many matrices :func:`corner_matrices` returns for these arguments."""
    Mf1, Mf2, Mg1, Mg2 = bounds_arrays(bounds)
    u = _input(u, Mg1.shape[2])
    Mug1, Mug2 = input_sector(Mg1, Mg2, u)
    if _injection(H, K, C, Mf1.shape[0]) is None:
        return 2 ** _free_count(Mf1 + Mug1, Mf2 + Mug2)
    return 2 ** (_free_count(Mf1, Mf2) + _free_count(Mug1, Mug2))


def _input(u: Any, m: int) -> np.ndarray:
    u = np.atleast_1d(np.asarray(u, dtype=float))
    if u.shape != (m,):
        raise LmiError(f"u must have shape ({m},); got {u.shape}.")
    return u


def corner_matrices(bounds: Any, u: Any, H: Any = None, K: Any = None, C: Any = None) -> np.ndarray:
    """The error-dynamics matrices ``A`` (with ``A_cl = A - L C``) at every corner.

    Thin entries (module docstring) are fixed at their midpoint; the rest of
    their range is :func:`thin_perturbation`.

    ``A = M_f (I - H C) + M_gu (I - K C) + (M_f1 H + M_ug1(u) K) C`` for ``M_f``
    at the corners of ``[M_f1, M_f2]`` and ``M_gu`` at the corners of
    ``[M_ug1(u), M_ug2(u)]`` (see the module docstring). With ``H = K = 0`` (or
    not given) ``A = M_f + M_gu`` at the corners of the summed box
    ``[M_f1 + M_ug1(u), M_f2 + M_ug2(u)]``.

    Parameters
    ----------
    bounds : JacobianBounds or mapping or (Mf1, Mf2, Mg1, Mg2)
        Jacobian bounds (see :func:`bounds_arrays`).
    u : array_like, shape (m,)
        The input (an input vertex, for a certificate).
    H, K : array_like, shape (n, q), optional
        Injection gains; both None (or both zero) means no injection.
    C : array_like, shape (q, n), optional
        Output matrix; needed with ``H, K``.

    Returns
    -------
    ndarray, shape (N, n, n)
        ``N =`` :func:`corner_count`.

    Raises
    ------
    LmiError
        For bad shapes, ``H`` or ``K`` not finite, or more than
        :data:`MAX_CORNERS` corners.
    """
    Mf1, Mf2, Mg1, Mg2 = bounds_arrays(bounds)
    n = Mf1.shape[0]
    u = _input(u, Mg1.shape[2])
    Mug1, Mug2 = input_sector(Mg1, Mg2, u)
    inj = _injection(H, K, C, n)
    if inj is None:
        lo, hi, _ = _collapse(Mf1 + Mug1, Mf2 + Mug2)
        return box_corners(lo, hi)
    H, K, C = inj
    count = 2 ** (_free_count(Mf1, Mf2) + _free_count(Mug1, Mug2))
    if count > MAX_CORNERS:
        raise LmiError(
            f"{count} corner matrices at u = {u.tolist()}, more than MAX_CORNERS = "
            f"{MAX_CORNERS}; tighten the Jacobian bounds or use a smaller box."
        )
    eye = np.eye(n)
    Af = box_corners(*_collapse(Mf1, Mf2)[:2]) @ (eye - H @ C)  # (Nf, n, n)
    Ag = box_corners(*_collapse(Mug1, Mug2)[:2]) @ (eye - K @ C)  # (Ng, n, n)
    A = Af[:, None] + Ag[None, :] + (Mf1 @ H + Mug1 @ K) @ C
    return A.reshape(-1, n, n)


def thin_perturbation(bounds: Any, u: Any, H: Any = None, K: Any = None, C: Any = None) -> float:
    """Bound on ``||A - A_corner||_2`` left out of :func:`corner_matrices` by thin entries.

    Every ``A`` of the Jacobian box lies within this spectral-norm distance of
    one of the returned corners (module docstring), so ``lambda_max(S)`` over
    the box is at most the corners' value plus ``2 ||P||_2`` times this.

    Parameters
    ----------
    bounds, u, H, K, C
        As for :func:`corner_matrices`.

    Returns
    -------
    float
        ``||D_f||_F ||I - H C||_2 + ||D_gu||_F ||I - K C||_2`` (``||D||_F`` of
        the summed box without injection); 0 when no entry is thin.
    """
    Mf1, Mf2, Mg1, Mg2 = bounds_arrays(bounds)
    n = Mf1.shape[0]
    u = _input(u, Mg1.shape[2])
    Mug1, Mug2 = input_sector(Mg1, Mg2, u)
    inj = _injection(H, K, C, n)
    if inj is None:
        return float(np.linalg.norm(_collapse(Mf1 + Mug1, Mf2 + Mug2)[2]))
    H, K, C = inj
    eye = np.eye(n)
    Df = float(np.linalg.norm(_collapse(Mf1, Mf2)[2]))
    Dg = float(np.linalg.norm(_collapse(Mug1, Mug2)[2]))
    out = 0.0
    if Df:
        out += Df * float(np.linalg.norm(eye - H @ C, 2))
    if Dg:
        out += Dg * float(np.linalg.norm(eye - K @ C, 2))
    return float(out)


def vertex_corners(
    bounds: Any, input_bound: float, H: Any = None, K: Any = None, C: Any = None, hint: str = ""
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """:func:`corner_matrices` at each input vertex, all of them within :data:`MAX_CORNERS`.

    The total is checked at once; each vertex's corners are built as the
    iterator reaches it, so only one vertex's are held at a time.

    Parameters
    ----------
    bounds, H, K, C
        As for :func:`corner_matrices`.
    input_bound : float
        ``lambda_bar``, checked by the caller: the vertices of
        :func:`ofrl_drake.sector.input_vertices`.
    hint : str
        One more way out, after "tighten the Jacobian bounds" and "use a
        smaller box", in the message past :data:`MAX_CORNERS`.

    Returns
    -------
    iterator of (ndarray, ndarray)
        ``(u vertex, corner matrices at u)``, in the order of the vertices.

    Raises
    ------
    LmiError
        For bad shapes, or more than :data:`MAX_CORNERS` corner matrices over
        all the vertices.
    """
    m = bounds_arrays(bounds)[2].shape[2]
    vertices = input_vertices(float(input_bound), m)
    total = sum(corner_count(bounds, u, H, K, C) for u in vertices)
    if total > MAX_CORNERS:
        fixes = ["tighten the Jacobian bounds", "use a smaller box", *([hint] if hint else [])]
        raise LmiError(
            f"the decay certificate needs {total} corner matrices over {len(vertices)} "
            f"input vertices, more than MAX_CORNERS = {MAX_CORNERS}; "
            f"{', '.join(fixes[:-1])} or {fixes[-1]}."
        )
    return ((u, corner_matrices(bounds, u, H, K, C)) for u in vertices)


def decay_matrices(P: np.ndarray, A_cl: np.ndarray, alpha: float) -> np.ndarray:
    """``S = A_cl^T P + P A_cl + 2 alpha P`` for a stack of ``A_cl`` (no checks).

    ``dV/dt + 2 alpha V = e^T S e`` for ``V = e^T P e`` and ``e' = A_cl e``.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        Symmetric.
    A_cl : ndarray, shape (..., n, n)
        Closed-loop error matrices.
    alpha : float
        Decay rate.

    Returns
    -------
    ndarray, shape (..., n, n)
        Symmetric matrices.
    """
    PA = P @ A_cl
    return PA + np.swapaxes(PA, -1, -2) + 2.0 * alpha * P


def polytopic_lmi(
    P: np.ndarray, R: np.ndarray, A: np.ndarray, C: np.ndarray, alpha: float
) -> np.ndarray:
    """``A^T P + P A - C^T R^T - R C + 2 alpha P`` for a stack of ``A`` (no checks).

    With ``R = P L`` this is :func:`decay_matrices` at ``A_cl = A - L C``; it is
    affine in ``(P, R)``, the LMI of the polytopic design.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        Symmetric (or a stack of them whose leading axes broadcast against
        ``A``'s, e.g. ``(B, 1, n, n)``).
    R : ndarray, shape (n, q)
        ``P L`` (stacked like ``P``).
    A : ndarray, shape (..., n, n)
        From :func:`corner_matrices`.
    C : ndarray, shape (q, n)
        Output matrix.
    alpha : float
        Decay rate.

    Returns
    -------
    ndarray, shape (..., n, n)
        Symmetric matrices; the design asks for them ``<= -margin I``.
    """
    PA = P @ A - R @ C
    return PA + np.swapaxes(PA, -1, -2) + 2.0 * alpha * P


def decay_certificate(
    P: np.ndarray,
    L: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    bounds: Any,
    input_bound: float,
    alpha: float,
) -> list[tuple[np.ndarray, float]]:
    """Largest eigenvalue of ``A_cl^T P + P A_cl + 2 alpha P`` per input vertex.

    The maximum, at each of the ``3**m`` input vertices, over every corner of
    the Jacobian bounds (:func:`corner_matrices`) of ``lambda_max(S)`` with
    ``S = A_cl^T P + P A_cl + 2 alpha P`` and ``A_cl = A - L C``, plus
    ``2 ||P||_2`` :func:`thin_perturbation` for the thin entries. All negative
    (and ``P`` positive definite) is a sound certificate that ``V = e^T P e``
    obeys ``dV/dt <= -2 alpha V`` along the true nonlinear error dynamics for
    every ``x, xhat`` in the box of the bounds and every ``|u_k| <=
    input_bound``; the derivation is in the module docstring.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        Lyapunov matrix (symmetrized here).
    L, H, K : ndarray, shape (n, q)
        Observer gains.
    C : ndarray, shape (q, n)
        Output matrix.
    bounds : JacobianBounds or mapping or (Mf1, Mf2, Mg1, Mg2)
        Jacobian bounds over the box.
    input_bound : float
        ``lambda_bar``.
    alpha : float
        Decay rate.

    Returns
    -------
    list of (ndarray, float)
        ``(u vertex, max eigenvalue over the corners)``, in the order of
        :func:`ofrl_drake.sector.input_vertices`.

    Raises
    ------
    LmiError
        For bad shapes or numbers, or more than :data:`MAX_CORNERS` corner
        matrices over all vertices.

    Examples
    --------
    >>> import numpy as np
    >>> Z = np.zeros((1, 1, 1))
    >>> cert = decay_certificate([[1.0]], [[3.0]], [[0.0]], [[0.0]], [[1.0]],
    ...                          ([[-1.0]], [[1.0]], Z, Z), 1.0, 0.5)
    >>> [(u.tolist(), ev) for u, ev in cert]
    [([-1.0], -3.0), ([0.0], -3.0), ([1.0], -3.0)]
    """
    P, L, H, K, C = _gains(P, L, H, K, C)
    if not np.isfinite(alpha):
        raise LmiError(f"alpha must be finite; got {alpha!r}.")
    if not (np.isfinite(input_bound) and input_bound >= 0):
        raise LmiError(f"input_bound must be finite and >= 0; got {input_bound!r}.")
    Mf1 = bounds_arrays(bounds)[0]
    n = P.shape[0]
    if Mf1.shape != (n, n):
        raise LmiError(f"bounds are for n = {Mf1.shape[0]} but P is {n} x {n}.")
    corners = vertex_corners(bounds, input_bound, H, K, C)
    P = 0.5 * (P + P.T)
    P_norm = float(np.linalg.norm(P, 2))
    out = []
    for u, A in corners:
        A_cl = A - L @ C
        S = decay_matrices(P, A_cl, alpha)
        thin = 2.0 * P_norm * thin_perturbation(bounds, u, H, K, C)
        out.append((u, float(np.linalg.eigvalsh(S)[:, -1].max()) + thin))
    return out


def is_decay_certified(
    P: np.ndarray,
    L: np.ndarray,
    H: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    bounds: Any,
    input_bound: float,
    alpha: float,
) -> bool:
    """True if ``P > 0`` and :func:`decay_certificate` is < 0 (:func:`certifies`)."""
    return certifies(P, lambda: decay_certificate(P, L, H, K, C, bounds, input_bound, alpha))
