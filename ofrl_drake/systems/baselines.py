"""Baseline blocks for ablations: each replaces one slot of the closed loop.

They use the port names of the blocks they replace, so
:func:`~ofrl_drake.build_closed_loop` wires them by name:

* :class:`FullStateObserver` (``observer`` slot): the "estimate" is the true state.
* :class:`LinearizedLuenbergerObserver` (``observer``): Drake's
  ``LuenbergerObserver`` on the linearization at the origin.
* :class:`SaturatedLqrController` (``controller``): Drake's
  ``LinearQuadraticRegulator`` on the linearization, clipped at ``lambda_bar``.
* :class:`ConstantController` (``controller``): the input held at a given value.
* :class:`MovingBellmanExtrapolator` (``bellman``): the Bellman extrapolation at
  points ``xhat + offsets`` that move with the estimate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike
from pydrake.common.value import AbstractValue
from pydrake.systems.controllers import (
    DiscreteTimeLinearQuadraticRegulator,
    LinearQuadraticRegulator,
)
from pydrake.systems.estimators import LuenbergerObserver
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
from pydrake.systems.primitives import (
    ConstantVectorSource,
    LinearSystem,
    Saturation,
)

from ofrl_drake.baselines import linearized_observer_certificate
from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.bellman import (
    BellmanExtrapolation,
    extrapolate,
    features_at,
    learning_condition,
    point_features,
)
from ofrl_drake.checks import (
    array_of_shape,
    finite_vector,
    integer_at_least,
    is_real_number,
    nonnegative_matrix,
    positive_number,
    positive_vector,
    spd_matrix,
)
from ofrl_drake.drake_typing import DrakeArray, drake_array, vector_value
from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem, require_system
from ofrl_drake.observer_certificate import ObserverCertificate

__all__ = [
    "ConstantController",
    "FullStateObserver",
    "LinearizedLuenbergerObserver",
    "LqrResult",
    "MovingBellmanExtrapolator",
    "SaturatedLqrController",
]


class FullStateObserver(LeafSystem):
    """Full-state feedback in the observer slot: ``estimated_state = state``.

    Stateless, with direct feedthrough. The plant's ``state`` output has none,
    so feeding it through to the controller closes no algebraic loop.

    .. pydrake_system::

        name: FullStateObserver
        input_ports:
        - state
        output_ports:
        - estimated_state

    Parameters
    ----------
    num_states : int
        n, the size of the state.

    Raises
    ------
    ModelError
        If ``num_states`` is not an integer >= 1.
    """

    def __init__(self, num_states: int) -> None:
        super().__init__()
        self.num_states = num_states
        n = integer_at_least("FullStateObserver: num_states", num_states, 1)
        self._state_port = self.DeclareVectorInputPort("state", n)
        self._xhat_port = self.DeclareVectorOutputPort(
            "estimated_state",
            n,
            self._calc_estimated_state,
            prerequisites_of_calc={self._state_port.ticket()},
        )

    def get_state_input_port(self) -> InputPort:
        """The true state x (size n)."""
        return self._state_port

    def observer_certificate(self) -> ObserverCertificate:
        """Nothing to certify: the estimate is the state."""
        return ObserverCertificate.none(type(self).__name__)

    def get_estimated_state_output_port(self) -> OutputPort:
        """The "estimate", equal to x (size n)."""
        return self._xhat_port

    def _calc_estimated_state(self, context, output) -> None:
        output.SetFromVector(vector_value(self._state_port, context))


class LinearizedLuenbergerObserver(Diagram):
    """Drake's ``LuenbergerObserver`` on the linearization, with ports ``y, u``.

    The observer runs the linear model ``xhat' = A xhat + B u + L (y - C xhat
    - D u)``; its state is the estimate itself.

    .. pydrake_system::

        name: LinearizedLuenbergerObserver
        input_ports:
        - y
        - u
        output_ports:
        - estimated_state

    Parameters
    ----------
    linearization : LinearSystem
        ``(A, B, C, D)`` of the plant at the origin
        (:func:`ofrl_drake.baselines.linearize_at_origin`).
    gain : array_like, shape (n, q)
        Observer gain L (e.g. :func:`ofrl_drake.baselines.luenberger_gain`).
    alpha : float, optional
        The decay rate the gain is meant to achieve; :meth:`observer_certificate`
        then reports the Lyapunov certificate of the linearized error at that
        rate (:func:`ofrl_drake.baselines.linearized_observer_certificate`).

    Raises
    ------
    ModelError
        If ``gain`` is not a finite array of shape (n, q), the number of
        states by the number of outputs of ``linearization``.

    Notes
    -----
    ``xhat(0)`` is set in a context with :meth:`set_estimated_state` (a run
    does it). Its default is zero: Drake's ``LuenbergerObserver`` declares its
    state with a zero default, and a ``Diagram`` cannot give a subsystem
    another (pydrake binds no ``SetDefaultState`` to override; see
    `LuenbergerObserver <https://drake.mit.edu/doxygen_cxx/classdrake_1_1systems_1_1estimators_1_1_luenberger_observer.html>`_).
    """

    def __init__(
        self,
        linearization: LinearSystem,
        gain: np.ndarray,
        alpha: float | None = None,
    ) -> None:
        super().__init__()
        self.linearization = linearization
        self.gain = gain
        self.alpha = alpha
        # Drake's LuenbergerObserver would abort the process on a wrong shape (an assertion).
        array_of_shape(
            "LinearizedLuenbergerObserver: gain",
            gain,
            (linearization.num_states(), linearization.num_outputs()),
            meaning="(n, q)",
            fix=", n states by q outputs of the linearization; build it with "
            "ofrl_drake.baselines.luenberger_gain(A, C, poles)",
        )
        builder = DiagramBuilder()
        observer = LuenbergerObserver(
            linearization, linearization.CreateDefaultContext(), drake_array(gain)
        )
        builder.AddNamedSystem("luenberger", observer)
        self._observer = observer
        y_index = builder.ExportInput(observer.get_observed_system_output_input_port(), "y")
        u_index = builder.ExportInput(observer.get_observed_system_input_input_port(), "u")
        xhat_index = builder.ExportOutput(
            observer.get_estimated_state_output_port(), "estimated_state"
        )
        builder.BuildInto(self)
        self._y_port = self.get_input_port(int(y_index))
        self._u_port = self.get_input_port(int(u_index))
        self._xhat_port = self.get_output_port(int(xhat_index))

    def set_estimated_state(self, context: Context, xhat: ArrayLike) -> None:
        """Set the estimate to ``xhat`` in ``context``, this block's own context."""
        A: DrakeArray = self.linearization.A()
        value: DrakeArray = finite_vector("LinearizedLuenbergerObserver: xhat", xhat, A.shape[0])
        self.GetMutableSubsystemContext(self._observer, context).SetContinuousState(value)

    def get_y_input_port(self) -> InputPort:
        """The measurement ``y`` (size q)."""
        return self._y_port

    def get_u_input_port(self) -> InputPort:
        """The applied input ``u`` (size m)."""
        return self._u_port

    def get_estimated_state_output_port(self) -> OutputPort:
        """The estimate ``xhat`` (size n)."""
        return self._xhat_port

    def observer_certificate(self) -> ObserverCertificate:
        """Kind ``"local"``: the linearized error's certificate at ``alpha``, no box."""
        A: DrakeArray = self.linearization.A()
        C: DrakeArray = self.linearization.C()
        design = (
            None
            if self.alpha is None
            else linearized_observer_certificate(A, C, self.gain, self.alpha).to_dict()
        )
        return ObserverCertificate(
            "local",
            design=design,
            note=(
                f"observer {type(self).__name__} runs the linearization: its gain has a local "
                "certificate (observer_design) for the linear error dynamics only, and no box; "
                "only |u_k| <= lambda_bar was checked"
            ),
        )


@dataclass(frozen=True)
class LqrResult:
    """The LQR solution a :class:`SaturatedLqrController` acts on.

    Attributes
    ----------
    K : ndarray, shape (m, n)
        The gain: the unclipped input is ``u = -K xhat``.
    S : ndarray, shape (n, n)
        The solution of the Riccati equation: ``x^T S x`` is the cost-to-go of
        the linearization.
    """

    K: np.ndarray
    S: np.ndarray


def _input_weight(R: ArrayLike, m: int) -> ArrayLike:
    """``R`` as a matrix: a number, or a vector of one entry, is ``[[R]]`` when ``m = 1``."""
    if is_real_number(R):
        return np.array([[R]], dtype=float)
    if m == 1 and np.ndim(R) == 1 and np.size(R) == 1:
        return np.reshape(R, (1, 1))
    return R


class SaturatedLqrController(Diagram):
    """Drake's ``LinearQuadraticRegulator`` on the linearization, clipped at lbar.

    ``u = clip(-K xhat, -lbar, lbar)`` with ``K`` the LQR gain of
    ``(A, B, Q, R)`` (:meth:`lqr_result`), a Drake ``LinearSystem`` followed by
    a ``Saturation``. The gain block is the one Drake's
    ``LinearQuadraticRegulator(system, Q, R)`` builds, from the solution of
    ``LinearQuadraticRegulator(A, B, Q, R)`` (its discrete-time counterpart
    for a discrete ``linearization``), solved once here.
    Near the origin ``U(u) ~ r u^2``, so ``R = diag(r)`` is the quadratic part of
    the scenario's input cost.

    .. pydrake_system::

        name: SaturatedLqrController
        input_ports:
        - estimated_state
        output_ports:
        - u

    Parameters
    ----------
    linearization : LinearSystem
        ``(A, B)`` of the plant at the origin.
    Q : array_like, shape (n, n)
        State weight, symmetric positive semidefinite.
    R : array_like, shape (m, m)
        Input weight, symmetric positive definite (a number, or a vector of
        one entry, if m = 1).
    input_bound : float
        lbar > 0.

    Raises
    ------
    ModelError
        If ``Q`` is not a finite symmetric positive semidefinite (n, n)
        matrix, ``R`` not a finite symmetric positive definite (m, m) matrix,
        or ``input_bound`` not a finite number > 0.
    """

    def __init__(
        self, linearization: LinearSystem, Q: np.ndarray, R: np.ndarray, input_bound: float
    ) -> None:
        super().__init__()
        self.linearization = linearization
        self.Q = Q
        self.R = R
        self.input_bound = input_bound
        A: DrakeArray = linearization.A()
        B: DrakeArray = linearization.B()
        n, m = B.shape
        Q_arr = nonnegative_matrix("SaturatedLqrController: Q", Q, n)
        R_arr = spd_matrix("SaturatedLqrController: R", _input_weight(R, m), m)
        bound = positive_number("SaturatedLqrController: input_bound", input_bound)
        period = linearization.time_period()
        solve = LinearQuadraticRegulator if period == 0 else DiscreteTimeLinearQuadraticRegulator
        K, S = solve(A, B, drake_array(Q_arr), drake_array(R_arr))
        self._lqr_result = LqrResult(K=np.asarray(K, dtype=float), S=np.asarray(S, dtype=float))
        builder = DiagramBuilder()
        # u = -K x, as Drake's LinearQuadraticRegulator(system, Q, R) returns it.
        gain = LinearSystem(
            drake_array(np.zeros((0, 0))),
            drake_array(np.zeros((0, n))),
            drake_array(np.zeros((m, 0))),
            drake_array(-self._lqr_result.K),
            period,
        )
        builder.AddNamedSystem("lqr", gain)
        saturation = builder.AddNamedSystem(
            "saturation",
            Saturation(drake_array(-bound * np.ones(m)), drake_array(bound * np.ones(m))),
        )
        builder.Connect(gain.get_output_port(), saturation.get_input_port())
        xhat_index = builder.ExportInput(gain.get_input_port(), "estimated_state")
        u_index = builder.ExportOutput(saturation.get_output_port(), "u")
        builder.BuildInto(self)
        self._xhat_port = self.get_input_port(int(xhat_index))
        self._u_port = self.get_output_port(int(u_index))

    def lqr_result(self) -> LqrResult:
        """The LQR gain ``K`` and Riccati solution ``S`` of ``(A, B, Q, R)``."""
        return self._lqr_result

    @property
    def K(self) -> np.ndarray:
        """The LQR gain, ``lqr_result().K`` (shape ``(m, n)``)."""
        return self._lqr_result.K

    def get_estimated_state_input_port(self) -> InputPort:
        """The state estimate xhat (size n)."""
        return self._xhat_port

    def get_u_output_port(self) -> OutputPort:
        """The clipped input u (size m)."""
        return self._u_port


class ConstantController(Diagram):
    """The input held at ``value``: Drake's ``ConstantVectorSource``, exported as ``u``.

    No inputs, so it ignores the estimate; useful to hold the plant at an
    equilibrium while the observer runs, and as an open-loop ablation.

    .. pydrake_system::

        name: ConstantController
        output_ports:
        - u

    Parameters
    ----------
    value : array_like, shape (m,)
        The input, finite.

    Raises
    ------
    ModelError
        If ``value`` is empty or not finite.
    """

    def __init__(self, value: Sequence[float]) -> None:
        super().__init__()
        self.value = value
        u: DrakeArray = np.atleast_1d(np.asarray(value, dtype=float))
        if u.ndim != 1 or u.size == 0 or not np.all(np.isfinite(u)):
            raise ModelError(f"value must be a non-empty finite vector; got {value!r}.")
        builder = DiagramBuilder()
        source = builder.AddNamedSystem("constant", ConstantVectorSource(u))
        u_index = builder.ExportOutput(source.get_output_port(), "u")
        builder.BuildInto(self)
        self._u_port = self.get_output_port(int(u_index))

    def get_u_output_port(self) -> OutputPort:
        """The held input u (size m)."""
        return self._u_port


class MovingBellmanExtrapolator(LeafSystem):
    """Bellman errors at N points ``xhat + offsets`` that move with the estimate.

    Like :class:`~ofrl_drake.systems.BellmanExtrapolator`, but the point
    features are recomputed at every evaluation, for all N points at once
    (:func:`~ofrl_drake.bellman.point_features`, no loop over points, so the
    model's ``f`` and ``g`` must accept batches). One cache
    entry, depending on both inputs, feeds the three outputs.

    .. pydrake_system::

        name: MovingBellmanExtrapolator
        input_ports:
        - weights
        - policy_weights
        - estimated_state
        output_ports:
        - critic_sum
        - gain_sum
        - learning_condition

    Parameters
    ----------
    system : ControlAffineSystem
    basis : PolynomialBasis
    offsets : array_like, shape (n, N)
        Point offsets from the estimate
        (:func:`ofrl_drake.baselines.point_offsets`).
    Q : array_like, shape (n, n)
        State weight.
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar.
    nu : float
        The default normalization gain of rho, a numeric parameter of the
        context (:meth:`set_nu`).
    metric : array_like, shape (L,), optional
        Diagonal of the metric of rho (default ones, the paper's).

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`~ofrl_drake.model.ControlAffineSystem`,
        ``offsets`` is not of shape (n, N), ``r`` is not m finite numbers
        > 0, ``input_bound`` or ``nu`` is not a finite number > 0, or
        ``system`` is not :attr:`~ofrl_drake.model.ControlAffineSystem.vectorized`
        (each evaluation would loop over the points in Python).

    Notes
    -----
    ``gain_sum`` is output row-major, flattened to ``L * L``.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        basis: PolynomialBasis,
        offsets: np.ndarray,
        Q: np.ndarray,
        r: np.ndarray,
        input_bound: float,
        nu: float,
        metric: np.ndarray | None = None,
    ) -> None:
        super().__init__()
        self.system = system
        self.basis = basis
        self.offsets = offsets
        self.Q = Q
        self.r = r
        self.input_bound = input_bound
        self.nu = nu
        self.metric = metric
        require_system(system, "MovingBellmanExtrapolator: system")
        self._offsets = np.asarray(offsets, dtype=float)
        if self._offsets.ndim != 2 or self._offsets.shape[0] != system.n:
            raise ModelError(
                f"offsets must have shape (n, N) = ({system.n}, N); got {self._offsets.shape}."
            )
        system.require_vectorized("MovingBellmanExtrapolator")
        self._Q = np.asarray(Q, dtype=float)
        # The system, basis, offsets and Q checked once here (at xhat = 0), so
        # that each evaluation computes its features without re-checking them.
        point_features(system, basis, self._offsets, self._Q)
        self._r = positive_vector("MovingBellmanExtrapolator: r", r, system.m)
        positive_number("MovingBellmanExtrapolator: input_bound", input_bound)
        positive_number("MovingBellmanExtrapolator: nu", nu)
        size = basis.size
        self._nu_index = self.DeclareNumericParameter(BasicVector(drake_array([float(nu)])))
        self._weights_port = self.DeclareVectorInputPort("weights", size)
        self._policy_port = self.DeclareVectorInputPort("policy_weights", size)
        self._xhat_port = self.DeclareVectorInputPort("estimated_state", system.n)
        self._cache = self.DeclareCacheEntry(
            "bellman_extrapolation",
            ValueProducer(
                allocate=AbstractValue.Make(object()).Clone,
                calc=self._calc_extrapolation,
            ),
            prerequisites_of_calc={
                self._weights_port.ticket(),
                self._policy_port.ticket(),
                self._xhat_port.ticket(),
                self.numeric_parameter_ticket(NumericParameterIndex(self._nu_index)),
            },
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

    def get_policy_weights_input_port(self) -> InputPort:
        """Weights of the policy the Bellman errors follow (size L)."""
        return self._policy_port

    def get_estimated_state_input_port(self) -> InputPort:
        """The estimate xhat the points move with (size n)."""
        return self._xhat_port

    def get_critic_sum_output_port(self) -> OutputPort:
        """``(1/N) sum omega_i delta_i / rho_i`` (size L)."""
        return self._critic_sum_port

    def get_gain_sum_output_port(self) -> OutputPort:
        """``(1/N) sum omega_i omega_i^T / rho_i^2``, flattened (size L*L)."""
        return self._gain_sum_port

    def get_learning_condition_output_port(self) -> OutputPort:
        """``c = lambda_min(gain_sum)`` (size 1)."""
        return self._learning_condition_port

    def extrapolation(self, context: Context) -> BellmanExtrapolation:
        """The cached :class:`~ofrl_drake.bellman.BellmanExtrapolation`."""
        return cast(BellmanExtrapolation, self._cache.Eval(context))

    def get_nu(self, context: Context) -> float:
        """The normalization gain in ``context`` (this block's own)."""
        return context.get_numeric_parameter(self._nu_index).GetAtIndex(0)

    def set_nu(self, context: Context, nu: float) -> None:
        """Set the normalization gain ``nu > 0`` in ``context`` (this block's own)."""
        value = positive_number("MovingBellmanExtrapolator: nu", nu)
        context.get_mutable_numeric_parameter(self._nu_index).SetAtIndex(0, value)

    def _calc_extrapolation(self, context, value) -> None:
        W = vector_value(self._weights_port, context)
        xhat = vector_value(self._xhat_port, context)
        if not np.all(np.isfinite(xhat)):
            # A diverged estimate is the run's outcome, for the run guard to
            # report, not bad input: NaN sums, as the arithmetic would give.
            value.set_value(self._undefined())
            return
        features = features_at(self.system, self.basis, xhat[:, None] + self._offsets, self._Q)
        value.set_value(
            extrapolate(
                features,
                W,
                self._r,
                self.input_bound,
                self.get_nu(context),
                W_policy=vector_value(self._policy_port, context),
                metric=self.metric,
            )
        )

    def _undefined(self) -> BellmanExtrapolation:
        """Every field NaN: the extrapolation at a non-finite estimate."""
        L, N, m = self.basis.size, self._offsets.shape[1], self.system.m
        return BellmanExtrapolation(
            critic_sum=np.full(L, np.nan),
            gain_sum=np.full((L, L), np.nan),
            D=np.full((m, N), np.nan),
            u=np.full((m, N), np.nan),
            omega=np.full((L, N), np.nan),
            delta=np.full(N, np.nan),
            rho=np.full(N, np.nan),
        )

    def _calc_critic_sum(self, context, output) -> None:
        output.SetFromVector(self.extrapolation(context).critic_sum)

    def _calc_gain_sum(self, context, output) -> None:
        output.SetFromVector(self.extrapolation(context).gain_sum.ravel())

    def _calc_learning_condition(self, context, output) -> None:
        output.SetAtIndex(0, learning_condition(self.extrapolation(context).gain_sum))
