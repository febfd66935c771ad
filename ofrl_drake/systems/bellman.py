"""The stateless Bellman-extrapolation block shared by the critic and Gamma."""

from __future__ import annotations

from typing import cast

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import (
    BasicVector,
    Context,
    Diagram,
    DiagramBuilder,
    InputPort,
    LeafSystem,
    NumericParameterIndex,
    OutputPort,
    ValueProducer,
)
from pydrake.systems.primitives import Demultiplexer

from ofrl_drake.bellman import BellmanSums, Extrapolator, PointFeatures, learning_condition
from ofrl_drake.checks import positive_number
from ofrl_drake.drake_typing import drake_array, vector_reader, vector_value

__all__ = ["BellmanExtrapolator"]


class _HeldExtrapolator:
    """The :class:`~ofrl_drake.bellman.Extrapolator` in a context's cache entry.

    A cloned context shares the extrapolator instead of deep-copying its point
    data (its only mutable part is a scratch array, used within one compiled
    call that holds the GIL); the holder itself is the clone's own.
    """

    __slots__ = ("extrapolator",)

    def __init__(self, extrapolator: Extrapolator) -> None:
        self.extrapolator = extrapolator

    def __deepcopy__(self, memo: dict[int, object]) -> _HeldExtrapolator:
        return _HeldExtrapolator(self.extrapolator)


class _StackedSums(LeafSystem):
    """Both sums in one vector ``[critic_sum; vec(gain_sum)]``, one compiled call each.

    The kernel writes straight into the output, so a derivative evaluation
    makes one Python call here and allocates nothing. ``nu`` is a numeric
    parameter: the :class:`~ofrl_drake.bellman.Extrapolator` of the default
    ``nu`` is kept by the block, that of a context's ``nu`` in a cache entry of
    the context (recomputed only when its ``nu`` changes), so no calc writes to
    the block.
    """

    def __init__(self, extrapolator: Extrapolator, size: int) -> None:
        super().__init__()
        self.extrapolator = extrapolator
        self._size = size
        self._nu_index = self.DeclareNumericParameter(BasicVector(drake_array([extrapolator.nu])))
        nu_ticket = self.numeric_parameter_ticket(NumericParameterIndex(self._nu_index))
        self._extrapolator_cache = self.DeclareCacheEntry(
            "extrapolator at the context's nu",
            ValueProducer(
                allocate=lambda: AbstractValue.Make(_HeldExtrapolator(extrapolator)),
                calc=self._calc_extrapolator,
            ),
            {nu_ticket},
        )
        self._weights_port = self.DeclareVectorInputPort("weights", size)
        self._policy_port = self.DeclareVectorInputPort("policy_weights", size)
        self._weights_value = vector_reader(self._weights_port)
        self._policy_value = vector_reader(self._policy_port)
        inputs = {self._weights_port.ticket(), self._policy_port.ticket(), nu_ticket}
        self._sums_port = self.DeclareVectorOutputPort(
            "sums", size + size * size, self._calc_sums, prerequisites_of_calc=inputs
        )
        self._learning_condition_port = self.DeclareVectorOutputPort(
            "learning_condition",
            1,
            self._calc_learning_condition,
            prerequisites_of_calc=inputs,
        )

    def get_weights_input_port(self) -> InputPort:
        """Critic weights W (size L)."""
        return self._weights_port

    def get_policy_weights_input_port(self) -> InputPort:
        """Weights of the policy the Bellman errors follow (size L)."""
        return self._policy_port

    def get_sums_output_port(self) -> OutputPort:
        """``[critic_sum; vec(gain_sum)]`` (size L + L*L)."""
        return self._sums_port

    def get_learning_condition_output_port(self) -> OutputPort:
        """``c = lambda_min(gain_sum)`` (size 1)."""
        return self._learning_condition_port

    def nu(self, context: Context) -> float:
        """The normalization gain in ``context`` (this block's own)."""
        return context.get_numeric_parameter(self._nu_index).GetAtIndex(0)

    def set_nu(self, context: Context, nu: float) -> None:
        """Set the normalization gain ``nu > 0`` in ``context`` (this block's own)."""
        value = positive_number("BellmanExtrapolator: nu", nu)
        context.get_mutable_numeric_parameter(self._nu_index).SetAtIndex(0, value)

    def extrapolator_for(self, nu: float) -> Extrapolator:
        """The :class:`~ofrl_drake.bellman.Extrapolator` of this block's points at ``nu``.

        The block's own at its default ``nu``, else a new one; the block is not
        changed (a context keeps its own in :meth:`extrapolator_in`).
        """
        e = self.extrapolator
        if nu == e.nu:
            return e
        return Extrapolator(e.features, e.r, e.input_bound, nu, e.metric)

    def extrapolator_in(self, context: Context) -> Extrapolator:
        """The extrapolator at the ``nu`` of ``context`` (this block's own), from its cache."""
        return cast(_HeldExtrapolator, self._extrapolator_cache.Eval(context)).extrapolator

    def _calc_extrapolator(self, context, value) -> None:
        nu = context.get_numeric_parameter(self._nu_index).GetAtIndex(0)
        value.set_value(_HeldExtrapolator(self.extrapolator_for(nu)))

    def _calc_sums(self, context, output) -> None:
        L = self._size
        value = output.get_mutable_value()
        self.extrapolator_in(context).sums_into(
            self._weights_value(context),
            value[:L],
            value[L:].reshape(L, L),
            self._policy_value(context),
        )

    def _calc_learning_condition(self, context, output) -> None:
        L = self._size
        sums = vector_value(self._sums_port, context)
        output.SetAtIndex(0, learning_condition(sums[L:].reshape(L, L)))


class BellmanExtrapolator(Diagram):
    """Bellman errors at N fixed points, computed once per evaluation.

    The errors ``delta_i = W^T omega_i + Q(x_i) + U(u_i)`` take the value's
    weights ``W`` from ``weights`` and the policy ``u_i`` (hence ``omega_i``)
    from ``policy_weights``: the paper's law feeds the same weights to both,
    policy iteration the policy in force.

    One Python block computes both sums for the current weights in one
    compiled pass over the points, as one vector; Drake's ``Demultiplexer``
    splits it into the two outputs in C++. The critic and Gamma laws thus
    share one computation, and one Python call, per derivative evaluation.

    .. pydrake_system::

        name: BellmanExtrapolator
        input_ports:
        - weights
        - policy_weights
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
        The default normalization gain of rho: a numeric parameter of the
        context (:meth:`set_nu`), so a sweep over it needs no rebuild.
    metric : array_like, shape (L,), optional
        Diagonal of the metric of rho (default ones, the paper's; see
        :class:`~ofrl_drake.bellman.Extrapolator`).

    Raises
    ------
    ModelError
        If ``r`` is not m finite numbers > 0, ``input_bound`` or ``nu`` is not
        a finite number > 0, or ``metric`` is not L finite numbers > 0
        (checked by :class:`~ofrl_drake.bellman.Extrapolator`).

    Notes
    -----
    ``gain_sum`` is output row-major, flattened to ``L * L``.
    """

    def __init__(
        self,
        features: PointFeatures,
        r: np.ndarray,
        input_bound: float,
        nu: float,
        metric: np.ndarray | None = None,
    ) -> None:
        super().__init__()
        self.features = features
        self.r = r
        self.input_bound = input_bound
        self.nu = nu
        self.metric = metric
        size = features.drift.shape[0]
        builder = DiagramBuilder()
        sums = _StackedSums(Extrapolator(features, r, input_bound, nu, metric), size)
        builder.AddNamedSystem("sums", sums)
        split = builder.AddNamedSystem("split_sums", Demultiplexer([size, size * size]))
        builder.Connect(sums.get_sums_output_port(), split.get_input_port())
        weights = builder.ExportInput(sums.get_weights_input_port(), "weights")
        policy = builder.ExportInput(sums.get_policy_weights_input_port(), "policy_weights")
        critic_sum = builder.ExportOutput(split.GetOutputPort("y0"), "critic_sum")
        gain_sum = builder.ExportOutput(split.GetOutputPort("y1"), "gain_sum")
        condition = builder.ExportOutput(
            sums.get_learning_condition_output_port(), "learning_condition"
        )
        builder.BuildInto(self)
        self._sums = sums
        self._size = size
        self._weights_port = self.get_input_port(int(weights))
        self._policy_port = self.get_input_port(int(policy))
        self._critic_sum_port = self.get_output_port(int(critic_sum))
        self._gain_sum_port = self.get_output_port(int(gain_sum))
        self._learning_condition_port = self.get_output_port(int(condition))

    def get_weights_input_port(self) -> InputPort:
        """Critic weights W (size L)."""
        return self._weights_port

    def get_policy_weights_input_port(self) -> InputPort:
        """Weights of the policy the Bellman errors follow (size L)."""
        return self._policy_port

    def get_critic_sum_output_port(self) -> OutputPort:
        """``(1/N) sum omega_i delta_i / rho_i`` (size L)."""
        return self._critic_sum_port

    def get_gain_sum_output_port(self) -> OutputPort:
        """``(1/N) sum omega_i omega_i^T / rho_i^2``, flattened (size L*L)."""
        return self._gain_sum_port

    def get_learning_condition_output_port(self) -> OutputPort:
        """``c = lambda_min(gain_sum)`` (size 1)."""
        return self._learning_condition_port

    def set_nu(self, context: Context, nu: float) -> None:
        """Set the normalization gain ``nu > 0`` in ``context`` (this block's own)."""
        self._sums.set_nu(self.GetMutableSubsystemContext(self._sums, context), nu)

    def get_nu(self, context: Context) -> float:
        """The normalization gain in ``context`` (this block's own)."""
        return self._sums.nu(self.GetSubsystemContext(self._sums, context))

    def learning_condition_of(
        self, weights: np.ndarray, context: Context | None = None
    ) -> np.ndarray:
        """The ``learning_condition`` output for many policy weights, ``(T, L)`` -> ``(T,)``.

        The same values as the port, in one compiled call: what the simulation
        uses for its logs after the run, instead of evaluating the port at every
        publish (where the sums' cache is always stale: an integrator marks the
        state changed at the start of each step). At the ``nu`` of ``context``
        (this block's own; the default ``nu`` without one).
        """
        if context is None:
            return self._sums.extrapolator.learning_conditions(weights)
        sums_context = self.GetSubsystemContext(self._sums, context)
        return self._sums.extrapolator_in(sums_context).learning_conditions(weights)

    def extrapolation(self, context: Context) -> BellmanSums:
        """The two sums in ``context`` (this block's own), as :class:`BellmanSums`."""
        L = self._size
        stacked = vector_value(
            self._sums.get_sums_output_port(), self.GetSubsystemContext(self._sums, context)
        )
        return BellmanSums(stacked[:L].copy(), stacked[L:].reshape(L, L).copy())
