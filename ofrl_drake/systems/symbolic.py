"""The plant, observer, controller and running cost as Drake C++ systems.

When the model's ``f`` and ``g`` can be traced on ``pydrake.symbolic`` states
(:meth:`~ofrl_drake.model.ControlAffineSystem.symbolic`), the three blocks
that evaluate them and the running cost are built from Drake's
``SymbolicVectorSystem``: their right-hand sides are
expressions that Drake evaluates in C++, with no Python callback per
derivative evaluation, and they convert to ``AutoDiffXd`` (for
``Linearize``, for example). Each is a small ``Diagram`` with the ports of
the Python block of its slot, like :class:`~ofrl_drake.systems.DrakePlant`:

* a ``Multiplexer`` stacks a block's input ports into the one input of its
  ``SymbolicVectorSystem``;
* the plant's and the observer's state is x (xhat) itself, set in a context
  with ``set_state`` (``set_estimated_state``), as a run does. Its default is
  zero: a ``SymbolicVectorSystem`` declares its state with a zero default
  (`symbolic_vector_system.cc
  <https://github.com/RobotLocomotion/drake/blob/v1.51.0/systems/primitives/symbolic_vector_system.cc>`_,
  ``DeclareContinuousState(state_vars_.size())``) and neither it nor a
  ``Diagram`` around it lets Python set another (pydrake binds no
  ``SetDefaultState`` to override);
* Drake 1.51's ``SymbolicVectorSystem`` aborts when a continuous ``Diagram``
  asks a stateless one for its derivatives (``symbolic_vector_system.cc``:
  ``DRAKE_DEMAND(dynamics_.size() > 0)``), so the controller carries one
  state that stays at zero. The integrator's error estimate of it is zero.

The critic stays the Python :class:`~ofrl_drake.systems.CriticWeights`: its
law ``W' = -k_c Gamma critic_sum`` is linear algebra over ``L**2 + 2 L``
variables, where a ``SymbolicVectorSystem`` (which copies its variable
environment and walks each expression per call) measured as fast at L = 3
and slower from L = 4 on: at L = 10, 13.6 us per derivative against 2.6 us
(``benchmarks/RESULTS.md``).

The math is the one of the Python blocks
(:func:`~ofrl_drake.observer.observer_rhs_expression`,
:func:`~ofrl_drake.policy.policy_expression`,
:func:`~ofrl_drake.cost.stage_cost_expression`), tested against their
compiled kernels. One difference: the running cost clips an input beyond the
bound where :class:`~ofrl_drake.systems.RunningCost` raises.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike
from pydrake.symbolic import MakeVectorVariable
from pydrake.systems.framework import (
    Context,
    Diagram,
    DiagramBuilder,
    InputPort,
    InputPortIndex,
    OutputPort,
)
from pydrake.systems.primitives import MatrixGain, Multiplexer, SymbolicVectorSystem

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.cost import check_cost_arguments, stage_cost_expression
from ofrl_drake.drake_typing import DrakeArray, SymbolicArray, set_state_vector
from ofrl_drake.model import ControlAffineSystem, require_system
from ofrl_drake.observer import (
    ObserverGains,
    observer_rhs_expression,
    require_observer_arguments,
)
from ofrl_drake.observer_certificate import ObserverCertificate
from ofrl_drake.policy import check_policy_arguments, policy_expression

if TYPE_CHECKING:  # annotations only
    from ofrl_drake.design import ObserverDesign

__all__ = [
    "SymbolicController",
    "SymbolicObserver",
    "SymbolicPlant",
    "SymbolicRunningCost",
]


def _add_symbolic_system(
    builder: DiagramBuilder,
    name: str,
    inputs: Sequence[tuple[str, SymbolicArray]],
    *,
    state: SymbolicArray,
    dynamics: Any,
    output: Any,
) -> tuple[SymbolicVectorSystem, list[InputPortIndex]]:
    """Add a ``SymbolicVectorSystem`` and export its inputs as the named ports.

    ``inputs`` is ``(port name, variables)`` in order; several ports are
    stacked into the system's one input by a ``Multiplexer``. Returns the
    system and the indices of the exported inputs, in the order of ``inputs``.
    """
    system = SymbolicVectorSystem(
        state=state,
        input=np.concatenate([variables for _, variables in inputs]),
        dynamics=dynamics,
        output=output,
    )
    builder.AddNamedSystem(name, system)
    if len(inputs) == 1:
        return system, [builder.ExportInput(system.get_input_port(), inputs[0][0])]
    mux = builder.AddNamedSystem("stack_inputs", Multiplexer([v.size for _, v in inputs]))
    builder.Connect(mux.get_output_port(), system.get_input_port())
    indices = [
        builder.ExportInput(mux.GetInputPort(f"u{i}"), port) for i, (port, _) in enumerate(inputs)
    ]
    return system, indices


class SymbolicPlant(Diagram):
    """``x' = f(x) + g(x) u``, ``y = C x`` evaluated by Drake in C++.

    .. pydrake_system::

        name: SymbolicPlant
        input_ports:
        - u
        output_ports:
        - y
        - state

    Parameters
    ----------
    system : ControlAffineSystem
        The model; ``system.symbolic()`` must succeed.

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`ControlAffineSystem`, or its ``f`` or
        ``g`` cannot be traced symbolically.

    Notes
    -----
    The state starts at zero in a default context; set x(0) with
    :meth:`set_state` (see the module docstring).

    See Also
    --------
    ofrl_drake.systems.ControlAffinePlant : the same block in Python.
    """

    def __init__(self, system: ControlAffineSystem) -> None:
        super().__init__()
        self.system = system
        require_system(system, "SymbolicPlant: system")
        model = system.symbolic()
        x = model.x
        u: SymbolicArray = MakeVectorVariable(system.m, "u")
        with np.errstate(invalid="ignore"):  # numpy's object loops flag Drake expressions
            xdot = model.f + model.g @ u
        builder = DiagramBuilder()
        dynamics, (u_index,) = _add_symbolic_system(
            builder, "dynamics", [("u", u)], state=x, dynamics=xdot, output=x
        )
        C: DrakeArray = system.output_matrix
        output = builder.AddNamedSystem("output_map", MatrixGain(C))
        builder.Connect(dynamics.get_output_port(), output.get_input_port())
        y_index = builder.ExportOutput(output.get_output_port(), "y")
        state_index = builder.ExportOutput(dynamics.get_output_port(), "state")
        builder.BuildInto(self)
        self._u_port = self.get_input_port(int(u_index))
        self._y_port = self.get_output_port(int(y_index))
        self._state_port = self.get_output_port(int(state_index))

    def get_u_input_port(self) -> InputPort:
        """The input ``u`` (size m)."""
        return self._u_port

    def get_y_output_port(self) -> OutputPort:
        """The measured output ``y = C x`` (size q)."""
        return self._y_port

    def get_state_output_port(self) -> OutputPort:
        """The true state ``x`` (size n)."""
        return self._state_port

    def set_state(self, context: Context, x: ArrayLike) -> None:
        """Set the plant's state to ``x`` in ``context``, this block's own context."""
        set_state_vector(context, x, self.system.n, "SymbolicPlant: x")


class SymbolicObserver(Diagram):
    """The three-gain observer evaluated by Drake in C++.

    .. pydrake_system::

        name: SymbolicObserver
        input_ports:
        - y
        - u
        output_ports:
        - estimated_state

    Parameters
    ----------
    system : ControlAffineSystem
        The model the observer runs; ``system.symbolic()`` must succeed.
    gains : ObserverGains
    design : ObserverDesign, optional
        The design ``gains`` come from, reported by :meth:`observer_certificate`.

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`ControlAffineSystem`, ``gains`` not an
        :class:`ObserverGains` whose gains have the shapes ``system``'s n, q
        and m give (:func:`~ofrl_drake.observer.require_gains`), ``f`` or
        ``g`` cannot be traced symbolically, or ``design`` has other gains.

    Notes
    -----
    The estimate starts at zero in a default context; set xhat(0) with
    :meth:`set_estimated_state` (see the module docstring).

    See Also
    --------
    ofrl_drake.systems.ThreeGainObserver : the same block in Python.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        gains: ObserverGains,
        design: ObserverDesign | None = None,
    ) -> None:
        super().__init__()
        self.system = system
        self.gains = gains
        self.design = design
        require_observer_arguments("SymbolicObserver", system, gains, design)
        model = system.symbolic()
        xhat: SymbolicArray = MakeVectorVariable(system.n, "xhat")
        y: SymbolicArray = MakeVectorVariable(system.q, "y")
        u: SymbolicArray = MakeVectorVariable(system.m, "u")
        rhs = observer_rhs_expression(model, system.output_matrix, gains, xhat, y, u)
        builder = DiagramBuilder()
        dynamics, (y_index, u_index) = _add_symbolic_system(
            builder, "dynamics", [("y", y), ("u", u)], state=xhat, dynamics=rhs, output=xhat
        )
        xhat_index = builder.ExportOutput(dynamics.get_output_port(), "estimated_state")
        builder.BuildInto(self)
        self._y_port = self.get_input_port(int(y_index))
        self._u_port = self.get_input_port(int(u_index))
        self._xhat_port = self.get_output_port(int(xhat_index))

    def get_y_input_port(self) -> InputPort:
        """The measurement ``y`` (size q)."""
        return self._y_port

    def get_u_input_port(self) -> InputPort:
        """The applied input ``u`` (size m)."""
        return self._u_port

    def get_estimated_state_output_port(self) -> OutputPort:
        """The estimate ``xhat`` (size n)."""
        return self._xhat_port

    def set_estimated_state(self, context: Context, xhat: ArrayLike) -> None:
        """Set the estimate to ``xhat`` in ``context``, this block's own context."""
        set_state_vector(context, xhat, self.system.n, "SymbolicObserver: xhat")

    def observer_certificate(self) -> ObserverCertificate:
        """The design and its box, or nothing when built without a design."""
        return ObserverCertificate.of_design(self.design, type(self).__name__)


class SymbolicController(Diagram):
    """The saturated policy ``u = -lbar tanh(D)`` evaluated by Drake in C++.

    .. pydrake_system::

        name: SymbolicController
        input_ports:
        - estimated_state
        - policy_weights
        output_ports:
        - u

    Parameters
    ----------
    system : ControlAffineSystem
        ``system.symbolic()`` must succeed.
    basis : PolynomialBasis
    r : array_like, shape (m,)
        Diagonal of R.
    input_bound : float
        lbar > 0.

    Raises
    ------
    ModelError
        As :class:`~ofrl_drake.systems.SaturatedController`, or if ``f`` or
        ``g`` cannot be traced symbolically.

    Notes
    -----
    Its one continuous state stays at zero (see the module docstring).
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
        require_system(system, "SymbolicController: system")
        r_arr = check_policy_arguments(
            "SymbolicController", system.n, system.m, basis, r, input_bound
        )
        model = system.symbolic()
        W: SymbolicArray = MakeVectorVariable(basis.size, "W")
        u = policy_expression(basis, model.x, model.g, W, r_arr, float(input_bound))
        unused: SymbolicArray = MakeVectorVariable(1, "unused")
        builder = DiagramBuilder()
        policy, (xhat_index, weights_index) = _add_symbolic_system(
            builder,
            "policy",
            [("estimated_state", model.x), ("policy_weights", W)],
            state=unused,
            dynamics=[0.0 * unused[0]],
            output=u,
        )
        u_index = builder.ExportOutput(policy.get_output_port(), "u")
        builder.BuildInto(self)
        self._xhat_port = self.get_input_port(int(xhat_index))
        self._weights_port = self.get_input_port(int(weights_index))
        self._u_port = self.get_output_port(int(u_index))

    def get_estimated_state_input_port(self) -> InputPort:
        """The state estimate xhat (size n)."""
        return self._xhat_port

    def get_policy_weights_input_port(self) -> InputPort:
        """The weights of the policy in force (size L): the critic's W under the paper's law."""
        return self._weights_port

    def get_u_output_port(self) -> OutputPort:
        """The saturated input u (size m)."""
        return self._u_port


class SymbolicRunningCost(Diagram):
    """``J' = Q(x) + U(u)``, ``J(0) = 0``, evaluated by Drake in C++.

    .. pydrake_system::

        name: SymbolicRunningCost
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
        As :class:`~ofrl_drake.systems.RunningCost`.

    Notes
    -----
    ``U`` is :func:`~ofrl_drake.cost.stage_cost_expression`'s: an input beyond
    the bound is clipped to it, where :class:`~ofrl_drake.systems.RunningCost`
    raises; either way the validity report flags ``|u_k| > lambda_bar``.
    """

    def __init__(self, Q: np.ndarray, r: np.ndarray, input_bound: float) -> None:
        super().__init__()
        self.Q = Q
        self.r = r
        self.input_bound = input_bound
        Q_arr, r_arr, lbar = check_cost_arguments("SymbolicRunningCost", Q, r, input_bound)
        n, m = Q_arr.shape[0], r_arr.size
        J: SymbolicArray = MakeVectorVariable(1, "J")
        x: SymbolicArray = MakeVectorVariable(n, "x")
        u: SymbolicArray = MakeVectorVariable(m, "u")
        rate = stage_cost_expression(x, u, Q_arr, r_arr, lbar)
        builder = DiagramBuilder()
        integrand, (state_index, u_index) = _add_symbolic_system(
            builder, "stage_cost", [("state", x), ("u", u)], state=J, dynamics=[rate], output=J
        )
        cost_index = builder.ExportOutput(integrand.get_output_port(), "cost")
        builder.BuildInto(self)
        self._state_port = self.get_input_port(int(state_index))
        self._u_port = self.get_input_port(int(u_index))
        self._cost_port = self.get_output_port(int(cost_index))

    def get_state_input_port(self) -> InputPort:
        """The true state x (size n)."""
        return self._state_port

    def get_u_input_port(self) -> InputPort:
        """The applied input u (size m)."""
        return self._u_port

    def get_cost_output_port(self) -> OutputPort:
        """The accumulated cost J (size 1)."""
        return self._cost_port
