"""The structured (norm-bounded) observer decay LMI and its re-checks: pure numpy.

The same claim as the polytopic certificate of :mod:`ofrl_drake.lmi`
---------------------------------------------------------------------
:func:`ofrl_drake.lmi.decay_certificate` proves ``dV/dt <= -2 alpha V`` for
``V = e^T P e`` along the true error dynamics ``e' = A_cl e`` with

    A_cl = M_f (I - H C) + M_gu (I - K C) + (M_f1 H + M_ug1(u) K) C - L C,

``M_f`` anywhere in the element-wise box ``[M_f1, M_f2]`` and ``M_gu`` in
``[M_ug1(u), M_ug2(u)]`` (the row-wise mean value theorem and the
sign-correct input sector), at each input vertex ``u in {-b, 0, b}^m``. Without
injection (``H = K = 0``) only the sum ``M_f + M_gu`` matters, which ranges over
the summed box ``[M_f1 + M_ug1(u), M_f2 + M_ug2(u)]``. It enumerates the
``2**k`` corners of a box with ``k`` uncertain entries.

Here the box is written as a norm-bounded perturbation instead. At one input
vertex, with ``mid`` and ``w`` the midpoint and half-width of each entry,

    A(delta) = A0 + sum_l delta_l w_l e_{i_l} F_l,   |delta_l| <= 1,

one term per uncertain entry ``l = (i_l, j_l)``: ``A0`` is ``A_cl + L C`` at the
midpoints, and ``F_l`` is row ``j_l`` of ``I - H C`` for an entry of ``M_f``, of
``I - K C`` for an entry of ``M_gu`` (row ``j_l`` of ``I``, i.e. ``e_{j_l}^T``,
without injection, where the summed box is used). :func:`vertex_model` builds
it. Every ``A`` of the box is an ``A(delta)`` and conversely, so certifying all
of them is exactly the polytopic claim.

The S-procedure
---------------
With ``R = P L`` and ``S0 = A0^T P + P A0 - C^T R^T - R C + 2 alpha P``,

    dV/dt + 2 alpha V = e^T S0 e + 2 e^T P E p,

where ``p`` collects the perturbation signals. Two groupings (``grouping=``):

``"entry"``: one signal per uncertain entry, ``p_l = delta_l w_l F_l e`` and
    ``E = [e_{i_1}, ..., e_{i_k}]``; each obeys ``p_l^2 <= e^T D_l e`` with
    ``D_l = w_l^2 F_l^T F_l``.
``"row"``: one signal per uncertain row ``i``, ``p_i = sum_{l in i} delta_l w_l
    F_l e`` and ``E = [e_i, ...]``; by Cauchy-Schwarz ``p_i^2 <= (sum w_l) sum w_l
    (F_l e)^2 = e^T D_i e`` with ``D_i = s_i sum_{l in i} w_l F_l^T F_l``,
    ``s_i = sum_{l in i} w_l``.

With one multiplier ``tau_g >= 0`` per signal (``T = diag(tau)``), the LMI

    M = [[S0 + sum_g tau_g D_g,  P E],
         [E^T P,                 -T  ]]  <=  -margin I

implies, for every admissible ``p``, ``e^T S0 e + 2 e^T P E p <= e^T S0 e + 2
e^T P E p + sum_g tau_g (e^T D_g e - p_g^2) <= -margin (|e|^2 + |p|^2)``, so
``A(delta)^T P + P A(delta) - C^T R^T - R C + 2 alpha P <= -margin I`` for every
``delta`` in the box: the polytopic LMI at every corner at once. It is one
matrix of size ``n + r`` per input vertex (``r = k`` signals for ``"entry"``,
the number of uncertain rows for ``"row"``) instead of ``2**k`` matrices of
size ``n``, and affine in ``(P, R, tau)`` jointly.

``"row"`` is ``"entry"`` with the multipliers tied (``tau_l = tau_i s_i / w_l``
reproduces it through the Schur complement), so ``"entry"`` certifies at least
every rate ``"row"`` does, with a larger LMI. Both may certify less than the
polytopic LMI: the S-procedure is lossless for one signal (``k = 1``) but not
in general.

Thin entries (``lmi.THIN_RTOL``) are fixed at their midpoint exactly as in the
polytopic certificate, and the re-check adds the same ``2 ||P||_2``
:func:`ofrl_drake.lmi.thin_perturbation` term.

Re-checks
---------
:func:`structured_certificate` recomputes ``lambda_max(M)`` at each input
vertex from ``P``, ``L`` and the multipliers alone; all negative (with ``P``
positive definite) proves the decay claim, because ``M <= mu I`` with ``mu <=
0`` gives ``S(delta) <= mu I`` for every ``delta`` in the box by the argument
above. :func:`delta_check` does not use the multipliers: it evaluates
``lambda_max(A(delta)_cl^T P + P A(delta)_cl + 2 alpha P)`` at every vertex of
the ``delta`` box when there are at most :data:`MAX_DELTA_VERTICES` of them
(then it is a proof too, the polytopic one), or at random vertices and
interior points of the box (then it can only find counterexamples).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ofrl_drake.lmi import (
    LmiError,
    _collapse,
    _injection,
    block_matrix,
    bounds_arrays,
    decay_matrices,
    gain_matrix,
    thin_perturbation,
)
from ofrl_drake.sector import input_sector, input_vertices

__all__ = [
    "GROUPINGS",
    "MAX_DELTA_VERTICES",
    "DeltaCheck",
    "StructuredLmi",
    "UncertainModel",
    "delta_check",
    "structured_certificate",
    "structured_lmi",
    "structured_lmi_blocks",
    "vertex_model",
]

GROUPINGS = ("entry", "row")
#: :func:`delta_check` enumerates every vertex of the ``delta`` box up to this many.
MAX_DELTA_VERTICES = 2**12


@dataclass(frozen=True, eq=False)
class UncertainModel:
    """``A(delta) = A0 + sum_l delta_l w_l e_{rows[l]} F[l]`` at one input vertex.

    Attributes
    ----------
    u : ndarray, shape (m,)
        The input vertex.
    A0 : ndarray, shape (n, n)
        The error-dynamics matrix at the midpoints of the Jacobian box, without
        ``- L C``.
    rows, cols : ndarray of int, shape (k,)
        Row and column of each uncertain entry (of ``M_f`` first, then of
        ``M_gu``, when there is injection; of the summed box otherwise).
    widths : ndarray, shape (k,)
        Half-widths ``w_l > 0``, rounded up so that ``A0 +- w`` covers the box.
    F : ndarray, shape (k, n)
        ``F_l``: row ``cols[l]`` of ``I - H C`` (entries of ``M_f``) or ``I - K C``
        (entries of ``M_gu``); ``e_{cols[l]}^T`` without injection.
    thin : float
        :func:`ofrl_drake.lmi.thin_perturbation` at this vertex: the spectral-norm
        bound on what the thin entries fixed at their midpoint leave out.
    """

    u: np.ndarray
    A0: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    widths: np.ndarray
    F: np.ndarray
    thin: float

    @property
    def n(self) -> int:
        """State dimension."""
        return int(self.A0.shape[0])

    @property
    def k(self) -> int:
        """Number of uncertain entries."""
        return int(self.widths.size)

    def matrices(self, delta: np.ndarray) -> np.ndarray:
        """``A(delta)`` for a stack of ``delta``, shape ``(N, k)`` -> ``(N, n, n)``."""
        delta = np.atleast_2d(np.asarray(delta, dtype=float))
        if delta.shape[1] != self.k:
            raise LmiError(f"delta must have {self.k} columns; got shape {delta.shape}.")
        # sum_l delta_l w_l e_{i_l} F_l: scatter-add the rows w_l F_l into row i_l.
        out = np.repeat(self.A0[None], delta.shape[0], axis=0)
        scaled = (delta * self.widths)[:, :, None] * self.F[None]  # (N, k, n)
        np.add.at(out, (np.arange(delta.shape[0])[:, None], self.rows[None, :]), scaled)
        return out

    def signals(self, grouping: str) -> tuple[np.ndarray, np.ndarray]:
        """The S-procedure data ``(E, D)`` of ``grouping`` (module docstring).

        Returns
        -------
        E : ndarray, shape (n, r)
            Unit columns ``e_i``: where each signal enters ``e'``.
        D : ndarray, shape (r, n, n)
            Positive semidefinite: signal ``g`` obeys ``p_g^2 <= e^T D_g e``.
        """
        n = self.n
        if grouping == "entry":
            E = np.eye(n)[:, self.rows]
            wF = self.widths[:, None] * self.F
            D = wF[:, :, None] * wF[:, None, :]
            return E, D
        if grouping == "row":
            groups = np.unique(self.rows)
            E = np.eye(n)[:, groups]
            D = np.zeros((groups.size, n, n))
            for g, i in enumerate(groups):
                sel = self.rows == i
                w, F = self.widths[sel], self.F[sel]
                D[g] = w.sum() * np.einsum("l,la,lb->ab", w, F, F)
            return E, D
        raise LmiError(f"grouping must be one of {GROUPINGS}; got {grouping!r}.")


def _check_box(lo: np.ndarray, hi: np.ndarray, what: str) -> None:
    bad = ~(np.isfinite(lo) & np.isfinite(hi) & (lo <= hi))
    if np.any(bad):
        where = [int(i) for i in np.argwhere(bad)[0]]
        raise LmiError(
            f"{what} bounds at entry {where}: lower = {lo[tuple(where)]:.6g}, upper = "
            f"{hi[tuple(where)]:.6g}; they must be finite with lower <= upper. Check f and g "
            "on the observer box, or shrink the box."
        )


def _entries(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mid, free, w)`` of a box whose thin entries are already collapsed.

    ``w`` is rounded up by one ulp, so ``[lo, hi]`` lies within ``mid +- w``
    despite the rounding of the two subtractions.
    """
    mid = lo + 0.5 * (hi - lo)
    free = np.argwhere(lo != hi)
    w = np.maximum(hi - mid, mid - lo)[lo != hi]
    return mid, free, np.nextafter(w, np.inf)


def vertex_model(
    bounds: Any, u: Any, H: Any = None, K: Any = None, C: Any = None
) -> UncertainModel:
    """The norm-bounded model of the Jacobian box at input ``u`` (module docstring).

    Parameters
    ----------
    bounds : JacobianBounds or mapping or (Mf1, Mf2, Mg1, Mg2)
        Jacobian bounds (see :func:`ofrl_drake.lmi.bounds_arrays`).
    u : array_like, shape (m,)
        The input (an input vertex, for a certificate).
    H, K : array_like, shape (n, q), optional
        Injection gains; both None (or both zero) means no injection, and the
        summed box ``[M_f1 + M_ug1(u), M_f2 + M_ug2(u)]`` is used, as in
        :func:`ofrl_drake.lmi.corner_matrices`.
    C : array_like, shape (q, n), optional
        Output matrix; needed with ``H, K``.

    Returns
    -------
    UncertainModel
        ``A0 +- w`` covers the same matrices as the corners of
        :func:`ofrl_drake.lmi.corner_matrices`.

    Raises
    ------
    LmiError
        For bad shapes, or bounds that are not finite or are crossed.

    Examples
    --------
    >>> import numpy as np
    >>> Z = np.zeros((2, 2, 1))
    >>> model = vertex_model(([[0.0, 1.0], [-3.0, 0.0]], [[0.0, 1.0], [-1.0, 0.0]], Z, Z), [0.0])
    >>> model.A0.tolist(), model.rows.tolist(), model.cols.tolist(), model.widths.tolist()
    ([[0.0, 1.0], [-2.0, 0.0]], [1], [0], [1.0000000000000002])
    """
    Mf1, Mf2, Mg1, Mg2 = bounds_arrays(bounds)
    n, m = Mf1.shape[0], Mg1.shape[2]
    u = np.atleast_1d(np.asarray(u, dtype=float))
    if u.shape != (m,) or not np.all(np.isfinite(u)):
        raise LmiError(f"u must be a finite array of shape ({m},); got {u.tolist()}.")
    Mug1, Mug2 = input_sector(Mg1, Mg2, u)
    _check_box(Mf1, Mf2, "Mf")
    _check_box(Mug1, Mug2, f"input sector at u = {u.tolist()}")
    thin = thin_perturbation(bounds, u, H, K, C)
    inj = _injection(H, K, C, n)
    eye = np.eye(n)
    if inj is None:
        mid, free, w = _entries(*_collapse(Mf1 + Mug1, Mf2 + Mug2)[:2])
        F = eye[free[:, 1]]
        return UncertainModel(u, mid, free[:, 0], free[:, 1], w, F.reshape(-1, n), thin)
    H, K, C = inj
    Hf, Kg = eye - H @ C, eye - K @ C
    mid_f, free_f, w_f = _entries(*_collapse(Mf1, Mf2)[:2])
    mid_g, free_g, w_g = _entries(*_collapse(Mug1, Mug2)[:2])
    A0 = mid_f @ Hf + mid_g @ Kg + (Mf1 @ H + Mug1 @ K) @ C
    free = np.concatenate([free_f, free_g]).reshape(-1, 2)
    F = np.concatenate([Hf[free_f[:, 1]], Kg[free_g[:, 1]]]).reshape(-1, n)
    return UncertainModel(u, A0, free[:, 0], free[:, 1], np.concatenate([w_f, w_g]), F, thin)


def _same(a: UncertainModel, b: UncertainModel) -> bool:
    return (
        a.thin == b.thin
        and np.array_equal(a.A0, b.A0)
        and np.array_equal(a.rows, b.rows)
        and np.array_equal(a.widths, b.widths)
        and np.array_equal(a.F, b.F)
    )


@dataclass(frozen=True, eq=False)
class StructuredLmi:
    """The numeric data of the structured observer LMI (the SDP's constraints).

    The analogue of the polytopic ``corners``: one :class:`UncertainModel` per
    distinct input vertex, each giving one LMI of size ``n + r``.

    Attributes
    ----------
    C : ndarray, shape (q, n)
        Output matrix.
    models : tuple of UncertainModel
        One per input vertex, identical ones merged (the vertices of an input
        that does not enter the Jacobian bounds give one model).
    grouping : str
        ``"entry"`` or ``"row"``: one multiplier per uncertain entry or per row.
    alpha, margin : float
        Decay rate and strict margin (``M <= -margin I``).
    """

    C: np.ndarray
    models: tuple[UncertainModel, ...]
    grouping: str
    alpha: float
    margin: float

    @property
    def n(self) -> int:
        """State dimension."""
        return int(self.C.shape[1])

    @property
    def q(self) -> int:
        """Output dimension."""
        return int(self.C.shape[0])

    @property
    def multiplier_counts(self) -> list[int]:
        """Multipliers ``r`` of each model's LMI."""
        return [m.signals(self.grouping)[0].shape[1] for m in self.models]

    @property
    def sizes(self) -> list[int]:
        """Size ``n + r`` of each model's LMI."""
        return [self.n + r for r in self.multiplier_counts]

    @property
    def uncertain_entries(self) -> int:
        """The largest ``k`` over the models."""
        return max((m.k for m in self.models), default=0)


def structured_lmi(
    C: Any,
    bounds: Any,
    input_bound: float,
    alpha: float,
    *,
    margin: float,
    grouping: str = "entry",
    H: Any = None,
    K: Any = None,
) -> StructuredLmi:
    """Build the structured LMI data at the ``3**m`` input vertices.

    Parameters
    ----------
    C : array_like, shape (q, n)
        Output matrix.
    bounds : JacobianBounds or mapping or (Mf1, Mf2, Mg1, Mg2)
        Jacobian bounds over the box.
    input_bound : float
        ``lambda_bar``: the input vertices have entries in ``{-b, 0, b}``.
    alpha : float
        Decay rate.
    margin : float
        Strict margin asked of the solver.
    grouping : {"entry", "row"}
        One multiplier per uncertain entry or per uncertain row.
    H, K : array_like, shape (n, q), optional
        Pinned injection gains (None: ``H = K = 0``, the polytopic design's).

    Raises
    ------
    LmiError
        For a bad grouping, numbers or shapes.
    """
    if grouping not in GROUPINGS:
        raise LmiError(f"grouping must be one of {GROUPINGS}; got {grouping!r}.")
    for name, value in (("alpha", alpha), ("input_bound", input_bound), ("margin", margin)):
        if not (np.isfinite(value) and value >= 0):
            raise LmiError(f"{name} must be a finite number >= 0; got {value!r}.")
    C = np.atleast_2d(np.asarray(C, dtype=float))
    m = bounds_arrays(bounds)[2].shape[2]
    models: list[UncertainModel] = []
    for u in input_vertices(float(input_bound), m):
        model = vertex_model(bounds, u, H, K, C if H is not None or K is not None else None)
        if model.n != C.shape[1]:
            raise LmiError(f"bounds are for n = {model.n} but C is {C.shape}.")
        if not any(_same(model, seen) for seen in models):
            models.append(model)
    return StructuredLmi(C, tuple(models), grouping, float(alpha), float(margin))


def structured_lmi_blocks(
    problem: StructuredLmi, P: np.ndarray, R: np.ndarray, tau: list[np.ndarray]
) -> list[np.ndarray]:
    """The matrix ``M`` of each model (module docstring), for numbers ``P, R, tau``.

    Affine in ``(P, R, tau)`` jointly (no checks), so a backend can read the
    coefficient matrices of the LMI ``-M - margin I >= 0`` off it. Every
    argument may carry the same leading (batch) axes, e.g. one per decision
    variable whose coefficients are read at once.

    Parameters
    ----------
    problem : StructuredLmi
        The data.
    P : ndarray, shape (..., n, n)
        Symmetric Lyapunov matrix.
    R : ndarray, shape (..., n, q)
        ``P L``.
    tau : list of ndarray
        The multipliers of each model, shapes ``(..., r_v)``.

    Returns
    -------
    list of ndarray, shapes (..., n + r_v, n + r_v)
        Symmetric; the certificate needs each negative definite.
    """
    C, alpha = problem.C, problem.alpha
    out = []
    for model, t in zip(problem.models, tau, strict=True):
        E, D = model.signals(problem.grouping)
        PA = P @ model.A0 - R @ C
        n = D.shape[-1]
        tD = (t @ D.reshape(D.shape[0], n * n)).reshape(*t.shape[:-1], n, n)  # sum_g t_g D_g
        S = PA + np.swapaxes(PA, -1, -2) + 2.0 * alpha * P + tD
        PE = P @ E
        T = t[..., :, None] * np.eye(t.shape[-1])  # diag(t), of each stacked t
        M = block_matrix([[S, PE], [np.swapaxes(PE, -1, -2), -T]])
        out.append(0.5 * (M + np.swapaxes(M, -1, -2)))
    return out


def _numbers(
    problem: StructuredLmi, P: Any, L: Any, tau: Any
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    n, q = problem.n, problem.q
    L = gain_matrix("L", L, n, q)
    P = np.asarray(P, dtype=float)
    if P.shape != (n, n):
        raise LmiError(f"P must be ({n}, {n}) and L ({n}, {q}); got {P.shape} and {L.shape}.")
    counts = problem.multiplier_counts
    tau = [np.asarray(t, dtype=float).ravel() for t in tau]
    if [t.size for t in tau] != counts:
        raise LmiError(
            f"tau must hold {counts} multipliers (one array per model); got "
            f"{[t.size for t in tau]}."
        )
    return 0.5 * (P + P.T), L, tau


def structured_certificate(
    problem: StructuredLmi, P: Any, L: Any, tau: Any
) -> list[tuple[np.ndarray, float]]:
    """``lambda_max(M) + 2 ||P||_2 thin`` at each model, from the numbers alone.

    All negative, with ``P`` positive definite, proves ``dV/dt <= -2 alpha V``
    for every ``x, xhat`` in the box of the bounds and every ``|u_k| <=
    input_bound`` (module docstring). ``M`` is rebuilt with ``R = P L`` from
    the ``L`` given, not from the solver's ``R``.

    Parameters
    ----------
    problem : StructuredLmi
        The data.
    P : array_like, shape (n, n)
        Lyapunov matrix (symmetrized here).
    L : array_like, shape (n, q)
        Observer gain.
    tau : sequence of array_like
        The multipliers of each model.

    Returns
    -------
    list of (ndarray, float)
        ``(u vertex, value)`` per model.

    Raises
    ------
    LmiError
        If ``P`` is not ``(n, n)``, ``L`` not a finite ``(n, q)`` array, or
        ``tau`` does not hold one array of multipliers of the right size per model.

    Examples
    --------
    >>> import numpy as np
    >>> Z = np.zeros((1, 1, 1))
    >>> prob = structured_lmi([[1.0]], ([[-2.0]], [[0.0]], Z, Z), 1.0, 0.5, margin=0.0)
    >>> cert = structured_certificate(prob, [[1.0]], [[1.0]], [[1.0]])
    >>> [(u.tolist(), round(v, 6)) for u, v in cert]
    [([-1.0], -0.381966)]
    """
    P, L, tau = _numbers(problem, P, L, tau)
    P_norm = float(np.linalg.norm(P, 2))
    blocks = structured_lmi_blocks(problem, P, P @ L, tau)
    return [
        (model.u.copy(), float(np.linalg.eigvalsh(M)[-1]) + 2.0 * P_norm * model.thin)
        for model, M in zip(problem.models, blocks, strict=True)
    ]


@dataclass(frozen=True)
class DeltaCheck:
    """What :func:`delta_check` found at one model.

    Attributes
    ----------
    u : ndarray
        The input vertex.
    worst : float
        The largest ``lambda_max(A_cl^T P + P A_cl + 2 alpha P)`` over the points,
        plus ``2 ||P||_2 thin``.
    delta : ndarray, shape (k,)
        Where it was found.
    points : int
        How many ``delta`` were evaluated.
    exhaustive : bool
        True if every vertex of the ``delta`` box was evaluated: then ``worst <
        0`` is a proof (convexity), otherwise a sample.
    """

    u: np.ndarray
    worst: float
    delta: np.ndarray
    points: int
    exhaustive: bool


def delta_check(
    problem: StructuredLmi,
    P: Any,
    L: Any,
    *,
    samples: int = 2000,
    seed: int = 0,
    max_vertices: int = MAX_DELTA_VERTICES,
) -> list[DeltaCheck]:
    """The Lyapunov inequality at points of the ``delta`` box, without multipliers.

    ``lambda_max(S)`` is convex in ``delta``, so its maximum over the box is at
    a vertex: with ``2**k <= max_vertices`` every vertex is evaluated and the
    check is exhaustive (a proof, the polytopic one, computed from the
    structured model); otherwise ``samples`` random vertices and ``samples``
    uniform interior points are (a falsification attempt).

    Parameters
    ----------
    problem : StructuredLmi
        The data (its ``alpha``; its multipliers are not used).
    P, L : array_like
        Lyapunov matrix and gain.
    samples : int
        Random vertices, and as many interior points, when not exhaustive.
    seed : int
        Seed of the samples.
    max_vertices : int
        Enumerate every vertex up to this many.

    Returns
    -------
    list of DeltaCheck
        One per model.
    """
    if int(samples) != samples or samples < 1:
        raise LmiError(f"samples must be a positive integer; got {samples!r}.")
    P, L, _ = _numbers(problem, P, L, [np.zeros(c) for c in problem.multiplier_counts])
    P_norm = float(np.linalg.norm(P, 2))
    LC = L @ problem.C
    rng = np.random.default_rng(seed)
    out = []
    for model in problem.models:
        k = model.k
        exhaustive = 2**k <= max_vertices
        if exhaustive:
            bits = (np.arange(2**k)[:, None] >> np.arange(k)[None, :]) & 1
            deltas = 2.0 * bits - 1.0
        else:
            vertices = rng.choice([-1.0, 1.0], size=(int(samples), k))
            inside = rng.uniform(-1.0, 1.0, size=(int(samples), k))
            deltas = np.concatenate([vertices, inside])
        worst, where = -np.inf, np.zeros(k)
        for start in range(0, deltas.shape[0], 4096):
            chunk = deltas[start : start + 4096]
            S = decay_matrices(P, model.matrices(chunk) - LC, problem.alpha)
            top = np.linalg.eigvalsh(S)[:, -1]
            best = int(np.argmax(top))
            if top[best] > worst:
                worst, where = float(top[best]), chunk[best].copy()
        out.append(
            DeltaCheck(
                model.u.copy(),
                worst + 2.0 * P_norm * model.thin,
                where,
                int(deltas.shape[0]),
                exhaustive,
            )
        )
    return out
