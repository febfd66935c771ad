"""The plant block ``x' = f(x) + g(x) u``, ``y = C x``."""

from __future__ import annotations

from numpy.typing import ArrayLike
from pydrake.systems.framework import BasicVector, Context, InputPort, LeafSystem, OutputPort

from ofrl_drake.checks import initial_vector
from ofrl_drake.drake_typing import DrakeArray, set_state_vector, vector_value
from ofrl_drake.model import ControlAffineSystem, require_system

__all__ = ["ControlAffinePlant"]


class ControlAffinePlant(LeafSystem):
    """A :class:`~ofrl_drake.model.ControlAffineSystem` as a Drake block.

    .. pydrake_system::

        name: ControlAffinePlant
        input_ports:
        - u
        output_ports:
        - state
        - y

    Parameters
    ----------
    system : ControlAffineSystem
        The model; its ``f`` and ``g`` are evaluated in double precision.
    initial_state : array_like, shape (n,), optional
        Default value of the continuous state x (zeros if omitted); a run
        writes its own (:meth:`set_state`).

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`~ofrl_drake.model.ControlAffineSystem`
        or ``initial_state`` is not a finite vector of length n.

    Notes
    -----
    ``y`` depends on the state only (no direct feedthrough), so a controller
    that reads ``y`` closes no algebraic loop.
    """

    def __init__(self, system: ControlAffineSystem, initial_state: ArrayLike | None = None) -> None:
        super().__init__()
        self.system = system
        self.initial_state = initial_state
        require_system(system, "ControlAffinePlant: system")
        x0: DrakeArray = initial_vector(
            "ControlAffinePlant: initial_state", initial_state, system.n
        )
        self._C = system.output_matrix
        self._state_index = self.DeclareContinuousState(BasicVector(x0))
        self._u_port = self.DeclareVectorInputPort("u", system.m)
        self._state_port = self.DeclareStateOutputPort("state", self._state_index)
        self._y_port = self.DeclareVectorOutputPort(
            "y", system.q, self._calc_y, prerequisites_of_calc={self.xc_ticket()}
        )

    def get_u_input_port(self) -> InputPort:
        """The input ``u`` (size m)."""
        return self._u_port

    def get_y_output_port(self) -> OutputPort:
        """The measured output ``y = C x`` (size q)."""
        return self._y_port

    def get_state_output_port(self) -> OutputPort:
        """The true state ``x`` (size n)."""
        return self._state_port

    def set_state(self, context: Context, x: ArrayLike) -> None:
        """Set the plant's state to ``x`` in ``context``, this block's own context."""
        set_state_vector(context, x, self.system.n, "ControlAffinePlant: x")

    def _calc_y(self, context, output) -> None:
        x = context.get_continuous_state_vector().CopyToVector()
        output.SetFromVector(self._C @ x)

    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        x = context.get_continuous_state_vector().CopyToVector()
        u = vector_value(self._u_port, context)
        derivatives.SetFromVector(self.system.dynamics(x, u))
