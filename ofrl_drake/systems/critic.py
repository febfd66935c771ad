"""The critic-weight block, update law (W_c)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from pydrake.systems.framework import BasicVector, Context, InputPort, LeafSystem, OutputPort

from ofrl_drake.bellman import critic_rate, packed_size
from ofrl_drake.checks import finite_vector, positive_number
from ofrl_drake.drake_typing import DrakeArray, drake_array, set_state_vector, vector_reader

__all__ = ["CriticWeights"]


class CriticWeights(LeafSystem):
    """Critic weights W with ``W' = -k_c Gamma critic_sum``.

    ``critic_sum = (1/N) sum_i omega_i delta_i / rho_i`` comes from the
    Bellman-extrapolation block, so this is (W_c) exactly.

    .. pydrake_system::

        name: CriticWeights
        input_ports:
        - critic_sum
        - gamma
        output_ports:
        - weights

    Parameters
    ----------
    initial_weights : array_like, shape (L,)
        The default W(0); also fixes L. A run writes its own W(0) into the
        context (:meth:`set_weights`).
    kc : float
        The default adaptation gain k_c >= 0 (0 freezes the critic, an
        ablation). ``kc`` is a numeric parameter of the context
        (:meth:`set_kc`), so a sweep over it needs no rebuild.

    Raises
    ------
    ModelError
        If ``initial_weights`` is not a finite, non-empty vector or ``kc`` is
        negative or not finite.
    """

    def __init__(self, initial_weights: Sequence[float], kc: float) -> None:
        super().__init__()
        self.initial_weights = initial_weights
        self.kc = kc
        W0: DrakeArray = finite_vector("CriticWeights: initial_weights", initial_weights)
        positive_number("CriticWeights: kc", kc, allow_zero=True)
        size = W0.size
        self._size = size
        self._rate = np.empty(size)  # scratch for the derivative, copied out at once
        self._state_index = self.DeclareContinuousState(BasicVector(W0))
        self._kc_index = self.DeclareNumericParameter(BasicVector(drake_array([float(kc)])))
        self._critic_sum_port = self.DeclareVectorInputPort("critic_sum", size)
        self._gamma_port = self.DeclareVectorInputPort("gamma", packed_size(size))
        self._weights_port = self.DeclareStateOutputPort("weights", self._state_index)
        self._gamma_value = vector_reader(self._gamma_port)
        self._critic_sum_value = vector_reader(self._critic_sum_port)

    def get_critic_sum_input_port(self) -> InputPort:
        """``(1/N) sum omega delta / rho`` (size L)."""
        return self._critic_sum_port

    def get_gamma_input_port(self) -> InputPort:
        """Gamma's upper triangle, row by row (size L (L + 1) / 2; see ``GammaGain``)."""
        return self._gamma_port

    def get_weights_output_port(self) -> OutputPort:
        """The weights W (size L)."""
        return self._weights_port

    def set_weights(self, context: Context, W: ArrayLike) -> None:
        """Set the weights to ``W`` in ``context``, this block's own context."""
        set_state_vector(context, W, self._size, "CriticWeights: W")

    def get_kc(self, context: Context) -> float:
        """The adaptation gain k_c in ``context`` (this block's own)."""
        return float(context.get_numeric_parameter(self._kc_index).GetAtIndex(0))

    def set_kc(self, context: Context, kc: float) -> None:
        """Set the adaptation gain k_c >= 0 in ``context`` (this block's own).

        Raises
        ------
        ModelError
            If ``kc`` is negative or not finite.
        """
        positive_number("CriticWeights: kc", kc, allow_zero=True)
        context.get_mutable_numeric_parameter(self._kc_index).SetAtIndex(0, float(kc))

    def DoCalcTimeDerivatives(self, context, derivatives) -> None:
        rate = self._rate
        kc = context.get_numeric_parameter(self._kc_index).GetAtIndex(0)
        critic_rate(
            self._gamma_value(context),
            self._critic_sum_value(context),
            kc,
            rate,
        )
        derivatives.SetFromVector(rate)
