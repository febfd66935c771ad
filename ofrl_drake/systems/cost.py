"""The accumulated-cost block ``J(t) = int Q(x) + U(u) dt``."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, InputPort, LeafSystem, OutputPort

from ofrl_drake.cost import check_cost_arguments, raise_input_out_of_bound, stage_cost_rate
from ofrl_drake.drake_typing import drake_array, vector_value

__all__ = ["RunningCost"]


class RunningCost(LeafSystem):
    """Integrates the stage cost along the closed-loop trajectory.

    .. pydrake_system::

        name: RunningCost
        input_ports:
        - state
        - u
        output_ports:
        - cost

    Parameters
    ----------
    Q : array_like, shape (n, n)
        State weight.
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar > 0.

    Raises
    ------
    ModelError
        If ``Q`` is not symmetric positive semidefinite, ``r`` has an entry
        <= 0, or ``input_bound <= 0``.
    """

    def __init__(self, Q: np.ndarray, r: np.ndarray, input_bound: float) -> None:
        super().__init__()
        self.Q = Q
        self.r = r
        self.input_bound = input_bound
        self._Q, self._r, self._lbar = check_cost_arguments("RunningCost", Q, r, input_bound)
        n, m = self._Q.shape[0], self._r.size
        self._state_index = self.DeclareContinuousState(BasicVector(drake_array([0.0])))
        self._x_port = self.DeclareVectorInputPort("state", n)
        self._u_port = self.DeclareVectorInputPort("u", m)
        self._cost_port = self.DeclareStateOutputPort("cost", self._state_index)

    def get_state_input_port(self) -> InputPort:
        """The true state x (size n)."""
        return self._x_port

    def get_u_input_port(self) -> InputPort:
        """The applied input u (size m)."""
        return self._u_port

    def get_cost_output_port(self) -> OutputPort:
        """The accumulated cost J (size 1)."""
        return self._cost_port

    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        u = vector_value(self._u_port, context)
        rate, worst = stage_cost_rate(
            vector_value(self._x_port, context), u, self._Q, self._r, self._lbar
        )
        if worst > 1.0 + 1e-12:
            raise_input_out_of_bound(u, self.input_bound)
        derivatives.get_mutable_vector().SetAtIndex(0, rate)
