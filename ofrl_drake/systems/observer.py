"""The three-gain observer block (eq:observerdynamics_x)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from numpy.typing import ArrayLike
from pydrake.systems.framework import BasicVector, Context, InputPort, LeafSystem, OutputPort

from ofrl_drake.checks import initial_vector
from ofrl_drake.drake_typing import DrakeArray, set_state_vector, vector_value
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.observer import ObserverGains, observer_rhs, require_observer_arguments
from ofrl_drake.observer_certificate import ObserverCertificate

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = ["ThreeGainObserver"]


class ThreeGainObserver(LeafSystem):
    """State estimator with linear gain L and injection gains H, K.

    .. pydrake_system::

        name: ThreeGainObserver
        input_ports:
        - y
        - u
        output_ports:
        - estimated_state

    Parameters
    ----------
    system : ControlAffineSystem
        The model the observer runs.
    gains : ObserverGains
        L, H, K and the Jacobian bounds M_f1, M_g1, M_g2 that define the input
        sector. Build them with :meth:`ObserverGains.from_design` from a
        certified ``ObserverDesign`` or :meth:`ObserverGains.from_arrays`.
    initial_state : array_like, shape (n,), optional
        Default xhat(0) (zeros if omitted); a run writes its own
        (:meth:`set_estimated_state`).
    design : ObserverDesign, optional
        The design ``gains`` come from; then :meth:`observer_certificate`
        reports it and its box. Without it the block certifies nothing.

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`ControlAffineSystem`, ``gains`` not an
        :class:`ObserverGains` whose gains have the shapes ``system``'s n, q
        and m give (:func:`~ofrl_drake.observer.require_gains`), ``design``
        is given and its L, H, K differ from ``gains``, or ``initial_state``
        is not a finite vector of length n.

    See Also
    --------
    ofrl_drake.observer.observer_rhs : the right-hand side this block wraps.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        gains: ObserverGains,
        initial_state: ArrayLike | None = None,
        design: ObserverDesign | None = None,
    ) -> None:
        super().__init__()
        self.system = system
        self.gains = gains
        self.initial_state = initial_state
        self.design = design
        require_observer_arguments("ThreeGainObserver", system, gains, design)
        x0: DrakeArray = initial_vector("ThreeGainObserver: initial_state", initial_state, system.n)
        self._state_index = self.DeclareContinuousState(BasicVector(x0))
        self._y_port = self.DeclareVectorInputPort("y", system.q)
        self._u_port = self.DeclareVectorInputPort("u", system.m)
        self._xhat_port = self.DeclareStateOutputPort("estimated_state", self._state_index)

    def get_y_input_port(self) -> InputPort:
        """The measurement ``y`` (size q)."""
        return self._y_port

    def get_u_input_port(self) -> InputPort:
        """The applied input ``u`` (size m)."""
        return self._u_port

    def get_estimated_state_output_port(self) -> OutputPort:
        """The estimate ``xhat`` (size n)."""
        return self._xhat_port

    def set_estimated_state(self, context: Context, xhat: ArrayLike) -> None:
        """Set the estimate to ``xhat`` in ``context``, this block's own context."""
        set_state_vector(context, xhat, self.system.n, "ThreeGainObserver: xhat")

    def observer_certificate(self) -> ObserverCertificate:
        """The design and its box, or nothing when built without a design."""
        return ObserverCertificate.of_design(self.design, type(self).__name__)

    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        xhat = context.get_continuous_state_vector().CopyToVector()
        y = vector_value(self._y_port, context)
        u = vector_value(self._u_port, context)
        derivatives.SetFromVector(observer_rhs(self.system, self.gains, xhat, y, u))
