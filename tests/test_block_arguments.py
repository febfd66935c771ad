"""Block constructors refuse bad arguments with a ModelError that names them.

Each case here used to build a block that failed later with a generic error
(an AttributeError, a numpy ValueError, a std::bad_alloc, a Drake assertion)
or ran to a wrong result.
"""

import dataclasses

import numpy as np
import pytest
from pydrake.systems.primitives import LinearSystem

from ofrl_drake import PolynomialBasis
from ofrl_drake.errors import ModelError
from ofrl_drake.examples import make_system
from ofrl_drake.systems import (
    ControlAffinePlant,
    DrakePlant,
    FullStateObserver,
    LinearizedLuenbergerObserver,
    MovingBellmanExtrapolator,
    PolicyGate,
    PolicyPassThrough,
    SaturatedController,
    ScheduledThreeGainObserver,
    SymbolicController,
    SymbolicObserver,
    SymbolicPlant,
    ThreeGainObserver,
)
from tests.block_helpers import random_gains

OBSERVERS = [ThreeGainObserver, SymbolicObserver]


# ------------------------------------------------------------ observer gains
@pytest.mark.parametrize("block", OBSERVERS, ids=lambda b: b.__name__)
def test_observer_blocks_refuse_the_gains_of_another_model(block):
    # Gains of coupled_two_state (n = 4, q = 2, m = 2) in a two_state observer
    # used to run to "ok" with xhat stuck at zero (ThreeGainObserver) or fail in numpy.
    system = make_system("two_state")
    other = random_gains(make_system("coupled_two_state"))
    name = block.__name__
    with pytest.raises(
        ModelError,
        match=(
            rf"^{name}: gains\.L must have shape \(2, 1\); got \(4, 2\); the model "
            r"'two_state' has n = 2, q = 1, m = 1: build them with "
            r"ObserverGains\.from_design\(system, design\)"
        ),
    ):
        block(system, other)


@pytest.mark.parametrize("block", OBSERVERS, ids=lambda b: b.__name__)
def test_observer_blocks_refuse_bounds_for_another_number_of_inputs(block):
    system = make_system("two_state")  # m = 1
    gains = random_gains(system)
    two_inputs = dataclasses.replace(
        gains, Mg1=np.zeros((2, 2, 2)), Mg2=np.ones((2, 2, 2))
    )  # L, H, K fit: only the bounds are for m = 2
    with pytest.raises(
        ModelError,
        match=rf"^{block.__name__}: gains\.Mg1 must have shape \(2, 2, 1\); got \(2, 2, 2\)",
    ):
        block(system, two_inputs)


@pytest.mark.parametrize("block", OBSERVERS, ids=lambda b: b.__name__)
@pytest.mark.parametrize("gains", [None, "gains"], ids=["None", "str"])
def test_observer_blocks_refuse_what_is_not_gains(block, gains):
    with pytest.raises(
        ModelError,
        match=(
            rf"^{block.__name__}: gains must be an ObserverGains; got "
            rf"{type(gains).__name__}; build them with ObserverGains\.from_design"
        ),
    ):
        block(make_system("two_state"), gains)


@pytest.mark.parametrize("block", OBSERVERS, ids=lambda b: b.__name__)
def test_observer_blocks_refuse_non_finite_gains(block):
    gains = random_gains(make_system("two_state"))
    nan_gains = dataclasses.replace(gains, H=np.array([[np.nan], [0.0]]))
    with pytest.raises(
        ModelError, match=rf"^{block.__name__}: gains\.H must be finite; got \[\[nan\], \[0\.0\]\]"
    ):
        block(make_system("two_state"), nan_gains)


@pytest.mark.parametrize("L", ["abc", [[1j], [0.0]]], ids=["text", "complex"])
def test_gains_that_are_not_numbers_are_refused_naming_them(L):
    # Before: a bare ValueError / TypeError from numpy's conversion.
    from ofrl_drake.observer import ObserverGains

    system = make_system("two_state")
    arrays = dataclasses.asdict(random_gains(system))
    arrays = {k: v for k, v in arrays.items() if k in ("H", "K", "Mf1", "Mg1", "Mg2")}
    with pytest.raises(ModelError, match=r"^observer gain L must be numeric; got"):
        ObserverGains.from_arrays(system, L=L, **arrays)


# ------------------------------------------------------------ Luenberger gain
def _linearization():
    A, B, C = np.array([[0.0, 1.0], [-1.0, 0.0]]), np.array([[0.0], [1.0]]), np.eye(1, 2)
    return LinearSystem(A, B, C, np.zeros((1, 1)))


@pytest.mark.parametrize(
    ("gain", "message"),
    [
        (
            [[1.0, 1.0]],
            r"gain must have shape \(n, q\) = \(2, 1\); got \(1, 2\), n states by q outputs "
            r"of the linearization; build it with ofrl_drake\.baselines\.luenberger_gain",
        ),
        ([1.0, 1.0], r"gain must have shape \(n, q\) = \(2, 1\); got \(2,\)"),
        ([[np.nan], [1.0]], r"gain must be finite; got \[\[nan\], \[1\.0\]\]"),
    ],
    ids=["transposed", "1-D", "nan"],
)
def test_linearized_luenberger_observer_checks_its_gain(gain, message):
    # The transposed gain used to end the process in Drake's luenberger_observer.cc.
    with pytest.raises(ModelError, match=rf"^LinearizedLuenbergerObserver: {message}"):
        LinearizedLuenbergerObserver(_linearization(), np.array(gain))


# ------------------------------------------------------ a name, not a model
def _arguments(paper_design):
    basis = PolynomialBasis(2, [2])
    gains = random_gains(make_system("two_state"))
    r = np.array([1.0])
    return {
        ControlAffinePlant: (),
        SymbolicPlant: (),
        ThreeGainObserver: (gains,),
        SymbolicObserver: (gains,),
        SaturatedController: (basis, r, 3.0),
        SymbolicController: (basis, r, 3.0),
        MovingBellmanExtrapolator: (basis, np.zeros((2, 4)), np.eye(2), r, 3.0, 1.0),
        DrakePlant: (),
        ScheduledThreeGainObserver: (paper_design,),
    }


_KEYWORDS = {
    ScheduledThreeGainObserver: {
        "period": 1.0,
        "half_width": [1.0, 1.0],
        "input_bound": 3.0,
        "alpha": 0.5,
    }
}


@pytest.mark.parametrize(
    "block",
    [
        ControlAffinePlant,
        SymbolicPlant,
        ThreeGainObserver,
        SymbolicObserver,
        SaturatedController,
        SymbolicController,
        MovingBellmanExtrapolator,
        DrakePlant,
        ScheduledThreeGainObserver,
    ],
    ids=lambda b: b.__name__,
)
def test_blocks_refuse_a_model_name_for_the_model(block, paper_design):
    # Each used to fail with "'str' object has no attribute 'n'" (or 'symbolic', ...).
    args = _arguments(paper_design)[block]
    with pytest.raises(
        ModelError,
        match=(
            rf"^{block.__name__}: system must be a ControlAffineSystem; got str 'two_state'; "
            r"for the registered example, pass ofrl_drake\.examples\.make_system\('two_state'\)"
        ),
    ):
        block("two_state", *args, **_KEYWORDS.get(block, {}))


def test_scheduled_observer_refuses_what_is_not_a_design():
    with pytest.raises(
        ModelError,
        match=(
            r"^ScheduledThreeGainObserver: initial_design must be an ObserverDesign; got str; "
            r"design one with ofrl_drake\.design\.design_observer"
        ),
    ):
        ScheduledThreeGainObserver(
            make_system("two_state"), "design", **_KEYWORDS[ScheduledThreeGainObserver]
        )


# ------------------------------------------------------------------- sizes
@pytest.mark.parametrize(
    ("block", "argument", "value"),
    [
        (FullStateObserver, "num_states", -1),
        (FullStateObserver, "num_states", 2.0),
        (FullStateObserver, "num_states", "2"),
        (PolicyPassThrough, "size", -3),
        (PolicyPassThrough, "size", 2.5),
    ],
    ids=["n -1", "n 2.0", "n '2'", "L -3", "L 2.5"],
)
def test_size_arguments_are_integers_of_at_least_one(block, argument, value):
    # -1 and -3 used to raise MemoryError (std::bad_alloc); 2.0 pydrake's TypeError;
    # 2.5 was read as 2 weights.
    with pytest.raises(
        ModelError,
        match=rf"^{block.__name__}: {argument} must be an integer >= 1; got {value!r}\.",
    ):
        block(value)


# ------------------------------------------------------------- policy gate
def _gate_arguments():
    rng = np.random.default_rng(0)
    return {
        "initial_weights": [1.0, 0.0, 1.0],
        "period": 1.0,
        "A": np.array([[0.0, 1.0], [-1.0, -0.5]]),
        "B": np.array([[0.0], [1.0]]),
        "Q": np.eye(2),
        "r": np.array([1.0]),
        "basis": PolynomialBasis(2, [2]),
        "points": rng.uniform(-1.0, 1.0, (2, 10)),
    }


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"A": np.eye(3)}, r"A must have shape \(n, n\) = \(2, 2\); got \(3, 3\)"),
        ({"A": [[0.0, np.nan], [0.0, 0.0]]}, r"A must be finite; got \[\[0\.0, nan\]"),
        ({"B": np.ones((2, 2))}, r"B must have shape \(n, m\) = \(2, 1\); got \(2, 2\)"),
        ({"B": np.ones(2)}, r"B must have shape \(n, m\) = \(2, 1\); got \(2,\)"),
        ({"Q": np.full((2, 2), np.nan)}, r"Q must be finite; got \[\[nan, nan\]"),
        ({"Q": np.eye(3)}, r"Q must have shape \(2, 2\); got \(3, 3\)"),
        ({"Q": -np.eye(2)}, r"Q must be positive semidefinite"),
        ({"r": np.array([-1.0])}, r"r must have entries > 0; got \[-1\.0\]"),
        (
            {"points": np.zeros((3, 10))},
            r"points must have shape \(n, N\) = \(2, N\); got \(3, 10\)",
        ),
        ({"points": np.zeros((2, 0))}, r"points must have shape \(n, N\) = \(2, N\); got \(2, 0\)"),
        ({"points": [[np.inf, 0.0], [0.0, 0.0]]}, r"points must be finite; got \[\[inf"),
    ],
    ids=[
        "A 3x3",
        "A nan",
        "B 2 inputs",
        "B 1-D",
        "Q nan",
        "Q 3x3",
        "Q negative",
        "r negative",
        "points 3 rows",
        "no points",
        "points inf",
    ],
)
def test_policy_gate_checks_the_linearization_weights_and_points(given, message):
    # These used to build, then raise numpy ValueErrors at t = period (A, points,
    # Q) or run to "ok" on a wrong test (B, r).
    with pytest.raises(ModelError, match=rf"^PolicyGate: {message}"):
        PolicyGate(**(_gate_arguments() | given))
