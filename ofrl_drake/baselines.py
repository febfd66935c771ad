"""The math behind the ablation baselines: linearization, observer gains, moving points.

The baseline blocks of :mod:`ofrl_drake.systems.baselines` replace one part of
the paper's method with a textbook alternative. What they need besides Drake
blocks lives here:

* :func:`symbolic_plant` and :func:`linearize_at_origin`: the plant
  ``x' = f(x) + g(x) u``, ``y = C x`` as a Drake ``SymbolicVectorSystem``, and
  its linearization ``(A, B, C)`` at ``x = 0, u = 0`` by Drake's ``Linearize``.
  The origin must be an equilibrium (``f(0) = 0``).
* :func:`luenberger_poles` and :func:`luenberger_gain`: an observer gain ``L``
  placing the eigenvalues of ``A - L C`` by pole placement, and
  :func:`linearized_observer_certificate`: a Lyapunov matrix proving that the
  *linearized* error ``e' = (A - L C) e`` decays at rate alpha, re-checkable
  in numpy. It is local: it says nothing about the nonlinear error away from
  the origin, which the three-gain LMI certificate covers on its box.
* :func:`point_offsets`: the extrapolation points of a scenario as offsets from
  the centre of their box, for points that move with the estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from pydrake.symbolic import MakeVectorVariable
from pydrake.systems.primitives import Linearize, LinearSystem, SymbolicVectorSystem
from scipy.linalg import solve_continuous_lyapunov
from scipy.signal import place_poles

from ofrl_drake.errors import ModelError, ScenarioError, one_line
from ofrl_drake.model import ControlAffineSystem

__all__ = [
    "LinearizedObserverCertificate",
    "linearize_at_origin",
    "linearized_observer_certificate",
    "luenberger_gain",
    "luenberger_poles",
    "point_offsets",
    "symbolic_plant",
]


def symbolic_plant(system: ControlAffineSystem) -> SymbolicVectorSystem:
    """``x' = f(x) + g(x) u``, ``y = C x`` as a Drake ``SymbolicVectorSystem``.

    ``f`` and ``g`` are traced once on symbolic states
    (:meth:`~ofrl_drake.model.ControlAffineSystem.symbolic`), so the result
    supports Drake's scalar conversion (``Linearize``, trajectory optimization).

    Raises
    ------
    ModelError
        If Drake cannot trace ``f`` or ``g`` (they branch on the state, call
        scipy...): the baselines that linearize the plant need them symbolic.
    """
    try:
        traced = system.symbolic()
    except ModelError as err:
        cause = err.__cause__ or err
        raise ModelError(
            f"the baselines that linearize the plant (controller lqr, observer "
            f"drake_luenberger or kalman) trace f and g on symbolic states, and those of the "
            f"model {system.name!r} cannot be traced ({type(cause).__name__}: "
            f"{one_line(cause, 200)}); write f and g with numpy functions (np.cos, np.exp, **) "
            "and no branches on the state, or choose another variant."
        ) from err
    u = MakeVectorVariable(system.m, "u")
    # numpy's object loops flag "invalid value" on Drake symbolic values; harmless.
    with np.errstate(invalid="ignore"):
        dynamics = traced.f + traced.g @ u
        output = system.output_matrix @ traced.x
    return SymbolicVectorSystem(state=traced.x, input=u, dynamics=dynamics, output=output)


def linearize_at_origin(system: ControlAffineSystem, *, tol: float = 1e-9) -> LinearSystem:
    """Drake's ``Linearize`` of the plant at ``x = 0``, ``u = 0``.

    Parameters
    ----------
    system : ControlAffineSystem
    tol : float
        Largest ``|f(0)|`` accepted as an equilibrium.

    Returns
    -------
    LinearSystem
        ``A = df/dx(0)``, ``B = g(0)``, ``C``, ``D = 0``; its state is ``x``
        itself since the operating point is the origin.

    Raises
    ------
    ScenarioError
        If the origin is not an equilibrium of ``f``.
    """
    f0 = np.asarray(system.f(np.zeros(system.n)), dtype=float)
    if np.max(np.abs(f0)) > tol:
        raise ScenarioError(
            f"{system.name}: the origin is not an equilibrium (f(0) = {f0.tolist()}); "
            "the linearized baselines (lqr, drake_luenberger) need f(0) = 0."
        )
    plant = symbolic_plant(system)
    context = plant.CreateDefaultContext()
    context.SetContinuousState(np.zeros(system.n))  # type: ignore[arg-type]  # pydrake array stub
    plant.get_input_port().FixValue(context, np.zeros(system.m))
    return Linearize(plant, context, equilibrium_check_tolerance=tol)


def luenberger_poles(alpha: float, n: int) -> np.ndarray:
    """The default observer poles ``-2 alpha (1 + k/n)``, ``k = 0 .. n-1``.

    Twice the decay rate ``alpha`` asked of the certified observer, spread so
    that they are distinct (pole placement with ``q < n`` outputs needs that).
    For the paper's ``alpha = 2``, ``n = 2`` they are ``-4`` and ``-6``.
    """
    if not (np.isfinite(alpha) and alpha > 0):
        raise ModelError(f"alpha must be a positive number; got {alpha!r}.")
    return -2.0 * alpha * (1.0 + np.arange(n) / n)


def luenberger_gain(A: np.ndarray, C: np.ndarray, poles: np.ndarray) -> np.ndarray:
    """``L`` with ``eig(A - L C) = poles``, by pole placement on ``(A^T, C^T)``.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (q, n)
    poles : ndarray, shape (n,)
        Desired eigenvalues (real, or in conjugate pairs); none repeated more
        than ``q`` times.

    Returns
    -------
    L : ndarray, shape (n, q)

    Raises
    ------
    ScenarioError
        If ``(A, C)`` is not observable, so the poles cannot be placed.
    """
    A = np.asarray(A, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    n = A.shape[0]
    observability = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(n)])
    if np.linalg.matrix_rank(observability) < n:
        raise ScenarioError(
            f"variant.observer: (A, C) of the linearization is not observable "
            f"(A = {A.tolist()}, C = {C.tolist()}); no Luenberger gain places its poles."
        )
    placed = place_poles(A.T, C.T, np.asarray(poles, dtype=float))
    return np.asarray(placed.gain_matrix, dtype=float).T


@dataclass(frozen=True)
class LinearizedObserverCertificate:
    """Decay certificate of a Luenberger gain on the linearization ``(A, C)``.

    ``P`` proves that ``V(e) = e^T P e`` decays at rate ``2 alpha`` along
    ``e' = (A - L C) e`` when :meth:`certificate` is negative and ``P`` is
    positive definite, both recomputed in numpy from ``A, C, L, P, alpha``.
    The scope is the linear model: Drake's ``LuenbergerObserver`` on the
    linearization has no guarantee for the nonlinear plant away from the
    origin.

    Attributes
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (q, n)
    L : ndarray, shape (n, q)
    alpha : float
    P : ndarray, shape (n, n)
    """

    A: np.ndarray
    C: np.ndarray
    L: np.ndarray
    alpha: float
    P: np.ndarray

    def certificate(self) -> float:
        """Largest eigenvalue of ``(A - L C)^T P + P (A - L C) + 2 alpha P``."""
        Acl = self.A - self.L @ self.C
        M = Acl.T @ self.P + self.P @ Acl + 2.0 * self.alpha * self.P
        return float(np.linalg.eigvalsh(0.5 * (M + M.T))[-1])

    @property
    def is_certified(self) -> bool:
        """True if ``P > 0`` and :meth:`certificate` ``< 0``."""
        P = 0.5 * (self.P + self.P.T)
        return bool(np.linalg.eigvalsh(P)[0] > 0 and self.certificate() < 0)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the matrices, the eigenvalues of ``A - L C`` and the certificate."""
        poles = np.linalg.eigvals(self.A - self.L @ self.C)
        return {
            "kind": "linearized_luenberger",
            "scope": "linear error dynamics e' = (A - L C) e at the origin only",
            "A": self.A.tolist(),
            "C": self.C.tolist(),
            "L": self.L.tolist(),
            "alpha": self.alpha,
            "P": self.P.tolist(),
            "poles": {"real": poles.real.tolist(), "imag": poles.imag.tolist()},
            "certificate_max_eigenvalue": self.certificate(),
            "certified": self.is_certified,
        }


def linearized_observer_certificate(
    A: np.ndarray, C: np.ndarray, L: np.ndarray, alpha: float
) -> LinearizedObserverCertificate:
    """The Lyapunov certificate of ``e' = (A - L C) e`` at decay rate ``alpha``.

    Solves ``(A - L C + alpha I)^T P + P (A - L C + alpha I) = -I``, which has
    a positive definite solution exactly when every eigenvalue of ``A - L C``
    has real part below ``-alpha``; the result reports honestly (through
    :attr:`~LinearizedObserverCertificate.is_certified`) whether it does.

    Raises
    ------
    ModelError
        If the shapes do not match or ``alpha`` is not a positive number.
    """
    A = np.asarray(A, dtype=float)
    C = np.atleast_2d(np.asarray(C, dtype=float))
    L = np.asarray(L, dtype=float).reshape(A.shape[0], C.shape[0])
    if A.shape != (A.shape[0], A.shape[0]) or C.shape[1] != A.shape[0]:
        raise ModelError(f"A must be (n, n) and C (q, n); got {A.shape} and {C.shape}.")
    if not (np.isfinite(alpha) and alpha > 0):
        raise ModelError(f"alpha must be a positive number; got {alpha!r}.")
    shifted = A - L @ C + alpha * np.eye(A.shape[0])
    P = solve_continuous_lyapunov(shifted.T, -np.eye(A.shape[0]))
    return LinearizedObserverCertificate(A=A, C=C, L=L, alpha=float(alpha), P=0.5 * (P + P.T))


def point_offsets(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Extrapolation points as offsets from the centre of their box, shape ``(n, N)``.

    Points that move with the estimate are ``xhat + offsets``; for the paper's
    grid on ``[-1, 1]^2`` the offsets are the grid itself.
    """
    centre = 0.5 * (np.asarray(lower, dtype=float) + np.asarray(upper, dtype=float))
    return np.asarray(points, dtype=float) - centre[:, None]
