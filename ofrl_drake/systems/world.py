"""Sensors and actuators around the plant and the controller: real-world conditions.

:class:`MeasuredPlant` wraps whatever block fills the plant slot: the plant
receives ``u`` plus a constant disturbance, and ``y`` reaches the loop with
Gaussian noise from Drake's ``RandomSource``, sampled and held by a
``ZeroOrderHold``. :class:`SampledController` wraps the controller slot's block:
its output is held for a period, a sampled-data controller. Both keep the
slot's port names, so the rest of the loop is wired as usual.

A run prepares its context in three steps: :func:`initialize_context` lets
each block set what its default context cannot hold (a multibody plant's
velocities and masses), the run's initial values are written through the
blocks' setters (``set_state`` ...), and :func:`start_holds` starts every hold
at its input's value at ``t = 0``, which depends on them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from pydrake.common import RandomDistribution
from pydrake.systems.framework import (
    Context,
    Diagram,
    DiagramBuilder,
    InputPort,
    OutputPort,
    OutputPortIndex,
    System,
)
from pydrake.systems.primitives import (
    Adder,
    ConstantVectorSource,
    MatrixGain,
    RandomSource,
    ZeroOrderHold,
)

from ofrl_drake.checks import finite_vector, positive_number
from ofrl_drake.contracts import ContextInitializer, HoldStarter, PlantStateSetter
from ofrl_drake.drake_typing import DrakeArray, vector_value
from ofrl_drake.errors import ModelError

__all__ = ["MeasuredPlant", "SampledController", "initialize_context", "start_holds"]


def initialize_context(system: System, context: Context) -> None:
    """Let ``system`` set what its default context cannot hold (its own ``context``).

    Blocks that need it define ``initialize_context(context)``
    (:class:`~ofrl_drake.contracts.ContextInitializer`): a multibody plant's
    initial velocities and body masses. Others are left as they are.
    """
    if isinstance(system, ContextInitializer):
        system.initialize_context(context)


def start_holds(system: System, context: Context) -> None:
    """Start the holds of ``system`` at their input's value (its own ``context``).

    Call it once the context holds the initial state: blocks with a hold define
    ``start_holds(context)`` (:class:`~ofrl_drake.contracts.HoldStarter`:
    :class:`MeasuredPlant`, :class:`SampledController`).
    """
    if isinstance(system, HoldStarter):
        system.start_holds(context)


def _optional_vector(name: str, value: ArrayLike | None, size: int) -> np.ndarray:
    """``value`` as a finite vector of length ``size``; zeros if it is None or empty."""
    if value is None:
        return np.zeros(size)
    try:
        empty = np.size(value) == 0
    except ValueError:  # ragged: finite_vector says what is wrong with it
        empty = False
    return np.zeros(size) if empty else finite_vector(name, value, size)


def _export_other_ports(
    builder: DiagramBuilder, inner: System, skip_in: set[str], skip_out: set[str]
) -> dict[str, OutputPortIndex]:
    """Export the ports of ``inner`` not named in ``skip_*`` under their own names.

    Returns the index of each exported output by name, for the accessors.
    """
    for i in range(inner.num_input_ports()):
        input_port = inner.get_input_port(i)
        if input_port.get_name() not in skip_in:
            builder.ExportInput(input_port, input_port.get_name())
    outputs: dict[str, OutputPortIndex] = {}
    for i in range(inner.num_output_ports()):
        output_port = inner.get_output_port(i)
        name = output_port.get_name()
        if name not in skip_out:
            outputs[name] = builder.ExportOutput(output_port, name)
    return outputs


class MeasuredPlant(Diagram):
    """A plant block whose input gets a disturbance and whose output is noisy and sampled.

    .. pydrake_system::

        name: MeasuredPlant
        input_ports:
        - u
        output_ports:
        - y
        - state

    plus any other port of ``plant``, exported under its own name.

    ``y_k = C x(t_k) + v_k`` with ``v_k ~ N(0, diag(noise_std)^2)`` drawn by
    a ``RandomSource`` every ``period`` and held by a ``ZeroOrderHold``
    (``t_k = k period``); the plant receives ``u + disturbance``. The noise
    is seeded by the root context's random generator (``SetRandomContext``).

    Parameters
    ----------
    plant : System
        The block with ports ``u``, ``y`` and ``state``.
    noise_std : array_like, shape (q,), optional
        Standard deviations of the measurement noise (none if omitted or
        empty).
    period : float
        Sampling period of ``y`` in seconds (0: continuous; noise needs > 0).
    disturbance : array_like, shape (m,), optional
        Constant input disturbance (none if omitted or empty).

    Raises
    ------
    ModelError
        If the sizes do not match the plant's ports, a value is negative or
        not finite, or noise is asked for with ``period = 0``.
    """

    def __init__(
        self,
        plant: System,
        *,
        noise_std: ArrayLike | None = None,
        period: float = 0.0,
        disturbance: ArrayLike | None = None,
    ) -> None:
        super().__init__()
        self.plant = plant
        self.noise_std = noise_std
        self.period = period
        self.disturbance = disturbance
        q = plant.GetOutputPort("y").size()
        m = plant.GetInputPort("u").size()
        positive_number("MeasuredPlant: period", period, allow_zero=True)
        std = _optional_vector("MeasuredPlant: noise_std", noise_std, q)
        if np.any(std < 0):
            raise ModelError(f"MeasuredPlant: noise_std must be >= 0; got {std.tolist()}.")
        if np.any(std > 0) and period == 0:
            raise ModelError("MeasuredPlant: noise needs a sampling period > 0; got 0.")
        d: DrakeArray = _optional_vector("MeasuredPlant: disturbance", disturbance, m)
        builder = DiagramBuilder()
        inner = builder.AddNamedSystem("plant", plant)
        if np.any(d != 0):
            add_d = builder.AddNamedSystem("add_disturbance", Adder(2, m))
            source = builder.AddNamedSystem("disturbance", ConstantVectorSource(d))
            builder.Connect(source.get_output_port(), add_d.GetInputPort("u1"))
            builder.Connect(add_d.get_output_port(), inner.GetInputPort("u"))
            u_index = builder.ExportInput(add_d.GetInputPort("u0"), "u")
        else:
            u_index = builder.ExportInput(inner.GetInputPort("u"), "u")
        y = inner.GetOutputPort("y")
        self._hold: ZeroOrderHold | None = None
        if np.any(std > 0):
            noise = builder.AddNamedSystem(
                "noise", RandomSource(RandomDistribution.kGaussian, q, float(period))
            )
            scale = builder.AddNamedSystem("noise_std", MatrixGain(np.diag(std)))
            add_v = builder.AddNamedSystem("add_noise", Adder(2, q))
            builder.Connect(noise.GetOutputPort("output"), scale.get_input_port())
            builder.Connect(y, add_v.GetInputPort("u0"))
            builder.Connect(scale.get_output_port(), add_v.GetInputPort("u1"))
            y = add_v.get_output_port()
        if period > 0:
            self._hold = ZeroOrderHold(float(period), q)
            builder.AddNamedSystem("sample_and_hold", self._hold)
            builder.Connect(y, self._hold.get_input_port())
            y = self._hold.get_output_port()
        y_index = builder.ExportOutput(y, "y")
        others = _export_other_ports(builder, inner, {"u"}, {"y"})
        builder.BuildInto(self)
        self._inner = inner
        self._u_port = self.get_input_port(int(u_index))
        self._y_port = self.get_output_port(int(y_index))
        self._state_port = self.get_output_port(int(others["state"])) if "state" in others else None

    def get_u_input_port(self) -> InputPort:
        """The input ``u`` (size m), before the disturbance is added."""
        return self._u_port

    def get_y_output_port(self) -> OutputPort:
        """The measured output ``y``, noisy and sampled (size q)."""
        return self._y_port

    def get_state_output_port(self) -> OutputPort:
        """The inner plant's true state ``x`` (size n).

        Raises
        ------
        ModelError
            If the inner plant has no output port ``state``.
        """
        if self._state_port is None:
            raise ModelError(
                f"MeasuredPlant: the plant {type(self._inner).__name__} has no output port "
                "'state', so its state cannot be read; give it one."
            )
        return self._state_port

    def initialize_context(self, context: Context) -> None:
        """The inner plant's own initialization (:func:`initialize_context`)."""
        initialize_context(self._inner, self.GetMutableSubsystemContext(self._inner, context))

    def set_state(self, context: Context, x: ArrayLike) -> None:
        """Set the inner plant's state to ``x`` in ``context``, this block's own context.

        Raises
        ------
        ModelError
            If the inner plant has no ``set_state(context, x)``.
        """
        if not isinstance(self._inner, PlantStateSetter):
            raise ModelError(
                f"MeasuredPlant: the plant {type(self._inner).__name__} has no "
                "set_state(context, x), so its state cannot be set; give it one."
            )
        self._inner.set_state(self.GetMutableSubsystemContext(self._inner, context), x)

    def start_holds(self, context: Context) -> None:
        """The sample-and-hold starts at ``y(0)`` with one noise draw (after the state is set).

        What a log at ``t = 0`` shows. The periodic update at ``t = 0`` then
        samples ``y(0)`` again with the next draw, and that is what the loop
        uses on ``[0, period)``: every sample ``t_k = k period``, ``t = 0``
        included, takes a new draw.
        """
        start_holds(self._inner, self.GetMutableSubsystemContext(self._inner, context))
        if self._hold is not None:
            hold_context = self.GetMutableSubsystemContext(self._hold, context)
            value = vector_value(self._hold.get_input_port(), hold_context)
            self._hold.SetVectorState(hold_context, value)


class SampledController(Diagram):
    """A controller block whose output ``u`` is held for ``period`` seconds.

    .. pydrake_system::

        name: SampledController
        input_ports:
        - (the inputs of ``controller``)
        output_ports:
        - u

    The hold samples at ``t_k = k period`` and starts at the controller's
    ``u(0)``.

    Parameters
    ----------
    controller : System
        A block with an output ``u``.
    period : float
        Hold period in seconds, > 0.
    """

    def __init__(self, controller: System, period: float) -> None:
        super().__init__()
        self.controller = controller
        self.period = period
        positive_number("SampledController: period", period)
        m = controller.GetOutputPort("u").size()
        builder = DiagramBuilder()
        inner = builder.AddNamedSystem("controller", controller)
        self._hold = ZeroOrderHold(float(period), m)
        builder.AddNamedSystem("hold", self._hold)
        builder.Connect(inner.GetOutputPort("u"), self._hold.get_input_port())
        u_index = builder.ExportOutput(self._hold.get_output_port(), "u")
        _export_other_ports(builder, inner, set(), {"u"})
        builder.BuildInto(self)
        self._inner = inner
        self._u_port = self.get_output_port(int(u_index))

    def get_u_output_port(self) -> OutputPort:
        """The held input ``u`` (size m)."""
        return self._u_port

    def initialize_context(self, context: Context) -> None:
        """The inner controller's own initialization (:func:`initialize_context`)."""
        initialize_context(self._inner, self.GetMutableSubsystemContext(self._inner, context))

    def start_holds(self, context: Context) -> None:
        """The hold starts at the controller's ``u(0)`` (after the loop's state is set)."""
        start_holds(self._inner, self.GetMutableSubsystemContext(self._inner, context))
        hold_context = self.GetMutableSubsystemContext(self._hold, context)
        self._hold.SetVectorState(
            hold_context, vector_value(self._hold.get_input_port(), hold_context)
        )
