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
* a ``SymbolicVectorSystem`` has no way to set a default state, so the plant
  and the observer integrate the offset ``z = x - x(0)`` from a zero default
  and output ``z + x(0)``; their ports carry x itself, and ``set_state`` and
  ``set_estimated_state`` write one into a context;
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
from typing import Any

import numpy as np
from pydrake.symbolic import MakeVectorVariable
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, InputPort, OutputPort
from pydrake.systems.primitives import MatrixGain, Multiplexer, SymbolicVectorSystem

from ofrl_drake.basis import PolynomialBasis
from ofrl_drake.checks import (
    nonnegative_matrix,
    positive_number,
    positive_vector,
)
from ofrl_drake.cost import stage_cost_expression
from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem
from ofrl_drake.observer import ObserverGains, observer_rhs_expression
from ofrl_drake.observer_certificate import ObserverCertificate
from ofrl_drake.policy import check_policy_arguments, policy_expression

__all__ = [
    "SymbolicController",
    "SymbolicObserver",
    "SymbolicPlant",
    "SymbolicRunningCost",
]


def _initial(value: Sequence[float] | None, n: int, what: str) -> np.ndarray:
    x0 = np.zeros(n) if value is None else np.asarray(value, dtype=float)
    if x0.shape != (n,):
        raise ModelError(f"{what} must have length n = {n}; got shape {x0.shape}.")
    return x0


def _offset_state(x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """State variables ``z`` of the offset from ``x0``, and ``x = z + x0`` in them."""
    z = MakeVectorVariable(x0.size, "z")
    with np.errstate(invalid="ignore"):  # numpy's object loops flag Drake expressions
        return z, z + x0


def _set_offset_state(context: Context, value: Sequence[float], offset: np.ndarray) -> None:
    """Write the state ``value`` as the offset ``value - offset`` the block integrates."""
    context.SetContinuousState(np.asarray(value, dtype=float) - offset)


def _add_symbolic_system(
    builder: DiagramBuilder,
    name: str,
    inputs: Sequence[tuple[str, np.ndarray]],
    *,
    state: np.ndarray,
    dynamics: Any,
    output: Any,
) -> SymbolicVectorSystem:
    """Add a ``SymbolicVectorSystem`` and export its inputs as the named ports.

    ``inputs`` is ``(port name, variables)`` in order; several ports are
    stacked into the system's one input by a ``Multiplexer``.
    """
    system = builder.AddNamedSystem(
        name,
        SymbolicVectorSystem(
            state=state,
            input=np.concatenate([variables for _, variables in inputs]),
            dynamics=dynamics,
            output=output,
        ),
    )
    if len(inputs) == 1:
        builder.ExportInput(system.get_input_port(), inputs[0][0])
        return system
    mux = builder.AddNamedSystem("stack_inputs", Multiplexer([v.size for _, v in inputs]))
    builder.Connect(mux.get_output_port(), system.get_input_port())
    for i, (port, _) in enumerate(inputs):
        builder.ExportInput(mux.get_input_port(i), port)
    return system


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
    initial_state : array_like, shape (n,), optional
        Default value of x (zeros if omitted).

    Raises
    ------
    ModelError
        If ``f`` or ``g`` cannot be traced symbolically, or ``initial_state``
        has the wrong length.

    See Also
    --------
    ofrl_drake.systems.ControlAffinePlant : the same block in Python.
    """

    def __init__(
        self, system: ControlAffineSystem, initial_state: Sequence[float] | None = None
    ) -> None:
        super().__init__()
        self.system = system
        self.initial_state = initial_state
        model = system.symbolic()
        self._offset = _initial(initial_state, system.n, f"{system.name}: initial_state")
        z, x = _offset_state(self._offset)
        u = MakeVectorVariable(system.m, "u")
        with np.errstate(invalid="ignore"):  # numpy's object loops flag Drake expressions
            f, g = model.substitute(x)
            xdot = f + g @ u
        builder = DiagramBuilder()
        dynamics = _add_symbolic_system(
            builder, "dynamics", [("u", u)], state=z, dynamics=xdot, output=x
        )
        output = builder.AddNamedSystem("output_map", MatrixGain(system.output_matrix))
        builder.Connect(dynamics.get_output_port(), output.get_input_port())
        builder.ExportOutput(output.get_output_port(), "y")
        builder.ExportOutput(dynamics.get_output_port(), "state")
        builder.BuildInto(self)

    def get_u_input_port(self) -> InputPort:
        """The input ``u`` (size m)."""
        return self.GetInputPort("u")

    def get_y_output_port(self) -> OutputPort:
        """The measured output ``y = C x`` (size q)."""
        return self.GetOutputPort("y")

    def get_state_output_port(self) -> OutputPort:
        """The true state ``x`` (size n)."""
        return self.GetOutputPort("state")

    def set_state(self, context: Context, x: Sequence[float]) -> None:
        """Set the plant's state to ``x`` in ``context``, this block's own context."""
        _set_offset_state(context, x, self._offset)


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
    initial_state : array_like, shape (n,), optional
        Default xhat(0) (zeros if omitted).
    design : ObserverDesign, optional
        The design ``gains`` come from, reported by :meth:`observer_certificate`.

    Raises
    ------
    ModelError
        If ``f`` or ``g`` cannot be traced symbolically, ``initial_state`` has
        the wrong length, or ``design`` has other gains.

    See Also
    --------
    ofrl_drake.systems.ThreeGainObserver : the same block in Python.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        gains: ObserverGains,
        initial_state: Sequence[float] | None = None,
        design: Any = None,
    ) -> None:
        super().__init__()
        self.system = system
        self.gains = gains
        self.initial_state = initial_state
        self.design = design
        if design is not None:
            gains.check_design(design)
        model = system.symbolic()
        what = f"{system.name}: observer initial_state"
        self._offset = _initial(initial_state, system.n, what)
        z, xhat = _offset_state(self._offset)
        y = MakeVectorVariable(system.q, "y")
        u = MakeVectorVariable(system.m, "u")
        rhs = observer_rhs_expression(model, system.output_matrix, gains, xhat, y, u)
        builder = DiagramBuilder()
        dynamics = _add_symbolic_system(
            builder, "dynamics", [("y", y), ("u", u)], state=z, dynamics=rhs, output=xhat
        )
        builder.ExportOutput(dynamics.get_output_port(), "estimated_state")
        builder.BuildInto(self)

    def get_y_input_port(self) -> InputPort:
        """The measurement ``y`` (size q)."""
        return self.GetInputPort("y")

    def get_u_input_port(self) -> InputPort:
        """The applied input ``u`` (size m)."""
        return self.GetInputPort("u")

    def get_estimated_state_output_port(self) -> OutputPort:
        """The estimate ``xhat`` (size n)."""
        return self.GetOutputPort("estimated_state")

    def set_estimated_state(self, context: Context, xhat: Sequence[float]) -> None:
        """Set the estimate to ``xhat`` in ``context``, this block's own context."""
        _set_offset_state(context, xhat, self._offset)

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
        r_arr = check_policy_arguments(
            "SymbolicController", system.n, system.m, basis, r, input_bound
        )
        model = system.symbolic()
        W = MakeVectorVariable(basis.size, "W")
        u = policy_expression(basis, model.x, model.g, W, r_arr, float(input_bound))
        unused = MakeVectorVariable(1, "unused")
        builder = DiagramBuilder()
        policy = _add_symbolic_system(
            builder,
            "policy",
            [("estimated_state", model.x), ("policy_weights", W)],
            state=unused,
            dynamics=[0.0 * unused[0]],
            output=u,
        )
        builder.ExportOutput(policy.get_output_port(), "u")
        builder.BuildInto(self)

    def get_estimated_state_input_port(self) -> InputPort:
        """The state estimate xhat (size n)."""
        return self.GetInputPort("estimated_state")

    def get_policy_weights_input_port(self) -> InputPort:
        """The weights of the policy in force (size L): the critic's W under the paper's law."""
        return self.GetInputPort("policy_weights")

    def get_u_output_port(self) -> OutputPort:
        """The saturated input u (size m)."""
        return self.GetOutputPort("u")


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
        Q_arr = nonnegative_matrix("SymbolicRunningCost: Q", Q)
        r_arr = positive_vector("SymbolicRunningCost: r", r)
        positive_number("SymbolicRunningCost: input_bound", input_bound)
        n, m = Q_arr.shape[0], r_arr.size
        J = MakeVectorVariable(1, "J")
        x = MakeVectorVariable(n, "x")
        u = MakeVectorVariable(m, "u")
        rate = stage_cost_expression(x, u, Q_arr, r_arr, float(input_bound))
        builder = DiagramBuilder()
        integrand = _add_symbolic_system(
            builder, "stage_cost", [("state", x), ("u", u)], state=J, dynamics=[rate], output=J
        )
        builder.ExportOutput(integrand.get_output_port(), "cost")
        builder.BuildInto(self)

    def get_state_input_port(self) -> InputPort:
        """The true state x (size n)."""
        return self.GetInputPort("state")

    def get_u_input_port(self) -> InputPort:
        """The applied input u (size m)."""
        return self.GetInputPort("u")

    def get_cost_output_port(self) -> OutputPort:
        """The accumulated cost J (size 1)."""
        return self.GetOutputPort("cost")
