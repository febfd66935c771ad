"""The least-squares gain block, update law (gamma)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from pydrake.systems.framework import BasicVector, Context, InputPort, LeafSystem, OutputPort

from ofrl_drake.bellman import gamma_rate, pack_symmetric, packed_size
from ofrl_drake.checks import positive_number, spd_matrix
from ofrl_drake.drake_typing import DrakeArray, drake_array, vector_reader
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
        The default Gamma(0), symmetric positive definite (its symmetric part is
        packed). A run writes its own into the context (:meth:`set_initial_gamma`).
    kc : float
        Adaptation gain k_c.
    beta : float
        Forgetting factor beta. ``beta = 0`` and ``kc = 0`` give a constant gain.
    gamma_bound : float, optional
        ``k0`` of bounded-gain forgetting (:func:`ofrl_drake.learning.bounded_forgetting`):
        the forgetting factor is ``beta (1 - tr(Gamma0^{-1} Gamma) / (k0 L))``, so
        ``tr(Gamma0^{-1} Gamma) / L`` never exceeds ``max(1, k0)``. None (the
        paper's law) keeps ``beta`` constant.

    Notes
    -----
    ``kc``, ``beta`` and ``gamma_bound`` are the defaults of numeric parameters
    of the context (:meth:`set_kc`, :meth:`set_beta`, :meth:`set_gamma_bound`;
    no bound is held as ``inf``), and so is the reference ``Gamma0^{-1}`` of
    bounded forgetting (:meth:`set_initial_gamma`): a sweep over them needs no
    rebuild.

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
        bound = math.inf if gamma_bound is None else float(gamma_bound)
        # The packed index of each entry of the row-major L x L matrix: Gamma
        # unpacked for the trace, the same dot product as on the full matrix.
        self._full_index = np.empty(L * L, dtype=np.intp)
        rows, cols = np.triu_indices(L)
        self._full_index[rows * L + cols] = np.arange(rows.size)
        self._full_index[cols * L + rows] = np.arange(rows.size)
        self._rate = np.empty(packed_size(L))  # scratch for the derivative, copied out at once
        initial: DrakeArray = pack_symmetric(0.5 * (G0 + G0.T))
        self._state_index = self.DeclareContinuousState(BasicVector(initial))
        # [kc, beta, gamma_bound] and the reference Gamma0^{-1} (row-major) of bounded forgetting.
        self._gains_index = self.DeclareNumericParameter(
            BasicVector(drake_array([float(kc), float(beta), bound]))
        )
        self._reference_index = self.DeclareNumericParameter(
            BasicVector(drake_array(np.linalg.inv(G0).ravel()))
        )
        self._gain_sum_port = self.DeclareVectorInputPort("gain_sum", L * L)
        self._gain_sum_value = vector_reader(self._gain_sum_port)
        self._gamma_port = self.DeclareStateOutputPort("gamma", self._state_index)

    def get_gain_sum_input_port(self) -> InputPort:
        """``(1/N) sum omega omega^T / rho^2``, flattened row-major (size L*L)."""
        return self._gain_sum_port

    def get_gamma_output_port(self) -> OutputPort:
        """Gamma's upper triangle, row by row (size L (L + 1) / 2)."""
        return self._gamma_port

    def set_initial_gamma(self, context: Context, gamma: ArrayLike) -> None:
        """Start from ``Gamma(0) = gamma`` in ``context`` (this block's own).

        Sets the state and the reference ``Gamma0^{-1}`` of bounded forgetting.

        Raises
        ------
        ModelError
            If ``gamma`` is not a symmetric positive definite L x L matrix.
        """
        G0 = spd_matrix("GammaGain: Gamma(0)", gamma, self._size)
        packed: DrakeArray = pack_symmetric(0.5 * (G0 + G0.T))
        context.SetContinuousState(packed)
        context.get_mutable_numeric_parameter(self._reference_index).SetFromVector(
            drake_array(np.linalg.inv(G0).ravel())
        )

    def _set_gain(self, context: Context, index: int, value: float) -> None:
        context.get_mutable_numeric_parameter(self._gains_index).SetAtIndex(index, value)

    def set_kc(self, context: Context, kc: float) -> None:
        """Set the adaptation gain k_c >= 0 in ``context`` (this block's own)."""
        self._set_gain(context, 0, positive_number("GammaGain: kc", kc, allow_zero=True))

    def set_beta(self, context: Context, beta: float) -> None:
        """Set the forgetting factor beta >= 0 in ``context`` (this block's own)."""
        self._set_gain(context, 1, positive_number("GammaGain: beta", beta, allow_zero=True))

    def set_gamma_bound(self, context: Context, gamma_bound: float | None) -> None:
        """Set ``k0`` of bounded-gain forgetting (> 0, or None for none) in ``context``."""
        if gamma_bound is None:
            self._set_gain(context, 2, math.inf)
        else:
            self._set_gain(context, 2, positive_number("GammaGain: gamma_bound", gamma_bound))

    def get_gains(self, context: Context) -> tuple[float, float, float | None]:
        """``(kc, beta, gamma_bound)`` in ``context`` (this block's own); None for no bound."""
        kc, beta, bound = context.get_numeric_parameter(self._gains_index).CopyToVector()
        return float(kc), float(beta), (None if math.isinf(bound) else float(bound))

    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        rate = self._rate
        gamma = context.get_continuous_state_vector().CopyToVector()
        kc, beta, bound = context.get_numeric_parameter(self._gains_index).get_value().tolist()
        if bound < math.inf:  # tr(Gamma0^{-1} Gamma) / L, both symmetric
            reference = context.get_numeric_parameter(self._reference_index).get_value()
            ratio = float(reference @ gamma[self._full_index]) / self._size
            beta = bounded_forgetting(beta, ratio, bound)
        gamma_rate(gamma, self._gain_sum_value(context), kc, beta, rate)
        derivatives.SetFromVector(rate)
