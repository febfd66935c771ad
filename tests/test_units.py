"""Units: a multibody model knows them from its joints; a hand-written one may state them."""

import numpy as np
import pytest

from ofrl_drake.errors import ModelError
from ofrl_drake.model import ControlAffineSystem

CART_POLE_SDF = "package://drake/examples/multibody/cart_pole/cart_pole.sdf"
ACROBOT_URDF = "package://drake/examples/acrobot/Acrobot.urdf"


def _f(x):
    return np.array([x[1], -x[0]])


def _g(x):
    return np.array([[0 * x[0]], [1 + 0 * x[0]]])


def test_multibody_units_come_from_the_joint_types():
    cart_pole = ControlAffineSystem.from_multibody(CART_POLE_SDF)
    assert cart_pole.state_units == ("m", "rad", "m/s", "rad/s")  # prismatic cart, revolute pole
    assert cart_pole.input_units == ("N",)  # a force on the cart
    acrobot = ControlAffineSystem.from_multibody(ACROBOT_URDF)
    assert acrobot.state_units == ("rad", "rad", "rad/s", "rad/s")
    assert acrobot.input_units == ("N·m",)  # a torque at the elbow
    shifted = acrobot.shifted([np.pi, 0.0, 0.0, 0.0])
    assert shifted.state_units == acrobot.state_units  # an equilibrium keeps the units


def test_stated_units_are_kept_and_unknown_units_are_none():
    s = ControlAffineSystem(_f, _g, [[1.0, 0.0]], state_units=["rad", "rad/s"], input_units=["N·m"])
    assert s.state_units == ["rad", "rad/s"]  # stored as given
    assert ControlAffineSystem(_f, _g, [[1.0, 0.0]]).state_units is None


@pytest.mark.parametrize(
    ("key", "units", "message"),
    [
        (
            "state_units",
            ["rad"],
            r"state_units must give one string per state \(2 in all\); got \['rad'\]",
        ),
        (
            "state_units",
            "rad",
            r"state_units must give one string per state \(2 in all\); got 'rad'",
        ),
        ("input_units", ["N", "N"], r"input_units must give one string per input \(1 in all\)"),
        (
            "input_units",
            [3.0],
            r"input_units must give one string per input \(1 in all\); got \[3\.0\]",
        ),
    ],
)
def test_units_of_the_wrong_length_or_type_are_refused(key, units, message):
    with pytest.raises(ModelError, match=message):
        ControlAffineSystem(_f, _g, [[1.0, 0.0]], **{key: units})
