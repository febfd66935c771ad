"""ofrl_drake.drake_typing changes types only: drake_array is np.asarray(x, float),
vector_value is the port's Eval, and vector_reader is the port's bound Eval."""

import numpy as np
from pydrake.systems.primitives import ConstantVectorSource

from ofrl_drake.drake_typing import drake_array, vector_reader, vector_value


def test_drake_array_is_asarray_as_float():
    x = np.array([0.5, -1.25])
    assert drake_array(x) is x  # a float array is passed through, not copied
    converted = drake_array([1, 2])
    assert converted.dtype == np.float64
    np.testing.assert_array_equal(converted, [1.0, 2.0])


def test_vector_value_is_the_ports_value():
    source = ConstantVectorSource(np.array([0.25, 4.0]))
    context = source.CreateDefaultContext()
    port = source.get_output_port()
    value = vector_value(port, context)
    assert isinstance(value, np.ndarray)
    np.testing.assert_array_equal(value, port.Eval(context))
    np.testing.assert_array_equal(value, [0.25, 4.0])


def test_vector_reader_is_the_ports_eval_bound_once():
    source = ConstantVectorSource(np.array([0.25, 4.0]))
    context = source.CreateDefaultContext()
    port = source.get_output_port()
    read = vector_reader(port)
    np.testing.assert_array_equal(read(context), port.Eval(context))
    source.get_mutable_source_value(context).SetFromVector([1.0, -2.0])
    np.testing.assert_array_equal(read(context), [1.0, -2.0])  # reads the context it is given
