"""The saturated controller block (u_app)."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import InputPort, LeafSystem, OutputPort

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.drake_typing import vector_value
from ofrl_drake.model import ControlAffineSystem, require_system
from ofrl_drake.policy import check_policy_arguments, policy_kernel, policy_scale

__all__ = ["SaturatedController"]


class SaturatedController(LeafSystem):
    """``u = -lbar tanh((1/(2 lbar)) R^{-1} g(xhat)^T grad sigma(xhat)^T W)``.

    Stateless, with direct feedthrough from both inputs.

    .. pydrake_system::

        name: SaturatedController
        input_ports:
        - estimated_state
        - policy_weights
        output_ports:
        - u

    Parameters
    ----------
    system : ControlAffineSystem
    basis : PolynomialBasis
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar > 0.

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`~ofrl_drake.model.ControlAffineSystem`,
        ``basis`` is not for ``system.n`` states, ``r`` is not ``m``
        positive numbers, or ``input_bound <= 0``.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        basis: PolynomialBasis,
        r: np.ndarray,
        input_bound: float,
    ) -> None:
        super().__init__()
        self.system = system
        self.basis = basis
        self.r = r
        self.input_bound = input_bound
        require_system(system, "SaturatedController: system")
        self._r = check_policy_arguments(
            "SaturatedController", system.n, system.m, basis, r, input_bound
        )
        self._scale = policy_scale(self._r, input_bound)
        self._lbar = float(input_bound)
        self._tables = basis.gradient_tables
        self._xhat_port = self.DeclareVectorInputPort("estimated_state", system.n)
        self._weights_port = self.DeclareVectorInputPort("policy_weights", basis.size)
        self._u_port = self.DeclareVectorOutputPort(
            "u",
            system.m,
            self._calc_u,
            prerequisites_of_calc={self._xhat_port.ticket(), self._weights_port.ticket()},
        )

    def get_estimated_state_input_port(self) -> InputPort:
        """The state estimate xhat (size n)."""
        return self._xhat_port

    def get_policy_weights_input_port(self) -> InputPort:
        """The weights of the policy in force (size L): the critic's W under the paper's law."""
        return self._weights_port

    def get_u_output_port(self) -> OutputPort:
        """The saturated input u (size m)."""
        return self._u_port

    def _calc_u(self, context, output) -> None:
        xhat = vector_value(self._xhat_port, context)
        g = np.asarray(self.system.g(xhat), dtype=float)
        lowered, index, factor = self._tables
        u = policy_kernel(
            xhat, g, vector_value(self._weights_port, context), lowered, index, factor,
            self._scale, self._lbar,
        )  # fmt: skip
        output.SetFromVector(u)
