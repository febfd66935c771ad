"""The LMI formulations of the observer design, each a :class:`Formulation` object.

A formulation owns everything that differs between the two ways of posing the
observer LMI: the SDP data it needs (:meth:`Formulation.problem`), its LMI
blocks in each backend (:meth:`Formulation.lmi_blocks`,
:meth:`Formulation.cvxpy_blocks`) and the numpy re-check of a design's numbers
(:meth:`Formulation.certificate`, :meth:`Formulation.is_certified`).
:data:`FORMULATIONS` holds them by name (``design_observer(formulation=...)``).

``"polytopic"`` (default): a sound decay certificate.
    ``H = K = 0`` are fixed; the error then obeys ``e' = (M_f + M_gu - L C) e``
    with ``M_f + M_gu`` in the element-wise box ``[M_f1 + M_ug1(u), M_f2 +
    M_ug2(u)]`` (the row-wise mean value theorem; :mod:`ofrl_drake.lmi`), and
    ``P A_cl`` is linear in ``P`` and ``R = P L``. One common ``(P, R)`` is asked
    to satisfy

        A^T P + P A - C^T R^T - R C + 2 alpha P <= -margin I

    at every corner ``A`` of that box and every input vertex
    ``u_k in {-input_bound, 0, +input_bound}``
    (:func:`ofrl_drake.lmi.corner_matrices`); by convexity this gives
    ``dV/dt <= -2 alpha V`` for ``V = e^T P e``, every ``x, xhat`` in the box and
    every ``|u_k| <= input_bound``. Feasible only for rates the plant allows: on
    the two-state example no quadratic ``V`` certifies ``alpha >= 1``.
``"paper"``: the paper's (lmi2), exactly as stated, with the sign-correct input
    sector, at the ``3**m`` input vertices (docs/paper_notes.md, "one set of gains"), linear
    in ``(P, R, H, K)``. It is the paper's method, kept for reproduction and
    comparison, but it is not a decay certificate for nonlinear plants (a design
    that satisfies it at alpha = 2 on the two-state example has ``dV/dt = +39 V``
    at some states; see :mod:`ofrl_drake.lmi`). ``injection_gains=False`` pins
    ``H = K = 0`` (a linear Luenberger observer certified by (lmi2)).

Every design also carries the polytopic decay certificate of its own numbers
(:meth:`~ofrl_drake.design.ObserverDesign.decay_certificate`), so a "paper"
design says honestly whether it certifies decay.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ofrl_drake.design.errors import DesignError
from ofrl_drake.design.sdp import LmiProblem
from ofrl_drake.jacobian_bounds import JacobianBounds
from ofrl_drake.lmi import (
    SECTORS,
    LmiError,
    certificate,
    certifies,
    is_certified,
    lmi2_blocks,
    polytopic_lmi,
    vertex_corners,
    vertex_data,
)
from ofrl_drake.sector import input_vertices
from ofrl_drake.structured_lmi import (
    StructuredLmi,
    structured_certificate,
    structured_lmi,
    structured_lmi_blocks,
)

if TYPE_CHECKING:
    from ofrl_drake.design.result import ObserverDesign

__all__ = [
    "FORMULATIONS",
    "Formulation",
    "PaperFormulation",
    "PolytopicFormulation",
    "StructuredFormulation",
    "get_formulation",
]


def _sym(M: Any) -> Any:
    return 0.5 * (M + M.T)


def _zero_injection(n: int, q: int) -> tuple[np.ndarray, np.ndarray]:
    """``(H, K) = (0, 0)``, shapes ``(n, q)``: no injection, a linear Luenberger observer."""
    return np.zeros((n, q)), np.zeros((n, q))


class Formulation(ABC):
    """One way to pose the observer LMI: its SDP data, LMI blocks and numpy re-check.

    Attributes
    ----------
    name : str
        Its key in :data:`FORMULATIONS` and in ``ObserverDesign.formulation``.
    sign_correct_only : bool
        True if it always uses the sign-correct input sector (every
        formulation but ``"paper"``).
    proves_decay : bool
        True if a solution proves the decay claim for the true error
        dynamics on the box (every formulation but ``"paper"``, whose (lmi2)
        reads the Jacobians' lower bounds only). Then the LMI is infeasible
        wherever the error's linearization has a mode slower than alpha that
        no gain reaches.
    """

    name: ClassVar[str]
    sign_correct_only: ClassVar[bool] = True
    proves_decay: ClassVar[bool] = True

    def check_sector(self, sector: str) -> None:
        """Raise :class:`DesignError` unless ``sector`` can be used with this formulation."""
        if sector not in SECTORS:
            raise DesignError(f"sector must be one of {SECTORS}; got {sector!r}.")
        if self.sign_correct_only and sector != "sign_correct":
            raise DesignError(
                f"sector={sector!r} applies to formulation='paper' only; the {self.name} "
                "formulation always uses the sign-correct input sector."
            )

    @abstractmethod
    def problem(
        self,
        C: np.ndarray,
        bounds: JacobianBounds,
        input_bound: float,
        alpha: float,
        margin: float,
        objective: str,
        max_gain: float | None,
        sector: str,
        *,
        L: np.ndarray | None = None,
        HK: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> LmiProblem:
        """The SDP data of this formulation (arguments checked by the caller).

        Parameters
        ----------
        C : ndarray, shape (q, n)
            Output matrix.
        bounds : JacobianBounds
            The Jacobian bounds.
        input_bound, alpha, margin : float
            ``|u_k| <= input_bound``, decay rate, strict margin.
        objective : str
            One of :data:`ofrl_drake.design.sdp.OBJECTIVES`.
        max_gain : float or None
            Cap on ``||R||_2``.
        sector : str
            The input sector (checked by :meth:`check_sector`).
        L, HK : optional
            Pinned gains (see :class:`~ofrl_drake.design.sdp.LmiProblem`).

        Raises
        ------
        DesignError
            If the formulation cannot be set up (too many corners).
        """

    @abstractmethod
    def lmi_blocks(
        self,
        problem: LmiProblem,
        P: np.ndarray,
        R: np.ndarray,
        H: np.ndarray,
        K: np.ndarray,
        tau: list[np.ndarray] | None = None,
    ) -> list[np.ndarray]:
        """The matrices ``-LMI - margin I`` that must be positive semidefinite, in numpy.

        Built from :mod:`ofrl_drake.lmi`'s (or :mod:`ofrl_drake.structured_lmi`'s)
        assembly and affine in ``P, R, H, K`` (and the multipliers ``tau`` of a
        structured formulation, one array per model), so the Drake backend
        reads its coefficient matrices off them. ``P, R, H, K`` and each
        ``tau`` may carry the same leading (batch) axes, shapes ``(..., n, n)``,
        ``(..., n, q)`` and ``(..., r)``; every block then has them too, so the
        backend reads the coefficients of many decision variables in one call.
        """

    @abstractmethod
    def cvxpy_blocks(
        self, problem: LmiProblem, P: Any, R: Any, H: Any, K: Any, tau: list[Any] | None = None
    ) -> list[Any]:
        """The same matrices as cvxpy expressions, for cvxpy variables ``P, R`` (``H, K``, ``tau``).

        Written in cvxpy expressions directly, independently of the numpy
        assembly of :meth:`lmi_blocks`, so agreement of the two backends is a
        check of both.
        """

    @abstractmethod
    def certificate(self, design: ObserverDesign) -> list[tuple[np.ndarray, float]]:
        """``(u vertex, max eigenvalue)`` of this formulation's LMI at ``design``'s numbers."""

    @abstractmethod
    def is_certified(self, design: ObserverDesign) -> bool:
        """True if ``design``'s ``P`` is positive definite and :meth:`certificate` is negative."""


class PolytopicFormulation(Formulation):
    """The sound decay certificate over every corner of the Jacobian bounds, ``H = K = 0``.

    Its LMI is ``A^T P + P A - C^T R^T - R C + 2 alpha P <= -margin I`` at every
    corner matrix ``A``; its certificate is the decay certificate.
    """

    name = "polytopic"

    def problem(
        self,
        C: np.ndarray,
        bounds: JacobianBounds,
        input_bound: float,
        alpha: float,
        margin: float,
        objective: str,
        max_gain: float | None,
        sector: str,
        *,
        L: np.ndarray | None = None,
        HK: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> LmiProblem:
        """The distinct corner matrices over all input vertices, built with ``H, K`` (0 if None).

        Raises
        ------
        DesignError
            If there are more than :data:`ofrl_drake.lmi.MAX_CORNERS` corners.
        """
        if HK is None:
            HK = _zero_injection(C.shape[1], C.shape[0])
        H, K = HK
        try:
            vertices = vertex_corners(bounds, input_bound, H, K, C, "formulation='paper'")
            stacks = [corners for _, corners in vertices]
        except LmiError as err:
            raise DesignError(f"formulation='polytopic': {err}") from err
        corners = np.unique(np.concatenate(stacks), axis=0)
        return LmiProblem(self.name, C, [], corners, alpha, margin, objective, max_gain, L, HK)

    def lmi_blocks(
        self,
        problem: LmiProblem,
        P: np.ndarray,
        R: np.ndarray,
        H: np.ndarray,
        K: np.ndarray,
        tau: list[np.ndarray] | None = None,
    ) -> list[np.ndarray]:
        """One block per corner, from :func:`ofrl_drake.lmi.polytopic_lmi`."""
        # (..., 1, n, n) against the corners' (N, n, n): (..., N, n, n).
        M = polytopic_lmi(
            P[..., None, :, :], R[..., None, :, :], problem.corners, problem.C, problem.alpha
        )
        blocks = -M - problem.margin * np.eye(problem.n)
        return [blocks[..., c, :, :] for c in range(blocks.shape[-3])]

    def cvxpy_blocks(
        self, problem: LmiProblem, P: Any, R: Any, H: Any, K: Any, tau: list[Any] | None = None
    ) -> list[Any]:
        """One block per corner."""
        C, eye = problem.C, np.eye(problem.n)
        blocks = []
        for A in problem.corners:
            M = A.T @ P + P @ A - C.T @ R.T - R @ C + 2.0 * problem.alpha * P
            blocks.append(_sym(-M) - problem.margin * eye)
        return blocks

    def certificate(self, design: ObserverDesign) -> list[tuple[np.ndarray, float]]:
        """The decay certificate (:meth:`ObserverDesign.decay_certificate`)."""
        return design.decay_certificate()

    def is_certified(self, design: ObserverDesign) -> bool:
        """:attr:`ObserverDesign.is_decay_certified`."""
        return design.is_decay_certified


class PaperFormulation(Formulation):
    """The paper's (lmi2) at the ``3**m`` input vertices, in the chosen input sector."""

    name = "paper"
    sign_correct_only = False
    proves_decay = False

    def problem(
        self,
        C: np.ndarray,
        bounds: JacobianBounds,
        input_bound: float,
        alpha: float,
        margin: float,
        objective: str,
        max_gain: float | None,
        sector: str,
        *,
        L: np.ndarray | None = None,
        HK: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> LmiProblem:
        """The constant matrices of (lmi2) at each input vertex.

        From :func:`ofrl_drake.lmi.vertex_data` in the given input ``sector``.
        """
        n = C.shape[1]
        vertices = []
        for u in input_vertices(input_bound, bounds.m):
            A, Jf21, Jg21 = vertex_data(bounds, u, sector)
            vertices.append((u, A, Jf21, Jg21))
        corners = np.zeros((0, n, n))
        return LmiProblem(
            self.name, C, vertices, corners, alpha, margin, objective, max_gain, L, HK
        )

    def lmi_blocks(
        self,
        problem: LmiProblem,
        P: np.ndarray,
        R: np.ndarray,
        H: np.ndarray,
        K: np.ndarray,
        tau: list[np.ndarray] | None = None,
    ) -> list[np.ndarray]:
        """One ``2n x 2n`` block per input vertex, from :func:`ofrl_drake.lmi.lmi2_blocks`."""
        n, C = problem.n, problem.C
        blocks = []
        for _, A, Jf21, Jg21 in problem.vertices:
            M = lmi2_blocks(P, R, H, K, C, A, Jf21, Jg21, problem.alpha)
            blocks.append(-M - problem.margin * np.eye(2 * n))
        return blocks

    def cvxpy_blocks(
        self, problem: LmiProblem, P: Any, R: Any, H: Any, K: Any, tau: list[Any] | None = None
    ) -> list[Any]:
        """One ``2n x 2n`` block per input vertex."""
        import cvxpy as cp  # on first use: the Drake backend does not pay its import time

        n, C = problem.n, problem.C
        eye = np.eye(n)
        blocks = []
        for _, A, Jf21, Jg21 in problem.vertices:
            J21 = Jf21 @ (eye - H @ C) + Jg21 @ (eye - K @ C)
            M11 = A.T @ P + P @ A - C.T @ R.T - R @ C + 2.0 * problem.alpha * P
            M21 = P - J21
            M = cp.bmat([[M11, M21.T], [M21, -2.0 * eye]])
            blocks.append(_sym(-M) - problem.margin * np.eye(2 * n))
        return blocks

    def certificate(self, design: ObserverDesign) -> list[tuple[np.ndarray, float]]:
        """The (lmi2) eigenvalues at each input vertex (:func:`ofrl_drake.lmi.certificate`)."""
        return certificate(*design._numbers(), design.sector)

    def is_certified(self, design: ObserverDesign) -> bool:
        """:func:`ofrl_drake.lmi.is_certified`."""
        return is_certified(*design._numbers(), design.sector)


class StructuredFormulation(Formulation):
    """The polytopic claim as one norm-bounded S-procedure LMI per input vertex, ``H = K = 0``.

    The Jacobian box is written ``A(delta) = A0 + sum_l delta_l w_l e_{i_l} F_l``,
    ``|delta_l| <= 1`` (:mod:`ofrl_drake.structured_lmi`), and one LMI of size
    ``n + r`` per distinct input vertex, affine in ``(P, R, tau)`` with ``r``
    multipliers ``tau >= 0`` (one per uncertain entry for ``grouping="entry"``,
    per uncertain row for ``"row"``), implies the polytopic LMI at every corner
    at once. Its cost does not grow as ``2**k``; its re-check is
    :func:`ofrl_drake.structured_lmi.structured_certificate` from ``P, L`` and
    the design's ``tau``, which proves the same ``dV/dt <= -2 alpha V`` as the
    polytopic decay certificate (docs/structured_certificate.md).

    Parameters
    ----------
    name : str
        Its registry key.
    grouping : {"entry", "row"}
        One multiplier per uncertain entry or per uncertain row.
    """

    def __init__(self, name: str, grouping: str) -> None:
        self.name = name  # type: ignore[misc]  # per-instance registry key
        self.grouping = grouping

    def data(
        self,
        C: np.ndarray,
        bounds: JacobianBounds,
        input_bound: float,
        alpha: float,
        margin: float,
        HK: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> StructuredLmi:
        """The structured LMI data (:func:`ofrl_drake.structured_lmi.structured_lmi`).

        Raises
        ------
        DesignError
            For bounds that are not finite or are crossed.
        """
        H, K = (None, None) if HK is None else HK
        try:
            return structured_lmi(
                C, bounds, input_bound, alpha, margin=margin, grouping=self.grouping, H=H, K=K
            )
        except LmiError as err:
            raise DesignError(f"formulation={self.name!r}: {err}") from err

    def problem(
        self,
        C: np.ndarray,
        bounds: JacobianBounds,
        input_bound: float,
        alpha: float,
        margin: float,
        objective: str,
        max_gain: float | None,
        sector: str,
        *,
        L: np.ndarray | None = None,
        HK: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> LmiProblem:
        """The norm-bounded model at each distinct input vertex, ``H, K`` pinned (0 if None)."""
        n, q = C.shape[1], C.shape[0]
        if HK is None:
            HK = _zero_injection(n, q)
        data = self.data(C, bounds, input_bound, alpha, margin, HK)
        return LmiProblem(
            self.name,
            C,
            [],
            np.zeros((0, n, n)),
            alpha,
            margin,
            objective,
            max_gain,
            L,
            HK,
            structured=data,
        )

    def lmi_blocks(
        self,
        problem: LmiProblem,
        P: np.ndarray,
        R: np.ndarray,
        H: np.ndarray,
        K: np.ndarray,
        tau: list[np.ndarray] | None = None,
    ) -> list[np.ndarray]:
        """One ``(n + r)`` block per model, from ``structured_lmi_blocks``."""
        assert problem.structured is not None and tau is not None
        return [
            -M - problem.margin * np.eye(M.shape[-1])
            for M in structured_lmi_blocks(problem.structured, P, R, tau)
        ]

    def cvxpy_blocks(
        self, problem: LmiProblem, P: Any, R: Any, H: Any, K: Any, tau: list[Any] | None = None
    ) -> list[Any]:
        """``cp.bmat([[S0 + sum tau_g D_g, P E], [E^T P, -diag(tau)]])`` per model."""
        import cvxpy as cp

        assert problem.structured is not None and tau is not None
        data, C = problem.structured, problem.C
        blocks = []
        for model, t in zip(data.models, tau, strict=True):
            E, D = model.signals(data.grouping)
            S = model.A0.T @ P + P @ model.A0 - C.T @ R.T - R @ C + 2.0 * problem.alpha * P
            S = S + sum(t[g] * D[g] for g in range(D.shape[0]))
            M = cp.bmat([[S, P @ E], [E.T @ P, -cp.diag(t)]])
            blocks.append(_sym(-M) - problem.margin * np.eye(problem.n + E.shape[1]))
        return blocks

    def design_data(self, design: ObserverDesign) -> StructuredLmi:
        """The structured LMI data of ``design`` (its ``C``, bounds, rate, margin, ``H, K``)."""
        return self.data(
            design.C,
            design.bounds,
            design.input_bound,
            design.alpha,
            design.margin,
            (np.asarray(design.H), np.asarray(design.K)),
        )

    def certificate(self, design: ObserverDesign) -> list[tuple[np.ndarray, float]]:
        """:func:`~ofrl_drake.structured_lmi.structured_certificate` at ``design``'s ``P, L, tau``.

        Raises
        ------
        DesignError
            If the design's multipliers do not match the LMI (e.g. none stored).
        """
        data = self.design_data(design)
        try:
            return structured_certificate(data, design.P, design.L, list(design.tau))
        except LmiError as err:
            raise DesignError(
                f"formulation={self.name!r} needs the S-procedure multipliers tau of the "
                f"design: {err} Re-solve it (design_observer, or from_gains with P=None)."
            ) from err

    def is_certified(self, design: ObserverDesign) -> bool:
        """True if ``P > 0`` and every structured certificate value is < 0 (``lmi.certifies``)."""
        return certifies(design.P, design.certificate)


#: The formulations by name; the first is the default.
FORMULATIONS: dict[str, Formulation] = {
    f.name: f
    for f in (
        PolytopicFormulation(),
        PaperFormulation(),
        StructuredFormulation("structured", "entry"),
        StructuredFormulation("structured_row", "row"),
    )
}


def get_formulation(name: str, sector: str = "sign_correct") -> Formulation:
    """The formulation called ``name``, checked against the input ``sector``.

    Raises
    ------
    DesignError
        For an unknown formulation or sector, or a sector the formulation
        does not take.
    """
    if name not in FORMULATIONS:
        raise DesignError(f"formulation must be one of {tuple(FORMULATIONS)}; got {name!r}.")
    formulation = FORMULATIONS[name]
    formulation.check_sector(sector)
    return formulation
