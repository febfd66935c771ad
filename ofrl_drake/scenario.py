"""Scenario files: every parameter of one closed-loop experiment.

A scenario is a YAML file (see ``diagrams/two_state_paper.yaml``) loaded with
Drake's :func:`pydrake.common.yaml.yaml_load_typed` into the dataclasses
below. Before that, the raw YAML is walked against the schema so that unknown
keys, missing keys and values of the wrong type are reported with their full
key path (``critic.kc``); numbers such as ``1e-2``, which PyYAML's YAML 1.1
rules read as strings, count as the numbers YAML 1.2 reads.
:func:`validate_scenario` then checks values and dimensions against the named
system, after holding the dataclasses to the same schema (so does a scenario
built or changed in Python).

Keys marked *optional* in a dataclass docstring may be omitted; every other key
is required.
"""

# No "from __future__ import annotations": Drake reads the field types at run time.

import dataclasses
import re
import stat
import types
import typing
from dataclasses import dataclass, field
from decimal import ROUND_CEILING, Decimal
from pathlib import Path
from typing import Any, Optional

import numpy as np
import yaml
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.systems.analysis import GetIntegrationSchemes

from ofrl_drake.checks import drake_seed, integer_at_least
from ofrl_drake.errors import OfrlError, ScenarioError, ScenarioTypeError, one_line

__all__ = [
    "ABORT_BOX_FACTOR",
    "BLOCK_KINDS",
    "CRITIC_LAWS",
    "GAIN_CHOICES",
    "MANUAL_GAINS",
    "ActuationConfig",
    "BoxConfig",
    "CostConfig",
    "CriticConfig",
    "EquilibriumConfig",
    "MeasurementConfig",
    "ObserverConfig",
    "PlantConfig",
    "PointsConfig",
    "Scenario",
    "SimulationConfig",
    "TruthConfig",
    "VariantConfig",
    "abort_box",
    "check_scenario",
    "check_yaml",
    "critic_gains_choice",
    "dump_scenario",
    "load_scenario",
    "manual_gains",
    "validate_scenario",
    "variant_choices",
]

_OPTIONAL = {"optional": True}

#: The default ``simulation.abort_box`` is the observer box scaled this many
#: times about its centre.
ABORT_BOX_FACTOR = 10.0


@dataclass
class BoxConfig:
    """An axis-aligned box ``lower <= x <= upper``."""

    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)


@dataclass
class CostConfig:
    """``Q(x) = x^T Q x`` and ``R = diag(R)`` of the saturated input cost."""

    Q: list[list[float]] = field(default_factory=list)
    R: list[float] = field(default_factory=list)


#: The critic's learning laws (``critic.law``; see :mod:`ofrl_drake.learning`).
CRITIC_LAWS = ("policy_iteration", "paper")

#: How the learning gains are chosen (``critic.gains``).
GAIN_CHOICES = ("auto", "manual")

#: The gains ``critic.gains: manual`` needs, and ``auto`` derives.
MANUAL_GAINS = ("kc", "nu", "beta", "Gamma0")


@dataclass
class CriticConfig:
    """Value-function basis, initial weights, the learning law and its gains.

    ``law`` (optional): ``policy_iteration`` (default; normalized regressors,
    bounded-gain forgetting, policy updates that pass an acceptance test
    on the linearization) or ``paper`` (the laws (W_c) and (gamma) as printed); see
    :mod:`ofrl_drake.learning`. ``gains`` (optional): ``auto`` derives ``kc``,
    ``nu``, ``beta``, ``Gamma0`` and ``policy_period`` from the plant, the
    points and the horizon; ``manual`` takes them from the file. By default
    ``manual`` when any of ``kc``, ``nu``, ``beta``, ``Gamma0`` is given, else
    ``auto``. ``Gamma0`` is the full initial least-squares gain (symmetric
    positive definite). ``nu`` is the paper's normalization gain (its
    ``gamma``). ``policy_period`` (seconds between policy improvements) and
    ``gamma_bound`` (``k0`` of bounded-gain forgetting) apply to
    ``policy_iteration`` only.
    """

    basis_degrees: list[int] = field(default_factory=lambda: [2])
    W0: list[float] = field(default_factory=list)
    Gamma0: Optional[list[list[float]]] = field(default=None, metadata=_OPTIONAL)
    kc: Optional[float] = field(default=None, metadata=_OPTIONAL)
    nu: Optional[float] = field(default=None, metadata=_OPTIONAL)
    beta: Optional[float] = field(default=None, metadata=_OPTIONAL)
    law: str = field(default="policy_iteration", metadata=_OPTIONAL)
    gains: str = field(default="", metadata=_OPTIONAL)
    policy_period: Optional[float] = field(default=None, metadata=_OPTIONAL)
    gamma_bound: Optional[float] = field(default=None, metadata=_OPTIONAL)


@dataclass
class PointsConfig:
    """Bellman-error extrapolation points.

    ``kind`` is ``grid`` (uses ``counts``) or ``uniform`` (uses ``number`` and
    ``seed``). ``counts``, ``number`` and ``seed`` are optional.
    """

    kind: str = "grid"
    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)
    counts: list[int] = field(default_factory=list, metadata=_OPTIONAL)
    number: int = field(default=100, metadata=_OPTIONAL)
    seed: int = field(default=0, metadata=_OPTIONAL)


@dataclass
class ObserverConfig:
    """Observer design: decay rate ``alpha`` and the box of the Jacobian bounds.

    Optional: ``formulation``, any key of
    :data:`ofrl_drake.design.FORMULATIONS`: ``polytopic`` (default; a sound
    decay certificate over every corner of the Jacobian bounds, with H = K =
    0), ``structured`` (the same claim as one S-procedure LMI of size n + k per
    input vertex, one multiplier per uncertain entry, for plants with too many
    uncertain entries for the corners; ``structured_row``: one per row; see
    docs/structured_certificate.md) or ``paper`` (the paper's (lmi2) with the
    sign-correct sector, which does not imply decay for every nonlinear
    plant; see docs/theory.md);
    ``L``, ``H``, ``K`` pin the gains (all three or none);
    ``jacobian_method`` (``sampled`` or ``certified``), ``solver``;
    ``jacobian_tol`` (> 0) and ``jacobian_rtol`` (>= 0), the tolerances of the
    certified bounds' refinement (:func:`ofrl_drake.jacobian_bounds.jacobian_bounds`'s
    ``tol`` and ``rtol``; default: its defaults);
    ``schedule_period`` > 0 re-solves the LMI every that many seconds over the
    box ``xhat +- schedule_half_width`` (default: half the box width), the
    paper's "final values from the simulation".
    """

    alpha: float = 2.0
    box: BoxConfig = field(default_factory=BoxConfig)
    formulation: str = field(default="polytopic", metadata=_OPTIONAL)
    jacobian_method: str = field(default="certified", metadata=_OPTIONAL)
    jacobian_tol: Optional[float] = field(default=None, metadata=_OPTIONAL)
    jacobian_rtol: Optional[float] = field(default=None, metadata=_OPTIONAL)
    solver: str = field(default="clarabel", metadata=_OPTIONAL)
    L: Optional[list[list[float]]] = field(default=None, metadata=_OPTIONAL)
    H: Optional[list[list[float]]] = field(default=None, metadata=_OPTIONAL)
    K: Optional[list[list[float]]] = field(default=None, metadata=_OPTIONAL)
    schedule_period: float = field(default=0.0, metadata=_OPTIONAL)
    schedule_half_width: list[float] = field(default_factory=list, metadata=_OPTIONAL)


#: How the plant, observer and controller blocks are built (``simulation.blocks``).
BLOCK_KINDS = ("auto", "symbolic", "python")


@dataclass
class SimulationConfig:
    """Horizon and Drake integrator settings.

    ``integrator`` is a Drake scheme name (``runge_kutta3``, ``radau3``, ...);
    ``accuracy`` its error-control target; ``max_step`` its largest step;
    ``log_period`` the sampling period of the logs (optional, default 0.01 s).

    ``blocks`` (optional) picks how the plant, observer, controller, critic
    and running-cost blocks are built: ``"symbolic"``, as Drake C++ ``SymbolicVectorSystem``
    blocks evaluating ``f`` and ``g`` traced symbolically (fastest; see
    :mod:`ofrl_drake.systems.symbolic`); ``"python"``, as Python
    ``LeafSystem`` blocks calling ``f`` and ``g``; ``"auto"`` (default),
    symbolic whenever ``f`` and ``g`` can be traced, else python.

    Guards of the run (optional; see :mod:`ofrl_drake.guard`): the run stops
    with status ``diverged`` when x or xhat leaves ``abort_box`` (default: the
    observer box scaled :data:`ABORT_BOX_FACTOR` times about its centre, see
    :func:`abort_box`) or a state turns non-finite, and with status
    ``timeout`` after ``max_wall_time`` seconds of wall time (default: no limit).
    """

    duration: float = 30.0
    integrator: str = "runge_kutta3"
    accuracy: float = 1e-6
    max_step: float = 0.1
    log_period: float = field(default=0.01, metadata=_OPTIONAL)
    blocks: str = field(default="auto", metadata=_OPTIONAL)
    abort_box: Optional[BoxConfig] = field(default=None, metadata=_OPTIONAL)
    max_wall_time: Optional[float] = field(default=None, metadata=_OPTIONAL)
    regulation_tolerance: float = field(default=0.05, metadata=_OPTIONAL)


@dataclass
class VariantConfig:
    """One choice per slot of the registry (:mod:`ofrl_drake.slots`); all optional.

    The defaults are the registry's :data:`~ofrl_drake.slots.BASELINE`, but
    ``points``, which defaults to the scenario's ``points.kind``.
    ``constant_input`` is the input the ``constant`` controller holds (m
    entries, each within ``input_bound``).
    """

    observer: str = field(default="three_gain", metadata=_OPTIONAL)
    controller: str = field(default="learned", metadata=_OPTIONAL)
    points: str = field(default="", metadata=_OPTIONAL)
    gamma: str = field(default="least_squares", metadata=_OPTIONAL)
    constant_input: list[float] = field(default_factory=list, metadata=_OPTIONAL)


@dataclass
class PlantConfig:
    """A Drake plant: exactly one of ``multibody`` and ``drake_system``.

    ``multibody`` is a model file (SDF, URDF, MJCF; a relative path is taken
    from the scenario file's folder) or a ``package://`` URL; the state is
    ``[q; v]``, the input the actuation. ``drake_system`` is
    ``"module.path:callable"`` of a Drake ``System`` class or of a function of
    no arguments returning one, e.g. ``pydrake.examples:PendulumPlant``.
    Optional: ``C`` (required with ``drake_system``; for ``multibody`` the
    default measures the positions q), ``input_port`` (the name of the
    ``drake_system``'s input port; default: its first).
    """

    multibody: str = field(default="", metadata=_OPTIONAL)
    drake_system: str = field(default="", metadata=_OPTIONAL)
    C: Optional[list[list[float]]] = field(default=None, metadata=_OPTIONAL)
    input_port: str = field(default="", metadata=_OPTIONAL)


@dataclass
class EquilibriumConfig:
    """The operating point ``(x*, u*)`` to regulate to, in the plant's own coordinates.

    The method then runs on ``z = x - x*``, ``v = u - u*``; ``u`` is optional
    (zeros).
    """

    x: list[float] = field(default_factory=list)
    u: list[float] = field(default_factory=list, metadata=_OPTIONAL)


@dataclass
class TruthConfig:
    """The plant that is simulated, when it differs from the model (all keys optional).

    ``system`` or ``plant`` name it as the scenario's own keys do; with neither,
    the truth is the model's own plant. ``body_mass_scale`` multiplies the mass
    of named bodies of a multibody truth (``{Pole: 1.2}``), through Drake's
    parameters in the Context. The truth runs in the model's coordinates (the
    scenario's equilibrium), without checking that ``x*`` is an equilibrium
    of the truth: a wrong model may not have the same one.
    """

    system: str = field(default="", metadata=_OPTIONAL)
    plant: Optional[PlantConfig] = field(default=None, metadata=_OPTIONAL)
    body_mass_scale: dict[str, float] = field(default_factory=dict, metadata=_OPTIONAL)


@dataclass
class MeasurementConfig:
    """What the sensors do to ``y`` (all keys optional).

    Gaussian noise of standard deviations ``noise_std`` (one per output; empty
    for none) from Drake's ``RandomSource``, seeded by ``seed``, and ``y`` sampled
    and held every ``period`` seconds (0: continuous). Noise needs
    ``period > 0``.
    """

    noise_std: list[float] = field(default_factory=list, metadata=_OPTIONAL)
    period: float = field(default=0.0, metadata=_OPTIONAL)
    seed: int = field(default=0, metadata=_OPTIONAL)


@dataclass
class ActuationConfig:
    """What the actuators do to ``u`` (all keys optional).

    The controller's output is held for ``period`` seconds (0: continuous), a
    sampled-data controller; ``disturbance`` (one per input; empty for none)
    is a constant input disturbance the plant receives on top of it.
    """

    period: float = field(default=0.0, metadata=_OPTIONAL)
    disturbance: list[float] = field(default_factory=list, metadata=_OPTIONAL)


@dataclass
class Scenario:
    """One closed-loop experiment.

    The plant is named by exactly one of ``system`` (a registered example or
    ``"module.path:callable"``) and ``plant`` (a Drake system or multibody
    model). Optional: ``system``/``plant`` (one of them), ``equilibrium``
    (then ``x0``, ``xhat0``, the boxes, the points and ``input_bound`` are
    relative to it), ``name``, ``variant``, and the real-world conditions
    ``truth`` (the plant simulated, when it is not the model), ``measurement``
    (noisy, sampled ``y``) and ``actuation`` (held ``u``, an input disturbance).
    """

    system: str = field(default="", metadata=_OPTIONAL)
    x0: list[float] = field(default_factory=list)
    xhat0: list[float] = field(default_factory=list)
    input_bound: float = 1.0
    cost: CostConfig = field(default_factory=CostConfig)
    critic: CriticConfig = field(default_factory=CriticConfig)
    points: PointsConfig = field(default_factory=PointsConfig)
    observer: ObserverConfig = field(default_factory=ObserverConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    name: str = field(default="scenario", metadata=_OPTIONAL)
    variant: VariantConfig = field(default_factory=VariantConfig, metadata=_OPTIONAL)
    plant: Optional[PlantConfig] = field(default=None, metadata=_OPTIONAL)
    equilibrium: Optional[EquilibriumConfig] = field(default=None, metadata=_OPTIONAL)
    truth: Optional[TruthConfig] = field(default=None, metadata=_OPTIONAL)
    measurement: Optional[MeasurementConfig] = field(default=None, metadata=_OPTIONAL)
    actuation: Optional[ActuationConfig] = field(default=None, metadata=_OPTIONAL)


# --------------------------------------------------------------------------
# Raw-YAML checks: unknown, missing and mistyped keys, named by their path.
# --------------------------------------------------------------------------
def _strip_optional(tp: Any) -> tuple[Any, bool]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0], True
    return tp, False


#: The exact Python types a list item of the schema type may have without further checks.
_PLAIN_TYPES: dict[Any, tuple[type, ...]] = {float: (float, int), int: (int,), str: (str,)}


def _check_value(path: str, tp: Any, value: Any, *, typed: bool = False) -> None:
    """Check ``value`` against the schema type ``tp``, naming ``path`` when it does not fit.

    ``typed=False`` checks raw YAML data (a dataclass is a mapping of keys);
    ``typed=True`` checks the objects of a scenario built in Python (a
    dataclass is an instance of it, see :func:`_check_fields`).
    """
    tp, nullable = _strip_optional(tp)
    if value is None:
        if nullable:
            return
        raise ScenarioError(f"{path}: a value is required; got {'None' if typed else 'null'}.")
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if typed:
            _check_fields(path, tp, value)
        else:
            _check_mapping(path, tp, value)
        return
    origin = typing.get_origin(tp)
    if origin is dict:
        if not isinstance(value, dict):
            raise ScenarioError(f"{path}: expected a mapping; got {_shown(value)}.")
        key_tp, item_tp = typing.get_args(tp)
        for key, item in value.items():
            _check_value(f"{path}.{key}", key_tp, key, typed=typed)
            _check_value(f"{path}.{key}", item_tp, item, typed=typed)
        return
    if origin is list:
        if not isinstance(value, list):
            raise ScenarioError(f"{path}: expected a list; got {_shown(value)}.")
        (item_tp,) = typing.get_args(tp)
        plain = _PLAIN_TYPES.get(item_tp)
        if plain is not None and all(type(item) in plain for item in value):
            if not any(type(item) is int and _beyond_float(item) for item in value):
                return  # the common case, fast for a large Gamma0
        for i, item in enumerate(value):
            _check_value(f"{path}[{i}]", item_tp, item, typed=typed)
        return
    fix = ""
    if tp is float:
        # A plain 1e-2 is a number (YAML 1.2); Drake's typed loader reads it with float().
        ok = isinstance(value, _PlainNumber) or (
            isinstance(value, (int, float)) and not isinstance(value, bool)
        )
        kind = "a number"
        if isinstance(value, str) and _is_float_text(value):
            fix = " (a quoted string); write the number without quotes"
        if ok and isinstance(value, int) and _beyond_float(value):
            # Drake's typed loader would raise OverflowError: name the key instead.
            raise ScenarioError(
                f"{path}: the integer {_shown(value)} is beyond the largest float (about "
                "1.8e308); write a finite number."
            )
    elif tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
        kind = "an integer"
        fix = _integer_fix(value)
    elif tp is str:
        ok = isinstance(value, str)
        kind = "a string"
        if path == "system":
            fix = (
                "; a scenario names its plant: an example's name, or 'module.path:callable' "
                "(a function of no arguments returning a ControlAffineSystem; "
                "ofrl_drake.examples.register(name, factory) names one made in Python)"
            )
    else:  # pragma: no cover - schema types are all listed above
        ok, kind = True, str(tp)
    if not ok:
        raise ScenarioError(f"{path}: expected {kind}; got {_shown(value)}{fix}.")


def _beyond_float(value: int) -> bool:
    """Whether the integer ``value`` is beyond the largest float (``float()`` overflows)."""
    try:
        float(value)
    except OverflowError:
        return True
    return False


def _is_float_text(text: str) -> bool:
    """Whether ``text`` is a decimal number as YAML 1.2 writes one (``0.01``, ``1e-2``, ``3``)."""
    return _NUMBER_TEXT.fullmatch(text) is not None


def _integer_fix(value: Any) -> str:
    """How to write ``value`` as the integer it means, if it is a whole number in another form."""
    if isinstance(value, _PlainNumber):
        value = float(value)
    elif not isinstance(value, float):
        return ""
    if not value.is_integer() or abs(value) > 2**53:
        return ""
    return f"; write it as the integer {int(value)} (digits only, no decimal point or exponent)"


def _shown(value: Any) -> str:
    """``value`` for an error message, with the fix when it is a numpy array or scalar."""
    if isinstance(value, np.ndarray):
        return (
            f"a numpy array of shape {value.shape}; pass a list (e.g. array.tolist()): a "
            "scenario holds plain lists, which it writes to YAML and JSON"
        )
    if isinstance(value, np.generic):
        plain = type(value.item()).__name__
        return f"the numpy scalar {value!r}; pass a plain Python {plain} (e.g. value.item())"
    if isinstance(value, tuple):
        return f"the tuple {value!r}; pass a list"
    text = repr(value)
    return text if len(text) <= 200 else text[:200] + "..."


def _check_mapping(path: str, schema: type, data: Any) -> None:
    where = path or "scenario"
    if not isinstance(data, dict):
        what = "nothing (the file or section is empty)" if data is None else _shown(data)
        raise ScenarioError(f"{where}: expected a mapping of keys; got {what}.")
    hints = typing.get_type_hints(schema)
    fields = {f.name: f for f in dataclasses.fields(schema)}
    prefix = f"{path}." if path else ""
    unknown = sorted(set(data) - set(fields), key=str)  # a key may be a number: 1: ...
    if unknown:
        raise ScenarioError(
            f"{prefix}{unknown[0]}: unknown key in {where}; allowed keys are {sorted(fields)}."
        )
    for name, f in fields.items():
        if name not in data:
            if not f.metadata.get("optional", False):
                raise ScenarioError(f"{prefix}{name}: missing required key in {where}.")
            continue
        _check_value(prefix + name, hints[name], data[name])


def _check_fields(path: str, schema: type, obj: Any) -> None:
    """The schema check of :func:`_check_mapping`, on a dataclass built in Python.

    Every field of ``obj`` is checked against its type annotation, so that a
    scenario made with ``dataclasses.replace`` is held to the types a YAML file
    is held to.
    """
    where = path or "scenario"
    if not isinstance(obj, schema):
        keys = ", ".join(f"{f.name}=..." for f in dataclasses.fields(schema))
        raise ScenarioError(
            f"{where}: expected an instance of {schema.__name__}; got {_shown(obj)}; pass "
            f"ofrl_drake.scenario.{schema.__name__}({keys}) (mappings of keys are read from "
            "YAML files only)."
        )
    hints = typing.get_type_hints(schema)
    prefix = f"{path}." if path else ""
    for f in dataclasses.fields(schema):
        _check_value(prefix + f.name, hints[f.name], getattr(obj, f.name), typed=True)


# --------------------------------------------------------------------------
# Value and dimension checks.
# --------------------------------------------------------------------------
def _vector(path: str, value: list[float], size: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (size,):
        raise ScenarioError(f"{path}: expected {size} entries; got {len(value)}.")
    if not np.all(np.isfinite(arr)):
        raise ScenarioError(f"{path}: entries must be finite; got {value}.")
    return arr


def _matrix(path: str, value: list[list[float]], shape: tuple[int, int]) -> np.ndarray:
    if any(len(row) != len(value[0]) for row in value) if value else True:
        raise ScenarioError(
            f"{path}: expected a {shape[0]}x{shape[1]} matrix; got {_shown(value)}."
        )
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise ScenarioError(
            f"{path}: expected a {shape[0]}x{shape[1]} matrix; got {arr.shape[0]}x{arr.shape[1]}."
        )
    if not np.all(np.isfinite(arr)):
        i, j = (int(k) for k in np.argwhere(~np.isfinite(arr))[0])
        raise ScenarioError(f"{path}: entries must be finite; entry [{i}][{j}] is {arr[i, j]}.")
    return arr


def _positive(path: str, value: float, *, allow_zero: bool = False) -> None:
    bad = value < 0 if allow_zero else value <= 0
    if bad or np.isnan(value):
        need = ">= 0" if allow_zero else "> 0"
        raise ScenarioError(f"{path}: must be {need}; got {value}.")
    if not np.isfinite(value):
        raise ScenarioError(f"{path}: must be a finite number; got {value}.")


def _spd(path: str, M: np.ndarray, *, semi: bool = False) -> None:
    atol = 1e-12 * max(1.0, np.abs(M).max())
    if not np.allclose(M, M.T, rtol=0, atol=atol):
        i, j = (int(k) for k in np.argwhere(np.abs(M - M.T) > atol)[0])
        raise ScenarioError(
            f"{path}: must be symmetric; entry [{i}][{j}] is {M[i, j]:.17g} but [{j}][{i}] is "
            f"{M[j, i]:.17g}."
        )
    lam = np.linalg.eigvalsh(M)[0]
    if (lam < 0) if semi else (lam <= 0):
        kind = "positive semidefinite" if semi else "positive definite"
        raise ScenarioError(
            f"{path}: must be symmetric {kind}; its smallest eigenvalue is {lam:.6g}."
        )


#: The tightest ``simulation.accuracy``: below it the error estimate is round-off.
MIN_ACCURACY = 1e-12

#: The loosest ``simulation.accuracy``: Drake's integrators clamp a looser target to it.
MAX_ACCURACY = 0.1

#: Drake schemes that cannot run the closed loop: ``cenic`` needs a discrete
#: contact model, which no ofrl_drake plant has.
UNSUPPORTED_SCHEMES = ("cenic",)


def integration_schemes() -> list[str]:
    """Drake's integration schemes that run the closed loop, sorted."""
    return sorted(set(GetIntegrationSchemes()) - set(UNSUPPORTED_SCHEMES))


def check_scenario(scenario: object, caller: str, *, paths: bool = False) -> None:
    """Refuse a ``scenario`` argument that is not a :class:`~ofrl_drake.scenario.Scenario`.

    Parameters
    ----------
    scenario : object
        The argument.
    caller : str
        Who was given it (``"build_closed_loop"``), for the message.
    paths : bool, optional
        Whether ``caller`` also takes the path of a scenario file (it has
        loaded one before asking), as the message then says.

    Raises
    ------
    ScenarioError
        Naming what was given and :func:`~ofrl_drake.load_scenario` as the
        fix; it is also a ``TypeError``.
    """
    if isinstance(scenario, Scenario):
        return
    accepted = "a Scenario or the path of a scenario file" if paths else "a Scenario"
    if isinstance(scenario, (str, Path)):
        raise ScenarioTypeError(
            f"{caller}: scenario must be {accepted}; got the path {str(scenario)!r}. Load "
            f"it first with ofrl_drake.load_scenario({str(scenario)!r})."
        )
    raise ScenarioTypeError(
        f"{caller}: scenario must be {accepted}; got {type(scenario).__name__}. Load one "
        "with ofrl_drake.load_scenario(path)."
    )


def validate_scenario(scenario: Scenario) -> None:
    """Check every value of ``scenario`` against its system's dimensions.

    First every field is checked against the type the schema gives it, as a
    YAML file's keys are: a scenario built or changed in Python (with
    ``dataclasses.replace``) must hold lists where the schema has lists (not
    numpy arrays: ``Q.tolist()``), integers where it has integers (``points.seed``,
    ``points.counts``, ``measurement.seed``) and the config dataclasses where it
    has them (not mappings). ``scenario`` is not changed.

    Raises
    ------
    ScenarioError
        Naming the first bad key, its value and what is expected: a value of
        the wrong type, a wrong size or a value out of range, a basis without
        an even degree, a ``simulation.log_period`` so small that the logs
        would take more than :data:`MAX_LOG_BYTES` (naming the smallest period
        that fits), a ``simulation.max_step``, ``measurement.period`` or
        ``actuation.period`` that would take more than :data:`MAX_STEPS`
        integrator steps over the horizon, or an ``observer.schedule_period``
        more than :data:`MAX_SCHEDULE_SOLVES` LMI solves (each naming the
        smallest period allowed), a ``measurement.seed`` beyond the 32 bits
        Drake's random sources keep (``2**32 - 1``), or a truth whose sizes
        differ from the model's.
    """
    # Imported here: the registry imports model code, the scenario does not need it
    # for parsing.
    from ofrl_drake.basis import PolynomialBasis
    from ofrl_drake.design import FORMULATIONS, SOLVERS
    from ofrl_drake.jacobian_bounds import METHODS
    from ofrl_drake.plants import resolve_system

    check_scenario(scenario, "validate_scenario")
    _check_fields("", Scenario, scenario)
    if len(scenario.name) > MAX_NAME_LENGTH:
        raise ScenarioError(
            f"name: {len(scenario.name)} characters; a name is at most {MAX_NAME_LENGTH} "
            "(it labels the files, figures and diagram)."
        )
    system = resolve_system(scenario)
    n, m, q = system.n, system.m, system.q
    _vector("x0", scenario.x0, n)
    _vector("xhat0", scenario.xhat0, n)
    _positive("input_bound", scenario.input_bound)
    if scenario.input_bound > MAX_INPUT_BOUND:
        raise ScenarioError(
            f"input_bound: {scenario.input_bound:g} is beyond what the input sector and the "
            f"input cost hold in double precision (products with it overflow); at most "
            f"{MAX_INPUT_BOUND:g}."
        )

    Q = _matrix("cost.Q", scenario.cost.Q, (n, n))
    _spd("cost.Q", Q, semi=True)
    R = _vector("cost.R", scenario.cost.R, m)
    if np.any(R <= 0):
        raise ScenarioError(f"cost.R: entries must be > 0; got {scenario.cost.R}.")

    c = scenario.critic
    try:
        basis = PolynomialBasis(n, c.basis_degrees)
    except ValueError as err:
        raise ScenarioError(f"critic.basis_degrees: {err}") from None
    if not any(d % 2 == 0 for d in c.basis_degrees):
        raise ScenarioError(
            f"critic.basis_degrees: {c.basis_degrees} holds only odd degrees, so "
            "V(x) = W^T sigma(x) is odd (V(-x) = -V(x)) and can never be positive definite; "
            "add an even degree, e.g. [2] or [2, 3]."
        )
    L = basis.size
    _vector("critic.W0", c.W0, L)
    if c.law not in CRITIC_LAWS:
        raise ScenarioError(f"critic.law: must be one of {list(CRITIC_LAWS)}; got {c.law!r}.")
    gains = critic_gains_choice(c)
    given = [k for k in MANUAL_GAINS if getattr(c, k) is not None]
    if gains == "auto" and given:
        raise ScenarioError(
            f"critic.{given[0]}: given, but critic.gains is auto, which derives it; remove "
            f"{', '.join('critic.' + k for k in given)} or set critic.gains: manual."
        )
    if gains == "manual":
        kc, nu, beta, given_gamma0 = manual_gains(c)
        Gamma0 = _matrix("critic.Gamma0", given_gamma0, (L, L))
        _spd("critic.Gamma0", Gamma0)
        _positive("critic.kc", kc)
        _positive("critic.nu", nu)
        _positive("critic.beta", beta)
    if c.law == "paper":
        for key in ("policy_period", "gamma_bound"):
            if getattr(c, key) is not None:
                raise ScenarioError(
                    f"critic.{key}: applies to critic.law: policy_iteration only; the paper's "
                    "law has no policy updates and a constant forgetting factor. Remove it."
                )
    if c.policy_period is not None:
        _positive("critic.policy_period", c.policy_period)
    if c.gamma_bound is not None:
        _positive("critic.gamma_bound", c.gamma_bound)

    p = scenario.points
    if p.kind not in ("grid", "uniform"):
        raise ScenarioError(f"points.kind: must be 'grid' or 'uniform'; got {p.kind!r}.")
    lo = _vector("points.lower", p.lower, n)
    hi = _vector("points.upper", p.upper, n)
    if np.any(lo >= hi):
        raise ScenarioError(
            f"points.upper: must exceed points.lower element-wise; got lower={p.lower}, "
            f"upper={p.upper}."
        )
    if p.kind == "grid":
        if len(p.counts) != n or min(p.counts) < 1:
            raise ScenarioError(
                f"points.counts: expected {n} positive integers for a grid; got {p.counts}."
            )
    elif p.number < 1:
        raise ScenarioError(f"points.number: must be >= 1; got {p.number}.")
    integer_at_least("points.seed:", p.seed, 0, error=ScenarioError)  # numpy takes any size
    count = p.number if p.kind == "uniform" else int(np.prod([float(c) for c in p.counts]))
    per_point = POINT_BYTES_FACTOR * 8.0 * (L * n + 2 * m * L + L + n + 8)
    need = count * per_point
    if need > MAX_POINT_BYTES:
        key = "points.number" if p.kind == "uniform" else "points.counts"
        fit = int(MAX_POINT_BYTES / per_point)
        raise ScenarioError(
            f"{key}: {count:.3g} points would need about {need / 2**30:.3g} GiB for the "
            f"Bellman features (L = {L} basis functions, n = {n}); at most about {fit} "
            f"points fit in {MAX_POINT_BYTES / 2**30:g} GiB."
        )

    o = scenario.observer
    _positive("observer.alpha", o.alpha)
    blo = _vector("observer.box.lower", o.box.lower, n)
    bhi = _vector("observer.box.upper", o.box.upper, n)
    if np.any(blo >= bhi):
        raise ScenarioError(
            f"observer.box.upper: must exceed observer.box.lower element-wise; got "
            f"lower={o.box.lower}, upper={o.box.upper}."
        )
    if o.formulation not in FORMULATIONS:
        raise ScenarioError(
            f"observer.formulation: must be {' or '.join(map(repr, FORMULATIONS))}; got "
            f"{o.formulation!r}."
        )
    if o.jacobian_method not in METHODS:
        raise ScenarioError(
            f"observer.jacobian_method: must be {' or '.join(map(repr, METHODS))}; got "
            f"{o.jacobian_method!r}."
        )
    if o.jacobian_tol is not None:
        _positive("observer.jacobian_tol", o.jacobian_tol)
    if o.jacobian_rtol is not None:
        _positive("observer.jacobian_rtol", o.jacobian_rtol, allow_zero=True)
    if o.solver not in SOLVERS:
        raise ScenarioError(
            f"observer.solver: must be one of {', '.join(SOLVERS)}; got {o.solver!r}."
        )
    pinned = [k for k in ("L", "H", "K") if getattr(o, k) is not None]
    if pinned and len(pinned) != 3:
        missing = sorted({"L", "H", "K"} - set(pinned))
        raise ScenarioError(
            f"observer.{missing[0]}: pin all of L, H and K or none; got only {pinned}."
        )
    for k in pinned:
        _matrix(f"observer.{k}", getattr(o, k), (n, q))
    _positive("observer.schedule_period", o.schedule_period, allow_zero=True)
    if o.schedule_half_width:
        hw = _vector("observer.schedule_half_width", o.schedule_half_width, n)
        if np.any(hw <= 0):
            raise ScenarioError(
                f"observer.schedule_half_width: entries must be > 0; got {o.schedule_half_width}."
            )
    if o.schedule_period > 0 and pinned:
        raise ScenarioError(
            "observer.schedule_period: scheduled gains are re-designed, so they cannot be "
            "pinned; remove observer.L/H/K or set schedule_period: 0."
        )

    from ofrl_drake.slots import VARIANT_FACTORIES

    for slot, choice in variant_choices(scenario).items():
        if choice not in VARIANT_FACTORIES[slot]:
            raise ScenarioError(
                f"variant.{slot}: unknown choice {choice!r}; choose one of "
                f"{sorted(VARIANT_FACTORIES[slot])}."
            )

    if scenario.variant.controller == "constant":
        held = _vector("variant.constant_input", scenario.variant.constant_input, m)
        if np.any(np.abs(held) > scenario.input_bound):
            raise ScenarioError(
                f"variant.constant_input: entries must satisfy |u_k| <= input_bound = "
                f"{scenario.input_bound}; got {scenario.variant.constant_input}."
            )

    _validate_real_world(scenario, m, q)

    s = scenario.simulation
    _positive("simulation.duration", s.duration)
    _positive("simulation.accuracy", s.accuracy)
    if not MIN_ACCURACY <= s.accuracy <= MAX_ACCURACY:
        why = (
            "Drake's integrators use at most 0.1 (a looser target is clamped to it, so the run "
            "would not be the one recorded)"
            if s.accuracy > MAX_ACCURACY
            else "below that the error estimate is at double-precision round-off and the step "
            "shrinks without bound (1e-15 takes hours on the paper's scenario)"
        )
        raise ScenarioError(
            f"simulation.accuracy: must be between {MIN_ACCURACY:g} and {MAX_ACCURACY:g}; got "
            f"{s.accuracy:g}: {why}."
        )
    _positive("simulation.max_step", s.max_step)
    _check_event_counts(scenario)
    _positive("simulation.log_period", s.log_period)
    if s.integrator not in integration_schemes():
        raise ScenarioError(
            f"simulation.integrator: unknown scheme {s.integrator!r}; choose one of "
            f"{integration_schemes()}."
        )
    if s.log_period > s.duration:
        raise ScenarioError(
            f"simulation.log_period: {s.log_period} s is longer than the horizon "
            f"simulation.duration = {s.duration} s, so nothing after t = 0 would be logged; "
            "use a log period below the horizon."
        )
    _check_log_size(s, n, m, L)
    if s.blocks not in BLOCK_KINDS:
        raise ScenarioError(
            f"simulation.blocks: unknown kind {s.blocks!r}; choose one of {list(BLOCK_KINDS)}."
        )
    if s.abort_box is not None:
        alo = _vector("simulation.abort_box.lower", s.abort_box.lower, n)
        ahi = _vector("simulation.abort_box.upper", s.abort_box.upper, n)
        if np.any(alo >= ahi):
            raise ScenarioError(
                "simulation.abort_box.upper: must exceed simulation.abort_box.lower "
                f"element-wise; got lower={s.abort_box.lower}, upper={s.abort_box.upper}."
            )
    if s.max_wall_time is not None:
        _positive("simulation.max_wall_time", s.max_wall_time)
    _positive("simulation.regulation_tolerance", s.regulation_tolerance)


def _check_log_size(s: SimulationConfig, n: int, m: int, L: int) -> None:
    """Refuse a ``log_period`` whose logs would outgrow :data:`MAX_LOG_BYTES`.

    A run logs ``duration / log_period`` samples of x, xhat (n each), the
    critic's and the policy's weights (L each), Gamma (``L (L + 1) / 2``), u
    (m) and a few scalars and time stamps.
    """
    samples = s.duration / s.log_period
    per_sample = 8.0 * (2 * n + 2 * L + L * (L + 1) // 2 + m + _LOG_SCALARS)
    need = samples * per_sample
    if need > MAX_LOG_BYTES:
        least = _smallest_period(s.duration, MAX_LOG_BYTES / per_sample)
        raise ScenarioError(
            f"simulation.log_period: {s.log_period:g} s over simulation.duration = "
            f"{s.duration:g} s logs {samples:.3g} samples, about {need / 2**30:.3g} GiB "
            f"({per_sample / 8:.0f} numbers each: x, xhat, W, Gamma, u, ...); the logs may "
            f"take at most {MAX_LOG_BYTES / 2**30:g} GiB. Use a log_period of at least "
            f"{least:g} s (or a shorter duration)."
        )


def _smallest_period(duration: float, most: float) -> float:
    """``duration / most`` to three significant digits, rounded up: a period that passes."""
    least = duration / most
    nearest = float(f"{least:.3g}")
    if nearest >= least:
        return nearest
    exact = Decimal(least)
    return float(exact.quantize(Decimal(1).scaleb(exact.adjusted() - 2), rounding=ROUND_CEILING))


def _check_event_count(
    key: str, period: float, duration: float, what: str, most: int, most_name: str
) -> None:
    """Refuse a ``period`` > 0 that repeats more than ``most`` times over ``duration``.

    ``what`` names the events (``"integrator steps or more"``), ``most_name``
    the constant ``most`` is; the message names the smallest period allowed for
    this duration. A period of 0 (continuous) passes.
    """
    if period == 0 or period >= duration / most:
        return
    raise ScenarioError(
        f"{key}: {period:g} s over simulation.duration = {duration:g} s means "
        f"{duration / period:.3g} {what}; a run takes at most {most:,} ({most_name}), so "
        f"that it ends in minutes, not hours. Use a {key.rsplit('.', 1)[-1]} of at least "
        f"{_smallest_period(duration, most):g} s (or a shorter simulation.duration)."
    )


def _check_event_counts(scenario: Scenario) -> None:
    """Bound the integrator steps and the LMI solves the periods of ``scenario`` force.

    ``simulation.max_step``, ``measurement.period`` and ``actuation.period``
    each end an integrator step every that many seconds, so the horizon takes
    at least ``duration / period`` steps: at most :data:`MAX_STEPS`. Every
    ``observer.schedule_period`` solves an LMI: at most
    :data:`MAX_SCHEDULE_SOLVES` over the horizon.
    """
    meas, act = scenario.measurement, scenario.actuation
    ends_a_step = "(each ends an integrator step)"
    periods = [
        ("simulation.max_step", scenario.simulation.max_step, "integrator steps or more"),
        ("observer.schedule_period", scenario.observer.schedule_period, "LMI re-solves"),
        ("measurement.period", meas.period if meas else 0.0, f"samples {ends_a_step}"),
        ("actuation.period", act.period if act else 0.0, f"held inputs {ends_a_step}"),
    ]
    for key, period, what in periods:
        most, most_name = (
            (MAX_SCHEDULE_SOLVES, "MAX_SCHEDULE_SOLVES")
            if key == "observer.schedule_period"
            else (MAX_STEPS, "MAX_STEPS")
        )
        _check_event_count(key, period, scenario.simulation.duration, what, most, most_name)


def _validate_real_world(scenario: Scenario, m: int, q: int) -> None:
    """Check ``truth``, ``measurement`` and ``actuation`` against the model's sizes."""
    from ofrl_drake.plants import resolve_truth

    meas = scenario.measurement
    if meas is not None:
        if meas.noise_std:
            std = _vector("measurement.noise_std", meas.noise_std, q)
            if np.any(std < 0):
                raise ScenarioError(
                    f"measurement.noise_std: entries must be >= 0; got {meas.noise_std}."
                )
        _positive("measurement.period", meas.period, allow_zero=True)
        if meas.noise_std and any(v > 0 for v in meas.noise_std) and meas.period == 0:
            raise ScenarioError(
                "measurement.period: noise is drawn once per sample, so it needs a sampling "
                f"period > 0; got 0 with noise_std = {meas.noise_std}. Set e.g. period: 0.01."
            )
        drake_seed("measurement.seed:", meas.seed, error=ScenarioError)
    act = scenario.actuation
    if act is not None:
        _positive("actuation.period", act.period, allow_zero=True)
        if act.disturbance:
            _vector("actuation.disturbance", act.disturbance, m)
    truth = scenario.truth
    if truth is not None:
        if truth.system and truth.plant is not None:
            raise ScenarioError(
                "truth: give at most one of truth.system and truth.plant (neither: the "
                "model's own plant)."
            )
        for body, scale in truth.body_mass_scale.items():
            if not (np.isfinite(scale) and scale > 0):
                raise ScenarioError(
                    f"truth.body_mass_scale.{body}: must be a number > 0; got {scale}."
                )
        resolve_truth(scenario)  # builds it, checks its sizes against the model's


def manual_gains(critic: CriticConfig) -> tuple[float, float, float, list[list[float]]]:
    """``(kc, nu, beta, Gamma0)`` as ``critic.gains: manual`` gives them.

    Raises
    ------
    ScenarioError
        If one of them is missing.
    """
    kc, nu, beta, Gamma0 = critic.kc, critic.nu, critic.beta, critic.Gamma0
    if kc is None or nu is None or beta is None or Gamma0 is None:
        missing = [k for k in MANUAL_GAINS if getattr(critic, k) is None]
        raise ScenarioError(
            f"critic.{missing[0]}: missing; critic.gains: manual needs "
            f"{', '.join('critic.' + k for k in MANUAL_GAINS)} (or set critic.gains: auto)."
        )
    return kc, nu, beta, Gamma0


def critic_gains_choice(critic: CriticConfig) -> str:
    """``critic.gains`` in force: as given, else ``manual`` if any gain is given, else ``auto``.

    Raises
    ------
    ScenarioError
        If ``critic.gains`` is neither ``auto`` nor ``manual``.
    """
    if critic.gains:
        if critic.gains not in GAIN_CHOICES:
            raise ScenarioError(
                f"critic.gains: must be one of {list(GAIN_CHOICES)}; got {critic.gains!r}."
            )
        return critic.gains
    return "manual" if any(getattr(critic, k) is not None for k in MANUAL_GAINS) else "auto"


def abort_box(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)`` of the box a run must keep x and xhat in.

    ``simulation.abort_box`` if the scenario gives one, otherwise the observer
    box scaled :data:`ABORT_BOX_FACTOR` times about its centre (``[-2, 2]^2``
    gives ``[-20, 20]^2``).
    """
    given = scenario.simulation.abort_box
    if given is not None:
        return np.asarray(given.lower, dtype=float), np.asarray(given.upper, dtype=float)
    lower = np.asarray(scenario.observer.box.lower, dtype=float)
    upper = np.asarray(scenario.observer.box.upper, dtype=float)
    centre, half = 0.5 * (lower + upper), 0.5 * (upper - lower)
    return centre - ABORT_BOX_FACTOR * half, centre + ABORT_BOX_FACTOR * half


def dump_scenario(scenario: Scenario) -> str:
    """``scenario`` as YAML that :func:`load_scenario` reads back to an equal scenario.

    Every optional key is written with the value in force (defaults
    included, the abort box resolved by :func:`abort_box`), and floats are
    written in their shortest exact form, so a run of the file reproduces the
    run of ``scenario`` bit for bit.
    """
    lower, upper = abort_box(scenario)
    resolved = dataclasses.replace(
        scenario,
        simulation=dataclasses.replace(
            scenario.simulation,
            abort_box=BoxConfig(lower=lower.tolist(), upper=upper.tolist()),
        ),
    )
    header = (
        "# The scenario as run, every default resolved (ofrl_drake.scenario.dump_scenario).\n"
        "# `ofrl-drake run scenario.yaml --out DIR` reproduces trajectories.npz bit for bit.\n"
    )
    return header + yaml_dump_typed(resolved)


def variant_choices(scenario: Scenario) -> dict[str, str]:
    """The slot choices of ``scenario``, with ``points`` defaulting to ``points.kind``."""
    v = scenario.variant
    return {
        "observer": v.observer,
        "controller": v.controller,
        "points": v.points or scenario.points.kind,
        "gamma": v.gamma,
    }


def _locate_files(scenario: Scenario, folder: Path) -> None:
    """Make entries that name files relative to the scenario's folder absolute.

    A ``system: "module:callable"`` whose module lies beside the scenario file
    becomes ``"/abs/module.py:callable"``, which any process (a Dask worker
    started elsewhere) can import; so do ``plant.drake_system`` and a relative
    ``plant.multibody`` file, and the same keys under ``truth``.
    """
    _locate_plant(scenario, folder.resolve(), "")
    if scenario.truth is not None:
        _locate_plant(scenario.truth, folder.resolve(), "truth.")


def _locate_plant(owner: Scenario | TruthConfig, folder: Path, prefix: str) -> None:
    """:func:`_locate_files` for the ``system`` and ``plant`` of ``owner``, in place.

    ``prefix`` (``""`` or ``"truth."``) completes the key names of messages.
    """
    from ofrl_drake.plants import locate_model_file, locate_system_entry

    owner.system = locate_system_entry(owner.system, folder, key=f"{prefix}system")
    if owner.plant is not None:
        owner.plant.drake_system = locate_system_entry(
            owner.plant.drake_system, folder, key=f"{prefix}plant.drake_system"
        )
        owner.plant.multibody = locate_model_file(owner.plant.multibody, folder)


#: Largest ``input_bound``: the sector bounds multiply it with Jacobian bounds and
#: the input cost squares it, so far larger values overflow.
MAX_INPUT_BOUND = 1e12

#: Largest memory the extrapolation points may take, in bytes.
MAX_POINT_BYTES = 2 * 2**30

#: The peak memory of a run per extrapolation point, over the numbers its features hold
#: (the gradients and the per-point data, ``L n + 2 m L + L + n + 8``): measured 1.97 on
#: the paper's plant (393 bytes per point at 10^6 points) and 1.82 on the cart-pole
#: (1,196 bytes at 10^5), from the features' transients and the copies the
#: Bellman block and the policy evaluations hold. The estimate used 1 and passed 10^7
#: points on the paper's plant, which then took 3.6 GB.
POINT_BYTES_FACTOR = 2.0

#: Largest memory the logs of a run may take, in bytes: ``duration / log_period``
#: samples of x, xhat, W, the policy's weights, Gamma (``L (L + 1) / 2`` entries),
#: u and a few scalars (:func:`validate_scenario` estimates it). About ten million
#: samples of the paper's two-state example (27 numbers each), 80,000 of the
#: quadrotor (L = 78: 3,275 numbers): far above any real run (the shipped ones log
#: 600 to 3,000 samples); a ``log_period`` of 1e-12 s would otherwise fill the memory.
MAX_LOG_BYTES = 2 * 2**30

#: Numbers per logged sample besides the vectors: the running cost, the learning
#: condition, the policy updates and every logger's time stamps.
_LOG_SCALARS = 10

#: Most integrator steps a run may be forced to take over its horizon:
#: ``simulation.duration`` divided by ``simulation.max_step``, ``measurement.period``
#: or ``actuation.period`` (each period ends a step). A step of the two-state
#: example takes about 150 us (measured: 120 to 150 us with max_step, a
#: measurement or an actuation period of 1e-4 or 1e-5 s), so ten million steps
#: take about 25 minutes there (longer on larger plants): room for any honest
#: run, five thousand times the most a shipped scenario takes (2,000 samples of
#: ``cart_pole_real_world.yaml``), and about as many samples as the logs hold
#: (:data:`MAX_LOG_BYTES`). A period of 1e-9 s over a 1 s horizon (a billion
#: steps, about 42 hours) is refused.
MAX_STEPS = 10_000_000

#: Most LMI re-solves ``observer.schedule_period`` may ask for over the horizon:
#: each one designs the observer again (about 35 ms on the two-state example,
#: measured at periods of 0.01 and 0.002 s), so ten thousand take about six
#: minutes; the tests re-solve at most 300 times.
MAX_SCHEDULE_SOLVES = 10_000

#: Longest ``name``, in characters (it labels files, figures and the diagram).
MAX_NAME_LENGTH = 200

#: Largest scenario file read, in bytes: a scenario is a page of YAML.
MAX_SCENARIO_BYTES = 1_000_000

#: Deepest nesting of YAML lists and mappings a scenario file may hold. The
#: schema's deepest value, a row of ``truth.plant.C``, is 4 levels below the
#: root mapping; PyYAML composes nested values recursively, so a value nested a
#: few hundred levels deep would exhaust Python's stack.
MAX_YAML_DEPTH = 20

#: Most YAML nodes a scenario may expand to (aliases included): a bound on
#: "billion laughs" files, far above any real scenario.
MAX_YAML_NODES = 100_000


_MANTISSA = r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)"
#: A decimal number of the YAML 1.2 core schema (an integer or a float, not .inf or .nan).
_NUMBER_TEXT = re.compile(_MANTISSA + r"(?:[eE][-+]?[0-9]+)?$")


class _PlainNumber(str):
    """A plain (unquoted) YAML scalar that YAML 1.2 reads as a number and YAML 1.1 as a string.

    PyYAML, and so Drake's loader, follow YAML 1.1: an exponent makes a float
    only with a decimal point and a signed exponent (``1.0e-2``), and a
    leading point only without a sign (``.5``), so ``1e-2``, ``1e1``,
    ``5.0e0``, ``-.5`` and ``+.01`` are strings. YAML 1.2 reads them as the
    numbers they are, and so does the schema check: it accepts one where a
    float is expected (Drake's typed loader, which builds the
    :class:`Scenario`, then converts it with Python's ``float``), keeps it as
    written where a string is (``name: 1e3``), and refuses it, with the
    integer to write, where an integer is. A scalar that reads as a number
    but is a plain ``str`` was therefore quoted in the file.
    """

    def __repr__(self) -> str:  # as written, unquoted: messages show what the file holds
        return str(self)


class _RawLoader(yaml.SafeLoader):
    """PyYAML's safe loader, marking plain YAML 1.2 numbers as :class:`_PlainNumber`."""


_PLAIN_NUMBER_TAG = "tag:ofrl_drake,2025:plain_number"
# Appended after YAML 1.1's own resolvers: what they read as an int or a float
# (3, 1.0e-4, .5) stays what they make of it; only the rest is marked.
_RawLoader.add_implicit_resolver(_PLAIN_NUMBER_TAG, _NUMBER_TEXT, list("-+0123456789."))
_RawLoader.add_constructor(
    _PLAIN_NUMBER_TAG, lambda loader, node: _PlainNumber(loader.construct_scalar(node))
)


class _DepthLoader(yaml.SafeLoader):
    """PyYAML's safe loader, composing at most :data:`MAX_YAML_DEPTH` nested lists and mappings.

    Raises :class:`ScenarioError` (naming the line) at the first collection
    deeper than that, before PyYAML's recursion exhausts the stack.
    """

    depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()
        if not isinstance(event, yaml.MappingStartEvent | yaml.SequenceStartEvent):
            return super().compose_node(parent, index)
        if self.depth >= MAX_YAML_DEPTH:
            raise ScenarioError(
                f"line {event.start_mark.line + 1}: lists and mappings nested more than "
                f"{MAX_YAML_DEPTH} levels deep"
            )
        self.depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def _not_yaml(path: Path, err: Exception) -> ScenarioError:
    """The error for a file PyYAML refuses, on one line (its marks name lines of ``path``)."""
    text = one_line(str(err).replace('in "<unicode string>", ', ""), 300)
    return ScenarioError(f"{path}: not valid YAML: {text}")


def _raw_yaml(path: Path, text: str) -> Any:
    """The data of a scenario file, as Drake's ``yaml_load`` gives it, with exponent numbers marked.

    Root keys that begin with an underscore (YAML anchors, templates) are
    dropped, as Drake's loader drops them.

    Raises
    ------
    ScenarioError
        If the file cannot be constructed (an unknown tag, ...).
    """
    try:
        raw = yaml.load(text, Loader=_RawLoader)  # a SafeLoader: no arbitrary objects
    except yaml.YAMLError as err:
        raise _not_yaml(path, err) from None
    if isinstance(raw, dict):
        raw = {k: v for k, v in raw.items() if not (isinstance(k, str) and k.startswith("_"))}
    return raw


def check_yaml(
    path: Path, text: str, *, error: type[OfrlError] = ScenarioError, what: str = "scenario"
) -> Any:
    """Refuse alias bombs and duplicate keys before Drake's loader sees the file.

    For scenario files and the other YAML files a command reads (an
    ablation's variants file): ``what`` names the kind of file, ``error``
    the class raised.

    The file is composed (not constructed) with PyYAML's safe loader, at most
    :data:`MAX_YAML_DEPTH` lists and mappings deep; its node
    graph is walked as an expanding loader would walk it, counting every node
    an alias repeats, up to :data:`MAX_YAML_NODES`. A mapping that repeats a
    key is refused with the key and both lines (Drake's loader keeps the last).

    Returns
    -------
    yaml.Node or None
        The composed root node (None for an empty file), for a caller's own
        checks of the file's structure.

    Raises
    ------
    OfrlError
        ``error`` (default :class:`ScenarioError`), naming the line.
    """
    try:
        root = yaml.compose(text, Loader=_DepthLoader)
    except yaml.YAMLError as err:
        raise error(str(_not_yaml(path, err))) from None
    except ScenarioError as err:  # nested too deep
        fix = (
            "no scenario key nests more than 4 below the top level (the rows of "
            "truth.plant.C). Write the value as the table in docs/scenario.md gives it: a "
            "number, a string, a list or a list of rows."
            if what == "scenario"
            else f"no {what} needs that; write its values as lists of numbers or of rows."
        )
        raise error(f"{path}: {err}; {fix}") from None
    stack = [] if root is None else [root]
    expanded = 0
    checked: set[int] = set()
    visited: set[int] = set()
    repeated = False  # an alias made the walk see a node twice
    longest: Any = None  # the longest list, named when the file itself is too big
    while stack:
        node = stack.pop()
        expanded += 1
        repeated = repeated or id(node) in visited
        visited.add(id(node))
        if expanded > MAX_YAML_NODES:
            if repeated:
                raise error(
                    f"{path}: the YAML expands to more than {MAX_YAML_NODES} values (aliases "
                    f"repeat a part many times); write the {what} out without them."
                )
            where = (
                ""
                if longest is None
                else f"; the longest list ({len(longest.value)} entries) starts at line "
                f"{longest.start_mark.line + 1}"
            )
            example = (
                " (e.g. give a critic's Gamma0 for the basis in use, or leave it out for "
                "critic.gains: auto)"
                if what == "scenario"
                else ""
            )
            raise error(
                f"{path}: the YAML holds more than {MAX_YAML_NODES} values, far more than any "
                f"{what} needs{where}; shorten it{example}."
            )
        if isinstance(node, yaml.MappingNode):
            if id(node) not in checked:
                checked.add(id(node))
                seen: dict[str, int] = {}
                for key, _ in node.value:
                    name = key.value if isinstance(key, yaml.ScalarNode) else repr(key)
                    if name in seen:
                        raise error(
                            f"{path}: key {name[:80]!r} appears twice in one mapping (lines "
                            f"{seen[name] + 1} and {key.start_mark.line + 1}); keep one."
                        )
                    seen[name] = key.start_mark.line
            for key, value in node.value:
                stack.extend((key, value))
        elif isinstance(node, yaml.SequenceNode):
            if longest is None or len(node.value) > len(longest.value):
                longest = node
            stack.extend(node.value)
    return root


#: What a path that is not a regular file is, by its ``stat`` mode test.
_FILE_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _not_a_file(path: Path) -> str:
    """Why ``path``, which is not a regular file, cannot be read as a scenario file."""
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        return f"{path}: no such scenario file."
    except OSError as err:
        return f"{path}: cannot be read ({err.strerror or err})."
    kind = next((name for test, name in _FILE_KINDS if test(mode)), "a special file")
    if kind == "a directory":
        return (
            f"{path}: is a directory, not a scenario file; give the path of a scenario YAML "
            f"file in it (e.g. {path / 'scenario.yaml'})."
        )
    return (
        f"{path}: is {kind}, not a regular file; a scenario is read from a YAML file on "
        "disk: give that file's path."
    )


def load_scenario(path: str | Path) -> Scenario:
    """Load and validate a scenario YAML file.

    Parameters
    ----------
    path : str or Path
        The YAML file.

    Returns
    -------
    Scenario

    Raises
    ------
    ScenarioError
        If the path is empty, missing, a directory or not a regular file (a
        FIFO, a device: it is never opened), the file is unreadable, larger
        than :data:`MAX_SCENARIO_BYTES`, not YAML, nested more than
        :data:`MAX_YAML_DEPTH` levels deep, or a key is unknown, missing or
        bad: an integer key written with a decimal point or an exponent
        (``1e3``, naming the integer to write), a quoted number (``"0.01"``),
        a module or model file of ``system``, ``plant`` or ``truth`` that
        cannot be found, ... (see :func:`validate_scenario`).

    Notes
    -----
    Numbers are read as YAML 1.2 reads them: a plain ``1e-2``, ``1e1`` or
    ``5.0e0`` (strings to PyYAML's YAML 1.1 rules) is the float Python's
    ``float`` makes of it wherever the schema expects a float. Modules and
    relative model files named by ``system``, ``plant`` and ``truth`` are
    found beside the file and made absolute.
    """
    if isinstance(path, str) and not path:
        raise ScenarioError(
            "the scenario path is empty (''); give the path of a scenario YAML file, e.g. "
            "diagrams/two_state_paper.yaml."
        )
    path = Path(path)
    if not path.is_file():  # a stat, not an open: a FIFO would block a read
        raise ScenarioError(_not_a_file(path))
    size = path.stat().st_size
    if size > MAX_SCENARIO_BYTES:
        raise ScenarioError(
            f"{path}: the file is {size / 1e6:.1f} MB; a scenario file is at most "
            f"{MAX_SCENARIO_BYTES / 1e6:g} MB."
        )
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ScenarioError(f"{path}: cannot be read ({err}).") from None
    check_yaml(path, text)
    raw = _raw_yaml(path, text)
    try:
        _check_mapping("", Scenario, raw)
    except ScenarioError as err:
        raise ScenarioError(f"{path}: {err}") from None
    scenario = yaml_load_typed(schema=Scenario, filename=str(path), allow_schema_with_no_yaml=True)
    try:
        _locate_files(scenario, path.parent)
        validate_scenario(scenario)
    except ScenarioError as err:
        raise ScenarioError(f"{path}: {err}") from None
    return scenario
