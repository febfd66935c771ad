"""Certified Jacobian bounds of multibody plants from their mass-matrix structure.

A continuous multibody plant with state ``x = [q; v]`` and actuation ``u`` is

    x' = [qdot(q, v); a(q, v) + G(q) u],   a = M(q)^-1 r,  G = M(q)^-1 B,

with ``r = tau(q, v) + B u*`` (``tau = tau_app - C(q, v) v``: gravity and
the force elements minus the bias term, every generalized force at ``u = 0``;
``u*`` the input offset of a shifted model). The entries of ``M`` and ``tau``
are small expressions in ``sin``/``cos`` of ``q`` and polynomials in ``v``;
the entries of ``M^-1`` are not, so enclosing ``f`` and ``g`` written out
symbolically repeats each variable many times and interval arithmetic
overestimates badly. Instead, with ``M_j = dM/dx_j`` and
``r_j = dr/dx_j``, the Jacobians are

    da/dx_j = M^-1 (r_j - M_j a),            dG/dx_j = -M^-1 M_j G,
    d2a/dx_j dx_l = M^-1 (r_jl - M_jl a - M_j a_l - M_l a_j),
    d2G/dx_j dx_l = -M^-1 (M_jl G + M_j G_l + M_l G_j),

so over a box every quantity is enclosed by evaluating the small expressions
``M, M_j, M_jl, r, r_j, r_jl`` in interval arithmetic
(:class:`ofrl_drake.interval.ExpressionEvaluator`, tightened by Taylor forms,
see :class:`MultibodyJacobianEncloser`) and solving interval linear systems
with ``[M]`` (:class:`ofrl_drake.interval_linalg.IntervalLinearSystem`), never
forming a symbolic inverse. Each Jacobian entry ``J`` is enclosed over a box
``X`` with centre ``c`` by the intersection of

* the natural form: ``[J](X)`` from the solves above, and
* the mean-value form: ``[J](c) + sum_l [dJ/dx_l](X) (X_l - c_l)``, whose
  overestimation shrinks quadratically with the box.

Soundness: for every ``x`` in ``X`` the true ``M(x), r(x), ...`` lie in their
enclosures, every ``M`` in ``[M]`` is proved nonsingular by the solver, so
``a(x) = M(x)^-1 r(x)`` lies in the solver's enclosure of ``{M^-1 r}`` over
the enclosures, and so on up the formulas; the mean-value theorem does the
rest. Every operation is rounded outward.

The bounds come from the one branch and bound,
:func:`ofrl_drake.branch_and_bound.refine`, with a
:class:`MultibodyJacobianEncloser`: boxes whose enclosure of some entry reaches
more than the tolerance beyond the best inner estimate (sampled values plus
the values at every centre visited) are bisected, along the used variable that
adds the most width to the unsettled entries' mean-value forms (the encloser's
``spread``), until no box is left or a budget (boxes, wall time) is spent.
Every entry is enclosed on every open box to the end. The result is the hull
of the enclosures of the boxes that were settled or left open: always a sound
enclosure, tight when the refinement converged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from itertools import combinations_with_replacement
from typing import Any

import numpy as np
from pydrake.symbolic import Expression

from ofrl_drake.errors import ModelError, WallTimeExceeded
from ofrl_drake.interval import ExpressionEvaluator, Interval, as_expression
from ofrl_drake.interval_linalg import IntervalLinearSystem, interval_matmul

__all__ = [
    "MultibodyJacobianEncloser",
    "MultibodyStructure",
    "multibody_structure",
]

#: Boxes enclosed per call: at most this many node values (nodes * boxes) in memory.
_NODE_VALUES = 2_000_000
_MIN_CHUNK, _MAX_CHUNK = 64, 4096


def _frozen(a: Any, dtype: Any = float) -> np.ndarray:
    arr = np.array(a, dtype=dtype)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class MultibodyStructure:
    """``x' = [qdot; M(q)^-1 (tau(q, v) + B u)]`` of a multibody plant, symbolically.

    Built by :func:`multibody_structure` (for
    :func:`ofrl_drake.drake_models.from_multibody`) and offered by
    :meth:`ofrl_drake.model.ControlAffineSystem.multibody_structure`.

    Attributes
    ----------
    q, v : ndarray of Variable, shapes (nq,), (nv,)
        Positions and velocities; the state is ``x = [q; v]``.
    qdot : ndarray of Expression, shape (nq,)
        ``N(q) v``.
    M : ndarray of Expression, shape (nv, nv)
        The mass matrix ``M(q)``.
    tau : ndarray of Expression, shape (nv,)
        Every generalized force at ``u = 0``: ``tau_app(q, v) - C(q, v) v``
        (``tau_app``: gravity and the other force elements).
    B : ndarray, shape (nv, m)
        The actuation matrix.
    x_eq : ndarray, shape (n,)
        The model's state is ``z = x - x_eq`` (zeros unless shifted).
    u_eq : ndarray, shape (m,)
        The model's input is ``u - u_eq`` (zeros unless shifted).
    """

    q: np.ndarray
    v: np.ndarray
    qdot: np.ndarray
    M: np.ndarray
    tau: np.ndarray
    B: np.ndarray
    # None means zeros: __post_init__ stores the array.
    x_eq: np.ndarray = field(default=None)  # type: ignore[arg-type]
    u_eq: np.ndarray = field(default=None)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        nq, nv = len(self.q), len(self.v)
        B = _frozen(self.B)
        if B.ndim != 2 or B.shape[0] != nv:
            raise ModelError(f"B must have shape (nv, m) = ({nv}, m); got {B.shape}.")
        shapes = {"qdot": (nq,), "M": (nv, nv), "tau": (nv,)}
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise ModelError(
                    f"{name} must have shape {shape}; got {np.shape(getattr(self, name))}."
                )
        object.__setattr__(self, "B", B)
        n, m = nq + nv, B.shape[1]
        x_eq = np.zeros(n) if self.x_eq is None else self.x_eq
        u_eq = np.zeros(m) if self.u_eq is None else self.u_eq
        object.__setattr__(self, "x_eq", _frozen(x_eq))
        object.__setattr__(self, "u_eq", _frozen(u_eq))
        if self.x_eq.shape != (n,) or self.u_eq.shape != (m,):
            raise ModelError(
                f"x_eq and u_eq must have shapes ({n},) and ({m},); got "
                f"{self.x_eq.shape} and {self.u_eq.shape}."
            )

    @property
    def n(self) -> int:
        """State dimension ``nq + nv``."""
        return len(self.q) + len(self.v)

    @property
    def m(self) -> int:
        """Input dimension."""
        return int(self.B.shape[1])

    @property
    def x(self) -> np.ndarray:
        """The state variables ``[q; v]``."""
        return np.concatenate([self.q, self.v])

    def shifted(self, x_eq: Any, u_eq: Any) -> MultibodyStructure:
        """The structure seen from ``(x_eq, u_eq)``: state ``x - x_eq``, input ``u - u_eq``.

        Offsets add up, so a shifted structure can be shifted again.
        """
        return replace(
            self,
            x_eq=self.x_eq + np.asarray(x_eq, dtype=float),
            u_eq=self.u_eq + np.asarray(u_eq, dtype=float),
        )

    def dynamics(self, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``f`` and ``g`` at the columns of ``Z`` (model coordinates), in floating point.

        Parameters
        ----------
        Z : ndarray, shape (n, N)
            States ``z = x - x_eq``.

        Returns
        -------
        f : ndarray, shape (n, N)
        g : ndarray, shape (n, m, N)
        """
        Z = np.asarray(Z, dtype=float)
        nq, nv, m = len(self.q), len(self.v), self.m
        parts = ExpressionEvaluator([*np.ravel(self.M), *self.tau, *self.qdot], self.x)
        values = parts(Z + self.x_eq[:, None])
        N = Z.shape[1]
        M = np.moveaxis(values[: nv * nv].reshape(nv, nv, N), 2, 0)
        rhs = np.concatenate(
            [
                (values[nv * nv : nv * nv + nv] + (self.B @ self.u_eq)[:, None]).T[:, :, None],
                np.broadcast_to(self.B, (N, nv, m)),
            ],
            axis=2,
        )
        solved = np.linalg.solve(M, rhs)  # (N, nv, 1 + m)
        f = np.concatenate([values[nv * nv + nv :], solved[:, :, 0].T])
        g = np.concatenate([np.zeros((nq, m, N)), np.moveaxis(solved[:, :, 1:], 0, 2)])
        return f, g

    def used_states(self) -> tuple[int, ...]:
        """The state indices ``M``, ``tau``, ``qdot`` and their derivatives depend on."""
        used = _jacobian_evaluator(self).variables_used()
        return tuple(sorted({v for u in used for v in u}))

    def jacobians(self, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Jacobians of ``f`` and ``g`` at the columns of ``Z``, in floating point.

        From the structure, never from ``f`` and ``g`` written out:
        ``da/dx_j = M^-1 (r_j - M_j a)`` and ``dG/dx_j = -M^-1 M_j G`` (module
        docstring), with ``M_j``, ``r_j`` and ``d qdot / dx_j`` the symbolic
        derivatives of the small expressions, evaluated at the points.

        Parameters
        ----------
        Z : ndarray, shape (n, N)
            States ``z = x - x_eq``.

        Returns
        -------
        Jf : ndarray, shape (n, n, N)
            ``Jf[i, j] = d f_i / d x_j``.
        Jg : ndarray, shape (n, n, m, N)
            ``Jg[i, j, k] = d g[i, k] / d x_j``.
        """
        Z = np.asarray(Z, dtype=float)
        nq, nv, m, n = len(self.q), len(self.v), self.m, self.n
        N = Z.shape[1]
        values = _jacobian_evaluator(self)(Z + self.x_eq[:, None])
        at = 0
        M = np.moveaxis(values[at : at + nv * nv].reshape(nv, nv, N), 2, 0)  # (N, nv, nv)
        at += nv * nv
        r = values[at : at + nv].T + self.B @ self.u_eq  # (N, nv)
        at += nv
        dM = np.moveaxis(values[at : at + n * nv * nv].reshape(n, nv, nv, N), 3, 1)  # (n, N, ., .)
        at += n * nv * nv
        dr = np.moveaxis(values[at : at + n * nv].reshape(n, nv, N), 2, 1)  # (n, N, nv)
        at += n * nv
        dqdot = values[at : at + n * nq].reshape(n, nq, N)  # [j, i]
        rhs = np.concatenate([r[:, :, None], np.broadcast_to(self.B, (N, nv, m))], axis=2)
        aG = np.linalg.solve(M, rhs)  # (N, nv, 1 + m): a, then the columns of G
        # One solve for every j: [r_j - M_j a, -M_j G], stacked along the columns.
        products = dM @ aG[None]  # (n, N, nv, 1 + m)
        right = np.concatenate([dr[..., None] - products[..., :1], -products[..., 1:]], axis=3)
        right = np.moveaxis(right, 0, 2).reshape(N, nv, n * (1 + m))
        d = np.linalg.solve(M, right).reshape(N, nv, n, 1 + m)
        Jf = np.zeros((n, n, N))
        Jg = np.zeros((n, n, m, N))
        Jf[:nq] = np.swapaxes(dqdot, 0, 1)
        Jf[nq:] = np.transpose(d[:, :, :, 0], (1, 2, 0))
        Jg[nq:] = np.transpose(d[:, :, :, 1:], (1, 2, 3, 0))
        return Jf, Jg


def _jacobian_evaluator(structure: MultibodyStructure) -> ExpressionEvaluator:
    """``[M, tau, dM/dx_j, dtau/dx_j, dqdot/dx_j]`` as one evaluator (built once per structure)."""
    cached = structure.__dict__.get("_jacobian_evaluator")
    if cached is not None:
        return cached
    x = structure.x
    M = [as_expression(e) for e in np.ravel(structure.M)]
    tau = [as_expression(e) for e in structure.tau]
    qdot = [as_expression(e) for e in structure.qdot]
    parts = [*M, *tau]
    parts += [e.Differentiate(xj) for xj in x for e in M]
    parts += [e.Differentiate(xj) for xj in x for e in tau]
    parts += [e.Differentiate(xj) for xj in x for e in qdot]
    evaluator = ExpressionEvaluator(parts, x)
    object.__setattr__(structure, "_jacobian_evaluator", evaluator)  # a cache, not a field
    return evaluator


def _symbolic_state(
    plant: Any,
) -> tuple[Any, Any, np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray, Any]:
    """``plant`` made symbolic at the state ``x = [q; v]`` of new variables.

    Parameters
    ----------
    plant : MultibodyPlant
        Finalized and continuous.

    Returns
    -------
    symbolic : MultibodyPlant_[Expression]
        ``plant.ToSymbolic()``.
    context : Context_[Expression]
        Its default context, with positions ``q`` and velocities ``v``.
    q, v : numpy.ndarray of Variable
        The variables ``q(0), ...`` and ``v(0), ...``.
    qdot : numpy.ndarray of Expression
        ``MapVelocityToQDot(v)``.
    forces : MultibodyForces_[Expression]
        The forces of the force elements (``CalcForceElementsContribution``).
    """
    from pydrake.multibody.tree import MultibodyForces_
    from pydrake.symbolic import MakeVectorVariable

    symbolic = plant.ToSymbolic()
    context = symbolic.CreateDefaultContext()
    q = MakeVectorVariable(plant.num_positions(), "q")
    v = MakeVectorVariable(plant.num_velocities(), "v")
    symbolic.SetPositions(context, [Expression(s) for s in q])
    symbolic.SetVelocities(context, [Expression(s) for s in v])
    qdot = np.asarray(symbolic.MapVelocityToQDot(context, [Expression(s) for s in v]))
    forces = MultibodyForces_[Expression](symbolic)
    symbolic.CalcForceElementsContribution(context, forces)
    return symbolic, context, q, v, qdot, forces


def multibody_structure(plant: Any) -> MultibodyStructure:
    """The :class:`MultibodyStructure` of a finalized continuous ``MultibodyPlant``.

    On the symbolic plant: ``qdot`` is ``MapVelocityToQDot``, ``M`` is
    ``CalcMassMatrix``, ``tau = CalcGeneralizedForces(CalcForceElementsContribution)
    - CalcBiasTerm`` (gravity and every force element, minus ``C(q, v) v``) and
    ``B`` is ``MakeActuationMatrix``.

    ``M`` and ``C(q, v) v`` are taken with the positions of the revolute and
    prismatic joints whose parent body is anchored set to zero: such a joint
    moves everything beyond it rigidly, about or along an axis fixed in both
    of its frames, which changes no kinetic energy, so ``M`` and the
    Christoffel terms derived from it do not depend on its position. (Drake's
    expressions do contain it, e.g. through ``sin(q0)^2 + cos(q0)^2``, which
    interval arithmetic cannot cancel.) Forces keep every position.

    Parameters
    ----------
    plant : MultibodyPlant
        Finalized, continuous, with as many positions as velocities.

    Returns
    -------
    MultibodyStructure
    """
    from pydrake.multibody.tree import JointIndex

    nq = plant.num_positions()
    symbolic, context, q, v, qdot, forces = _symbolic_state(plant)
    applied = np.asarray(symbolic.CalcGeneralizedForces(context, forces))
    rooted = np.zeros(nq, dtype=bool)
    for i in range(plant.num_joints()):
        joint = plant.get_joint(JointIndex(i))
        if joint.type_name() in ("revolute", "prismatic") and plant.IsAnchored(joint.parent_body()):
            rooted[joint.position_start() : joint.position_start() + joint.num_positions()] = True
    symbolic.SetPositions(
        context, [Expression(0.0) if r else Expression(s) for s, r in zip(q, rooted, strict=True)]
    )
    M = np.asarray(symbolic.CalcMassMatrix(context))
    bias = np.asarray(symbolic.CalcBiasTerm(context))
    B = np.asarray(plant.MakeActuationMatrix(), dtype=float)
    # numpy's object loops flag "invalid value" on Drake expressions; harmless.
    with np.errstate(invalid="ignore"):
        tau = applied - bias
    return MultibodyStructure(q, v, qdot, M, tau, B)


# --------------------------------------------------------------- the encloser
def _squared(h: Interval) -> Interval:
    """``h**2`` for intervals ``h`` that hold 0: ``[0, mag(h)**2]``, rounded up."""
    m = Interval(h.mag, h.mag)
    return Interval(np.zeros_like(h.mag), (m * m).hi)


class MultibodyJacobianEncloser:
    """Enclosures of the Jacobians of ``f`` and ``g`` over many boxes at once.

    ``M`` and ``tau`` are differentiated symbolically up to third order along
    the state variables they depend on. Over a box ``X`` with centre ``c`` and
    ``h = X - c``, ``M``, ``tau`` and their first derivatives ``T`` are
    enclosed by the natural form intersected with the second-order Taylor form
    ``T(c) + T'(c) h + h^T T''(X) h / 2``, their second derivatives by the
    natural form intersected with the mean-value form. (Drake's ``M`` and
    ``tau`` repeat variables they do not depend on, e.g. the first joint angle
    through ``sin(q0)^2 + cos(q0)^2``; the Taylor form makes that dependence
    vanish to third order in the box width.) The Jacobian entries then follow
    from interval solves with ``[M]`` (see the module docstring).

    Parameters
    ----------
    structure : MultibodyStructure
        The plant.
    deadline : float, optional
        A ``time.monotonic()`` reading after which differentiating ``M`` and
        ``tau`` to third order stops (seconds to minutes on a plant of three
        links or more); None: no limit.

    Attributes
    ----------
    structure : MultibodyStructure
        As given.
    deadline : float or None
        As given.
    used : ndarray of int
        The state indices the Jacobians depend on (the others are not bisected).
    n_entries : int
        ``n * n + n * n * m``: the entries of ``Jf`` then ``Jg`` (indexed
        ``[i, j]`` and ``[i, j, k]``), flattened in C order.
    chunk : int
        The most boxes enclosed in one evaluation (bounds the memory).
    """

    def __init__(self, structure: MultibodyStructure, deadline: float | None = None) -> None:
        self.structure = structure
        self.deadline = deadline
        s = structure
        x = s.x
        n, m, nq, k = s.n, s.m, len(s.q), len(s.v)
        self._dims = (n, m, nq, k)
        base = [as_expression(e) for e in (*np.ravel(s.M), *s.tau)]
        qdot = [as_expression(e) for e in s.qdot]
        dqdot = [[e.Differentiate(xj) for e in qdot] for xj in x]
        used: set[int] = set()
        flat_dqdot = [e for row in dqdot for e in row]  # np.ravel(dqdot)
        for u in ExpressionEvaluator([*base, *flat_dqdot], x).variables_used():
            used.update(u)
        self.used = np.array(sorted(used), dtype=int)
        U, L = self.used, len(used)
        self._alphas = [
            alpha for order in range(4) for alpha in combinations_with_replacement(range(L), order)
        ]
        self._row = {alpha: i for i, alpha in enumerate(self._alphas)}
        derivative: dict[tuple[int, ...], list[Expression]] = {(): base}
        for alpha in self._alphas[1:]:
            self._check_deadline(alpha)
            derivative[alpha] = [e.Differentiate(x[U[alpha[-1]]]) for e in derivative[alpha[:-1]]]
        low = [alpha for alpha in self._alphas if len(alpha) <= 2]
        high = [alpha for alpha in self._alphas if len(alpha) == 3]
        d2qdot = [[[e.Differentiate(x[l]) for e in dqdot[j]] for l in U] for j in range(n)]
        self._low = ExpressionEvaluator(
            [
                *(e for alpha in low for e in derivative[alpha]),
                *flat_dqdot,
                *(e for rows in d2qdot for row in rows for e in row),  # np.ravel(d2qdot)
            ],
            x,
        )
        self._high = ExpressionEvaluator([e for alpha in high for e in derivative[alpha]], x)
        self._n_low = len(low)
        self.n_entries = n * n + n * n * m
        nodes = self._low.node_count + self._high.node_count
        self.chunk = int(np.clip(_NODE_VALUES // max(nodes, 1), _MIN_CHUNK, _MAX_CHUNK))
        Bu = Interval(np.zeros(k), np.zeros(k))
        for c in range(m):
            Bu = Bu + Interval(s.B[:, c], s.B[:, c]) * float(s.u_eq[c])
        self._Bu = Bu

    def _check_deadline(self, alpha: tuple[int, ...]) -> None:
        """Stop differentiating once :attr:`deadline` has passed.

        Raises
        ------
        WallTimeExceeded
            If it has, naming the derivative that was next.
        """
        if self.deadline is not None and time.monotonic() > self.deadline:
            order = "".join(f" d/dx{self.used[a]}" for a in alpha)
            raise WallTimeExceeded(
                "the multibody Taylor derivatives of M(q) and the bias were not done by the "
                f"deadline (max_wall_time, --max-wall):{order} was next; allow more wall time "
                "or certify a smaller box.",
                step="multibody Taylor derivatives",
            )

    def _at(self, *alpha: int) -> int:
        return self._row[tuple(sorted(alpha))]

    # ------------------------------------------------------------- tables
    def _tables(
        self, lower: np.ndarray, upper: np.ndarray, h: list[Interval]
    ) -> tuple[Interval, Interval, Interval]:
        """``M, tau`` and their derivatives (orders 0-2) over the boxes, tightened,
        and at the centres; ``d qdot / dx_j`` over the boxes and at the centres.

        Returns ``(T, dq, d2q)``: ``T`` is ``(A, k*k + k, 2B)`` (boxes, then
        centres), ``dq`` is ``(n, nq, 2B)``, ``d2q`` is ``(n, L, nq, B)``.
        """
        n, _, nq, k = self._dims
        R, L, A = k * k + k, self.used.size, self._n_low
        B = lower.shape[1]
        centre = 0.5 * (lower + upper)
        z = Interval(np.hstack([lower, centre]), np.hstack([upper, centre]))
        x = z + self.structure.x_eq[:, None]  # outward rounded
        V = self._low.interval(x.lo, x.hi)
        T = Interval(V.lo[: A * R].reshape(A, R, 2 * B), V.hi[: A * R].reshape(A, R, 2 * B))
        o = A * R
        dq = Interval(
            V.lo[o : o + n * nq].reshape(n, nq, 2 * B), V.hi[o : o + n * nq].reshape(n, nq, 2 * B)
        )
        o += n * nq
        d2q = Interval(V.lo[o:, :B].reshape(n, L, nq, B), V.hi[o:, :B].reshape(n, L, nq, B))
        if not L:
            return T, dq, d2q
        V3 = self._high.interval(x.lo[:, :B], x.hi[:, :B])
        box = Interval(
            np.concatenate([T.lo[..., :B], V3.lo.reshape(-1, R, B)]),
            np.concatenate([T.hi[..., :B], V3.hi.reshape(-1, R, B)]),
        )  # every order, over the boxes
        at_c = T[..., B:]
        # Orders 0 and 1: second-order Taylor form around the centre.
        near = [alpha for alpha in self._alphas if len(alpha) <= 1]
        rows = [self._row[alpha] for alpha in near]
        taylor = at_c[rows]
        for a in range(L):
            taylor = taylor + at_c[[self._at(*alpha, a) for alpha in near]] * h[a][None, None]
        for a in range(L):
            for b in range(a, L):
                hh = 0.5 * _squared(h[a]) if a == b else h[a] * h[b]
                taylor = taylor + box[[self._at(*alpha, a, b) for alpha in near]] * hh[None, None]
        # Order 2: mean-value form.
        far = [alpha for alpha in self._alphas if len(alpha) == 2]
        rows2 = [self._row[alpha] for alpha in far]
        mean_value = at_c[rows2]
        for a in range(L):
            mean_value = mean_value + box[[self._at(*alpha, a) for alpha in far]] * h[a][None, None]
        form_lo = np.concatenate([taylor.lo, mean_value.lo])
        form_hi = np.concatenate([taylor.hi, mean_value.hi])
        order = np.array(rows + rows2)
        lo = T.lo.copy()
        hi = T.hi.copy()
        lo[order, :, :B] = np.maximum(lo[order, :, :B], form_lo)
        hi[order, :, :B] = np.minimum(hi[order, :, :B], form_hi)
        # d qdot / dx_j: mean-value form with the second derivatives.
        dq_mv = dq[..., B:]
        for a in range(L):
            dq_mv = dq_mv + d2q[:, a] * h[a][None, None]
        dq = Interval(
            np.concatenate([np.maximum(dq.lo[..., :B], dq_mv.lo), dq.lo[..., B:]], axis=-1),
            np.concatenate([np.minimum(dq.hi[..., :B], dq_mv.hi), dq.hi[..., B:]], axis=-1),
        )
        return Interval(lo, hi), dq, d2q

    # ------------------------------------------------------------- solves
    def _solve_first(self, T: Interval) -> dict[str, Any]:
        """``[a, G]`` and their derivatives along the used variables."""
        _, m, _, k = self._dims
        L = self.used.size
        B2 = T.lo.shape[-1]
        M = T[self._row[()], : k * k].reshape((k, k, B2))
        system = IntervalLinearSystem(M)
        r = T[self._row[()], k * k :] + Interval(self._Bu.lo[:, None], self._Bu.hi[:, None])
        Bmat = np.broadcast_to(self.structure.B[:, :, None], (k, m, B2))
        aG = system.solve(
            Interval(
                np.concatenate([r.lo[:, None], Bmat], axis=1),
                np.concatenate([r.hi[:, None], Bmat], axis=1),
            )
        )  # (k, 1 + m, B2): a, then the columns of G
        dM = [T[self._row[(a,)], : k * k].reshape((k, k, B2)) for a in range(L)]
        parts_lo, parts_hi = [], []
        for a in range(L):
            prod = interval_matmul(dM[a], aG)
            col_a = T[self._row[(a,)], k * k :][:, None] - prod[:, 0:1]
            col_G = -prod[:, 1:]
            parts_lo += [col_a.lo, col_G.lo]
            parts_hi += [col_a.hi, col_G.hi]
        if L:
            d = system.solve(
                Interval(np.concatenate(parts_lo, axis=1), np.concatenate(parts_hi, axis=1))
            )
            d_aG = Interval(d.lo.reshape(k, L, 1 + m, B2), d.hi.reshape(k, L, 1 + m, B2))
        else:
            d_aG = Interval(np.zeros((k, 0, 1 + m, B2)), np.zeros((k, 0, 1 + m, B2)))
        return {"system": system, "dM": dM, "aG": aG, "d_aG": d_aG}

    def _entries(self, d_aG: Interval, dq: Interval) -> Interval:
        """``(E, B)``: the entries of ``Jf`` then ``Jg``."""
        n, m, nq, _ = self._dims
        B = d_aG.lo.shape[-1]
        Jf_lo, Jf_hi = np.zeros((n, n, B)), np.zeros((n, n, B))
        Jg_lo, Jg_hi = np.zeros((n, n, m, B)), np.zeros((n, n, m, B))
        Jf_lo[:nq] = np.swapaxes(dq.lo, 0, 1)
        Jf_hi[:nq] = np.swapaxes(dq.hi, 0, 1)
        U = self.used
        Jf_lo[nq:, U] = d_aG.lo[:, :, 0]
        Jf_hi[nq:, U] = d_aG.hi[:, :, 0]
        Jg_lo[nq:, U] = d_aG.lo[:, :, 1:]
        Jg_hi[nq:, U] = d_aG.hi[:, :, 1:]
        return Interval(
            np.concatenate([Jf_lo.reshape(n * n, B), Jg_lo.reshape(n * n * m, B)]),
            np.concatenate([Jf_hi.reshape(n * n, B), Jg_hi.reshape(n * n * m, B)]),
        )

    def _hessians(self, T: Interval, first: dict[str, Any], d2q: Interval) -> Interval:
        """``(E, L, B)``: each entry's derivative along each used variable."""
        n, m, nq, k = self._dims
        L = self.used.size
        B = T.lo.shape[-1]
        dM, aG, d_aG = first["dM"], first["aG"], first["d_aG"]
        pairs = [(a, b) for a in range(L) for b in range(a, L)]
        parts_lo, parts_hi = [], []
        for a, b in pairs:
            d2M = T[self._at(a, b), : k * k].reshape((k, k, B))
            total = (
                interval_matmul(d2M, aG)
                + interval_matmul(dM[a], d_aG[:, b])
                + interval_matmul(dM[b], d_aG[:, a])
            )
            col_a = T[self._at(a, b), k * k :][:, None] - total[:, 0:1]
            parts_lo += [col_a.lo, -total.hi[:, 1:]]
            parts_hi += [col_a.hi, -total.lo[:, 1:]]
        h = first["system"].solve(
            Interval(np.concatenate(parts_lo, axis=1), np.concatenate(parts_hi, axis=1))
        )
        P = len(pairs)
        h = Interval(h.lo.reshape(k, P, 1 + m, B), h.hi.reshape(k, P, 1 + m, B))
        where = {pair: i for i, pair in enumerate(pairs)}
        Hf_lo, Hf_hi = np.zeros((n, n, L, B)), np.zeros((n, n, L, B))
        Hg_lo, Hg_hi = np.zeros((n, n, m, L, B)), np.zeros((n, n, m, L, B))
        Hf_lo[:nq] = np.moveaxis(d2q.lo, 2, 0)  # [i, j, l]
        Hf_hi[:nq] = np.moveaxis(d2q.hi, 2, 0)
        for a, j in enumerate(self.used):
            for c in range(L):
                p = where[(min(a, c), max(a, c))]
                Hf_lo[nq:, j, c] = h.lo[:, p, 0]
                Hf_hi[nq:, j, c] = h.hi[:, p, 0]
                Hg_lo[nq:, j, :, c] = h.lo[:, p, 1:]
                Hg_hi[nq:, j, :, c] = h.hi[:, p, 1:]
        return Interval(
            np.concatenate([Hf_lo.reshape(n * n, L, B), Hg_lo.reshape(n * n * m, L, B)]),
            np.concatenate([Hf_hi.reshape(n * n, L, B), Hg_hi.reshape(n * n * m, L, B)]),
        )

    # ------------------------------------------------------------ enclosing
    def enclose(
        self, lower: np.ndarray, upper: np.ndarray
    ) -> tuple[Interval, Interval, np.ndarray]:
        """Enclose every Jacobian entry over each box, and at each box's centre.

        Parameters
        ----------
        lower, upper : ndarray, shape (n, B)
            ``B`` boxes in the model's coordinates ``z = x - x_eq``.

        Returns
        -------
        boxes : Interval
            Shape ``(E, B)``: each entry over each box (natural form intersected
            with the mean-value form); the whole line where ``[M]`` is too wide
            to be inverted.
        centres : Interval
            Shape ``(E, B)``: each entry at each box's centre (a few ulps wide).
        spread : ndarray
            Shape ``(E, L, B)``: the width each used variable ``l`` adds to each
            entry's mean-value form, ``mag([dJ/dx_l](X)) * mag(X_l - c_l)``;
            bisecting the variable with the largest share narrows it most.
        """
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        B = lower.shape[1]
        centre = 0.5 * (lower + upper)
        h = [  # X_l - c_l, rounded outward
            Interval(
                np.nextafter(lower[j] - centre[j], -np.inf),
                np.nextafter(upper[j] - centre[j], np.inf),
            )
            for j in self.used
        ]
        with np.errstate(all="ignore"):
            T, dq, d2q = self._tables(lower, upper, h)
            first = self._solve_first(T)
            J = self._entries(first["d_aG"], dq)
            natural, at_c = J[:, :B], J[:, B:]
            if not self.used.size:  # constant Jacobians
                return natural, at_c, np.zeros((self.n_entries, 0, B))
            on_boxes = {
                "system": first["system"].select(slice(0, B)),
                "dM": [d[..., :B] for d in first["dM"]],
                "aG": first["aG"][..., :B],
                "d_aG": first["d_aG"][..., :B],
            }
            H = self._hessians(T[..., :B], on_boxes, d2q)
            total = at_c
            for c in range(self.used.size):
                total = total + H[:, c] * h[c][None]
            spread = H.mag * np.stack([hc.mag for hc in h])[None]
        boxes = Interval(np.maximum(natural.lo, total.lo), np.minimum(natural.hi, total.hi))
        return boxes, at_c, np.where(np.isnan(spread), np.inf, spread)
