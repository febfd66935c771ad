"""The policy slot: which critic weights the controller acts on."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from pydrake.systems.framework import (
    BasicVector,
    Context,
    Diagram,
    DiagramBuilder,
    DiscreteValues,
    InputPort,
    LeafSystem,
    OutputPort,
)
from pydrake.systems.primitives import PassThrough

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.checks import (
    array_of_shape,
    finite_vector,
    integer_at_least,
    nonnegative_matrix,
    positive_number,
    positive_vector,
)
from ofrl_drake.drake_typing import DrakeArray, drake_array, vector_value
from ofrl_drake.learning import PolicyCheck, check_policy, second_moment

__all__ = ["PolicyGate", "PolicyPassThrough"]


class PolicyGate(LeafSystem):
    """Policy iteration's improvement step, guarded by an acceptance test.

    Holds the policy in force ``W_pi`` as discrete state. Every ``period``
    seconds (first at ``t = period``) it reads the critic's weights and puts
    them in force if they pass the acceptance test of
    :mod:`ofrl_drake.learning` (the value's quadratic part is positive
    definite, the value is positive at every point but the origin, the
    linearized loop of its policy is Hurwitz, and its local cost over the
    points is no larger than the policy in force's:
    :meth:`~ofrl_drake.learning.PolicyCheck.improves_on`); otherwise ``W_pi``
    is kept and the rejection counted.

    .. pydrake_system::

        name: PolicyGate
        input_ports:
        - weights
        output_ports:
        - policy_weights
        - policy_updates

    ``policy_updates`` is ``[accepted, rejected]``, the counts so far.

    Parameters
    ----------
    initial_weights : array_like, shape (L,)
        The default policy in force at ``t = 0``; a run writes its own
        (:meth:`set_policy_weights`).
    period : float
        Seconds between improvement steps, > 0.
    A, B : array_like, shapes (n, n) and (n, m)
        The plant's linearization at the target, ``x' = A x + B u``.
    Q : array_like, shape (n, n)
        State weight, symmetric positive semidefinite.
    r : array_like, shape (m,)
        Diagonal of R, entries > 0.
    basis : PolynomialBasis
        The critic's basis, over n = ``basis.n`` states.
    points : array_like, shape (n, N)
        The extrapolation points, whose second moment weighs the local cost
        and where the value must be positive.

    Raises
    ------
    ModelError
        If ``initial_weights`` is not a finite vector of the basis' size,
        ``period`` is not a positive number, ``r`` is not m finite numbers
        > 0, ``A``, ``B`` or ``points`` is not a finite array of shape
        (n, n), (n, m) or (n, N) with N >= 1, or ``Q`` is not a finite
        symmetric positive semidefinite (n, n) matrix. Each message starts
        with ``"PolicyGate: <argument>"``.
    """

    def __init__(
        self,
        initial_weights: Sequence[float],
        period: float,
        A: np.ndarray,
        B: np.ndarray,
        Q: np.ndarray,
        r: np.ndarray,
        basis: PolynomialBasis,
        points: np.ndarray,
    ) -> None:
        super().__init__()
        self.initial_weights = initial_weights
        self.period = period
        self.A = A
        self.B = B
        self.Q = Q
        self.r = r
        self.basis = basis
        self.points = points
        W0: DrakeArray = finite_vector(
            "PolicyGate: initial_weights", initial_weights, size=basis.size
        )
        positive_number("PolicyGate: period", period)
        n = basis.n
        self._r = positive_vector("PolicyGate: r", r)
        m = self._r.size
        self._A = array_of_shape("PolicyGate: A", A, (n, n), meaning="(n, n)")
        self._B = array_of_shape("PolicyGate: B", B, (n, m), meaning="(n, m)")
        self._Q = nonnegative_matrix("PolicyGate: Q", Q, n)
        self._points = array_of_shape("PolicyGate: points", points, (n, None), meaning="(n, N)")
        self._moment = second_moment(self._points)
        size = basis.size
        self._policy_index = self.DeclareDiscreteState(BasicVector(W0))
        self._updates_index = self.DeclareDiscreteState(BasicVector(drake_array([0.0, 0.0])))
        self._weights_port = self.DeclareVectorInputPort("weights", size)
        self._policy_port = self.DeclareStateOutputPort("policy_weights", self._policy_index)
        self._updates_port = self.DeclareStateOutputPort("policy_updates", self._updates_index)
        self.DeclarePeriodicDiscreteUpdateEvent(
            period_sec=float(period), offset_sec=float(period), update=self._improve
        )

    def get_weights_input_port(self) -> InputPort:
        """The critic's weights W (size L)."""
        return self._weights_port

    def get_policy_weights_output_port(self) -> OutputPort:
        """The weights of the policy in force (size L)."""
        return self._policy_port

    def get_policy_updates_output_port(self) -> OutputPort:
        """``[accepted, rejected]``: improvement steps so far (size 2)."""
        return self._updates_port

    def set_policy_weights(self, context: Context, W: ArrayLike) -> None:
        """Put the policy of weights ``W`` in force in ``context``, this block's own context."""
        value: DrakeArray = finite_vector("PolicyGate: W", W, size=self.basis.size)
        context.get_mutable_discrete_state(int(self._policy_index)).SetFromVector(value)

    def check(self, W: np.ndarray) -> PolicyCheck:
        """What the acceptance test reads off weights ``W``."""
        return check_policy(
            self._A, self._B, self._Q, self._r, self.basis, W, self._moment, points=self._points
        )

    def _improve(self, context: Context, discrete_state: DiscreteValues) -> None:
        W: DrakeArray = np.array(vector_value(self._weights_port, context), dtype=float)
        in_force: DrakeArray = context.get_discrete_state(int(self._policy_index)).CopyToVector()
        counts = discrete_state.get_mutable_vector(int(self._updates_index))
        if self.check(W).improves_on(self.check(in_force)):
            discrete_state.get_mutable_vector(int(self._policy_index)).SetFromVector(W)
            counts.SetAtIndex(0, counts.GetAtIndex(0) + 1.0)
        else:
            counts.SetAtIndex(1, counts.GetAtIndex(1) + 1.0)


class PolicyPassThrough(Diagram):
    """The paper's law: the controller acts on the critic's own weights, ``W_pi = W``.

    Drake's ``PassThrough`` (C++, direct feedthrough) under this slot's port
    names, so it costs no Python call.

    .. pydrake_system::

        name: PolicyPassThrough
        input_ports:
        - weights
        output_ports:
        - policy_weights

    Parameters
    ----------
    size : int
        L, the number of weights.

    Raises
    ------
    ModelError
        If ``size`` is not an integer >= 1.
    """

    def __init__(self, size: int) -> None:
        super().__init__()
        self.size = size
        L = integer_at_least("PolicyPassThrough: size", size, 1)
        builder = DiagramBuilder()
        through = builder.AddNamedSystem("pass_through", PassThrough(L))
        weights_index = builder.ExportInput(through.get_input_port(), "weights")
        policy_index = builder.ExportOutput(through.get_output_port(), "policy_weights")
        builder.BuildInto(self)
        self._weights_port = self.get_input_port(int(weights_index))
        self._policy_port = self.get_output_port(int(policy_index))

    def get_weights_input_port(self) -> InputPort:
        """The critic's weights W (size L)."""
        return self._weights_port

    def get_policy_weights_output_port(self) -> OutputPort:
        """The same weights (size L)."""
        return self._policy_port
