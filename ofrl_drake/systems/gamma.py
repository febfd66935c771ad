"""The least-squares gain block, update law (gamma)."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, InputPort, LeafSystem, OutputPort

from ofrl_drake.bellman import gamma_rate
from ofrl_drake.checks import positive_number, spd_matrix

__all__ = ["GammaGain"]


class GammaGain(LeafSystem):
    """Least-squares gain with forgetting: ``Gamma' = beta Gamma - k_c Gamma S Gamma``.

    ``S = gain_sum = (1/N) sum omega_i omega_i^T / rho_i^2``. Gamma is stored
    flattened row-major; its symmetric part is used and the derivative is
    symmetrized, so Gamma stays symmetric to round-off.

    .. pydrake_system::

        name: GammaGain
        input_ports:
        - gain_sum
        output_ports:
        - gamma

    Parameters
    ----------
    initial_gamma : array_like, shape (L, L)
        Gamma(0), symmetric positive definite.
    kc : float
        Adaptation gain k_c.
    beta : float
        Forgetting factor beta. ``beta = 0`` and ``kc = 0`` give a constant gain.

    Raises
    ------
    ModelError
        If ``initial_gamma`` is not a finite symmetric positive definite
        matrix, or ``kc`` or ``beta`` is negative or not finite.
    """

    def __init__(self, initial_gamma: np.ndarray, kc: float, beta: float) -> None:
        super().__init__()
        self.initial_gamma = initial_gamma
        self.kc = kc
        self.beta = beta
        G0 = spd_matrix("GammaGain: initial_gamma", initial_gamma)
        positive_number("GammaGain: kc", kc, allow_zero=True)
        positive_number("GammaGain: beta", beta, allow_zero=True)
        self._size = G0.shape[0]
        self._kc, self._beta = float(kc), float(beta)
        self._rate = np.empty(G0.size)  # scratch for the derivative, copied out at once
        self._state_index = self.DeclareContinuousState(BasicVector(G0.ravel()))
        self._gain_sum_port = self.DeclareVectorInputPort("gain_sum", G0.size)
        self._gamma_port = self.DeclareStateOutputPort("gamma", self._state_index)

    def get_gain_sum_input_port(self) -> InputPort:
        """``(1/N) sum omega omega^T / rho^2``, flattened (size L*L)."""
        return self._gain_sum_port

    def get_gamma_output_port(self) -> OutputPort:
        """Gamma, flattened row-major (size L*L)."""
        return self._gamma_port

    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        rate = self._rate
        gamma_rate(
            context.get_continuous_state_vector().CopyToVector(),
            self._gain_sum_port.Eval(context),
            self._kc,
            self._beta,
            rate,
        )
        derivatives.SetFromVector(rate)
