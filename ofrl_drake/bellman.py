"""Bellman-error extrapolation (BE1_i) and the sums the update laws need.

At each extrapolation point ``x_i`` (columns of ``X``, shape ``(n, N)``)::

    D_i     = (1/(2 lbar)) R^{-1} (grad sigma_i g_i)^T W
    u_i     = -lbar tanh(D_i)
    omega_i = grad sigma_i (f_i + g_i u_i)
    delta_i = W^T omega_i + Q(x_i) + U(u_i)
    rho_i   = 1 + nu omega_i^T omega_i

and the update laws (W_c), (gamma) use the means

    critic_sum = (1/N) sum_i omega_i delta_i / rho_i           (L,)
    gain_sum   = (1/N) sum_i omega_i omega_i^T / rho_i^2       (L, L)

so that ``W' = -k_c Gamma critic_sum`` and
``Gamma' = beta Gamma - k_c Gamma gain_sum Gamma``. The learning condition
(Assumption 2) is ``c = lambda_min(gain_sum)``.

Gamma is symmetric, so the loop carries only its upper triangle, row by row:
``L (L + 1) / 2`` numbers instead of ``L^2`` (:func:`pack_symmetric`,
:func:`unpack_symmetric`); :func:`critic_rate` and :func:`gamma_rate` read
and write that layout.

Everything that does not depend on ``W`` is precomputed once per point set in
:class:`PointFeatures`. The ``W``-dependent part is one compiled loop over
the points (:func:`bellman_kernel`, numba ``@njit``) that accumulates both
sums without forming per-point arrays, unless they are asked for
(:func:`extrapolate`); its packed arrays' rows are named by
:func:`kernel_layout`. The update laws themselves, :func:`critic_rate` and
:func:`gamma_rate`, are compiled too.

This module is the fast path. The same laws written as the equations, in
vectorized numpy, are :mod:`ofrl_drake.update_laws`, which the tests hold
these kernels to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ofrl_drake._jit import kernel
from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.checks import positive_number, positive_vector
from ofrl_drake.cost import log_cosh_abs, saturation_cost, state_cost, tanh_abs
from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem, require_system

__all__ = [
    "BellmanExtrapolation",
    "BellmanSums",
    "Extrapolator",
    "KernelLayout",
    "PerPointRows",
    "PointDataRows",
    "PointFeatures",
    "bellman_kernel",
    "critic_rate",
    "extrapolate",
    "features_at",
    "gamma_rate",
    "kernel_layout",
    "learning_condition",
    "pack_symmetric",
    "packed_size",
    "point_features",
    "unpack_symmetric",
]


@dataclass(frozen=True)
class PointFeatures:
    """The ``W``-independent part of the extrapolation at ``N`` points.

    Attributes
    ----------
    points : ndarray, shape (n, N)
    drift : ndarray, shape (L, N)
        ``grad sigma(x_i) f(x_i)``.
    input : ndarray, shape (m, L, N)
        ``(grad sigma(x_i) g(x_i))`` with the input index first.
    state_cost : ndarray, shape (N,)
        ``Q(x_i)``.
    """

    points: np.ndarray
    drift: np.ndarray
    input: np.ndarray
    state_cost: np.ndarray

    @property
    def num_points(self) -> int:
        return self.points.shape[1]


@dataclass(frozen=True)
class BellmanSums:
    """The two normalized sums the update laws need.

    Attributes
    ----------
    critic_sum : ndarray, shape (L,)
        ``(1/N) sum omega_i delta_i / rho_i``.
    gain_sum : ndarray, shape (L, L)
        ``(1/N) sum omega_i omega_i^T / rho_i^2``.
    """

    critic_sum: np.ndarray
    gain_sum: np.ndarray

    @property
    def learning_condition(self) -> float:
        """``c = lambda_min(gain_sum)``."""
        return learning_condition(self.gain_sum)


@dataclass(frozen=True)
class BellmanExtrapolation(BellmanSums):
    """Bellman errors at the extrapolation points and their sums.

    Attributes
    ----------
    D : ndarray, shape (m, N)
    u : ndarray, shape (m, N)
    omega : ndarray, shape (L, N)
    delta : ndarray, shape (N,)
    rho : ndarray, shape (N,)
    critic_sum, gain_sum
        As in :class:`BellmanSums`.
    """

    D: np.ndarray
    u: np.ndarray
    omega: np.ndarray
    delta: np.ndarray
    rho: np.ndarray


def point_features(
    system: ControlAffineSystem,
    basis: PolynomialBasis,
    points: np.ndarray,
    Q: np.ndarray,
) -> PointFeatures:
    """Precompute everything at ``points`` (shape ``(n, N)``) that does not depend on W.

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`ControlAffineSystem`, ``basis`` not a
        :class:`PolynomialBasis` of its ``n`` states, ``points`` not a finite
        array of shape ``(n, N)`` or ``Q`` not a finite ``(n, n)`` matrix; if
        the model's ``f`` or ``g`` is not finite at a point (outside its domain,
        or overflowing there); or if a feature overflows at a point
        (``grad sigma f``, ``grad sigma g`` or ``Q(x)`` beyond the largest float).
    """
    n = require_system(system, "point_features: system").n
    if not isinstance(basis, PolynomialBasis):
        raise ModelError(
            f"point_features: basis must be a PolynomialBasis; got {type(basis).__name__}."
        )
    if basis.n != n:
        raise ModelError(
            f"point_features: the basis is for n = {basis.n} states but the system "
            f"{system.name!r} has n = {n}; build it as PolynomialBasis({n}, ...)."
        )
    try:
        points = np.asarray(points, dtype=float)
        Q_arr = np.asarray(Q, dtype=float)
    except (TypeError, ValueError):
        raise ModelError(
            f"point_features: points and Q must be numeric arrays of shapes (n, N) = ({n}, N) "
            f"and (n, n) = ({n}, {n}); got {points!r} and {Q!r}."
        ) from None
    if points.ndim != 2 or points.shape[0] != n:
        raise ModelError(f"points must have shape (n, N) = ({n}, N); got {points.shape}.")
    if not np.isfinite(points).all():
        column = int(np.flatnonzero(~np.isfinite(points).all(axis=0))[0])
        raise ModelError(
            f"point_features: the points must be finite; point {column} is "
            f"{points[:, column].tolist()}."
        )
    if Q_arr.shape != (n, n) or not np.isfinite(Q_arr).all():
        raise ModelError(
            f"point_features: Q must be a finite (n, n) = ({n}, {n}) matrix (the state cost "
            f"x^T Q x); got {Q_arr.tolist()} of shape {Q_arr.shape}."
        )
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        f, g = _model_at(system, points)
    _require_finite_at_points(
        system, points, f, "the model's f", "f(x)", "the region where f and g are finite"
    )
    _require_finite_at_points(
        system, points, g, "the model's g", "g(x)", "the region where f and g are finite"
    )
    with np.errstate(over="ignore", invalid="ignore"):
        features = _assemble(basis, points, f, g, Q_arr)
    for what, values in (
        ("grad sigma(x) f(x)", features.drift),
        ("grad sigma(x) g(x)", features.input),
        ("the state cost x^T Q x", features.state_cost),
    ):
        _require_finite_at_points(
            system,
            points,
            values,
            f"the feature {what}",
            "the feature",
            "a box where the basis and cost stay below the largest float (about 1.8e308)",
        )
    return features


def _require_finite_at_points(
    system: ControlAffineSystem,
    points: np.ndarray,
    values: np.ndarray,
    what: str,
    label: str,
    region: str,
) -> None:
    """Raise ModelError naming the first point at which ``values`` (..., N) is not finite."""
    bad = ~np.isfinite(values.reshape(-1, points.shape[1])).all(axis=0)
    if not bad.any():
        return
    column = int(np.flatnonzero(bad)[0])
    shown = values[..., column].tolist()
    raise ModelError(
        f"point_features: {what} is not finite at extrapolation point {column} "
        f"x = {points[:, column].tolist()} ({label} = {shown}; {int(bad.sum())} of "
        f"{points.shape[1]} points) for the model {system.name!r}: the Bellman sums there "
        f"would be inf or NaN; shrink the extrapolation points (the scenario's points.lower, "
        f"points.upper) to {region}."
    )


def _model_at(system: ControlAffineSystem, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``f`` (n, N) and ``g`` (n, m, N) at the columns of ``points``."""
    return system.f_batch(points), system.g_batch(points)


def _assemble(
    basis: PolynomialBasis, points: np.ndarray, f: np.ndarray, g: np.ndarray, Q: np.ndarray
) -> PointFeatures:
    """The features at ``points`` from ``f`` (n, N) and ``g`` (n, m, N) there."""
    grad = basis.gradient(points)  # (L, n, N)
    drift = (grad * f[None, :, :]).sum(axis=1)  # (L, N)
    inp = (grad[:, :, None, :] * g[None, :, :, :]).sum(axis=1)  # (L, m, N)
    return PointFeatures(
        points=points,
        drift=np.ascontiguousarray(drift),
        input=np.ascontiguousarray(inp.transpose(1, 0, 2)),
        state_cost=state_cost(points, Q),
    )


def features_at(
    system: ControlAffineSystem, basis: PolynomialBasis, points: np.ndarray, Q: np.ndarray
) -> PointFeatures:
    """:func:`point_features` without its argument checks, for a caller that made them once.

    ``points`` (float, ``(n, N)``) and ``Q`` (float, ``(n, n)``) as
    :func:`point_features` leaves them after its checks: what a block that
    moves its points every evaluation calls
    (:class:`~ofrl_drake.systems.baselines.MovingBellmanExtrapolator`).
    Non-finite points, or an ``f`` or ``g`` not finite at a point, give
    non-finite features: this function does not check them.
    """
    f, g = _model_at(system, points)
    return _assemble(basis, points, f, g, Q)


class PointDataRows(NamedTuple):
    """Where each ``W``-independent quantity sits in the packed point data ``(rows, N)``.

    One column per point. Built by :func:`kernel_layout`; :class:`Extrapolator`
    fills the array and :func:`bellman_kernel` reads it.

    Attributes
    ----------
    policy_input : slice
        ``m L`` rows, input-major: row ``k L + a`` is
        ``(grad sigma_i g_i)_{a k} / (2 lbar r_k)``, so ``D_k`` is ``W`` times
        rows ``k L`` to ``k L + L - 1``.
    input : slice
        ``m L`` rows, input-major: ``(grad sigma_i g_i)_{a k}``.
    drift : slice
        ``L`` rows: ``grad sigma_i f_i``.
    state_cost : int
        The row of ``Q(x_i)``.
    rows : int
        The number of rows, ``2 m L + L + 1``.
    """

    policy_input: slice
    input: slice
    drift: slice
    state_cost: int
    rows: int


class PerPointRows(NamedTuple):
    """Where each per-point value sits in :func:`bellman_kernel`'s output ``(rows, N)``.

    Attributes
    ----------
    D, u : slice
        ``m`` rows each.
    omega : slice
        ``L`` rows.
    delta, rho : int
        One row each.
    scaled : slice
        ``L`` rows of scratch: ``omega / rho``.
    tanh_D, expm1_D : int
        One row each of scratch: ``tanh |D_k|`` and ``expm1(-2 |D_k|)``, one
        input at a time.
    rows : int
        The number of rows, ``2 m + 2 L + 4``.
    """

    D: slice
    u: slice
    omega: slice
    delta: int
    rho: int
    scaled: slice
    tanh_D: int
    expm1_D: int
    rows: int


class KernelLayout(NamedTuple):
    """The sizes and row layouts of :func:`bellman_kernel`'s two packed arrays.

    Attributes
    ----------
    num_inputs : int
        m.
    num_weights : int
        L.
    data : PointDataRows
        The ``W``-independent point data.
    per_point : PerPointRows
        The per-point output and scratch.
    """

    num_inputs: int
    num_weights: int
    data: PointDataRows
    per_point: PerPointRows


def kernel_layout(num_inputs: int, num_weights: int) -> KernelLayout:
    """The row layout of the packed arrays for ``m = num_inputs`` and ``L = num_weights``.

    Each block starts where the one before it ends. :func:`bellman_kernel`
    builds the same layout from ``m`` and ``L`` (this function, compiled), so
    its callers pass two integers, not this tuple: numba types a tuple
    argument on every call, which costs more than a small kernel's whole work.
    """
    m, L = num_inputs, num_weights
    policy_input = slice(0, m * L)
    inp = slice(policy_input.stop, policy_input.stop + m * L)
    drift = slice(inp.stop, inp.stop + L)
    state_cost = drift.stop
    data = PointDataRows(
        policy_input=policy_input,
        input=inp,
        drift=drift,
        state_cost=state_cost,
        rows=state_cost + 1,
    )
    D = slice(0, m)
    u = slice(D.stop, D.stop + m)
    omega = slice(u.stop, u.stop + L)
    delta = omega.stop
    rho = delta + 1
    scaled = slice(rho + 1, rho + 1 + L)
    tanh_D = scaled.stop
    expm1_D = tanh_D + 1
    per_point = PerPointRows(
        D=D,
        u=u,
        omega=omega,
        delta=delta,
        rho=rho,
        scaled=scaled,
        tanh_D=tanh_D,
        expm1_D=expm1_D,
        rows=expm1_D + 1,
    )
    return KernelLayout(num_inputs=m, num_weights=L, data=data, per_point=per_point)


#: :func:`kernel_layout` compiled, for the kernels only: numba cannot return
#: the slices it holds to Python.
_kernel_layout = kernel(kernel_layout)


@kernel
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """``a @ b``, accumulated in four interleaved partial sums.

    A single running sum waits for each addition in turn; four independent
    ones overlap, about twice as fast at the sizes of the Bellman sums. The
    order is fixed, so the result is the same on every run.
    """
    n = a.shape[0]
    n4 = n - n % 4
    s0 = s1 = s2 = s3 = 0.0
    for i in range(0, n4, 4):
        s0 += a[i] * b[i]
        s1 += a[i + 1] * b[i + 1]
        s2 += a[i + 2] * b[i + 2]
        s3 += a[i + 3] * b[i + 3]
    for i in range(n4, n):
        s0 += a[i] * b[i]
    return (s0 + s1) + (s2 + s3)


@kernel
def _overflowed_quotients(
    per_point: np.ndarray,
    omega0: int,
    scaled0: int,
    L: int,
    i: int,
    nu: float,
    metric: np.ndarray,
) -> None:
    """``q_a = omega_a / rho`` at point ``i`` whose ``rho`` overflowed, without overflow.

    With ``s = max_a |omega_a|`` and ``w = omega / s``:
    ``rho / s^2 = 1 / s^2 + nu sum_a metric_a w_a^2`` is a modest number, and
    ``q_a = (w_a / (rho / s^2)) / s``. A non-finite ``omega`` is left as it is
    (``q`` NaN), for the run guard to report.
    """
    s = 0.0
    for a in range(L):
        s = max(s, abs(per_point[omega0 + a, i]))
    if not s < math.inf:
        return
    reduced = 0.0
    for a in range(L):
        w = per_point[omega0 + a, i] / s
        reduced += metric[a] * (w * w)
    reduced = 1.0 / s / s + nu * reduced
    for a in range(L):
        per_point[scaled0 + a, i] = per_point[omega0 + a, i] / s / reduced / s


@kernel
def bellman_kernel(
    W: np.ndarray,
    W_policy: np.ndarray,
    data: np.ndarray,
    num_inputs: int,
    weight: np.ndarray,
    input_bound: float,
    nu: float,
    metric: np.ndarray,
    per_point: np.ndarray,
    critic_sum: np.ndarray,
    gain_sum: np.ndarray,
    with_critic_sum: bool = True,
) -> None:
    """The Bellman extrapolation at ``N`` points: per-point values and both sums.

    Each stage is a loop over the points with the point index innermost
    (contiguous rows), so the stages without transcendental functions
    vectorize.

    Parameters
    ----------
    W : (L,)
        The critic weights of the value in ``delta_i = W^T omega_i + Q + U``.
    W_policy : (L,)
        The weights of the policy ``u_i`` (hence ``omega_i`` and ``U``): ``W``
        itself for the paper's law, the policy in force for policy iteration.
    data : (2 m L + L + 1, N)
        The ``W``-independent point data, rows as in
        ``kernel_layout(m, L).data`` (:class:`PointDataRows`):
        ``policy_input``, ``input``, ``drift``, ``state_cost``.
    num_inputs : int
        m.
    weight : (m,)
        ``lbar^2 r_k``, the factor of :func:`~ofrl_drake.cost.saturation_cost`.
    input_bound, nu : float
    metric : (L,)
        ``rho_i = 1 + nu sum_a metric_a omega_ai^2``; ones for the paper's ``rho``.
    per_point : (2 m + 2 L + 4, N)
        Output, rows as in ``kernel_layout(m, L).per_point``
        (:class:`PerPointRows`): ``D``, ``u``, ``omega``, ``delta``, ``rho``,
        then scratch.
    critic_sum : (L,); gain_sum : (L, L)
        Outputs: the normalized sums.
    with_critic_sum : bool
        If False, only ``gain_sum`` (and ``D``, ``u``, ``omega``, ``rho``):
        no stage cost, no log-cosh, ``delta`` and ``critic_sum`` untouched.
        ``gain_sum`` is the same to the bit, at about half the cost; the
        learning condition needs nothing else.

    Notes
    -----
    Where ``omega_i^T M omega_i`` overflows, ``rho_i`` is ``inf`` (its value
    rounded), and ``omega_i / rho_i`` is computed in a scaled form, so the
    point still counts in both sums; every other point's numbers are those of
    the plain formula.
    """
    m = num_inputs
    L = W.shape[0]
    N = data.shape[1]
    layout = _kernel_layout(m, L)
    # First rows of the blocks in ``data`` and ``per_point``.
    policy0, inp0 = layout.data.policy_input.start, layout.data.input.start
    drift0, cost_row = layout.data.drift.start, layout.data.state_cost
    rows = layout.per_point
    D0, u0, omega0, scaled0 = rows.D.start, rows.u.start, rows.omega.start, rows.scaled.start
    delta = per_point[rows.delta]
    rho = per_point[rows.rho]
    tanh_D = per_point[rows.tanh_D]
    expm1_D = per_point[rows.expm1_D]
    for a in range(L):
        omega = per_point[omega0 + a]
        drift = data[drift0 + a]
        for i in range(N):
            omega[i] = drift[i]
    if with_critic_sum:
        for i in range(N):
            delta[i] = data[cost_row, i]
    for k in range(m):
        D = per_point[D0 + k]
        u = per_point[u0 + k]
        for i in range(N):
            D[i] = 0.0
        for a in range(L):
            w = W_policy[a]
            row = data[policy0 + k * L + a]
            for i in range(N):
                D[i] += w * row[i]
        # Two passes, each of independent calls (see tanh_log_cosh).
        for i in range(N):
            t, e = tanh_abs(abs(D[i]))
            tanh_D[i] = t
            expm1_D[i] = e
            u[i] = -input_bound * t if D[i] >= 0.0 else input_bound * t
        if with_critic_sum:
            wk = weight[k]
            for i in range(N):
                a = abs(D[i])
                t = tanh_D[i]
                delta[i] += wk * saturation_cost(a, t, log_cosh_abs(a, t, expm1_D[i]))
        for a in range(L):
            omega = per_point[omega0 + a]
            row = data[inp0 + k * L + a]
            for i in range(N):
                omega[i] += row[i] * u[i]
    for i in range(N):
        rho[i] = 0.0
    for a in range(L):
        omega = per_point[omega0 + a]
        ma = metric[a]
        for i in range(N):
            rho[i] += ma * (omega[i] * omega[i])
    if with_critic_sum:
        for a in range(L):
            w = W[a]
            omega = per_point[omega0 + a]
            for i in range(N):
                delta[i] += w * omega[i]
    for i in range(N):
        rho[i] = 1.0 + nu * rho[i]
    # With q_a = omega_a / rho: critic_sum = q delta / N, gain_sum = q q^T / N.
    for a in range(L):
        omega = per_point[omega0 + a]
        q = per_point[scaled0 + a]
        for i in range(N):
            q[i] = omega[i] / rho[i]
    # Where omega^T M omega overflows, rho = inf and omega / rho would be 0: the
    # point would silently drop out. Those points (rare) again, in a scaled form.
    for i in range(N):
        if rho[i] == math.inf:
            _overflowed_quotients(per_point, omega0, scaled0, L, i, nu, metric)
    scale = 1.0 / N
    for a in range(L):
        q_a = per_point[scaled0 + a]
        if with_critic_sum:
            critic_sum[a] = _dot(q_a, delta) * scale
        for b in range(a + 1):
            gain_sum[a, b] = _dot(q_a, per_point[scaled0 + b]) * scale
            gain_sum[b, a] = gain_sum[a, b]


class Extrapolator:
    """:func:`extrapolate` for fixed ``r``, ``lbar`` and ``nu``.

    The scalings that do not depend on ``W`` are applied to the point data
    once here, and the data stacked into the one array
    :func:`bellman_kernel` reads, so that each call is only the
    ``W``-dependent work; the Bellman-extrapolation block holds one of these.

    Parameters
    ----------
    features : PointFeatures
        From :func:`point_features`.
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    nu : float
        Normalization gain of ``rho_i = 1 + nu omega_i^T M omega_i``.
    metric : array_like, shape (L,), optional
        The diagonal of ``M``; ones (the paper's ``rho``) by default. The
        normalized law passes the squared inverse scales of the basis
        functions (:func:`ofrl_drake.learning.basis_scales`), so that ``rho`` does
        not depend on the units of the state.

    Raises
    ------
    ModelError
        If ``r`` is not m finite numbers > 0, ``input_bound`` or ``nu`` is not
        a finite number > 0, or ``metric`` is not L finite numbers > 0.

    Notes
    -----
    :meth:`sums_into` reuses one per-point scratch array held here (its
    values are consumed inside the one kernel call) and writes the two sums
    into arrays the caller owns, so a derivative evaluation allocates nothing.
    """

    def __init__(
        self,
        features: PointFeatures,
        r: np.ndarray,
        input_bound: float,
        nu: float,
        metric: np.ndarray | None = None,
    ) -> None:
        inp = np.asarray(features.input, dtype=float)  # (m, L, N)
        m, L, N = inp.shape
        self.features = features
        self.r = r
        self.input_bound = input_bound
        self.nu = nu
        self.metric = metric
        # Checked and as floats: the compiled kernels take one signature.
        self._r = positive_vector("r", r, m)
        self._input_bound = positive_number("input_bound", input_bound)
        self._nu = positive_number("nu", nu)
        layout = kernel_layout(m, L)
        self._layout = layout
        # D_k = W @ policy_input[k], policy_input = input / (2 lbar r_k).
        policy_input = inp / (2.0 * self._input_bound * self._r)[:, None, None]
        rows = layout.data
        self._data = np.empty((rows.rows, N))
        self._data[rows.policy_input] = policy_input.reshape(m * L, N)
        self._data[rows.input] = inp.reshape(m * L, N)
        self._data[rows.drift] = features.drift
        self._data[rows.state_cost] = features.state_cost
        self._metric = np.ones(L) if metric is None else np.asarray(metric, dtype=float)
        if self._metric.shape != (L,) or not np.all(np.isfinite(self._metric) & (self._metric > 0)):
            raise ModelError(f"metric must hold {L} positive finite numbers; got {metric!r}.")
        self._weight = self._input_bound**2 * self._r
        self._scratch = np.empty((layout.per_point.rows, N))

    @property
    def layout(self) -> KernelLayout:
        """The rows of the packed point data and of the per-point values (:func:`kernel_layout`)."""
        return self._layout

    def _run(
        self,
        W: np.ndarray,
        W_policy: np.ndarray | None,
        per_point: np.ndarray,
        critic_sum: np.ndarray,
        gain_sum: np.ndarray,
    ) -> None:
        W = np.asarray(W, dtype=float)
        bellman_kernel(
            W,
            W if W_policy is None else np.asarray(W_policy, dtype=float),
            self._data,
            self._layout.num_inputs,
            self._weight,
            self._input_bound,
            self._nu,
            self._metric,
            per_point,
            critic_sum,
            gain_sum,
        )

    def empty_sums(self) -> BellmanSums:
        """A :class:`BellmanSums` with uninitialized arrays."""
        L = self._layout.num_weights
        return BellmanSums(np.empty(L), np.empty((L, L)))

    def sums_into(
        self,
        W: np.ndarray,
        critic_sum: np.ndarray,
        gain_sum: np.ndarray,
        W_policy: np.ndarray | None = None,
    ) -> None:
        """Both sums for weights ``W`` written into ``critic_sum`` (L,) and ``gain_sum`` (L, L).

        ``W_policy`` are the weights of the policy the Bellman errors follow
        (default: ``W`` itself, the paper's law). Allocates nothing; this is
        what the Bellman block computes per derivative evaluation, straight
        into its output vector.
        """
        self._run(W, W_policy, self._scratch, critic_sum, gain_sum)

    def learning_conditions(self, weights: np.ndarray) -> np.ndarray:
        """:func:`learning_condition` for each row of ``weights`` (T, L), in one compiled call.

        ``gain_sum`` depends only on the policy's weights, so pass the policy
        weights in force (the critic's own under the paper's law).
        """
        Ws = np.ascontiguousarray(weights, dtype=float)
        L = self._layout.num_weights
        if Ws.ndim != 2 or Ws.shape[1] != L:
            raise ModelError(f"weights must have shape (T, {L}); got {Ws.shape}.")
        out = np.empty(Ws.shape[0])
        _learning_conditions(
            Ws,
            self._data,
            self._layout.num_inputs,
            self._weight,
            self._input_bound,
            self._nu,
            self._metric,
            np.empty_like(self._scratch),
            out,
        )
        return out

    def sums(self, W: np.ndarray, W_policy: np.ndarray | None = None) -> BellmanSums:
        """Only the two sums for critic weights ``W`` (shape ``(L,)``): what the loop needs."""
        out = self.empty_sums()
        self.sums_into(W, out.critic_sum, out.gain_sum, W_policy)
        return out

    def __call__(self, W: np.ndarray, W_policy: np.ndarray | None = None) -> BellmanExtrapolation:
        """The extrapolation for critic weights ``W`` (shape ``(L,)``), per-point values too.

        ``W_policy``: the weights of the policy followed (default ``W``).
        """
        rows = self._layout.per_point
        per_point = np.empty_like(self._scratch)  # its own, since the result keeps views of it
        out = self.empty_sums()
        self._run(W, W_policy, per_point, out.critic_sum, out.gain_sum)
        return BellmanExtrapolation(
            critic_sum=out.critic_sum,
            gain_sum=out.gain_sum,
            D=per_point[rows.D],
            u=per_point[rows.u],
            omega=per_point[rows.omega],
            delta=per_point[rows.delta],
            rho=per_point[rows.rho],
        )

    def policy_evaluation(self, W_policy: np.ndarray) -> np.ndarray:
        """The critic weights at which ``critic_sum`` vanishes while ``W_policy`` is in force.

        Under ``critic.law: policy_iteration`` the Bellman errors follow the
        policy in force, so ``critic_sum(W) = (1/N) sum_i omega_i (W^T
        omega_i + r_i) / rho_i``, with ``r_i = Q(x_i) + U(u_i)``, is affine in
        ``W``: the critic law ``W' = -k_c Gamma critic_sum(W)`` (``Gamma > 0``)
        has this one rest point, the weighted least-squares fit

            min_W sum_i (W^T omega_i + r_i)^2 / rho_i

        of the policy's Bellman errors over the points. It is what the critic
        converges to between two policy updates (policy evaluation), so it
        shows, without a simulation, whether the basis holds the value of a
        policy on the points: the fit's quadratic part can be indefinite where
        the policy saturates (``docs/learning.md``).

        Parameters
        ----------
        W_policy : ndarray, shape (L,)
            The weights of the policy the Bellman errors follow.

        Returns
        -------
        ndarray, shape (L,)

        Raises
        ------
        ModelError
            If ``W_policy`` is not ``L`` finite numbers, or the regressors
            ``omega_i`` do not span the ``L`` weights (the learning condition
            is zero), so that the fit is not unique.
        """
        L = self._layout.num_weights
        policy = np.asarray(W_policy, dtype=float)
        if policy.shape != (L,) or not np.all(np.isfinite(policy)):
            raise ModelError(
                f"policy_evaluation: W_policy must hold {L} finite weights; got {W_policy!r}."
            )
        at = self(np.zeros(L), policy)  # with W = 0, delta_i = r_i
        scale = 1.0 / np.sqrt(at.rho)
        rows = (at.omega * scale).T
        weights, _, rank, _ = np.linalg.lstsq(rows, -at.delta * scale, rcond=None)
        if rank < L:
            raise ModelError(
                f"policy_evaluation: the regressors omega_i at the {rows.shape[0]} points span "
                f"only {rank} of the {L} weights (the learning condition is zero), so the fit "
                "is not unique; spread the points over a box where every basis function varies."
            )
        return weights


def extrapolate(
    features: PointFeatures,
    W: np.ndarray,
    r: np.ndarray,
    input_bound: float,
    nu: float,
    *,
    W_policy: np.ndarray | None = None,
    metric: np.ndarray | None = None,
) -> BellmanExtrapolation:
    """Bellman errors at every point for weights ``W`` and their normalized sums.

    Parameters
    ----------
    features : PointFeatures
        From :func:`point_features`.
    W : ndarray, shape (L,)
        Critic weights.
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    nu : float
        Normalization gain of ``rho_i = 1 + nu omega_i^T M omega_i``.
    W_policy : ndarray, shape (L,), optional
        Weights of the policy the errors follow (default ``W``).
    metric : ndarray, shape (L,), optional
        Diagonal of ``M`` (default ones).

    See Also
    --------
    Extrapolator : the same for many ``W`` with fixed ``r``, ``lbar``, ``nu``.
    """
    return Extrapolator(features, r, input_bound, nu, metric)(W, W_policy)


@kernel
def _min_eigenvalue(S: np.ndarray) -> float:
    """The smallest eigenvalue of symmetric ``S``; NaN if ``S`` has a non-finite entry."""
    for v in S.ravel():
        if not np.isfinite(v):
            return np.nan  # a diverged run's logs: no eigenvalue, and no exception
    return np.linalg.eigvalsh(S)[0]


@kernel
def _learning_conditions(
    Ws: np.ndarray,
    data: np.ndarray,
    num_inputs: int,
    weight: np.ndarray,
    input_bound: float,
    nu: float,
    metric: np.ndarray,
    per_point: np.ndarray,
    out: np.ndarray,
) -> None:
    """``out[t] = lambda_min(gain_sum(Ws[t]))``, arguments as for :func:`bellman_kernel`."""
    L = Ws.shape[1]
    critic_sum = np.empty(L)
    gain_sum = np.empty((L, L))
    for t in range(Ws.shape[0]):
        bellman_kernel(
            Ws[t],
            Ws[t],
            data,
            num_inputs,
            weight,
            input_bound,
            nu,
            metric,
            per_point,
            critic_sum,
            gain_sum,
            False,
        )
        out[t] = _min_eigenvalue(gain_sum)


def learning_condition(gain_sum: np.ndarray) -> float:
    """``lambda_min`` of the symmetric matrix ``gain_sum`` (Assumption 2); NaN if not finite."""
    return float(_min_eigenvalue(np.ascontiguousarray(gain_sum, dtype=float)))


def packed_size(size: int) -> int:
    """``L (L + 1) / 2``: the numbers of a symmetric ``L x L`` matrix's upper triangle."""
    return size * (size + 1) // 2


def _packed_order(packed: int) -> int:
    """``L`` with ``packed_size(L) == packed``; raises if there is none."""
    size = (math.isqrt(8 * packed + 1) - 1) // 2
    if packed_size(size) != packed:
        raise ModelError(
            f"a packed symmetric matrix has L (L + 1) / 2 entries; {packed} is not such a "
            "number (pack it with ofrl_drake.bellman.pack_symmetric)."
        )
    return size


def pack_symmetric(matrix: np.ndarray) -> np.ndarray:
    """The upper triangle of symmetric ``(..., L, L)``, row by row: ``(..., L (L + 1) / 2)``.

    Entry ``(a, b)``, ``a <= b``, lands at ``a L - a (a - 1) / 2 + b - a``
    (``numpy.triu_indices`` order). Only the upper triangle is read.
    """
    M = np.asarray(matrix, dtype=float)
    if M.ndim < 2 or M.shape[-1] != M.shape[-2]:
        raise ModelError(f"pack_symmetric needs square matrices (..., L, L); got {M.shape}.")
    rows, cols = np.triu_indices(M.shape[-1])
    return M[..., rows, cols]


def unpack_symmetric(packed: np.ndarray) -> np.ndarray:
    """The symmetric matrices ``(..., L, L)`` of upper triangles ``(..., L (L + 1) / 2)``.

    The inverse of :func:`pack_symmetric`.
    """
    v = np.asarray(packed, dtype=float)
    if v.ndim < 1:
        raise ModelError("unpack_symmetric needs a vector of L (L + 1) / 2 numbers; got a scalar.")
    L = _packed_order(v.shape[-1])
    rows, cols = np.triu_indices(L)
    out = np.empty((*v.shape[:-1], L, L))
    out[..., rows, cols] = v
    out[..., cols, rows] = v
    return out


@kernel
def _packed_index(a: int, b: int, size: int) -> int:
    """Where entry ``(a, b)`` of a symmetric ``size x size`` matrix sits in its packed form."""
    if a > b:
        a, b = b, a
    return a * size - (a * (a - 1)) // 2 + b - a


@kernel
def critic_rate(gamma: np.ndarray, critic_sum: np.ndarray, kc: float, out: np.ndarray) -> None:
    """(W_c): ``out = -k_c Gamma critic_sum``, with Gamma packed (L (L + 1) / 2,).

    ``gamma`` is Gamma's upper triangle, row by row (:func:`pack_symmetric`).
    The readable form: :func:`ofrl_drake.update_laws.critic_rate`.
    """
    L = critic_sum.shape[0]
    for a in range(L):
        acc = 0.0
        for b in range(L):
            acc += gamma[_packed_index(a, b, L)] * critic_sum[b]
        out[a] = -kc * acc


@kernel
def gamma_rate(
    gamma: np.ndarray, gain_sum: np.ndarray, kc: float, beta: float, out: np.ndarray
) -> None:
    """(gamma): ``out = beta G - k_c G S G``, Gamma and its rate packed (L (L + 1) / 2,).

    ``gamma`` and ``out`` are upper triangles, row by row
    (:func:`pack_symmetric`); ``gain_sum`` (``S``) is flattened row-major
    (L*L,). Each entry of the rate is the mean of ``(G S G)_ab`` and
    ``(G S G)_ba``, so it is the same number, to the bit, whichever triangle
    it came from. The readable form: :func:`ofrl_drake.update_laws.gamma_rate`.
    """
    L = int(np.sqrt(gain_sum.shape[0]) + 0.5)
    G = np.empty((L, L))
    for a in range(L):
        for b in range(a, L):
            value = gamma[_packed_index(a, b, L)]
            G[a, b] = value
            G[b, a] = value
    GS = np.empty((L, L))
    for a in range(L):
        for b in range(L):
            acc = 0.0
            for c in range(L):
                acc += G[a, c] * gain_sum[c * L + b]
            GS[a, b] = acc
    for a in range(L):
        for b in range(a + 1):
            acc1 = 0.0
            acc2 = 0.0
            for c in range(L):
                acc1 += GS[a, c] * G[c, b]
                acc2 += GS[b, c] * G[c, a]
            out[_packed_index(b, a, L)] = beta * G[a, b] - kc * 0.5 * (acc1 + acc2)
