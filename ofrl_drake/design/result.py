"""The result of an observer design: :class:`ObserverDesign`, its certificates and its JSON."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ofrl_drake.checks import array_of_shape, finite_array
from ofrl_drake.design.errors import DesignError
from ofrl_drake.design.formulations import get_formulation
from ofrl_drake.design.pipeline import (
    _box_and_bounds,
    _check_request,
    _finish,
    _problem,
)
from ofrl_drake.design.sdp import DEFAULT_MARGIN
from ofrl_drake.jacobian_bounds import Box, JacobianBounds
from ofrl_drake.lmi import LmiError, certifies, decay_certificate, gain_matrix
from ofrl_drake.model import ControlAffineSystem, require_system
from ofrl_drake.structured_lmi import DeltaCheck, StructuredLmi, delta_check

__all__ = ["ObserverDesign"]


def _array(a: Any) -> np.ndarray:
    arr = np.array(a, dtype=float)
    arr.setflags(write=False)
    return arr


def _finite(key: str, a: Any) -> np.ndarray:
    """A read-only copy of the design's ``key``, checked numeric and finite."""
    return _array(finite_array(f"the design's {key}", a, error=DesignError))


def _cert_list(cert: list[tuple[np.ndarray, float]]) -> list[dict[str, Any]]:
    return [{"input": u.tolist(), "max_eigenvalue": ev} for u, ev in cert]


@dataclass(frozen=True, eq=False)
class ObserverDesign:
    """Certified observer gains and everything needed to re-check them.

    Two certificates are kept, both recomputed in numpy from ``P, L, H, K, C``
    and the bounds only (never taken from the solver):

    * :meth:`certificate`: the check of the formulation that was solved:
      the (lmi2) eigenvalues at the ``3**m`` input vertices for ``"paper"``,
      the decay certificate for ``"polytopic"``, the S-procedure LMI at each
      distinct input vertex from ``P, L`` and the multipliers :attr:`tau` for
      ``"structured"`` (:func:`ofrl_drake.structured_lmi.structured_certificate`);
      :attr:`is_certified`.
    * :meth:`decay_certificate`: the sound polytopic check of ``dV/dt <= -2
      alpha V`` (:func:`ofrl_drake.lmi.decay_certificate`), whatever the
      formulation; :attr:`is_decay_certified` (which, for a structured
      design, is its structured certificate: it proves the same claim and
      needs no corner enumeration, so it also works past ``MAX_CORNERS``).

    Attributes
    ----------
    P : ndarray, shape (n, n)
        Lyapunov matrix of ``V_e = e^T P e``.
    L, H, K : ndarray, shape (n, q)
        Observer gains (eq:observerdynamics).
    R : ndarray, shape (n, q)
        ``P L``, the SDP variable.
    alpha : float
        The decay rate asked for: ``dV_e/dt <= -2 alpha V_e`` if
        :attr:`is_decay_certified`.
    box : Box
        Where the Jacobian bounds hold (x and x-hat must stay inside).
    input_bound : float
        ``lambda_bar``: certified for every ``|u_k| <= input_bound``.
    bounds : JacobianBounds
        The Jacobian bounds used.
    C : ndarray, shape (q, n)
        Output matrix.
    solver, backend : str
        Which solver and modelling layer produced the numbers.
    solve_time : float
        Wall-clock seconds of the solve (building included).
    status : str
        The solver's status.
    sector : str
        ``"sign_correct"`` (default) or ``"paper"`` (``"paper"`` formulation only).
    objective : str
        The objective used.
    margin : float
        The strict margin asked of the solver.
    formulation : str
        A key of :data:`~ofrl_drake.design.FORMULATIONS`: ``"polytopic"``
        (default), ``"paper"``, ``"structured"`` or ``"structured_row"``.
    tau : tuple of ndarray
        The S-procedure multipliers of each structured LMI (one array per
        distinct input vertex); empty for the other formulations.

    Raises
    ------
    DesignError
        If ``P, L, H, K, R`` or ``C`` is not numeric and finite (the message
        names it), or the formulation or sector is unknown.
    """

    P: np.ndarray
    L: np.ndarray
    H: np.ndarray
    K: np.ndarray
    R: np.ndarray
    alpha: float
    box: Box
    input_bound: float
    bounds: JacobianBounds
    C: np.ndarray
    solver: str
    solve_time: float
    status: str
    backend: str
    sector: str = "sign_correct"
    objective: str = "min_gain"
    margin: float = DEFAULT_MARGIN
    formulation: str = "polytopic"
    tau: tuple[np.ndarray, ...] = ()
    _cert: list = field(default_factory=list, init=False, repr=False)
    _decay: list = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        for key in ("P", "L", "H", "K", "R", "C"):
            object.__setattr__(self, key, _finite(key, getattr(self, key)))
        object.__setattr__(self, "box", Box.coerce(self.box))
        object.__setattr__(self, "alpha", float(self.alpha))
        object.__setattr__(self, "input_bound", float(self.input_bound))
        object.__setattr__(self, "solve_time", float(self.solve_time))
        object.__setattr__(self, "tau", tuple(_array(np.ravel(t)) for t in self.tau))
        formulation = get_formulation(self.formulation, self.sector)
        object.__setattr__(self, "_cert", formulation.certificate(self))

    def _numbers(
        self,
    ) -> tuple[
        np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, JacobianBounds, float, float
    ]:
        """The arguments of the :mod:`ofrl_drake.lmi` certificates (also the formulations')."""
        return (
            self.P,
            self.L,
            self.H,
            self.K,
            self.C,
            self.bounds,
            self.input_bound,
            self.alpha,
        )

    # ------------------------------------------------------------ certificate
    def certificate(self) -> list[tuple[np.ndarray, float]]:
        """``(u vertex, max eigenvalue)`` of the solved formulation's LMI.

        ``"paper"``: the largest eigenvalue of the (lmi2) matrix at each of the
        ``3**m`` input vertices. ``"polytopic"``: at each input vertex, the
        largest eigenvalue of ``A_cl^T P + P A_cl + 2 alpha P`` over every corner
        of the Jacobian bounds (the same as :meth:`decay_certificate`).
        Recomputed in numpy from ``P, L, H, K, C`` and the bounds only.
        """
        return [(u.copy(), ev) for u, ev in self._cert]

    def decay_certificate(self) -> list[tuple[np.ndarray, float]]:
        """``(u vertex, max eigenvalue over the corners)``: the sound decay check.

        :func:`ofrl_drake.lmi.decay_certificate` on this design's numbers; all
        negative (and ``P > 0``) means ``dV/dt <= -2 alpha V`` for every ``x``,
        ``xhat`` in the box (with ``xhat + H ytil``, ``xhat + K ytil`` in it too)
        and every ``|u_k| <= input_bound``.

        Raises
        ------
        LmiError
            If the corner enumeration exceeds :data:`ofrl_drake.lmi.MAX_CORNERS`.
        """
        if not self._decay:
            object.__setattr__(self, "_decay", decay_certificate(*self._numbers()))
        return [(u.copy(), ev) for u, ev in self._decay]

    @property
    def max_eigenvalue(self) -> float:
        """The largest eigenvalue of :meth:`certificate` (< 0 when certified)."""
        return max(ev for _, ev in self._cert)

    @property
    def is_certified(self) -> bool:
        """True if ``P`` is positive definite and every :meth:`certificate` value is < 0."""
        return get_formulation(self.formulation, self.sector).is_certified(self)

    @property
    def is_decay_certified(self) -> bool:
        """True if ``P > 0`` and every :meth:`decay_certificate` value is < 0.

        For a structured design, its structured certificate (:attr:`is_certified`),
        which proves the same ``dV/dt <= -2 alpha V`` on the same box without
        enumerating corners. For the others, False also when the corner
        enumeration is too large to check.
        """
        if self.is_structured:
            return self.is_certified
        try:
            return certifies(self.P, self.decay_certificate)
        except LmiError:
            return False

    @property
    def is_structured(self) -> bool:
        """True for a structured (S-procedure) formulation."""
        return self.formulation.startswith("structured")

    def structured_lmi(self) -> StructuredLmi:
        """The structured LMI data of this design (rebuilt from its bounds and numbers).

        Raises
        ------
        DesignError
            If the design is not structured.
        """
        formulation = get_formulation(self.formulation, self.sector)
        if not self.is_structured:
            raise DesignError(
                f"structured_lmi() needs a structured design; this one is "
                f"formulation={self.formulation!r}."
            )
        return formulation.design_data(self)  # type: ignore[attr-defined]

    @property
    def lmi_sizes(self) -> list[int]:
        """Size ``n + r`` of each structured LMI (one per distinct input vertex)."""
        return self.structured_lmi().sizes

    def delta_check(self, *, samples: int = 2000, seed: int = 0) -> list[DeltaCheck]:
        """The multiplier-free re-check (:func:`ofrl_drake.structured_lmi.delta_check`).

        Exhaustive over the ``delta`` box (a proof) up to ``2**12`` vertices per
        input vertex, sampled beyond. Structured designs only.
        """
        return delta_check(self.structured_lmi(), self.P, self.L, samples=samples, seed=seed)

    @property
    def bounds_are_guaranteed(self) -> bool:
        """True unless the Jacobian bounds are ``"sampled"`` (an inner estimate).

        A decay certificate proves ``V' <= -2 alpha V`` on the box only if the
        bounds enclose the Jacobians; ``"certified"`` bounds do, sampled ones
        usually but not provably do. ``"given"`` bounds are the caller's claim.
        """
        return self.bounds.method != "sampled"

    @property
    def condition_number(self) -> float:
        """``cond(P)`` (2-norm)."""
        return float(np.linalg.cond(self.P))

    @property
    def gain_norm(self) -> float:
        """``||L||_2``."""
        return float(np.linalg.norm(self.L, 2))

    # ----------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict.

        Keys: ``P, L, H, K`` (nested lists), ``alpha``, ``input_bound``,
        ``box`` ``{lower, upper}``, ``jacobian_bounds`` ``{Mf1, Mf2, Mg1, Mg2}``,
        ``certificate`` ``[{input, max_eigenvalue}, ...]``, ``solver``,
        ``solve_time``, ``formulation``, ``decay_certificate`` (same shape as
        ``certificate``; None if the corner enumeration is too large),
        ``is_decay_certified``; and also ``R, C, status, backend, sector,
        objective, margin, jacobian_method, condition_number, gain_norm,
        is_certified``; ``tau`` (a list of lists, one per structured LMI) for a
        structured design.
        """
        try:
            decay: list[dict[str, Any]] | None = _cert_list(self.decay_certificate())
        except LmiError:
            decay = None
        return {
            "P": self.P.tolist(),
            "L": self.L.tolist(),
            "H": self.H.tolist(),
            "K": self.K.tolist(),
            "alpha": self.alpha,
            "input_bound": self.input_bound,
            "box": self.box.to_dict(),
            "jacobian_bounds": self.bounds.to_dict(),
            "certificate": _cert_list(self._cert),
            "solver": self.solver,
            "solve_time": self.solve_time,
            "formulation": self.formulation,
            "decay_certificate": decay,
            "is_decay_certified": self.is_decay_certified,
            "bounds_are_guaranteed": self.bounds_are_guaranteed,
            "R": self.R.tolist(),
            "C": self.C.tolist(),
            "status": self.status,
            "backend": self.backend,
            "sector": self.sector,
            "objective": self.objective,
            "margin": self.margin,
            "jacobian_method": self.bounds.method,
            "condition_number": self.condition_number,
            "gain_norm": self.gain_norm,
            "is_certified": self.is_certified,
        } | ({"tau": [t.tolist() for t in self.tau]} if self.is_structured else {})

    def to_json(self, path: str | os.PathLike[str]) -> None:
        """Write :meth:`to_dict` to ``path`` as JSON."""
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh, indent=2)
            fh.write("\n")

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], system: ControlAffineSystem | None = None
    ) -> ObserverDesign:
        """Rebuild a design from :meth:`to_dict` output.

        The stored certificates are not trusted: they are recomputed from the
        numbers. Data without a ``formulation`` key were written before the
        polytopic formulation existed and are read as ``"paper"``.

        Parameters
        ----------
        data : dict
            As written by :meth:`to_dict`.
        system : ControlAffineSystem, optional
            Supplies ``C`` if ``data`` has no ``"C"`` key.

        Raises
        ------
        DesignError
            If a required key is missing, the formulation is unknown, or a
            matrix is not numeric and finite.
        """
        required = [
            "P",
            "L",
            "H",
            "K",
            "alpha",
            "input_bound",
            "box",
            "jacobian_bounds",
            "solver",
            "solve_time",
        ]
        missing = [k for k in required if k not in data]
        if missing:
            raise DesignError(f"observer design data is missing keys {missing}.")
        if "C" in data:
            C = np.asarray(data["C"], dtype=float)
        elif system is not None:
            C = system.output_matrix
        else:
            raise DesignError("observer design data has no 'C'; pass system= to supply it.")
        box = Box.coerce(data["box"])
        method = data.get("jacobian_method", "given")
        bounds = JacobianBounds.from_dict(data["jacobian_bounds"], box, method)
        P = np.asarray(data["P"], dtype=float)
        L = np.asarray(data["L"], dtype=float)
        R = np.asarray(data["R"], dtype=float) if "R" in data else P @ L
        return cls(
            P=P,
            L=L,
            H=data["H"],
            K=data["K"],
            R=R,
            alpha=data["alpha"],
            box=box,
            input_bound=data["input_bound"],
            bounds=bounds,
            C=C,
            solver=data["solver"],
            solve_time=data["solve_time"],
            status=data.get("status", "loaded"),
            backend=data.get("backend", "drake"),
            sector=data.get("sector", "sign_correct"),
            objective=data.get("objective", "min_gain"),
            margin=data.get("margin", DEFAULT_MARGIN),
            formulation=data.get("formulation", "paper"),
            tau=tuple(np.asarray(t, dtype=float) for t in data.get("tau", ())),
        )

    @classmethod
    def from_json(
        cls, path: str | os.PathLike[str], system: ControlAffineSystem | None = None
    ) -> ObserverDesign:
        """Read a design written by :meth:`to_json`."""
        with open(path, encoding="utf-8") as fh:
            return cls.from_dict(json.load(fh), system)

    @classmethod
    def from_gains(
        cls,
        system: ControlAffineSystem,
        box: Any,
        input_bound: float,
        alpha: float,
        L: Any,
        H: Any,
        K: Any,
        P: Any = None,
        bounds: JacobianBounds | None = None,
        *,
        solver: str = "clarabel",
        backend: str = "drake",
        jacobian_method: str = "certified",
        margin: float = DEFAULT_MARGIN,
        sector: str = "sign_correct",
        formulation: str = "polytopic",
        time_limit: float | None = None,
    ) -> ObserverDesign:
        """A design from pinned gains ``L, H, K`` (and optionally ``P``).

        If ``P`` is given, nothing is solved and the design is returned as it
        is: :meth:`certificate` and :attr:`is_certified` report honestly whether
        it certifies. If ``P`` is None, a small SDP looks for ``P >= I`` with
        the formulation's LMI ``<= -margin I`` at every vertex (``"paper"``) or
        every corner and vertex (``"polytopic"``, where the corners are built
        with the given ``H, K``, so nonzero injection gains are checked
        soundly too), ``L, H, K`` fixed, minimizing ``lambda_max(P)``;
        ``time_limit`` bounds the bounds computed here and that solve as in
        :func:`~ofrl_drake.design.design_observer`.

        Raises
        ------
        WallTimeExceeded
            If the bounds computed here left nothing of ``time_limit``, or the
            solve for ``P`` ran out of what they left.
        ObserverDesignInfeasible
            If ``P`` is None and no certifying ``P`` is found.
        DesignError
            Before any Jacobian bounds are computed: for a ``system`` that is
            not a ControlAffineSystem, gains (or a given ``P``) that are not
            finite or of the wrong shape, a bad solver, backend, formulation or
            sector (checked even with ``P`` given), or a bad ``alpha``,
            ``input_bound``, ``margin`` or ``time_limit``; later, for bounds
            that do not match, or (``P`` None) too many corners for the
            polytopic formulation.
        LmiError
            If ``P`` is given and the polytopic corner enumeration is too large.
        """
        require_system(system, "the observer design's system", DesignError)
        C = system.output_matrix
        n, q = system.n, system.q
        gains = [
            gain_matrix(name, G, n, q, DesignError) for name, G in (("L", L), ("H", H), ("K", K))
        ]
        if P is not None:
            P = array_of_shape("P", P, (n, n), error=DesignError)
        # All of it before the bounds, which can take seconds.
        alpha, input_bound, margin, time_limit, _ = _check_request(
            solver, backend, formulation, sector, alpha, input_bound, margin, time_limit
        )
        box, bounds, time_limit = _box_and_bounds(system, box, bounds, jacobian_method, time_limit)
        if P is not None:
            return cls(
                P=P,
                L=gains[0],
                H=gains[1],
                K=gains[2],
                R=P @ gains[0],
                alpha=alpha,
                box=box,
                input_bound=input_bound,
                bounds=bounds,
                C=C,
                solver="none",
                solve_time=0.0,
                status="given",
                backend="none",
                sector=sector,
                objective="given",
                margin=margin,
                formulation=formulation,
            )
        problem = _problem(
            C,
            bounds,
            input_bound,
            alpha,
            margin,
            "min_condition",
            None,
            sector,
            formulation,
            L=gains[0],
            HK=(gains[1], gains[2]),
        )
        return _finish(
            cls,
            problem,
            bounds,
            box,
            input_bound,
            solver,
            backend,
            sector,
            max_gain=None,
            time_limit=time_limit,
        )
