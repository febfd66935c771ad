"""What an ablation sweeps over: the variants and the initial states.

A :class:`Variant` is one choice per slot (see :mod:`ofrl_drake.slots`) for
the slots it names; the others keep the scenario's. :func:`default_variants`
is the baseline and every single-slot swap; :func:`load_variants` reads a
YAML file of them.

Initial states are given as true states ``x0``; the estimate starts at
``xhat0 = x0 + (scenario.xhat0 - scenario.x0)``, the scenario's own initial
estimation error. :func:`sample_initial_states` draws ``x0`` in the part of the
observer box where both ``x0`` and that ``xhat0`` lie in the box, so the
observer certificate applies from ``t = 0``. Each state is labelled by
:func:`initial_state_label`, the ``initial_state`` column of the table.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ofrl_drake.checks import count_at_most, finite_array, integer_at_least
from ofrl_drake.errors import OfrlError
from ofrl_drake.limits import INITIAL_STATES_FIX, MAX_INITIAL_STATES
from ofrl_drake.scenario import Scenario, check_yaml, variant_choices

__all__ = [
    "AblationError",
    "Variant",
    "default_variants",
    "initial_state_label",
    "initial_states_by_label",
    "load_variants",
    "sample_initial_states",
    "variant_list",
]


class AblationError(OfrlError):
    """A sweep was asked for with bad input (variants, initial states, output)."""


# ---------------------------------------------------------------- variants
@dataclass(frozen=True)
class Variant:
    """A named set of slot choices; slots it does not name keep the scenario's.

    Attributes
    ----------
    name : str
        The label in the table (``baseline``, ``observer=true_state``, ...).
    choices : dict of str to str
        Slot -> choice, e.g. ``{"observer": "true_state"}``.
    """

    name: str
    choices: dict[str, str] = field(default_factory=dict)

    def full_choices(self, scenario: Scenario) -> dict[str, str]:
        """Every slot's choice: the scenario's, overridden by this variant's."""
        return {**variant_choices(scenario), **self.choices}


def _check_choices(name: str, choices: Any) -> dict[str, str]:
    """``choices`` of the variant ``name``, checked: known slots, known choices.

    The one check of a variant's choices, for ``--variants`` files and the
    Python API alike.
    """
    from ofrl_drake.slots import VARIANT_FACTORIES

    if not isinstance(choices, Mapping):
        raise AblationError(
            f"variants.{name}: expected a mapping of slot: choice; got {choices!r}."
        )
    for slot, choice in choices.items():
        if slot not in VARIANT_FACTORIES:
            raise AblationError(
                f"variants.{name}.{slot}: unknown slot; slots are {sorted(VARIANT_FACTORIES)}."
            )
        if not isinstance(choice, str) or choice not in VARIANT_FACTORIES[slot]:
            raise AblationError(
                f"variants.{name}.{slot}: unknown choice {choice!r}; choose one of "
                f"{sorted(VARIANT_FACTORIES[slot])}."
            )
    return {str(k): str(v) for k, v in choices.items()}


def default_variants(scenario: Scenario) -> list[Variant]:
    """The baseline (the scenario's own choices) and every single-slot swap.

    For the paper's scenario: ``baseline`` plus ``observer=linear_luenberger``,
    ``observer=drake_luenberger``, ``observer=true_state``, ``controller=lqr``,
    ``controller=frozen_critic``, ``points=uniform``, ``points=around_estimate``
    and ``gamma=constant``. Choices that need scenario values
    (:data:`~ofrl_drake.slots.NEEDS_PARAMETERS`, e.g. ``controller=constant``)
    are left out.
    """
    from ofrl_drake.slots import NEEDS_PARAMETERS, VARIANT_FACTORIES

    base = variant_choices(scenario)
    out = [Variant("baseline", {})]
    for slot, options in VARIANT_FACTORIES.items():
        for choice in options:
            if choice != base[slot] and (slot, choice) not in NEEDS_PARAMETERS:
                out.append(Variant(f"{slot}={choice}", {slot: choice}))
    return out


def load_variants(path: str | os.PathLike[str]) -> list[Variant]:
    """Read variants from YAML: a mapping ``name: {slot: choice, ...}``.

    Example::

        baseline: {}
        full_state: {observer: true_state}
        lqr_full_state: {observer: true_state, controller: lqr}

    Raises
    ------
    AblationError
        If the file is missing, unreadable or not UTF-8 text, not a mapping,
        repeats a key in one mapping (e.g. a variant's name: Drake's loader
        would keep the last silently; the key and both lines named), has a
        name that YAML reads as a number, boolean or null (quote it) or that
        holds ``|`` or a control character, or names an unknown slot or choice.
    """
    from pydrake.common.yaml import yaml_load

    path = Path(path)
    if not path.is_file():
        raise AblationError(f"{path}: no such variants file.")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise AblationError(f"{path}: not UTF-8 text ({err}); save it as UTF-8.") from None
    except OSError as err:
        raise AblationError(f"{path}: cannot be read ({err.strerror or err}).") from None
    _string_keys(path, check_yaml(path, text, error=AblationError, what="variants file"))
    try:
        data = yaml_load(filename=str(path))
    except Exception as err:
        raise AblationError(f"{path}: not valid YAML: {err}".replace("\n", " ")) from None
    if not isinstance(data, Mapping) or not data:
        raise AblationError(
            f"{path}: expected a mapping of variant name -> {{slot: choice}}; got {data!r}."
        )
    try:
        return _from_mapping(data)
    except AblationError as err:
        raise AblationError(f"{path}: {err}") from None


def _from_mapping(data: Mapping[Any, Any]) -> list[Variant]:
    """Variants from a mapping ``name -> {slot: choice}`` (None: no choice), checked."""
    return [
        Variant(
            _checked_name(str(name), "variants"), _check_choices(str(name), {} if c is None else c)
        )
        for name, c in data.items()
    ]


def _checked_name(name: Any, where: str) -> str:
    """A variant's name: a non-empty string that fits a table cell and a line.

    ``|`` would split its cell in ``ablation.md``'s tables, and a control
    character (a newline, a tab) its row.
    """
    if not isinstance(name, str) or not name:
        raise AblationError(f"{where}: a variant's name must be a non-empty string; got {name!r}.")
    bad = [c for c in name if c == "|" or not c.isprintable()]
    if bad:
        raise AblationError(
            f"{where}: the variant name {name!r} holds {bad[0]!r}, which would break the "
            "tables of ablation.md; use letters, digits, spaces and _ . = - instead."
        )
    return name


def _string_keys(path: Path, root: Any) -> None:
    """Refuse a top-level key of ``root`` (the file's composed YAML, as
    :func:`~ofrl_drake.scenario.check_yaml` returns it) that YAML reads as
    another type than a string (``1:``, ``true:``, ``null:``): Drake's loader
    fails on it with an internal error."""
    import yaml

    if not isinstance(root, yaml.MappingNode):
        return
    for key, _ in root.value:
        if key.tag != "tag:yaml.org,2002:str":
            kind = key.tag.rsplit(":", 1)[-1]
            raise AblationError(
                f"{path}: line {key.start_mark.line + 1}: the variant name {key.value!r} reads "
                f"as a YAML {kind}, not a string; quote it ('{key.value}': ...)."
            )


def _checked_variant(index: int, variant: Any) -> Variant:
    """Item ``index`` of a sequence of variants: a :class:`Variant` with checked choices."""
    if not isinstance(variant, Variant):
        raise AblationError(
            f"variants[{index}]: expected a Variant(name, {{slot: choice}}); got {variant!r}. "
            "Pass Variant objects, or a mapping name -> {slot: choice}."
        )
    _checked_name(variant.name, f"variants[{index}]")
    return replace(variant, choices=_check_choices(variant.name, variant.choices))


def variant_list(scenario: Scenario, variants: Any) -> list[Variant]:
    """The variants of a sweep: ``variants`` (a sequence, or a mapping ``name ->
    {slot: choice}``), or :func:`default_variants` if None.

    Every variant's choices are checked as a ``--variants`` file's are.

    Raises
    ------
    AblationError
        If there is none, two share a name, an item is not a :class:`Variant`,
        or a variant names an unknown slot or choice (the message lists the
        slots or the slot's choices).
    """
    if variants is None:
        return default_variants(scenario)
    if isinstance(variants, Mapping):
        out = _from_mapping(variants)
    elif isinstance(variants, (str, bytes)) or not isinstance(variants, Iterable):
        raise AblationError(
            "variants: expected a list of Variant or a mapping name -> {slot: choice}; "
            f"got {variants!r}."
        )
    else:
        out = [_checked_variant(i, v) for i, v in enumerate(variants)]
    names = [v.name for v in out]
    if not out or len(set(names)) != len(names):
        raise AblationError(f"variants: need at least one, with distinct names; got {names}.")
    return out


# ---------------------------------------------------------- initial states
def initial_state_label(x0: Sequence[float]) -> str:
    """The ``initial_state`` column: ``x0`` as a JSON list, e.g. ``[-1.0, 1.0]``."""
    return json.dumps([float(v) for v in x0])


def sample_initial_states(scenario: Scenario, count: int, seed: int) -> np.ndarray:
    """The scenario's ``x0`` followed by ``count`` states drawn from ``seed``.

    Draws are uniform in the sub-box of the observer box where both ``x0`` and
    ``xhat0 = x0 + (scenario.xhat0 - scenario.x0)`` stay in the box, rounded to
    six decimals so their labels are short and exact.

    Returns
    -------
    ndarray, shape (count + 1, n)

    Raises
    ------
    AblationError
        If ``count`` or ``seed`` is not an integer >= 0, ``count`` is above
        :data:`~ofrl_drake.limits.MAX_INITIAL_STATES`, or the initial estimation
        error is wider than the box.
    """
    count_at_most(
        "count (--initial-states)",
        count,
        0,
        MAX_INITIAL_STATES,
        INITIAL_STATES_FIX,
        error=AblationError,
    )
    integer_at_least("seed (--seed)", seed, 0, error=AblationError)
    x0 = np.asarray(scenario.x0, dtype=float)
    offset = np.asarray(scenario.xhat0, dtype=float) - x0
    lower = np.asarray(scenario.observer.box.lower, dtype=float)
    upper = np.asarray(scenario.observer.box.upper, dtype=float)
    lo = np.maximum(lower, lower - offset)
    hi = np.minimum(upper, upper - offset)
    if np.any(lo >= hi):
        i = int(np.argmax(lo >= hi))
        raise AblationError(
            f"initial states: xhat0 - x0 = {offset.tolist()} is as wide as the observer box "
            f"in axis {i}; no x0 keeps both x0 and xhat0 inside it."
        )
    rng = np.random.default_rng(seed)
    draws = np.round(lo + (hi - lo) * rng.random((int(count), x0.size)), 6)
    return np.vstack([x0[None, :], draws])


def initial_states_by_label(
    scenario: Scenario, initial_states: Sequence[Sequence[float]] | np.ndarray | None
) -> dict[str, np.ndarray]:
    """``initial_states`` (default: the scenario's ``x0``) keyed by their labels, in order.

    Raises
    ------
    AblationError
        If a state is not ``n`` finite numbers, or two states are the same.
    """
    if initial_states is None:
        initial_states = [scenario.x0]
    states = np.atleast_2d(finite_array("initial states", initial_states, error=AblationError))
    n = len(scenario.x0)
    if states.ndim != 2 or states.shape[1] != n:
        raise AblationError(
            f"initial states: expected finite rows of {n} numbers; got shape {states.shape}."
        )
    labels = [initial_state_label(x) for x in states]
    if len(set(labels)) != len(labels):
        raise AblationError(f"initial states: repeated states in {labels}.")
    return dict(zip(labels, states, strict=True))
