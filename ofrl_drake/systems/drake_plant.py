"""The plant block as the Drake model itself: a multibody plant running in C++."""

from __future__ import annotations

from collections.abc import Mapping
from typing import cast

import numpy as np
from numpy.typing import ArrayLike
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, InputPort, OutputPort
from pydrake.systems.primitives import AffineSystem

from ofrl_drake.checks import finite_vector, initial_vector
from ofrl_drake.drake_typing import DrakeArray, drake_array
from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem, require_system

__all__ = ["DrakePlant"]


class DrakePlant(Diagram):
    """The source ``MultibodyPlant`` of a model, with the ports of the plant slot.

    Runs (a clone of) the continuous ``MultibodyPlant`` a model was built from
    with :meth:`ControlAffineSystem.from_multibody`, in the coordinates of
    ``system``: for a :class:`~ofrl_drake.model.ShiftedSystem` the input ``u``
    is the offset ``u - u*`` and the outputs are ``x - x*`` and ``C (x - x*)``.
    Three stateless ``AffineSystem`` blocks do the shifts:

    * ``add_input_offset``: actuation ``= u + u*``;
    * ``state_offset``: ``state = x - x*``;
    * ``output_map``: ``y = C (x - x*)``.

    Only the plant's state is continuous state, so this block and
    :class:`~ofrl_drake.systems.ControlAffinePlant` are interchangeable in the
    loop; their trajectories agree to the integrator's accuracy.

    .. pydrake_system::

        name: DrakePlant
        input_ports:
        - u
        output_ports:
        - y
        - state

    Parameters
    ----------
    system : ControlAffineSystem
        A model from :meth:`~ofrl_drake.model.ControlAffineSystem.from_multibody`,
        possibly shifted.
    initial_state : array_like, shape (n,), optional
        Default initial state, in the coordinates of ``system`` (zeros if
        omitted). The positions become the clone's default positions; a
        multibody plant has no default velocities, so :meth:`initialize_context`
        sets both in a context (``simulate`` calls it, then writes the run's
        own x(0) with :meth:`set_state`).
    body_mass_scale : mapping of str to float, optional
        Factors on the masses of named bodies, set as Drake parameters in the
        context by :meth:`initialize_context` (the center of mass and unit
        inertia kept): a truth that differs from the model. A default context
        holds the unscaled masses (Drake offers no way to change a finalized
        plant's defaults), so a context simulated by hand needs
        :meth:`initialize_context`, which
        :meth:`~ofrl_drake.diagram.ClosedLoop.set_initial_values` calls.

    Raises
    ------
    ModelError
        If ``system`` is not a :class:`~ofrl_drake.model.ControlAffineSystem`
        or was not built from a multibody plant, ``initial_state``
        is not a finite vector of length n, or ``body_mass_scale`` names no
        body of the plant.
    """

    def __init__(
        self,
        system: ControlAffineSystem,
        initial_state: ArrayLike | None = None,
        body_mass_scale: Mapping[str, float] | None = None,
    ) -> None:
        super().__init__()
        self.system = system
        self.initial_state = initial_state
        self.body_mass_scale = body_mass_scale
        require_system(system, "DrakePlant: system")
        source_plant = system.multibody_plant
        if source_plant is None:
            raise ModelError(
                f"{system.name}: DrakePlant runs the multibody plant of a model built by "
                "ControlAffineSystem.from_multibody; this model has none "
                f"(source = {type(system.source).__name__}). Use ControlAffinePlant instead."
            )
        n, m = system.n, system.m
        x_star, u_star = system.equilibrium
        x_eq, u_eq = drake_array(x_star), drake_array(u_star)
        x0: DrakeArray = initial_vector(f"{system.name}: initial_state", initial_state, n) + x_eq
        plant = cast(MultibodyPlant, source_plant.Clone())  # pydrake stub: Clone() -> System
        nq = plant.num_positions()
        plant.SetDefaultPositions(drake_array(x0[:nq]))
        self._x_eq = x_eq
        self._x0 = x0
        for body in body_mass_scale or {}:
            if not plant.HasBodyNamed(body):
                raise ModelError(
                    f"{system.name}: body_mass_scale names {body!r}, which is not a body of "
                    "the plant."
                )
        builder = DiagramBuilder()
        builder.AddNamedSystem("multibody_plant", plant)
        self._plant = plant
        offset = builder.AddNamedSystem(
            "add_input_offset", AffineSystem(D=drake_array(np.eye(m)), y0=u_eq)
        )
        state = builder.AddNamedSystem(
            "state_offset", AffineSystem(D=drake_array(np.eye(n)), y0=-x_eq)
        )
        C: DrakeArray = system.output_matrix
        y0: DrakeArray = -C @ x_eq
        output = builder.AddNamedSystem("output_map", AffineSystem(D=C, y0=y0))
        builder.Connect(offset.get_output_port(), plant.get_actuation_input_port())
        builder.Connect(plant.get_state_output_port(), state.get_input_port())
        builder.Connect(plant.get_state_output_port(), output.get_input_port())
        builder.ExportInput(offset.get_input_port(), "u")
        builder.ExportOutput(output.get_output_port(), "y")
        builder.ExportOutput(state.get_output_port(), "state")
        builder.BuildInto(self)

    def initialize_context(self, context: Context) -> None:
        """Set the default positions and velocities, and the scaled masses, in ``context``.

        A body of ``body_mass_scale`` whose mass in ``context`` is not its
        default mass keeps it: that mass was set on purpose (e.g. copied from
        ``simulate``'s ``parameters``), and a context already initialized is
        not scaled twice.
        """
        plant = self._plant
        plant_context = self.GetMutableSubsystemContext(plant, context)
        plant.SetPositionsAndVelocities(plant_context, self._x0)
        for body, scale in (self.body_mass_scale or {}).items():
            rigid = plant.GetBodyByName(body)
            if rigid.get_mass(plant_context) == rigid.default_mass():
                rigid.SetMass(plant_context, rigid.default_mass() * float(scale))

    def set_state(self, context: Context, x: ArrayLike) -> None:
        """Set the state to ``x`` (in the coordinates of ``system``) in ``context``, this
        block's own context: the plant's positions and velocities ``x + x*``."""
        z = finite_vector(f"{self.system.name}: x", x, self.system.n)
        plant_context = self.GetMutableSubsystemContext(self._plant, context)
        self._plant.SetPositionsAndVelocities(plant_context, drake_array(z + self._x_eq))

    @property
    def plant(self) -> MultibodyPlant:
        """The ``MultibodyPlant`` inside (a clone of ``system.multibody_plant``)."""
        return self._plant

    def get_u_input_port(self) -> InputPort:
        """The input ``u`` (size m), relative to ``u*`` for a shifted model."""
        return self.GetInputPort("u")

    def get_y_output_port(self) -> OutputPort:
        """The measured output ``y = C (x - x*)`` (size q)."""
        return self.GetOutputPort("y")

    def get_state_output_port(self) -> OutputPort:
        """The state ``x - x*`` (size n)."""
        return self.GetOutputPort("state")
