"""The stronger baseline: the closed loop as a careful numpy user writes it.

The same equations as :mod:`benchmarks.fused_numpy` (and as the diagram), with
everything that depends only on the fixed extrapolation points, or only on the
constant gains, computed once before the solve, so that each evaluation does
only the work that depends on the state:

* at the points: ``P_k = (grad sigma_i g_i)_k / (2 lbar r_k)`` (so ``D_i = W P``),
  ``lbar (grad sigma_i g_i)``, ``grad sigma_i f_i`` and ``Q(x_i)``;
* the observer: ``L - M_f1 H`` and the input sector as two constant matrices,
  ``min(M_g1, M_g2) K`` and ``max(M_g1, M_g2) K`` per input (the sector
  ``sum_k min(M_g1 u_k, M_g2 u_k) K`` is the first times ``u_k`` for
  ``u_k >= 0`` and the second for ``u_k < 0``);
* ``f`` and ``g`` of one state as one function per example, written with
  Python floats (``math.cos``), shared trigonometry computed once.

The right-hand side is then one vectorized pass over the points (about twenty
numpy calls) and the state-sized algebra in Python floats (at n = 2 to 4 a
numpy call costs more than its arithmetic), integrated by
``solve_ivp(method="LSODA")``: on the paper scenario 28 us per call against
the fused baseline's 50, and the whole solve 1.7 times faster (measured on
the benchmarks' machine). The state is ``z = [x, xhat, W, vec(Gamma), J]``,
as in the fused baseline. ``tests/test_benchmarks.py`` holds it to the fused
right-hand side at random states and to ``simulate()``'s trajectory.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from benchmarks.fused_numpy import _exponents, _gradient_table, _SolveIvpLoop

__all__ = ["ONE_STATE", "PrecomputedClosedLoop"]

_LN2 = math.log(2.0)


def _fg_two_state(x: list[float]) -> tuple[list[float], list[list[float]]]:
    """``(f(x), g(x))`` of (sim_dyn) at one state, as lists: 2, 2 x 1."""
    x0, x1 = x
    c = math.cos(2.0 * x0) + 2.0
    return [-x0 + x1, -x0 - 0.5 * x1 * (1.0 - c * c)], [[0.0], [c]]


def _fg_coupled(x: list[float]) -> tuple[list[float], list[list[float]]]:
    """``(f(x), g(x))`` of the coupled example at one state, as lists: 4, 4 x 2."""
    x0, x1, x2, x3 = x
    c1 = math.cos(2.0 * x0) + 2.0
    c2 = math.cos(2.0 * x2) + 2.0
    k = 0.1 * (x2 - x0)
    f = [
        -x0 + x1 + k,
        -x0 - 0.5 * x1 * (1.0 - c1 * c1),
        -x2 + x3 - k,
        -x2 - 0.5 * x3 * (1.0 - c2 * c2),
    ]
    return f, [[0.0, 0.0], [c1, 0.0], [0.0, 0.0], [0.0, c2]]


#: ``name -> (fg, C)``: ``f`` and ``g`` at one state, and the output matrix,
#: for the examples the benchmarks run (the keys of
#: :data:`benchmarks.fused_numpy.SYSTEMS`).
ONE_STATE: dict[str, tuple[Callable, np.ndarray]] = {
    "two_state": (_fg_two_state, np.array([[0.0, 1.0]])),
    "coupled_two_state": (
        _fg_coupled,
        np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]),
    ),
}


@dataclass
class PrecomputedClosedLoop(_SolveIvpLoop):
    """The whole closed loop as ``rhs(t, z)``, point and gain data precomputed.

    Parameters
    ----------
    system : str
        A key of :data:`ONE_STATE`.
    points : ndarray, shape (n, N)
        Extrapolation points.
    f_points : ndarray, shape (n, N)
        ``f`` at the points.
    g_points : ndarray, shape (n, m, N)
        ``g`` at the points.
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
    f_points: np.ndarray
    g_points: np.ndarray
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
        self._fg, self.C = ONE_STATE[self.system]
        self.n = self.C.shape[1]
        n = self.n
        E = _exponents(n, list(self.degrees))
        self.size = L = E.shape[0]
        self._U, S = _gradient_table(E)
        self._S3 = S.reshape(L, -1)
        X = np.asarray(self.points, dtype=float)
        self.N = X.shape[1]
        monomials = np.prod(X[None, :, :] ** self._U[:, :, None], axis=1)
        grad = (S @ monomials).reshape(L, n, -1)  # (L, n, N)
        inp = np.einsum("ljN,jkN->klN", grad, np.asarray(self.g_points, dtype=float))  # (m, L, N)
        self.m = m = inp.shape[0]
        lbar = float(self.input_bound)
        r = np.asarray(self.r, dtype=float)
        self._scale = 1.0 / (2.0 * lbar * r)
        # Everything that depends only on the points.
        self._P = np.ascontiguousarray(inp * self._scale[:, None, None])  # D_i = W @ P
        self._B = np.ascontiguousarray(lbar * inp)
        self._P0, self._B0 = self._P[0], self._B[0]  # the m = 1 path
        self._drift = np.ascontiguousarray(np.einsum("ljN,jN->lN", grad, self.f_points))
        self._ur2 = 2.0 * lbar**2 * r
        self._Qx = np.einsum("iN,ij,jN->N", X, self.Q, X)
        # Everything that depends only on the gains, as lists of Python floats
        # (at n = 2 to 4 a numpy call costs more than the arithmetic): the
        # observer's arguments xhat + H ytil, xhat + K ytil and ytil = C (x - xhat)
        # as one matrix applied to [x; xhat], and L - M_f1 H.
        C, H, K = self.C, np.asarray(self.H, float), np.asarray(self.K, float)
        eye = np.eye(n)
        observer_map = np.block([[H @ C, eye - H @ C], [K @ C, eye - K @ C], [C, -C]])
        self._observer_map = [
            [(j, v) for j, v in enumerate(row) if v != 0.0] for row in observer_map.tolist()
        ]
        self._correction = (self.L - self.Mf1 @ self.H).tolist()
        # sum_k min(M_g1 u_k, M_g2 u_k) K = sum_k (u_k >= 0 ? lo_k : hi_k) u_k.
        lo, hi = np.minimum(self.Mg1, self.Mg2), np.maximum(self.Mg1, self.Mg2)
        self._sector = [((lo[:, :, k] @ K).tolist(), (hi[:, :, k] @ K).tolist()) for k in range(m)]
        self._Ql = np.asarray(self.Q, dtype=float).tolist()
        self._scale_l = self._scale.tolist()
        self._ur2_l = self._ur2.tolist()
        self._w0 = float(self._ur2[0])
        # The controller's basis gradient at xhat: monomial k of the gradient
        # table is prod_j xhat_j ** U[k, j].
        self._powers = [[(j, int(p)) for j, p in enumerate(row) if p] for row in self._U]
        self._kcN = self.kc / self.N
        self._cuts = (n, 2 * n, 2 * n + L, 2 * n + L + L * L)

    def rhs(self, t: float, z: np.ndarray) -> np.ndarray:
        """``z'`` of the whole closed loop."""
        fg, lbar, n, m, L = self._fg, self.input_bound, self.n, self.m, self.size
        a, b, c, d = self._cuts
        state = z[:b].tolist()
        x, xh = state[:a], state[a:]
        W = z[b:c]
        G = z[c:d].reshape(L, L)
        # Controller (u_app) at the estimate: grad V = (W S) monomials(xhat).
        monomials = []
        for powers in self._powers:
            value = 1.0
            for j, p in powers:
                value *= xh[j] if p == 1 else xh[j] ** p
            monomials.append(value)
        WS = (W @ self._S3).tolist()  # (n, K) row-major
        K = len(monomials)
        grad_V = [sum(WS[j * K + k] * monomials[k] for k in range(K)) for j in range(n)]
        g_hat = fg(xh)[1]
        D = [self._scale_l[k] * sum(g_hat[j][k] * grad_V[j] for j in range(n)) for k in range(m)]
        tD = [math.tanh(Dk) for Dk in D]
        u = [-lbar * tk for tk in tD]
        # Plant.
        f, g = fg(x)
        out = [f[i] + sum(g[i][k] * u[k] for k in range(m)) for i in range(n)]
        # Observer with the sign-correct sector (see benchmarks.fused_numpy):
        # f(xhat + H ytil) + g(xhat + K ytil) u + (L - M_f1 H - M_ug1 K) ytil.
        Y = [sum(v * state[j] for j, v in row) for row in self._observer_map]
        ytil = Y[b:]
        f_o, g_o = fg(Y[:n])[0], fg(Y[n:b])[1]
        sectors = [self._sector[k][0 if u[k] >= 0.0 else 1] for k in range(m)]
        for i in range(n):
            acc = f_o[i]
            for k in range(m):
                acc += g_o[i][k] * u[k]
            for p, yp in enumerate(ytil):
                gain = self._correction[i][p] - sum(sectors[k][i][p] * u[k] for k in range(m))
                acc += gain * yp
            out.append(acc)
        # Cost at u = -lbar tanh(D): x^T Q x + sum_k 2 lbar^2 r_k (D tanh D - ln cosh D).
        dJ = sum(x[i] * sum(Qi[j] * x[j] for j in range(n)) for i, Qi in enumerate(self._Ql))
        for w, Dk, tk in zip(self._ur2_l, D, tD, strict=True):
            size = abs(Dk)
            dJ += w * (Dk * tk - (size + math.log1p(math.exp(-2.0 * size)) - _LN2))
        # Bellman errors at the points and the update laws, vectorized over the
        # points. ln cosh D as np.log(np.cosh(D)): a third of np.logaddexp's
        # time, exact while |D| < 710 (|D| < 5 at the points of every case run).
        if m == 1:
            Di = W @ self._P0  # (N,)
            ti = np.tanh(Di)
            omega = self._drift - self._B0 * ti
            cost = self._w0 * (Di * ti - np.log(np.cosh(Di)))
        else:
            Di = W @ self._P  # (m, N)
            ti = np.tanh(Di)
            omega = self._drift - np.einsum("kln,kn->ln", self._B, ti)
            cost = self._ur2 @ (Di * ti - np.log(np.cosh(Di)))
        delta = W @ omega + self._Qx + cost
        q = omega / (1.0 + self.nu * np.einsum("ln,ln->n", omega, omega))
        GS = G @ (q @ q.T)
        dW = (G @ (q @ delta)) * -self._kcN
        dG = self.beta * G - self._kcN * (GS @ G)
        out.append(dJ)
        head = np.array(out)  # [x', xhat', J']
        return np.concatenate((head[:b], dW, dG.ravel(), head[b:]))
