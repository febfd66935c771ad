"""The three-gain extended-Luenberger observer (eq:observerdynamics_x).

With ``ytil = y - C xhat`` the observer simplifies exactly to (docs/paper_notes.md)::

    xhat' = f(xhat + H ytil) + g(xhat + K ytil) u + (L - M_f1 H - M_ug1(u) K) ytil

where ``M_ug1(u)`` is the sign-correct lower input sector
(:func:`ofrl_drake.sector.input_sector`), here applied as precomputed
products with K (see :class:`ObserverGains`). The linear algebra around the
two calls of the model's ``f`` and ``g`` is compiled with numba
(:func:`injection_kernel`, :func:`correction_kernel`); ``f`` and ``g`` stay the
model's own Python functions. :func:`observer_rhs_expression` is the same
right-hand side as ``pydrake.symbolic`` expressions, which Drake evaluates in
C++ (:class:`~ofrl_drake.systems.SymbolicObserver`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from pydrake.symbolic import if_then_else

from ofrl_drake._jit import kernel
from ofrl_drake.checks import array_of_shape
from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem, SymbolicDynamics, require_system

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = [
    "ObserverGains",
    "correction_kernel",
    "injection_kernel",
    "observer_rhs",
    "observer_rhs_batch",
    "observer_rhs_expression",
    "pack_gains",
    "require_gains",
    "require_observer_arguments",
    "unpack_gains",
]


def _gain_shapes(system: ControlAffineSystem) -> dict[str, tuple[int, ...]]:
    """The shape of each gain of :class:`ObserverGains` for ``system``'s n, q and m."""
    n, m, q = system.n, system.m, system.q
    return {
        "L": (n, q),
        "H": (n, q),
        "K": (n, q),
        "Mf1": (n, n),
        "Mg1": (n, n, m),
        "Mg2": (n, n, m),
    }


def _matrix(
    name: str, value: Any, shape: tuple[int, ...], *, what: str = "observer gain ", fix: str = ""
) -> np.ndarray:
    """``value`` as a finite float array of ``shape``; a message names ``what + name``."""
    return array_of_shape(f"{what}{name}", value, shape, fix=fix)


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
    stacked : ndarray, shape ((3 + 2 m) n, q)
        Derived from the above (see Notes); not a constructor argument.

    Notes
    -----
    The gains are constant, so the right-hand side's products with them are
    folded into one matrix formed here, :attr:`stacked`, with row blocks
    ``H``, ``K``, ``L - M_f1 H`` and, per input k, ``min(M_g1, M_g2)[..., k] K``
    (used when ``u_k >= 0``) and ``max(M_g1, M_g2)[..., k] K`` (when
    ``u_k < 0``): ``min(a u_k, b u_k) = u_k min(a, b)`` for ``u_k >= 0`` and
    ``u_k max(a, b)`` otherwise, so these give ``M_ug1(u) K`` without forming
    ``M_ug1(u)``. One product ``stacked @ ytil`` then yields every term.
    """

    L: np.ndarray
    H: np.ndarray
    K: np.ndarray
    Mf1: np.ndarray
    Mg1: np.ndarray
    Mg2: np.ndarray
    stacked: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        H, K = np.asarray(self.H, dtype=float), np.asarray(self.K, dtype=float)
        Mg1, Mg2 = np.asarray(self.Mg1, dtype=float), np.asarray(self.Mg2, dtype=float)
        q = H.shape[1]
        # (m, n, n) with the input first, times K: (m, n, q), then rows.
        lower = (np.minimum(Mg1, Mg2).transpose(2, 0, 1) @ K).reshape(-1, q)
        upper = (np.maximum(Mg1, Mg2).transpose(2, 0, 1) @ K).reshape(-1, q)
        linear = np.asarray(self.L, dtype=float) - np.asarray(self.Mf1, dtype=float) @ H
        stacked = np.concatenate([H, K, linear, lower, upper]).reshape(-1, q)
        object.__setattr__(self, "stacked", stacked)

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
        shape = _gain_shapes(system)
        return cls(
            L=_matrix("L", L, shape["L"]),
            H=_matrix("H", H, shape["H"]),
            K=_matrix("K", K, shape["K"]),
            Mf1=_matrix("Mf1", Mf1, shape["Mf1"]),
            Mg1=_matrix("Mg1", Mg1, shape["Mg1"]),
            Mg2=_matrix("Mg2", Mg2, shape["Mg2"]),
        )

    @classmethod
    def from_design(cls, system: ControlAffineSystem, design: ObserverDesign) -> ObserverGains:
        """Take L, H, K and the Jacobian bounds from an ``ObserverDesign``."""
        b = design.bounds
        return cls.from_arrays(system, design.L, design.H, design.K, b.Mf1, b.Mg1, b.Mg2)

    def check_design(self, design: ObserverDesign) -> None:
        """Raise :class:`ModelError` unless ``design`` has these L, H and K.

        An observer block that reports ``design`` as its certificate must run
        exactly its gains.
        """
        for name in ("L", "H", "K"):
            if not np.array_equal(getattr(self, name), np.asarray(getattr(design, name))):
                raise ModelError(
                    f"gains.{name} differs from design.{name}; build the gains with "
                    "ObserverGains.from_design(system, design) or omit design=."
                )


def require_gains(value: Any, system: ControlAffineSystem, what: str) -> ObserverGains:
    """``value`` if it is an :class:`ObserverGains` that fits ``system``, else :class:`ModelError`.

    For the observer blocks, which run the gains as :attr:`ObserverGains.stacked`
    without re-reading their shapes: gains built for another model would
    raise deep inside numpy, or run with their row blocks misread (the
    estimate stuck while the run reports success).

    Parameters
    ----------
    value : object
        What was given as the gains.
    system : ControlAffineSystem
        The model the observer runs.
    what : str
        How the message names ``value`` (``"ThreeGainObserver: gains"``).

    Raises
    ------
    ModelError
        If ``value`` is not an :class:`ObserverGains`, or one of its gains has
        not the shape ``system``'s n, q and m give (:meth:`ObserverGains.from_arrays`)
        or is not finite. The message starts with ``what``, names the shapes
        got and expected and points to :meth:`ObserverGains.from_design`.
    """
    fix = "build them with ObserverGains.from_design(system, design)"
    if not isinstance(value, ObserverGains):
        raise ModelError(f"{what} must be an ObserverGains; got {type(value).__name__}; {fix}.")
    fix = (
        f"; the model {system.name!r} has n = {system.n}, q = {system.q}, m = {system.m}: "
        f"{fix} for this model"
    )
    for name, shape in _gain_shapes(system).items():
        _matrix(name, getattr(value, name), shape, what=f"{what}.", fix=fix)
    return value


def require_observer_arguments(
    block: str,
    system: Any,
    gains: Any,
    design: ObserverDesign | None = None,
) -> ObserverGains:
    """Check an observer block's ``system``, ``gains`` and ``design``; return ``gains``.

    Parameters
    ----------
    block : str
        The block's name, which starts each message (``"ThreeGainObserver"``).
    system : object
        What was given as the model.
    gains : object
        What was given as the gains.
    design : ObserverDesign, optional
        The design ``gains`` are said to come from.

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`~ofrl_drake.model.ControlAffineSystem`
        (:func:`~ofrl_drake.model.require_system`), ``gains`` do not fit it
        (:func:`require_gains`), or ``design`` is given and has other L, H
        or K (:meth:`ObserverGains.check_design`).
    """
    model = require_system(system, f"{block}: system")
    checked = require_gains(gains, model, f"{block}: gains")
    if design is not None:
        checked.check_design(design)
    return checked


def pack_gains(L: np.ndarray, H: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``[vec(L), vec(H), vec(K)]``, each row-major: ``3 n q`` entries.

    The layout of the scheduled observer's ``observer_gains`` output; read it
    back with :func:`unpack_gains`.
    """
    return np.concatenate([np.ravel(L), np.ravel(H), np.ravel(K)])


def unpack_gains(
    packed: Any, n: int, q: int, *, name: str = "observer_gains"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(L, H, K)`` from :func:`pack_gains`'s layout along the last axis of ``packed``.

    Parameters
    ----------
    packed : array_like, shape (..., 3 n q)
        One packed vector, or any stack of them (a log, shape ``(T, 3 n q)``).
    n, q : int
        The model's state and output sizes.
    name : str, optional
        How a message names ``packed``.

    Returns
    -------
    L, H, K : ndarray, shape (..., n, q)
        Views of ``packed`` (as a float array), the leading axes kept.

    Raises
    ------
    ModelError
        If ``packed`` is not numeric or its last axis has not ``3 n q``
        entries.
    """
    try:
        arr = np.asarray(packed, dtype=float)
    except (TypeError, ValueError) as err:
        raise ModelError(f"{name} must be numeric; got {packed!r}.") from err
    k = n * q
    if arr.ndim == 0 or arr.shape[-1] != 3 * k:
        raise ModelError(
            f"{name} must have 3 n q = {3 * k} entries on its last axis "
            f"([vec(L), vec(H), vec(K)]); got shape {arr.shape}."
        )
    lead = arr.shape[:-1]
    return (
        arr[..., :k].reshape(*lead, n, q),
        arr[..., k : 2 * k].reshape(*lead, n, q),
        arr[..., 2 * k :].reshape(*lead, n, q),
    )


@kernel
def injection_kernel(
    C: np.ndarray, stacked: np.ndarray, xhat: np.ndarray, y: np.ndarray, v: np.ndarray
) -> None:
    """``v = stacked @ (y - C xhat)``, then ``xhat`` added to its first two blocks.

    So ``v[:n] = xhat + H ytil`` and ``v[n:2n] = xhat + K ytil`` are the points
    where ``f`` and ``g`` are evaluated; the other blocks are as in
    :attr:`ObserverGains.stacked`.
    """
    q, n = C.shape
    ytil = np.empty(q)
    for i in range(q):
        acc = y[i]
        for j in range(n):
            acc -= C[i, j] * xhat[j]
        ytil[i] = acc
    for r in range(stacked.shape[0]):
        acc = 0.0
        for i in range(q):
            acc += stacked[r, i] * ytil[i]
        v[r] = acc
    for j in range(n):
        v[j] += xhat[j]
        v[n + j] += xhat[j]


@kernel
def correction_kernel(
    f_value: np.ndarray, g_value: np.ndarray, u: np.ndarray, v: np.ndarray, out: np.ndarray
) -> None:
    """``out = f + g u + (L - M_f1 H) ytil - M_ug1(u) K ytil`` from the blocks of ``v``."""
    n, m = g_value.shape
    for j in range(n):
        acc = f_value[j] + v[2 * n + j]
        for k in range(m):
            acc += g_value[j, k] * u[k]
        out[j] = acc
    for k in range(m):
        uk = u[k]
        start = (3 + k if uk >= 0.0 else 3 + m + k) * n
        for j in range(n):
            out[j] -= uk * v[start + j]


def observer_rhs(
    system: ControlAffineSystem,
    gains: ObserverGains,
    xhat: np.ndarray,
    y: np.ndarray,
    u: np.ndarray,
) -> np.ndarray:
    """``xhat'`` of the three-gain observer at one time."""
    xhat = np.asarray(xhat, dtype=float)
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    n = xhat.shape[0]
    # [xhat + H ytil; xhat + K ytil; (L - M_f1 H) ytil; sector-lower K ytil (m); upper (m)]
    v = np.empty(gains.stacked.shape[0])
    injection_kernel(system.output_matrix, gains.stacked, xhat, y, v)
    rhs = np.empty(n)
    correction_kernel(
        np.asarray(system.f(v[:n]), dtype=float),
        np.asarray(system.g(v[n : 2 * n]), dtype=float),
        u,
        v,
        rhs,
    )
    return rhs


def observer_rhs_expression(
    model: SymbolicDynamics,
    C: np.ndarray,
    gains: ObserverGains,
    xhat: np.ndarray,
    y: np.ndarray,
    u: np.ndarray,
) -> np.ndarray:
    """:func:`observer_rhs` as ``pydrake.symbolic`` expressions.

    Parameters
    ----------
    model : SymbolicDynamics
        The model's ``f`` and ``g`` (:meth:`ControlAffineSystem.symbolic`).
    C : ndarray, shape (q, n)
    gains : ObserverGains
    xhat, y, u : ndarray of Expression or Variable, shapes (n,), (q,), (m,)

    Returns
    -------
    ndarray of Expression, shape (n,)
        ``xhat'``; the input sector's choice between the lower and the upper
        product with K is an ``if_then_else`` on the sign of each ``u_k``, as in
        :func:`correction_kernel`.
    """
    n, m = len(xhat), len(u)
    with np.errstate(invalid="ignore"):  # numpy's object loops flag Drake expressions
        # The row blocks of ObserverGains.stacked: H, K, L - M_f1 H, lower (m), upper (m).
        v = gains.stacked @ (np.asarray(y) - np.asarray(C) @ np.asarray(xhat))
        f, _ = model.substitute(xhat + v[:n])
        _, g = model.substitute(xhat + v[n : 2 * n])
        rhs = f + g @ np.asarray(u) + v[2 * n : 3 * n]
        for k in range(m):
            lower = v[(3 + k) * n : (4 + k) * n]
            upper = v[(3 + m + k) * n : (4 + m + k) * n]
            sector = [if_then_else(u[k] >= 0.0, lower[j], upper[j]) for j in range(n)]
            rhs = rhs - u[k] * np.array(sector, dtype=object)
    return rhs


def observer_rhs_batch(
    system: ControlAffineSystem,
    gains: ObserverGains,
    Xhat: np.ndarray,
    Y: np.ndarray,
    U: np.ndarray,
) -> np.ndarray:
    """:func:`observer_rhs` at ``N`` points at once, one per column.

    Parameters
    ----------
    system : ControlAffineSystem
    gains : ObserverGains
    Xhat : ndarray, shape (n, N)
        Estimates.
    Y : ndarray, shape (q, N)
        Measurements.
    U : ndarray, shape (m, N)
        Inputs.

    Returns
    -------
    ndarray, shape (n, N)
        ``xhat'`` at each column, equal to :func:`observer_rhs` column by column.
    """
    Xhat = np.asarray(Xhat, dtype=float)
    U = np.asarray(U, dtype=float)
    n, m = system.n, system.m
    ytil = np.asarray(Y, dtype=float) - system.output_matrix @ Xhat
    v = gains.stacked @ ytil  # ((3 + 2 m) n, N)
    G = system.g_batch(Xhat + v[n : 2 * n])  # (n, m, N)
    rhs = system.f_batch(Xhat + v[:n]) + np.einsum("ikN,kN->iN", G, U) + v[2 * n : 3 * n]
    lower = v[3 * n : (3 + m) * n].reshape(m, n, -1)
    upper = v[(3 + m) * n :].reshape(m, n, -1)
    # - M_ug1(u) K ytil: per input, the lower sector row block for u_k >= 0, else the upper.
    chosen = np.where(U[:, None, :] >= 0.0, lower, upper)
    return rhs - np.einsum("kN,kiN->iN", U, chosen)
