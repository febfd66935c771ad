"""The stateless Bellman-extrapolation block shared by the critic and Gamma."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import InputPort, LeafSystem, OutputPort, ValueProducer

from ofrl_drake.bellman import BellmanSums, Extrapolator, PointFeatures, learning_condition

__all__ = ["BellmanExtrapolator"]


class BellmanExtrapolator(LeafSystem):
    """Bellman errors at N fixed points, computed once per evaluation.

    One cache entry holds the :class:`~ofrl_drake.bellman.BellmanSums` for
    the current weights (one compiled pass over the points); all three
    outputs read it, so the critic and Gamma laws share one computation per
    derivative evaluation.

    .. pydrake_system::

        name: BellmanExtrapolator
        input_ports:
        - weights
        output_ports:
        - critic_sum
        - gain_sum
        - learning_condition

    Parameters
    ----------
    features : PointFeatures
        Precomputed point data (:func:`ofrl_drake.bellman.point_features`).
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    nu : float
        Normalization gain of rho.

    Notes
    -----
    ``gain_sum`` is output row-major, flattened to ``L * L``.
    """

    def __init__(
        self, features: PointFeatures, r: np.ndarray, input_bound: float, nu: float
    ) -> None:
        super().__init__()
        self.features = features
        self.r = r
        self.input_bound = input_bound
        self.nu = nu
        self._extrapolator = Extrapolator(features, r, input_bound, nu)
        size = features.drift.shape[0]
        self._weights_port = self.DeclareVectorInputPort("weights", size)
        self._cache = self.DeclareCacheEntry(
            "bellman_extrapolation",
            ValueProducer(
                allocate=AbstractValue.Make(self._extrapolator.empty_sums()).Clone,
                calc=self._calc_extrapolation,
            ),
            prerequisites_of_calc={self._weights_port.ticket()},
        )
        deps = {self._cache.ticket()}
        self._critic_sum_port = self.DeclareVectorOutputPort(
            "critic_sum", size, self._calc_critic_sum, prerequisites_of_calc=deps
        )
        self._gain_sum_port = self.DeclareVectorOutputPort(
            "gain_sum", size * size, self._calc_gain_sum, prerequisites_of_calc=deps
        )
        self._learning_condition_port = self.DeclareVectorOutputPort(
            "learning_condition", 1, self._calc_learning_condition, prerequisites_of_calc=deps
        )

    def get_weights_input_port(self) -> InputPort:
        """Critic weights W (size L)."""
        return self._weights_port

    def get_critic_sum_output_port(self) -> OutputPort:
        """``(1/N) sum omega_i delta_i / rho_i`` (size L)."""
        return self._critic_sum_port

    def get_gain_sum_output_port(self) -> OutputPort:
        """``(1/N) sum omega_i omega_i^T / rho_i^2``, flattened (size L*L)."""
        return self._gain_sum_port

    def get_learning_condition_output_port(self) -> OutputPort:
        """``c = lambda_min(gain_sum)`` (size 1)."""
        return self._learning_condition_port

    def extrapolation(self, context) -> BellmanSums:
        """The cached :class:`~ofrl_drake.bellman.BellmanSums`."""
        return self._cache.Eval(context)

    def _calc_extrapolation(self, context, value) -> None:
        # Each context's cache value owns its arrays (Drake deep-copies the model value).
        self._extrapolator.sums_into(self._weights_port.Eval(context), value.get_mutable_value())

    def _calc_critic_sum(self, context, output) -> None:
        output.SetFromVector(self._cache.Eval(context).critic_sum)

    def _calc_gain_sum(self, context, output) -> None:
        output.SetFromVector(self._cache.Eval(context).gain_sum.ravel())

    def _calc_learning_condition(self, context, output) -> None:
        output.SetAtIndex(0, learning_condition(self._cache.Eval(context).gain_sum))
