"""Falsify an observer design against the true nonlinear error dynamics.

An observer design claims ``d/dt (e^T P e) <= -2 alpha e^T P e`` for every
``x, xhat`` in its box and every ``|u_k| <= lambda_bar``, with ``e = x - xhat``.
The LMI behind the claim bounds the error dynamics; :func:`verify_observer`
checks the claim on the dynamics themselves, the plant ``x' = f(x) + g(x) u``
and the observer of :mod:`ofrl_drake.observer`, by searching for the largest

    r(x, xhat, u) = (d/dt e^T P e) / (e^T P e) = 2 e^T P e' / e^T P e.

Three searches, all vectorized over points:

* **finite errors**: ``x`` and ``xhat`` drawn uniformly in the box; with
  ``H`` or ``K`` nonzero, only the pairs whose injection points ``xhat + H C
  e`` and ``xhat + K C e`` lie in the box too (the mean-value argument
  evaluates f and g there, so the claim covers no other pair);
* **the small-error limit**: as ``e -> 0`` along a direction ``d``,
  ``r -> d^T (A^T P + P A) d / d^T P d`` with ``A = de'/de`` at ``e = 0``,

      A(x, u) = (Df(x) + Dg_u(x)) - Df(x) H C - Dg_u(x) K C - (L - M_f1 H) C + M_ug1(u) K C,

  ``Dg_u = sum_k u_k Dg_k``; the worst direction at each sampled ``x`` is the
  top generalized eigenvector of ``(A^T P + P A, P)``. The Jacobians come from
  ``f`` and ``g`` themselves (``pydrake.symbolic.Jacobian``);
* **local refinement**: multi-start L-BFGS-B (scipy) from the worst samples of
  both searches, within the box.

The input is not sampled: ``e'`` is affine in ``u`` on each orthant (the
sector ``M_ug1(u)`` breaks only at ``u_k = 0``), so ``r`` at fixed ``x, xhat``
and the convex ``lambda_max`` of the limit are largest at one of the ``3**m``
inputs ``u_k in {-lambda_bar, 0, +lambda_bar}``, and every one is evaluated
(for ``3**m > MAX_INPUT_VERTICES``, a random vertex per sample).

A sample where the true error dynamics are not finite (f or g undefined, or
overflowing, at a state of the box) has the rate ``+inf``: the claim cannot
hold where the dynamics do not exist, and the report names the point.

Sampling can only find counterexamples: a report that is not ``falsified``
means that none was found with this budget, not that the claim holds. A
``polytopic`` design is a proof (when its bounds are certified); a ``paper``
design is not, and on the two-state example it is falsified (docs/theory.md).
"""

from __future__ import annotations

import math
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.optimize import minimize

from ofrl_drake.checks import deadline_or_none, point_text
from ofrl_drake.errors import OfrlError, WallTimeExceeded
from ofrl_drake.jacobian_bounds import MAX_POINTS, Box, symbolic_jacobians
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.observer import ObserverGains, observer_rhs_batch
from ofrl_drake.sector import input_vertices
from ofrl_drake.validity import injection_points

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = [
    "DEFAULT_SAMPLES",
    "DEFAULT_TOLERANCE",
    "MAX_INPUT_VERTICES",
    "VerificationError",
    "VerificationReport",
    "error_jacobians",
    "error_rates",
    "plant_jacobians",
    "small_error_rates",
    "verify_observer",
]

#: Points (and pairs) sampled by default: the paper design falsifies well within it.
DEFAULT_SAMPLES = 10_000
#: A rate above ``-2 alpha + tol * max(1, 2 alpha)`` falsifies the claim.
DEFAULT_TOLERANCE = 1e-6
#: Beyond this many input vertices ``3**m``, each sample gets one random vertex.
MAX_INPUT_VERTICES = 81
_CHUNK = 50_000  # point evaluations per batch (bounds memory)
_MIN_FINITE_ERROR = 1e-4  # relative to the box width: smaller errors are the limit's job


class VerificationError(OfrlError):
    """A verification was asked for with a bad argument (samples, seed, design...)."""


# -------------------------------------------------------------------- report
def _vec(a: Any) -> np.ndarray:
    arr = np.array(a, dtype=float).ravel()
    arr.setflags(write=False)
    return arr


def _exact(value: float) -> str:
    """The shortest text that reads back as ``value``, without a trailing ``.0``.

    ``:g`` printed alpha = 0.9999999 as 1, the rate the plant cannot be certified at.
    """
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def _rate_beside(rate: float, claimed: float) -> str:
    """``rate`` to 4 significant digits, or as many more as keep it on its side of ``claimed``.

    ``-2 <= -2`` hid a worst rate of -2 against a claim of -1.9999998.
    """
    side = np.sign(rate - claimed)
    for digits in range(4, 18):
        text = f"{rate:+.{digits}g}"
        if np.sign(float(text) - claimed) == side:
            return text
    return repr(rate)


@dataclass(frozen=True, eq=False)
class VerificationReport:
    """What a falsification attempt found.

    Attributes
    ----------
    alpha : float
        The design's decay rate; the claim is ``r <= claimed_rate = -2 alpha``.
    worst_rate : float
        The largest ``r`` found (finite errors, the small-error limit, refined).
    x, xhat, u : ndarray
        Where: the state, the estimate and the input. For the small-error
        limit ``xhat = x`` and :attr:`direction` is the error direction.
    direction : ndarray or None
        Unit error direction of the worst point in the small-error limit; None
        when the worst point has a finite error ``e = x - xhat``.
    kind : str
        ``"small_error_limit"`` or ``"finite_error"``: which search found it.
    worst_small_error_rate, worst_finite_rate : float
        The best of each search (refined).
    violating_fraction : float
        Fraction of the sampled ``(x, u)`` (each sampled ``x`` at each input
        vertex) at which some error direction violates the claim in the
        small-error limit.
    finite_violating_fraction : float
        Fraction of the sampled ``(x, xhat, u)`` violating it.
    finite_outside_fraction : float
        Fraction of the sampled ``(x, xhat, u)`` left out because an injection
        point ``xhat + H C e`` or ``xhat + K C e`` is outside the box, where
        the claim does not reach (0 when ``H = K = 0``).
    samples : int
        Points ``x`` for the limit, and as many pairs ``(x, xhat)``.
    input_vertices : int
        Inputs evaluated per sample.
    seed : int
        Seed of the samples.
    refined : bool
        Whether the local refinement ran.
    tolerance : float
        Relative tolerance: falsified when ``worst_rate > claimed_rate +
        tolerance * max(1, |claimed_rate|)``.
    wall_time : float
        Seconds spent.
    box : Box
        The design's box; ``input_bound`` its ``lambda_bar``.
    input_bound : float
    jacobians : str
        ``"symbolic"`` (``pydrake.symbolic.Jacobian``) or ``"finite_difference"``
        (when ``f`` or ``g`` cannot be differentiated symbolically).
    """

    alpha: float
    worst_rate: float
    x: np.ndarray
    xhat: np.ndarray
    u: np.ndarray
    direction: np.ndarray | None
    kind: str
    worst_small_error_rate: float
    worst_finite_rate: float
    violating_fraction: float
    finite_violating_fraction: float
    samples: int
    input_vertices: int
    seed: int
    refined: bool
    tolerance: float
    wall_time: float
    box: Box
    input_bound: float
    jacobians: str
    finite_outside_fraction: float = 0.0

    def __post_init__(self) -> None:
        for key in ("x", "xhat", "u"):
            object.__setattr__(self, key, _vec(getattr(self, key)))
        if self.direction is not None:
            object.__setattr__(self, "direction", _vec(self.direction))

    @property
    def claimed_rate(self) -> float:
        """``-2 alpha``: the design claims ``r <= -2 alpha`` everywhere."""
        return -2.0 * self.alpha

    @property
    def threshold(self) -> float:
        """The rate above which a point falsifies the claim."""
        return self.claimed_rate + self.tolerance * max(1.0, abs(self.claimed_rate))

    @property
    def falsified(self) -> bool:
        """True if some point violates the claim by more than the tolerance."""
        return bool(self.worst_rate > self.threshold)

    def summary_line(self) -> str:
        """One line: "decay-certified..." or "claims alpha = ...; falsified: ..."."""
        claim = f"claims alpha = {_exact(self.alpha)} (r <= {_exact(self.claimed_rate)})"
        if not self.falsified:
            return (
                f"{claim}; not falsified: "
                f"worst r = {_rate_beside(self.worst_rate, self.claimed_rate)} over "
                f"{self.samples} samples "
                f"(seed {self.seed}{', refined' if self.refined else ''})"
            )
        where = f"x = {point_text(self.x)}, u = {point_text(self.u)}"
        if not math.isfinite(self.worst_rate):
            state = "" if self.direction is not None else f", xhat = {point_text(self.xhat)}"
            return (
                f"{claim}; falsified: the "
                f"error dynamics are not finite at {where}{state} (f or g is undefined or "
                "overflows there, inside the box)"
            )
        if self.direction is not None:
            where += f", e -> 0 along {point_text(self.direction)}"
        else:
            where += f", xhat = {point_text(self.xhat)}"
        rate = _rate_beside(self.worst_rate, self.claimed_rate)
        return f"{claim}; falsified: r = {rate} at {where}"

    def verdict(self, decay_certified: bool, bounds_guaranteed: bool = True) -> str:
        """One line for a design with or without a sound decay certificate.

        ``"decay-certified and not falsified (...)"`` when both hold; otherwise
        :meth:`summary_line`, prefixed with ``"not decay-certified; "`` when
        the design has no sound certificate but no counterexample was found.
        A certificate on Jacobian bounds that are not guaranteed (sampled, an
        inner estimate: ``ObserverDesign.bounds_are_guaranteed``) proves
        nothing, and the line says so.
        """
        if decay_certified and not self.falsified:
            on = "" if bounds_guaranteed else " on sampled Jacobian bounds (not a proof)"
            relation = "<=" if self.worst_rate <= self.claimed_rate else "within tolerance of"
            return (
                f"decay-certified{on} and not falsified (alpha = {_exact(self.alpha)}: worst r = "
                f"{_rate_beside(self.worst_rate, self.claimed_rate)} {relation} "
                f"{_exact(self.claimed_rate)} over {self.samples} samples)"
            )
        prefix = "" if self.falsified or decay_certified else "not decay-certified; "
        return prefix + self.summary_line()

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of every attribute plus ``claimed_rate`` and ``falsified``."""
        return {
            "claimed_rate": self.claimed_rate,
            "alpha": self.alpha,
            "worst_rate": self.worst_rate,
            "falsified": self.falsified,
            "x": self.x.tolist(),
            "xhat": self.xhat.tolist(),
            "u": self.u.tolist(),
            "direction": None if self.direction is None else self.direction.tolist(),
            "kind": self.kind,
            "worst_small_error_rate": self.worst_small_error_rate,
            "worst_finite_rate": self.worst_finite_rate,
            "violating_fraction": self.violating_fraction,
            "finite_violating_fraction": self.finite_violating_fraction,
            "finite_outside_fraction": self.finite_outside_fraction,
            "samples": self.samples,
            "input_vertices": self.input_vertices,
            "seed": self.seed,
            "refined": self.refined,
            "tolerance": self.tolerance,
            "threshold": self.threshold,
            "wall_time": self.wall_time,
            "box": self.box.to_dict(),
            "input_bound": self.input_bound,
            "jacobians": self.jacobians,
            "summary": self.summary_line(),
        }


# ---------------------------------------------------------------- jacobians
_JACOBIANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _jacobian_function(
    system: ControlAffineSystem,
) -> tuple[Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], str]:
    """``X (n, N) -> (Jf (n, n, N), Jg (n, n, m, N))`` and how it is computed.

    Symbolic (exact) when ``f`` and ``g`` take ``pydrake.symbolic`` states and
    use supported functions; central differences of ``f_batch``/``g_batch``
    otherwise. Cached per system.
    """
    cached = _JACOBIANS.get(system)
    if cached is not None:
        return cached
    from ofrl_drake.interval import ExpressionEvaluator

    n, m = system.n, system.m
    try:
        x, Jf, Jg = symbolic_jacobians(system)
        evaluator = ExpressionEvaluator(np.concatenate([Jf.ravel(), Jg.ravel()]), tuple(x))
    except OfrlError:
        evaluator = None
    if evaluator is not None:

        def symbolic(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            vals = evaluator(X)
            N = X.shape[1]
            return vals[: n * n].reshape(n, n, N), vals[n * n :].reshape(n, n, m, N)

        result = (symbolic, "symbolic")
    else:

        def central(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            N = X.shape[1]
            h = 1e-6 * np.maximum(1.0, np.abs(X))
            Jf = np.empty((n, n, N))
            Jg = np.empty((n, n, m, N))
            for j in range(n):  # a loop over state dimensions, vectorized over points
                step = np.zeros_like(X)
                step[j] = h[j]
                Jf[:, j] = (system.f_batch(X + step) - system.f_batch(X - step)) / (2 * h[j])
                Jg[:, j] = (system.g_batch(X + step) - system.g_batch(X - step)) / (2 * h[j])
            return Jf, Jg

        result = (central, "finite_difference")
    _JACOBIANS[system] = result
    return result


def plant_jacobians(system: ControlAffineSystem, X: Any) -> tuple[np.ndarray, np.ndarray]:
    """``Df`` and ``Dg`` at the columns of ``X`` (shape ``(n, N)``).

    Returns
    -------
    Jf : ndarray, shape (n, n, N)
        ``Jf[i, j, p] = d f_i / d x_j`` at point p.
    Jg : ndarray, shape (n, n, m, N)
        ``Jg[i, j, k, p] = d g[i, k] / d x_j`` at point p.
    """
    jac, _ = _jacobian_function(system)
    return jac(np.asarray(X, dtype=float).reshape(system.n, -1))


# --------------------------------------------------------------------- rates
def _design_numbers(
    design: ObserverDesign, system: ControlAffineSystem
) -> tuple[np.ndarray, ObserverGains, Box, float, float]:
    try:
        P = np.asarray(design.P, dtype=float)
        gains = ObserverGains.from_design(system, design)
        box = Box.coerce(design.box, system.n)
        alpha = float(design.alpha)
        input_bound = float(design.input_bound)
    except AttributeError as err:
        raise VerificationError(
            f"design must be an ObserverDesign (with P, L, H, K, alpha, box, input_bound "
            f"and bounds); got {type(design).__name__} ({err})."
        ) from None
    n = system.n
    if P.shape != (n, n) or not np.all(np.isfinite(P)):
        raise VerificationError(f"design.P must be a finite ({n}, {n}) matrix; got {P.shape}.")
    P = 0.5 * (P + P.T)
    if np.linalg.eigvalsh(P)[0] <= 0:
        raise VerificationError(
            "design.P is not positive definite, so e^T P e is no Lyapunov function; "
            "there is no decay claim to verify."
        )
    return P, gains, box, alpha, input_bound


def error_rates(
    design: ObserverDesign, system: ControlAffineSystem, X: Any, Xhat: Any, U: Any
) -> np.ndarray:
    """``r = 2 e^T P e' / e^T P e`` under the true dynamics, one per column.

    Parameters
    ----------
    design : ObserverDesign
    system : ControlAffineSystem
    X, Xhat : array_like, shape (n, N)
        States and estimates (``e = x - xhat`` must be nonzero).
    U : array_like, shape (m, N)
        Inputs.

    Returns
    -------
    ndarray, shape (N,)
    """
    P, gains, *_ = _design_numbers(design, system)
    return _rates(system, gains, P, *(np.asarray(a, float) for a in (X, Xhat, U)))


def _injections_inside(
    gains: ObserverGains, C: np.ndarray, X: np.ndarray, Xhat: np.ndarray, box: Box
) -> np.ndarray:
    """Per column, whether ``xhat + H C e`` and ``xhat + K C e`` lie in ``box``."""
    inside = np.ones(X.shape[1], dtype=bool)
    for point in injection_points(X.T, Xhat.T, C, gains.H, gains.K).values():
        inside &= box.contains(point.T)
    return inside


def _undefined_is_worst(rates: np.ndarray) -> np.ndarray:
    """NaN rates (dynamics undefined at the sample) as ``+inf``: the worst there is."""
    return np.where(np.isnan(rates), np.inf, rates)


def _rates(
    system: ControlAffineSystem,
    gains: ObserverGains,
    P: np.ndarray,
    X: np.ndarray,
    Xhat: np.ndarray,
    U: np.ndarray,
) -> np.ndarray:
    xdot = system.f_batch(X) + np.einsum("ikN,kN->iN", system.g_batch(X), U)
    xhatdot = observer_rhs_batch(system, gains, Xhat, system.output_matrix @ X, U)
    E = X - Xhat
    PE = P @ E
    with np.errstate(divide="ignore", invalid="ignore"):
        return 2.0 * np.einsum("iN,iN->N", PE, xdot - xhatdot) / np.einsum("iN,iN->N", PE, E)


def error_jacobians(
    design: ObserverDesign, system: ControlAffineSystem, X: Any, U: Any
) -> np.ndarray:
    """``A = de'/de`` at ``e = 0`` (``xhat = x``), one per column: shape ``(N, n, n)``.

    See the module docstring for the formula; ``Df``, ``Dg`` from ``f`` and ``g``.
    """
    _, gains, *_ = _design_numbers(design, system)
    X, U = np.asarray(X, float), np.asarray(U, float)
    jac, _ = _jacobian_function(system)
    return _error_jacobians(system, gains, jac, X, U)


def _error_jacobians(
    system: ControlAffineSystem,
    gains: ObserverGains,
    jac: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    X: np.ndarray,
    U: np.ndarray,
) -> np.ndarray:
    C = system.output_matrix
    n = system.n
    Jf, Jg = jac(X)
    Df = np.moveaxis(Jf, -1, 0)  # (N, n, n)
    Dgu = np.einsum("ijkN,kN->Nij", Jg, U)  # sum_k u_k Dg_k
    eye = np.eye(n)
    # M_ug1(u) K: the sector is piecewise linear in u with breaks at u_k = 0.
    lo = np.minimum(gains.Mg1, gains.Mg2)
    hi = np.maximum(gains.Mg1, gains.Mg2)
    Mug1 = np.einsum("ijk,kN->Nij", lo, np.maximum(U, 0.0)) + np.einsum(
        "ijk,kN->Nij", hi, np.minimum(U, 0.0)
    )
    fixed = (gains.Mf1 @ gains.H - gains.L) @ C  # - (L - M_f1 H) C
    return Df @ (eye - gains.H @ C) + Dgu @ (eye - gains.K @ C) + fixed + Mug1 @ gains.K @ C


def _limit_from_jacobians(A: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest generalized eigenvalue of ``(A^T P + P A, P)`` and its unit eigenvector.

    ``+inf`` (and a NaN direction) where ``A`` is not finite: the dynamics are
    undefined there.
    """
    finite = np.all(np.isfinite(A), axis=(-2, -1))
    if not np.all(finite):
        rates = np.full(A.shape[:-2], np.inf)
        directions = np.full((*A.shape[:-2], A.shape[-1]), np.nan)
        if np.any(finite):
            rates[finite], directions[finite] = _limit_from_jacobians(A[finite], P)
        return rates, directions
    Lc = np.linalg.cholesky(P)
    Li = np.linalg.inv(Lc)  # P = Lc Lc^T; e = Li^T w gives e^T P e = w^T w
    S = np.swapaxes(A, -1, -2) @ P + P @ A
    M = Li @ S @ Li.T
    w, V = np.linalg.eigh(0.5 * (M + np.swapaxes(M, -1, -2)))
    d = Li.T @ V[..., -1][..., None]
    d = d[..., 0] / np.linalg.norm(d[..., 0], axis=-1, keepdims=True)
    return w[..., -1], d


def small_error_rates(
    design: ObserverDesign, system: ControlAffineSystem, X: Any, U: Any
) -> tuple[np.ndarray, np.ndarray]:
    """The small-error limit of ``r`` at each column, and its worst direction.

    Returns
    -------
    rates : ndarray, shape (N,)
        ``max_d d^T (A^T P + P A) d / d^T P d`` with ``A`` from :func:`error_jacobians`.
    directions : ndarray, shape (N, n)
        Unit directions attaining it: ``r(x, x - eps d, u) -> rates`` as ``eps -> 0``.
    """
    P, *_ = _design_numbers(design, system)
    return _limit_from_jacobians(error_jacobians(design, system, X, U), P)


# ---------------------------------------------------------------- sampling
def _inputs(input_bound: float, m: int) -> np.ndarray:
    """The input vertices, shape (V, m); empty when there are too many."""
    if 3**m > MAX_INPUT_VERTICES:
        return np.zeros((0, m))
    return input_vertices(input_bound, m)


def _tile(
    rng: np.random.Generator, points: list[np.ndarray], input_bound: float, m: int
) -> tuple[list[np.ndarray], np.ndarray, int]:
    """Repeat each point column for every input vertex; returns (points, U, V)."""
    vertices = _inputs(input_bound, m)
    N = points[0].shape[1]
    if vertices.shape[0] == 0:
        U = input_bound * rng.integers(-1, 2, size=(m, N)).astype(float)
        return points, U, 1
    V = vertices.shape[0]
    return [np.repeat(p, V, axis=1) for p in points], np.tile(vertices.T, (1, N)), V


@dataclass
class _Best:
    rate: float = -math.inf
    x: np.ndarray | None = None
    xhat: np.ndarray | None = None
    u: np.ndarray | None = None
    direction: np.ndarray | None = None


def _found(point: np.ndarray | None) -> np.ndarray:
    """A point of :class:`_Best`, NaN where no sample had a finite rate."""
    return np.full(1, math.nan) if point is None else point


def _chunks(N: int, per_point: int) -> list[slice]:
    step = max(1, _CHUNK // max(1, per_point))
    return [slice(i, min(N, i + step)) for i in range(0, N, step)]


# -------------------------------------------------------------- refinement
def _refine(
    objective: Callable[[np.ndarray], np.ndarray],
    z0: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    smooth: Callable[[np.ndarray], np.ndarray] | None = None,
    inequalities: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, float]:
    """Maximize a batched objective from ``z0`` in the bounds; returns ``(z, objective(z))``.

    ``objective(Z)`` takes columns ``Z (d, K)``; the gradient is by central
    differences, all ``2 d + 1`` points in one call. Without
    ``inequalities``: L-BFGS-B on ``objective``. With ``inequalities = (G,
    b)``, the linear region ``G z <= b`` where ``objective`` is defined
    (finite) in the bounds: SLSQP on ``smooth``, the same objective without
    that region's mask. L-BFGS-B cannot search there: a step that leaves the
    region sees ``-inf`` and ends the search at its start.
    """
    d = z0.size
    h = 1e-7 * np.maximum(1.0, upper - lower)
    searched = objective if smooth is None else smooth

    def fun(z: np.ndarray) -> tuple[float, np.ndarray]:
        plus = np.minimum(z[:, None] + np.diag(h), upper[:, None])
        minus = np.maximum(z[:, None] - np.diag(h), lower[:, None])
        vals = searched(np.concatenate([z[:, None], plus, minus], axis=1))
        if not np.all(np.isfinite(vals)):
            return math.inf, np.zeros(d)
        grad = (vals[1 : d + 1] - vals[d + 1 :]) / np.maximum(
            np.diag(plus - minus), np.finfo(float).tiny
        )
        return -float(vals[0]), -grad

    bounds = list(zip(lower, upper, strict=True))
    if inequalities is None:
        res = minimize(
            fun, z0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 200}
        )
    else:
        G, b = inequalities
        inside = {"type": "ineq", "fun": lambda z: b - G @ z, "jac": lambda z: -G}
        res = minimize(
            fun,
            z0,
            jac=True,
            method="SLSQP",
            bounds=bounds,
            constraints=[inside],
            options={"maxiter": 200},
        )
    z = np.clip(res.x, lower, upper)
    value = float(objective(z[:, None])[0])
    start = float(objective(z0[:, None])[0])
    if not value >= start:  # the search ended worse, or outside the region: keep the start
        return z0, start
    return z, value


def _injection_region(
    gains: ObserverGains, C: np.ndarray, box: Box
) -> tuple[np.ndarray, np.ndarray]:
    """``(G, b)`` with ``G [x; xhat] <= b`` iff both injection points lie in ``box``.

    ``xhat + M C (x - xhat) = M C x + (I - M C) xhat`` for ``M`` = ``H``, ``K``
    is linear in ``[x; xhat]``, so the region of :func:`_injections_inside` is
    a polytope.
    """
    n = box.lower.size
    rows, rhs = [], []
    for M in (gains.H, gains.K):
        MC = np.asarray(M, dtype=float) @ np.asarray(C, dtype=float)
        A = np.hstack([MC, np.eye(n) - MC])
        rows += [A, -A]
        rhs += [np.asarray(box.upper, dtype=float), -np.asarray(box.lower, dtype=float)]
    return np.vstack(rows), np.concatenate(rhs)


# ---------------------------------------------------------------- verifier
#: Most samples :func:`verify_observer` draws in one call (memory grows with them):
#: the one cap on points drawn at once, :data:`~ofrl_drake.jacobian_bounds.MAX_POINTS`.
MAX_SAMPLES = MAX_POINTS


def verify_observer(
    design: ObserverDesign,
    system: ControlAffineSystem,
    *,
    samples: int = DEFAULT_SAMPLES,
    seed: int = 0,
    refine: bool = True,
    starts: int = 8,
    tol: float = DEFAULT_TOLERANCE,
    deadline: float | None = None,
) -> VerificationReport:
    """Search for the worst decay rate of ``e^T P e`` under the true error dynamics.

    Parameters
    ----------
    design : ObserverDesign
        The design to falsify: its ``P, L, H, K``, Jacobian bounds, ``alpha``,
        ``box`` and ``input_bound``.
    system : ControlAffineSystem
        The plant the design is for.
    samples : int
        Points ``x`` for the small-error limit, and as many pairs ``(x, xhat)``
        for finite errors, uniform in the box; each at every input vertex.
    seed : int
        Seed of the samples.
    refine : bool
        Run multi-start local refinement from the worst samples.
    starts : int
        Refinement starts per search.
    tol : float
        Relative tolerance of :attr:`VerificationReport.falsified`.
    deadline : float, optional
        A ``time.monotonic()`` reading: the search stops at its next chunk of
        samples or refinement start after it. None: no limit.

    Returns
    -------
    VerificationReport

    Raises
    ------
    VerificationError
        For a bad ``samples``, ``seed``, ``starts``, ``tol`` or ``deadline``,
        or a design without a positive definite ``P``.
    WallTimeExceeded
        If ``deadline`` passed before the search was done (step
        ``"verification"``): a search cut short is no report.

    Examples
    --------
    >>> from ofrl_drake.design import design_observer
    >>> from ofrl_drake.examples import make_system
    >>> system = make_system("two_state")
    >>> sound = design_observer(system, ([-2, -2], [2, 2]), 3.0, 0.5)
    >>> verify_observer(sound, system, samples=2000).falsified
    False
    """
    for name, given, least in (("samples", samples, 1), ("starts", starts, 0)):
        if isinstance(given, bool) or not isinstance(given, int | np.integer) or given < least:
            raise VerificationError(f"{name} must be an integer >= {least}; got {given!r}.")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise VerificationError(f"seed must be an integer >= 0; got {seed!r}.")
    if samples > MAX_SAMPLES:
        raise VerificationError(
            f"samples: {samples} would need about {samples * 8 * 6 * system.n / 2**30:.3g} GiB "
            f"for the sampled states; at most {MAX_SAMPLES} per run (run several seeds)."
        )
    if not (isinstance(tol, int | float) and math.isfinite(tol) and tol >= 0):
        raise VerificationError(f"tol must be a finite number >= 0; got {tol!r}.")
    deadline = deadline_or_none("deadline", deadline, error=VerificationError)
    start = time.perf_counter()

    def on_time(stage: str) -> None:
        if deadline is not None and time.monotonic() >= deadline:
            raise WallTimeExceeded(
                f"the observer's verification ran out of wall time "
                f"{time.perf_counter() - start:.3g} s into its search, before {stage}",
                step="verification",
            )

    P, gains, box, alpha, input_bound = _design_numbers(design, system)
    jac, jac_kind = _jacobian_function(system)
    n, m = system.n, system.m
    rng = np.random.default_rng(int(seed))
    lo, hi, width = box.lower, box.upper, box.width
    threshold = -2.0 * alpha + tol * max(1.0, 2.0 * alpha)

    def uniform(N: int) -> np.ndarray:
        return lo[:, None] + rng.random((n, N)) * width[:, None]

    # -- the small-error limit at sampled x, every input vertex
    X = uniform(samples)
    limit = _Best()
    limit_violations = 0
    limit_starts: list[tuple[float, np.ndarray, np.ndarray]] = []
    V = 1
    chunks = _chunks(samples, 3**m if 3**m <= MAX_INPUT_VERTICES else 1)
    for k, sl in enumerate(chunks):
        on_time(f"chunk {k + 1} of {len(chunks)} of the small-error search")
        (Xs,), Us, V = _tile(rng, [X[:, sl]], input_bound, m)
        rates, dirs = _limit_from_jacobians(_error_jacobians(system, gains, jac, Xs, Us), P)
        per = rates.reshape(-1, V)
        arg = per.argmax(axis=1)
        limit_violations += int(np.count_nonzero(rates > threshold))
        cols = np.arange(per.shape[0]) * V + arg
        for c in cols[np.argsort(per.max(axis=1))[::-1][:starts]]:
            limit_starts.append((float(rates[c]), Xs[:, c].copy(), Us[:, c].copy()))
        i = int(np.argmax(rates))
        if rates[i] > limit.rate:
            limit = _Best(
                float(rates[i]), Xs[:, i].copy(), Xs[:, i].copy(), Us[:, i].copy(), dirs[i]
            )
    violating = limit_violations / float(samples * V)

    # -- finite errors at sampled pairs, every input vertex
    X1, X2 = uniform(samples), uniform(samples)
    finite = _Best()
    finite_violations = 0
    outside = 0
    finite_starts: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
    for k, sl in enumerate(chunks):
        on_time(f"chunk {k + 1} of {len(chunks)} of the finite-error search")
        (Xs, Xh), Us, V = _tile(rng, [X1[:, sl], X2[:, sl]], input_bound, m)
        covered = _injections_inside(gains, system.output_matrix, Xs, Xh, box)
        outside += int(np.count_nonzero(~covered))
        rates = np.where(
            covered, _undefined_is_worst(_rates(system, gains, P, Xs, Xh, Us)), -np.inf
        )
        per = rates.reshape(-1, V)
        arg = per.argmax(axis=1)
        finite_violations += int(np.count_nonzero(rates > threshold))
        cols = np.arange(per.shape[0]) * V + arg
        for c in cols[np.argsort(per.max(axis=1))[::-1][:starts]]:
            finite_starts.append(
                (float(rates[c]), Xs[:, c].copy(), Xh[:, c].copy(), Us[:, c].copy())
            )
        i = int(np.argmax(rates))
        if rates[i] > finite.rate:
            finite = _Best(float(rates[i]), Xs[:, i].copy(), Xh[:, i].copy(), Us[:, i].copy())
    finite_violating = finite_violations / float(samples * V)
    finite_outside = outside / float(samples * V)

    # -- local refinement from the worst samples of each search
    if refine and starts > 0:
        limit_starts.sort(key=lambda s: -s[0])
        for k, (_, x0, u0) in enumerate(limit_starts[:starts]):
            on_time(f"refinement {k + 1} of the small-error limit")

            def limit_objective(Z: np.ndarray, u0: np.ndarray = u0) -> np.ndarray:
                U = np.repeat(u0[:, None], Z.shape[1], axis=1)
                A = _error_jacobians(system, gains, jac, Z, U)
                return _limit_from_jacobians(A, P)[0]

            z, value = _refine(limit_objective, x0, lo, hi)
            if value > limit.rate:
                u = u0.copy()
                A = _error_jacobians(system, gains, jac, z[:, None], u[:, None])
                _, d = _limit_from_jacobians(A, P)
                limit = _Best(value, z, z.copy(), u, d[0])
        finite_starts.sort(key=lambda s: -s[0])
        floor = _MIN_FINITE_ERROR * float(np.max(width))
        region = _injection_region(gains, system.output_matrix, box)
        for k, (_, x0, xh0, u0) in enumerate(finite_starts[:starts]):
            on_time(f"refinement {k + 1} of the finite errors")

            def finite_rate(Z: np.ndarray, u0: np.ndarray = u0) -> np.ndarray:
                U = np.repeat(u0[:, None], Z.shape[1], axis=1)
                return _rates(system, gains, P, Z[:n], Z[n:], U)

            def finite_objective(Z: np.ndarray) -> np.ndarray:
                r = finite_rate(Z)
                small = np.linalg.norm(Z[:n] - Z[n:], axis=0) < floor
                covered = _injections_inside(gains, system.output_matrix, Z[:n], Z[n:], box)
                return np.where(small | ~covered | ~np.isfinite(r), -math.inf, r)

            z, value = _refine(
                finite_objective,
                np.concatenate([x0, xh0]),
                np.tile(lo, 2),
                np.tile(hi, 2),
                smooth=finite_rate,
                inequalities=region,
            )
            if np.isfinite(value) and value > finite.rate:
                finite = _Best(value, z[:n], z[n:], u0.copy())

    best = limit if limit.rate >= finite.rate else finite
    return VerificationReport(
        alpha=alpha,
        worst_rate=best.rate,
        x=_found(best.x),
        xhat=_found(best.xhat),
        u=_found(best.u),
        direction=best.direction,
        kind="small_error_limit" if best is limit else "finite_error",
        worst_small_error_rate=limit.rate,
        worst_finite_rate=finite.rate,
        violating_fraction=violating,
        finite_violating_fraction=finite_violating,
        finite_outside_fraction=finite_outside,
        samples=int(samples),
        input_vertices=V,
        seed=int(seed),
        refined=bool(refine and starts > 0),
        tolerance=float(tol),
        wall_time=time.perf_counter() - start,
        box=box,
        input_bound=input_bound,
        jacobians=jac_kind,
    )
