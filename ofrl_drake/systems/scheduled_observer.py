"""The three-gain observer with gains re-solved along the trajectory.

The paper reports "final values from the simulation" for P, L, H, K, which
suggests gains re-solved as the estimate moves. This block re-solves the
observer LMI at a fixed period over a box centred on the current estimate,
holding the gains, and the box they are certified on, in discrete state
between solves. A failed solve keeps the previous gains and box, is flagged on
the ``solve_failed`` output and counted on ``solve_counts``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike
from pydrake.systems.framework import BasicVector, Context, InputPort, LeafSystem, OutputPort

from ofrl_drake.checks import initial_vector, positive_number, positive_vector
from ofrl_drake.drake_typing import DrakeArray, drake_array, set_state_vector, vector_value
from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem, require_system
from ofrl_drake.observer import ObserverGains, observer_rhs, pack_gains
from ofrl_drake.observer_certificate import ObserverCertificate

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = ["VERIFY_SAMPLES", "ScheduledThreeGainObserver"]

#: Samples of the cheap falsification attempt on every design put in force.
VERIFY_SAMPLES = 1000


def _design_options(owner: str, options: object) -> dict[str, Any]:
    """``options`` checked to be keyword arguments of :func:`~ofrl_drake.design.design_observer`.

    Only its keyword-only ones: the block passes the system, box, input bound
    and rate itself. A bad key found here, not as a ``TypeError`` at the first
    re-solve in the middle of a run.
    """
    import inspect

    from ofrl_drake.design import design_observer

    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise ModelError(
            f"{owner}: design_options must be a dict of keyword arguments of design_observer; "
            f"got {options!r}."
        )
    parameters = inspect.signature(design_observer).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        return dict(options)  # a wrapper that forwards any keyword: nothing to check
    accepted = [p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY]
    unknown = [key for key in options if key not in accepted]
    if unknown:
        keys = ", ".join(repr(key) for key in unknown)
        raise ModelError(
            f"{owner}: design_options has unknown key{'s' if len(unknown) > 1 else ''} {keys}; "
            f"use keyword arguments of design_observer: {accepted}."
        )
    return dict(options)


def _require_design(owner: str, design: object) -> None:
    """Raise :class:`ModelError` unless ``design`` is an ``ObserverDesign``."""
    from ofrl_drake.design import ObserverDesign

    if not isinstance(design, ObserverDesign):
        raise ModelError(
            f"{owner}: initial_design must be an ObserverDesign; got {type(design).__name__}; "
            "design one with ofrl_drake.design.design_observer(system, box, input_bound, alpha)."
        )


class ScheduledThreeGainObserver(LeafSystem):
    """Three-gain observer whose gains are re-designed every ``period`` seconds.

    .. pydrake_system::

        name: ScheduledThreeGainObserver
        input_ports:
        - y
        - u
        output_ports:
        - estimated_state
        - observer_gains
        - certified_box
        - lyapunov_matrix
        - certificate
        - solve_failed
        - solve_counts
        - verification

    Parameters
    ----------
    system : ControlAffineSystem
    initial_design : ObserverDesign
        Gains and Jacobian bounds used until the first re-solve.
    period : float
        Seconds between re-solves (> 0).
    half_width : array_like, shape (n,)
        Half-widths of the box ``[xhat - half_width, xhat + half_width]`` over
        which the Jacobian bounds of each re-solve are computed.
    input_bound : float
        lbar, the input bound every re-solve certifies.
    alpha : float
        Decay rate every re-solve certifies.
    design_options : dict, optional
        Extra keyword arguments for :func:`ofrl_drake.design.design_observer`;
        its ``time_limit`` bounds each re-solve (bounds and LMI), and a re-solve
        that runs out of it counts as failed like any other.
    initial_state : array_like, shape (n,), optional
        Default xhat(0) (zeros if omitted); a run writes its own
        (:meth:`set_estimated_state`).

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`~ofrl_drake.model.ControlAffineSystem`,
        ``initial_design`` not an :class:`~ofrl_drake.design.ObserverDesign`,
        ``period`` is not a finite number > 0, ``half_width`` is not n
        finite numbers > 0, ``input_bound`` or ``alpha`` is not a finite
        number >= 0 (what :func:`~ofrl_drake.design.design_observer` accepts),
        ``design_options`` holds a key that is not a keyword-only argument of
        :func:`~ofrl_drake.design.design_observer`, or ``initial_state`` is
        not a finite vector of length n. Each message starts with
        ``"ScheduledThreeGainObserver: <argument>"``.

    Notes
    -----
    ``observer_gains`` is ``[vec(L), vec(H), vec(K)]`` (row-major, ``3 n q``
    entries: :func:`~ofrl_drake.observer.pack_gains`, read back with
    :func:`~ofrl_drake.observer.unpack_gains`); ``certified_box`` is ``[lower,
    upper]`` (``2 n``) of the box the gains in force are certified on;
    ``lyapunov_matrix`` is their ``P`` (row-major, ``n^2``) and
    ``certificate`` the largest eigenvalue of their LMI over the input
    vertices (negative when certified), so every gain in force can be
    re-checked from the logs: in numpy for the ``polytopic`` and ``paper``
    formulations (:meth:`ObserverDesign.from_gains` with ``P`` and the logged
    box); a ``structured`` design's S-procedure multipliers are not logged
    (their number follows each re-solve's bounds), so its gains re-check with
    ``from_gains(..., P=None, formulation="structured")`` at the logged box,
    which solves for a certifying ``P`` and multipliers with the gains fixed
    (and raises ``ObserverDesignInfeasible`` if there is none);
    ``solve_failed`` is 1 after a re-solve that found no certified design (the
    previous gains and box stay in force), else 0; ``solve_counts`` is
    ``[re-solves run, re-solves failed]`` since the start; ``verification``
    is ``[worst rate found, claimed rate -2 alpha, 1 if falsified else 0]``
    of a falsification attempt
    (:func:`ofrl_drake.verification.verify_observer` with
    :data:`VERIFY_SAMPLES` samples, no refinement, seeded by the re-solve
    count) on each design put in force, the initial one included. All are
    discrete state, so a logger sampling at a re-solve time reads the values
    from before it.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        initial_design: ObserverDesign,
        *,
        period: float,
        half_width: ArrayLike,
        input_bound: float,
        alpha: float,
        design_options: dict[str, Any] | None = None,
        initial_state: ArrayLike | None = None,
    ) -> None:
        super().__init__()
        self.system = system
        self.initial_design = initial_design
        self.period = period
        self.half_width = half_width
        self.input_bound = input_bound
        self.alpha = alpha
        self.design_options = design_options
        self.initial_state = initial_state
        name = type(self).__name__
        require_system(system, f"{name}: system")
        _require_design(name, initial_design)
        self._period = positive_number(f"{name}: period", period)
        self._half_width = positive_vector(f"{name}: half_width", half_width, system.n)
        self._input_bound = positive_number(f"{name}: input_bound", input_bound, allow_zero=True)
        self._alpha = positive_number(f"{name}: alpha", alpha, allow_zero=True)
        self._design_options = _design_options(name, design_options)
        n, q = system.n, system.q
        self._gain_shape = (n, q)
        gains = ObserverGains.from_design(system, initial_design)
        x0: DrakeArray = initial_vector(f"{name}: initial_state", initial_state, n)
        self._xhat_index = self.DeclareContinuousState(BasicVector(x0))
        self._gains_index = self.DeclareDiscreteState(self._pack_gains(gains))
        self._bounds_index = self.DeclareDiscreteState(self._pack_bounds(gains))
        box = initial_design.box
        self._box_index = self.DeclareDiscreteState(
            drake_array(
                np.concatenate([np.asarray(box.lower, float), np.asarray(box.upper, float)])
            )
        )
        self._P_index = self.DeclareDiscreteState(drake_array(np.ravel(initial_design.P)))
        self._certificate_index = self.DeclareDiscreteState(
            drake_array([float(initial_design.max_eigenvalue)])
        )
        # Eager on purpose: the falsification of the initial design is the default
        # value of the `verification` state (logged from t = 0, like each re-solve's),
        # and Drake takes a state's default when it is declared. Seeded, so every
        # context and run reads the same numbers.
        self._verification_index = self.DeclareDiscreteState(self._verify(initial_design, 0))
        self._failed_index = self.DeclareDiscreteState(1)
        self._counts_index = self.DeclareDiscreteState(2)
        self._y_port = self.DeclareVectorInputPort("y", q)
        self._u_port = self.DeclareVectorInputPort("u", system.m)
        self._xhat_port = self.DeclareStateOutputPort("estimated_state", self._xhat_index)
        self._gains_port = self.DeclareStateOutputPort("observer_gains", self._gains_index)
        self._box_port = self.DeclareStateOutputPort("certified_box", self._box_index)
        self._P_port = self.DeclareStateOutputPort("lyapunov_matrix", self._P_index)
        self._certificate_port = self.DeclareStateOutputPort("certificate", self._certificate_index)
        self._failed_port = self.DeclareStateOutputPort("solve_failed", self._failed_index)
        self._counts_port = self.DeclareStateOutputPort("solve_counts", self._counts_index)
        self._verification_port = self.DeclareStateOutputPort(
            "verification", self._verification_index
        )
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, self._period, self._resolve)

    # ------------------------------------------------------------- accessors
    def get_y_input_port(self) -> InputPort:
        """The measurement ``y`` (size q)."""
        return self._y_port

    def get_u_input_port(self) -> InputPort:
        """The applied input ``u`` (size m)."""
        return self._u_port

    def get_estimated_state_output_port(self) -> OutputPort:
        """The estimate ``xhat`` (size n)."""
        return self._xhat_port

    def get_observer_gains_output_port(self) -> OutputPort:
        """``[vec(L), vec(H), vec(K)]`` currently in force (size 3 n q)."""
        return self._gains_port

    def get_certified_box_output_port(self) -> OutputPort:
        """``[lower, upper]`` of the box the gains in force are certified on (size 2 n)."""
        return self._box_port

    def get_lyapunov_matrix_output_port(self) -> OutputPort:
        """``P`` of the design in force, row-major (size n^2)."""
        return self._P_port

    def get_certificate_output_port(self) -> OutputPort:
        """Largest LMI eigenvalue of the design in force over the input vertices (size 1)."""
        return self._certificate_port

    def get_solve_failed_output_port(self) -> OutputPort:
        """1 if the latest re-solve failed, else 0 (size 1)."""
        return self._failed_port

    def get_solve_counts_output_port(self) -> OutputPort:
        """``[re-solves run, re-solves failed]`` since the start (size 2)."""
        return self._counts_port

    def get_verification_output_port(self) -> OutputPort:
        """``[worst rate found, -2 alpha, falsified]`` of the design in force (size 3)."""
        return self._verification_port

    def set_estimated_state(self, context: Context, xhat: ArrayLike) -> None:
        """Set the estimate to ``xhat`` in ``context``, this block's own context.

        The gains in force stay the initial design's until the first re-solve.
        """
        set_state_vector(context, xhat, self.system.n, f"{type(self).__name__}: xhat")

    def observer_certificate(self) -> ObserverCertificate:
        """Kind ``"scheduled"``: the initial design; the boxes in force are logged."""
        return ObserverCertificate(
            "scheduled",
            design=self.initial_design.to_dict(),
            note=(
                f"observer {type(self).__name__} re-designs its gains along the run: x and "
                "xhat checked against the box of the design in force"
            ),
        )

    def _verify(self, design: ObserverDesign, seed: int) -> DrakeArray:
        from ofrl_drake.verification import verify_observer

        report = verify_observer(
            design, self.system, samples=VERIFY_SAMPLES, seed=seed, refine=False
        )
        return drake_array([report.worst_rate, report.claimed_rate, float(report.falsified)])

    # --------------------------------------------------------------- packing
    @staticmethod
    def _pack_gains(gains: ObserverGains) -> DrakeArray:
        return pack_gains(gains.L, gains.H, gains.K)

    @staticmethod
    def _pack_bounds(gains: ObserverGains) -> DrakeArray:
        return np.concatenate([gains.Mf1.ravel(), gains.Mg1.ravel(), gains.Mg2.ravel()])

    def _unpack(self, context) -> ObserverGains:
        # Per derivative evaluation: the layout of pack_gains, read inline (no call
        # to unpack_gains); tests/test_scheduled_observer.py pins the two together.
        n, m, q = self.system.n, self.system.m, self.system.q
        g = context.get_discrete_state(self._gains_index).get_value()
        b = context.get_discrete_state(self._bounds_index).get_value()
        k = n * q
        return ObserverGains(
            L=g[:k].reshape(n, q),
            H=g[k : 2 * k].reshape(n, q),
            K=g[2 * k :].reshape(n, q),
            Mf1=b[: n * n].reshape(n, n),
            Mg1=b[n * n : n * n * (1 + m)].reshape(n, n, m),
            Mg2=b[n * n * (1 + m) :].reshape(n, n, m),
        )

    # -------------------------------------------------------------- dynamics
    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        xhat = context.get_continuous_state_vector().CopyToVector()
        y = vector_value(self._y_port, context)
        u = vector_value(self._u_port, context)
        gains = self._unpack(context)
        derivatives.SetFromVector(observer_rhs(self.system, gains, xhat, y, u))

    def _resolve(self, context, discrete_state) -> None:
        from ofrl_drake.design import design_observer
        from ofrl_drake.errors import OfrlError
        from ofrl_drake.jacobian_bounds import Box

        xhat = context.get_continuous_state_vector().CopyToVector()
        box = Box(xhat - self._half_width, xhat + self._half_width)
        counts = context.get_discrete_state(self._counts_index).CopyToVector()
        try:
            design = design_observer(
                self.system, box, self._input_bound, self._alpha, **self._design_options
            )
        except OfrlError:
            discrete_state.get_mutable_vector(self._failed_index).SetFromVector([1.0])
            discrete_state.get_mutable_vector(self._counts_index).SetFromVector(counts + 1.0)
            return
        gains = ObserverGains.from_design(self.system, design)
        discrete_state.get_mutable_vector(self._gains_index).SetFromVector(self._pack_gains(gains))
        discrete_state.get_mutable_vector(self._bounds_index).SetFromVector(
            self._pack_bounds(gains)
        )
        discrete_state.get_mutable_vector(self._box_index).SetFromVector(
            np.concatenate([box.lower, box.upper])
        )
        discrete_state.get_mutable_vector(self._P_index).SetFromVector(
            np.asarray(design.P, float).ravel()
        )
        discrete_state.get_mutable_vector(self._certificate_index).SetFromVector(
            [float(design.max_eigenvalue)]
        )
        discrete_state.get_mutable_vector(self._verification_index).SetFromVector(
            self._verify(design, int(counts[0]) + 1)
        )
        discrete_state.get_mutable_vector(self._failed_index).SetFromVector([0.0])
        discrete_state.get_mutable_vector(self._counts_index).SetFromVector(
            counts + np.array([1.0, 0.0])
        )
