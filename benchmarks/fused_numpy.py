"""The closed loop as one hand-written numpy right-hand side, for ``solve_ivp``.

This is the baseline the Drake diagram is measured against: what a researcher
would write in a page of numpy. It is written from the paper's equations
directly and shares no math code with :mod:`ofrl_drake` (only the points and
the observer gains are taken as given data), so it doubles as an independent
check of the diagram. The state is ``z = [x, xhat, W, vec(Gamma), J]``:

* plant (eq:dynamics_x): ``x' = f(x) + g(x) u``;
* observer (eq:observerdynamics_x) with the sign-correct input sector
  ``M_ug1(u) = sum_k min(M_g1 u_k, M_g2 u_k)`` (docs/paper_notes.md). Substituting
  ``fbar(z) = f(z) - M_f1 z`` and ``gbar_u(z) = g(z) u - M_ug1 z``, the linear
  terms cancel and, with ``ytil = C x - C xhat``::

      xhat' = f(xhat + H ytil) + g(xhat + K ytil) u + (L - M_f1 H - M_ug1 K) ytil;

* controller (u_app): ``u = -lbar tanh(D)``,
  ``D = (1/(2 lbar)) R^{-1} g(xhat)^T grad sigma(xhat)^T W``;
* critic (W_c) and Gamma (gamma) from the Bellman errors (BE1_i) at the N
  extrapolation points;
* cost: ``J' = x^T Q x + U(u)``, ``U = sum_k r_k lbar^2 (2 D_k tanh D_k - 2 ln cosh D_k)``.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

__all__ = ["SYSTEMS", "FusedClosedLoop"]


# --------------------------------------------------------------- the systems
def _f_two_state(x: np.ndarray) -> np.ndarray:
    """Drift of (sim_dyn), for one state (2,) or a batch (2, N)."""
    c = np.cos(2.0 * x[0]) + 2.0
    return np.array([-x[0] + x[1], -x[0] - 0.5 * x[1] * (1.0 - c * c)])


def _g_two_state(x: np.ndarray) -> np.ndarray:
    """Input matrix of (sim_dyn), (2, 1) or (2, 1, N)."""
    c = np.cos(2.0 * x[0]) + 2.0
    return np.array([[0.0 * c], [c]])


def _f_coupled(x: np.ndarray) -> np.ndarray:
    """Two copies of the (sim_dyn) drift coupled by ``0.1 (x3 - x1)``."""
    c1 = np.cos(2.0 * x[0]) + 2.0
    c2 = np.cos(2.0 * x[2]) + 2.0
    k = 0.1 * (x[2] - x[0])
    return np.array(
        [
            -x[0] + x[1] + k,
            -x[0] - 0.5 * x[1] * (1.0 - c1 * c1),
            -x[2] + x[3] - k,
            -x[2] - 0.5 * x[3] * (1.0 - c2 * c2),
        ]
    )


def _g_coupled(x: np.ndarray) -> np.ndarray:
    """Input 1 on row 2, input 2 on row 4: (4, 2) or (4, 2, N)."""
    c1 = np.cos(2.0 * x[0]) + 2.0
    c2 = np.cos(2.0 * x[2]) + 2.0
    zero = 0.0 * c1
    return np.array([[zero, zero], [c1, zero], [zero, zero], [zero, c2]])


#: ``name -> (f, g, C)`` for the examples the benchmarks run.
SYSTEMS: dict[str, tuple[Callable, Callable, np.ndarray]] = {
    "two_state": (_f_two_state, _g_two_state, np.array([[0.0, 1.0]])),
    "coupled_two_state": (
        _f_coupled,
        _g_coupled,
        np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]),
    ),
}


def _exponents(n: int, degrees: list[int]) -> np.ndarray:
    """Monomial exponents, (L, n), in ``combinations_with_replacement`` order."""
    rows = []
    for d in degrees:
        for combo in itertools.combinations_with_replacement(range(n), d):
            rows.append(np.bincount(combo, minlength=n))
    return np.array(rows)


def _gradient_table(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``grad sigma(x) = (S @ prod(x ** U, axis=1)).reshape(L, n)``: returns (U, S).

    ``d x^e / d x_j = e_j x^(e - 1_j)``; ``U`` lists the distinct lowered
    exponents and ``S`` (L n, len(U)) holds the factors ``e_j``.
    """
    lowered: dict[tuple[int, ...], int] = {}
    entries = []
    for l, e in enumerate(E):
        for j in np.flatnonzero(e):
            key = tuple(e - np.eye(len(e), dtype=int)[j])
            k = lowered.setdefault(key, len(lowered))
            entries.append((l * len(e) + j, k, float(e[j])))
    S = np.zeros((E.size, len(lowered)))
    for row, k, value in entries:
        S[row, k] = value
    return np.array(list(lowered), dtype=float), S


def _log_cosh(a: np.ndarray) -> np.ndarray:
    a = np.abs(a)
    return a + np.log1p(np.exp(-2.0 * a)) - np.log(2.0)


class _SolveIvpLoop:
    """``initial_state``, ``solve`` and ``weights`` of a baseline loop.

    Field-less, so each baseline stays a plain dataclass of its own fields;
    the subclass provides ``rhs(t, z)``, the state size ``n`` and the basis
    size ``size`` (``z = [x, xhat, W, vec(Gamma), J]``).
    """

    n: int
    size: int
    rhs: Callable[[float, np.ndarray], np.ndarray]

    def initial_state(
        self, x0: np.ndarray, xhat0: np.ndarray, W0: np.ndarray, Gamma0: np.ndarray
    ) -> np.ndarray:
        """``z(0) = [x0, xhat0, W0, vec(Gamma0), 0]``."""
        return np.concatenate([x0, xhat0, W0, np.ravel(Gamma0), [0.0]])

    def solve(
        self,
        z0: np.ndarray,
        duration: float,
        *,
        method: str = "LSODA",
        rtol: float = 1e-9,
        atol: float = 1e-11,
        t_eval: np.ndarray | None = None,
        dense_output: bool = False,
    ):
        """``scipy.integrate.solve_ivp`` of :meth:`rhs` over ``[0, duration]``."""
        return solve_ivp(
            self.rhs,
            (0.0, duration),
            z0,
            method=method,
            rtol=rtol,
            atol=atol,
            t_eval=t_eval,
            dense_output=dense_output,
        )

    def weights(self, z: np.ndarray) -> np.ndarray:
        """The ``W`` part of a state ``z``."""
        return z[2 * self.n : 2 * self.n + self.size]


@dataclass
class FusedClosedLoop(_SolveIvpLoop):
    """The whole closed loop as one function ``rhs(t, z)``.

    Parameters
    ----------
    system : str
        A key of :data:`SYSTEMS`.
    points : ndarray, shape (n, N)
        Extrapolation points.
    degrees : list of int
        Total degrees of the monomial basis.
    Q : ndarray, shape (n, n)
    r : ndarray, shape (m,)
        Diagonal of R.
    input_bound, kc, nu, beta : float
        lbar and the learning gains.
    L, H, K : ndarray, shape (n, q)
        Observer gains.
    Mf1 : ndarray, shape (n, n)
    Mg1, Mg2 : ndarray, shape (n, n, m)
        Jacobian bounds.
    """

    system: str
    points: np.ndarray
    degrees: list[int]
    Q: np.ndarray
    r: np.ndarray
    input_bound: float
    kc: float
    nu: float
    beta: float
    L: np.ndarray
    H: np.ndarray
    K: np.ndarray
    Mf1: np.ndarray
    Mg1: np.ndarray
    Mg2: np.ndarray

    def __post_init__(self) -> None:
        self._f, self._g, self.C = SYSTEMS[self.system]
        self.n = self.C.shape[1]
        E = _exponents(self.n, list(self.degrees))
        self.size = E.shape[0]
        self._U, self._S = _gradient_table(E)
        # sum_l W_l d sigma_l / d x = (W @ S3) @ monomials, with S3 of shape (L, n K).
        self._S3 = self._S.reshape(self.size, -1)
        X = np.asarray(self.points, dtype=float)
        monomials = np.prod(X[None, :, :] ** self._U[:, :, None], axis=1)  # (K, N)
        grad = (self._S @ monomials).reshape(self.size, self.n, -1)  # (L, n, N)
        f, g = self._f(X), self._g(X)  # (n, N), (n, m, N)
        self.m = g.shape[1]
        # W-independent per-point data: grad sigma f (L, N), grad sigma g (m, L, N).
        self.drift = np.einsum("ljN,jN->lN", grad, f)
        self.inp = np.ascontiguousarray(np.einsum("ljN,jkN->klN", grad, g))
        self.Qx = np.einsum("iN,ij,jN->N", X, self.Q, X)
        self.N = X.shape[1]
        self.r = np.asarray(self.r, dtype=float)
        self.scale = 1.0 / (2.0 * self.input_bound * self.r)
        self._ur = self.input_bound**2 * self.r
        self._correction = self.L - self.Mf1 @ self.H

    def rhs(self, t: float, z: np.ndarray) -> np.ndarray:
        """``z'`` of the whole closed loop."""
        n, size, lbar = self.n, self.size, self.input_bound
        x, xh = z[:n], z[n : 2 * n]
        W = z[2 * n : 2 * n + size]
        G = z[2 * n + size : 2 * n + size + size * size].reshape(size, size)
        # Controller (u_app) at the estimate.
        monomials = np.prod(xh**self._U, axis=1)
        grad_V = (W @ self._S3).reshape(n, -1) @ monomials
        D = self.scale * (self._g(xh).T @ grad_V)
        tD = np.tanh(D)
        u = -lbar * tD
        # Plant.
        dx = self._f(x) + self._g(x) @ u
        # Observer (eq:observerdynamics_x) with the sign-correct sector: the
        # M_f1 and M_ug1 terms of fbar, gbar_u cancel against the linear parts.
        ytil = self.C @ (x - xh)
        Mug1 = np.minimum(self.Mg1 * u, self.Mg2 * u).sum(axis=-1)
        dxh = (
            self._f(xh + self.H @ ytil)
            + self._g(xh + self.K @ ytil) @ u
            + (self._correction - Mug1 @ self.K) @ ytil
        )
        # Bellman errors (BE1_i) at the points and the update laws (W_c), (gamma).
        Di = self.scale[:, None] * (W @ self.inp)  # (m, N)
        ti = np.tanh(Di)
        omega = self.drift - lbar * (self.inp * ti[:, None, :]).sum(axis=0)
        Ui = self._ur @ (2.0 * Di * ti - 2.0 * _log_cosh(Di))
        delta = W @ omega + self.Qx + Ui
        rho = 1.0 + self.nu * (omega * omega).sum(axis=0)
        wr = omega / rho
        GS = G @ (wr @ wr.T)
        dW = -(self.kc / self.N) * (G @ (wr @ delta))
        dG = self.beta * G - (self.kc / self.N) * (GS @ G)
        # Cost (costfunction) at u = -lbar tanh(D).
        dJ = x @ self.Q @ x + self._ur @ (2.0 * D * tD - 2.0 * _log_cosh(D))
        return np.concatenate([dx, dxh, dW, dG.ravel(), [dJ]])
