"""The least-squares gain block, update law (gamma)."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, InputPort, LeafSystem, OutputPort

from ofrl_drake.bellman import gamma_rate, pack_symmetric, packed_size
from ofrl_drake.checks import positive_number, spd_matrix
from ofrl_drake.learning import bounded_forgetting

__all__ = ["GammaGain"]


class GammaGain(LeafSystem):
    """Least-squares gain with forgetting: ``Gamma' = beta Gamma - k_c Gamma S Gamma``.

    With ``gamma_bound``, ``beta`` is Slotine and Li's bounded-gain forgetting
    factor (see :mod:`ofrl_drake.learning`).

    ``S = gain_sum = (1/N) sum omega_i omega_i^T / rho_i^2``. Gamma is
    symmetric, so its state and its ``gamma`` output are its upper triangle,
    row by row: ``L (L + 1) / 2`` numbers instead of ``L^2``
    (:func:`~ofrl_drake.bellman.pack_symmetric`; ``unpack_symmetric`` gives
    the matrix back).

    .. pydrake_system::

        name: GammaGain
        input_ports:
        - gain_sum
        output_ports:
        - gamma

    Parameters
    ----------
    initial_gamma : array_like, shape (L, L)
        Gamma(0), symmetric positive definite (its symmetric part is packed).
    kc : float
        Adaptation gain k_c.
    beta : float
        Forgetting factor beta. ``beta = 0`` and ``kc = 0`` give a constant gain.
    gamma_bound : float, optional
        ``k0`` of bounded-gain forgetting (:func:`ofrl_drake.learning.bounded_forgetting`):
        the forgetting factor is ``beta (1 - tr(Gamma0^{-1} Gamma) / (k0 L))``, so
        ``tr(Gamma0^{-1} Gamma) / L`` never exceeds ``max(1, k0)``. None (the
        paper's law) keeps ``beta`` constant.

    Raises
    ------
    ModelError
        If ``initial_gamma`` is not a finite symmetric positive definite
        matrix, or ``kc``, ``beta`` or ``gamma_bound`` is negative or not finite.
    """

    def __init__(
        self,
        initial_gamma: np.ndarray,
        kc: float,
        beta: float,
        gamma_bound: float | None = None,
    ) -> None:
        super().__init__()
        self.initial_gamma = initial_gamma
        self.kc = kc
        self.beta = beta
        self.gamma_bound = gamma_bound
        G0 = spd_matrix("GammaGain: initial_gamma", initial_gamma)
        positive_number("GammaGain: kc", kc, allow_zero=True)
        positive_number("GammaGain: beta", beta, allow_zero=True)
        if gamma_bound is not None:
            positive_number("GammaGain: gamma_bound", gamma_bound)
        L = G0.shape[0]
        self._size = L
        self._kc, self._beta = float(kc), float(beta)
        self._bound = None if gamma_bound is None else float(gamma_bound)
        self._inverse_initial = np.linalg.inv(G0).ravel()
        # The packed index of each entry of the row-major L x L matrix: Gamma
        # unpacked for the trace, the same dot product as on the full matrix.
        self._full_index = np.empty(L * L, dtype=np.intp)
        rows, cols = np.triu_indices(L)
        self._full_index[rows * L + cols] = np.arange(rows.size)
        self._full_index[cols * L + rows] = np.arange(rows.size)
        self._rate = np.empty(packed_size(L))  # scratch for the derivative, copied out at once
        initial = pack_symmetric(0.5 * (G0 + G0.T))
        self._state_index = self.DeclareContinuousState(BasicVector(initial))
        self._gain_sum_port = self.DeclareVectorInputPort("gain_sum", L * L)
        self._gamma_port = self.DeclareStateOutputPort("gamma", self._state_index)

    def get_gain_sum_input_port(self) -> InputPort:
        """``(1/N) sum omega omega^T / rho^2``, flattened row-major (size L*L)."""
        return self._gain_sum_port

    def get_gamma_output_port(self) -> OutputPort:
        """Gamma's upper triangle, row by row (size L (L + 1) / 2)."""
        return self._gamma_port

    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        rate = self._rate
        gamma = context.get_continuous_state_vector().CopyToVector()
        beta = self._beta
        if self._bound is not None:  # tr(Gamma0^{-1} Gamma) / L, both symmetric
            ratio = float(self._inverse_initial @ gamma[self._full_index]) / self._size
            beta = bounded_forgetting(beta, ratio, self._bound)
        gamma_rate(gamma, self._gain_sum_port.Eval(context), self._kc, beta, rate)
        derivatives.SetFromVector(rate)
