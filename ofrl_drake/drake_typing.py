"""pydrake's typed boundary: the array type its stubs accept, and a vector port's value.

pydrake's stubs (pybind11-stubgen) write an Eigen vector or matrix as
``numpy.ndarray[numpy.float64[m, 1]]``. numpy's own stubs read the first
parameter of ``ndarray`` as the array's *shape* type, so a type checker sees
an array whose shape is typed ``float64``. No array that numpy builds matches
such a parameter (numpy types shapes as tuples: ``np.zeros(n)`` is an
``ndarray[tuple[int], ...]``), and the arrays pydrake returns match no
``np.ndarray`` parameter of ours. An array whose shape type is ``Any`` matches
both: :data:`DrakeArray` (float) and :data:`SymbolicArray` (``pydrake.symbolic``
variables and expressions). Arrays handed to pydrake are typed with them,
through :func:`drake_array` where they are built, and so are the values of
vector ports (:func:`vector_value`, or :func:`vector_reader` in a block's
per-evaluation code), whose stub says ``object``.

:func:`input_port_names` and :func:`output_port_names` list a system's ports
for messages that name what a block has. :func:`set_state_vector` is the
blocks' state setter: the value checked, then written into a context.

None changes a value: :func:`drake_array` is ``np.asarray(values,
dtype=float)``, :func:`vector_value` is ``port.Eval(context)``, and
:func:`vector_reader` is ``port.Eval`` itself.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeAlias, cast

import numpy as np
from numpy.typing import ArrayLike

from ofrl_drake.checks import finite_vector

if TYPE_CHECKING:  # annotations only
    from pydrake.systems.framework import Context, InputPort, OutputPort

__all__ = [
    "DrakeArray",
    "SymbolicArray",
    "drake_array",
    "input_port_names",
    "output_port_names",
    "set_state_vector",
    "vector_reader",
    "vector_value",
]

#: A float array as pydrake's stubs take and give it: any shape (see the module docstring).
DrakeArray: TypeAlias = np.ndarray[Any, np.dtype[np.float64]]
#: An array of ``pydrake.symbolic`` variables or expressions, as pydrake's stubs take and give it.
SymbolicArray: TypeAlias = np.ndarray[Any, np.dtype[np.object_]]


def drake_array(values: ArrayLike) -> DrakeArray:
    """``values`` as a float array that pydrake's stubs accept (``np.asarray(values, float)``)."""
    return np.asarray(values, dtype=float)


def vector_value(port: InputPort | OutputPort, context: Context) -> DrakeArray:
    """The value of the vector-valued ``port`` in ``context``: ``port.Eval(context)``.

    ``Eval``'s stub returns ``object`` (an abstract-valued port gives any
    object); a vector-valued port gives a float array.
    """
    return cast(DrakeArray, port.Eval(context))


def vector_reader(port: InputPort | OutputPort) -> Callable[[Context], DrakeArray]:
    """``port.Eval``, typed as :func:`vector_value` is: bind it once, call it per evaluation.

    A block whose calc runs at every derivative evaluation keeps the bound
    method and calls it with the context, one call into pydrake with no Python
    frame or ``cast`` around it (about 0.4 us per read, measured in the paper
    scenario's loop).
    """
    return cast("Callable[[Context], DrakeArray]", port.Eval)


def input_port_names(system: Any) -> list[str]:
    """The names of ``system``'s input ports, in port order (a System of any scalar type)."""
    return [system.get_input_port(i).get_name() for i in range(system.num_input_ports())]


def output_port_names(system: Any) -> list[str]:
    """The names of ``system``'s output ports, in port order (a System of any scalar type)."""
    return [system.get_output_port(i).get_name() for i in range(system.num_output_ports())]


def set_state_vector(context: Context, value: ArrayLike, n: int, what: str) -> None:
    """Write ``value``, checked to be a finite vector of length ``n``, as the continuous
    state of ``context``, the context of a block whose whole continuous state it is.

    Raises
    ------
    ModelError
        If ``value`` is not a finite vector of length ``n``; the message
        starts with ``what`` (``"ControlAffinePlant: x"``).
    """
    x: DrakeArray = finite_vector(what, value, n)
    context.SetContinuousState(x)
