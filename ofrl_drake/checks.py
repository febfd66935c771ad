"""Argument checks shared by the blocks: each raises :class:`ModelError`, or the
class given as ``error`` where a module raises its own (:func:`finite_array`,
:func:`integer_at_least`, :func:`positive_number`); :func:`is_real_number` is a test.

Every message names the owner (``"GammaGain: initial_gamma"``), the value it
got and what would be accepted, so a user can fix the call without reading
the source.
"""

from __future__ import annotations

import math
import reprlib
from typing import Any

import numpy as np

from ofrl_drake.errors import ModelError, OfrlError

__all__ = [
    "MAX_DRAKE_SEED",
    "array_of_shape",
    "deadline_or_none",
    "drake_seed",
    "finite_array",
    "finite_vector",
    "initial_vector",
    "integer_at_least",
    "is_real_number",
    "json_ready",
    "nonnegative_matrix",
    "number_from_json",
    "number_to_json",
    "object_from_json",
    "optional_number_from_json",
    "point_text",
    "positive_number",
    "positive_vector",
    "spd_matrix",
    "string_from_json",
    "vector_from_json",
    "vector_to_json",
]


def finite_array(name: str, value: Any, *, error: type[OfrlError] = ModelError) -> np.ndarray:
    """``value`` as a float array of any shape, checked numeric and finite.

    Raises ``error`` (default :class:`ModelError`).
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as err:
        raise error(f"{name} must be numeric; got {value!r}.") from err
    if not np.all(np.isfinite(arr)):
        raise error(f"{name} must be finite; got {arr.tolist()}.")
    return arr


def array_of_shape(
    name: str,
    value: Any,
    shape: tuple[int | None, ...],
    *,
    meaning: str = "",
    fix: str = "",
    error: type[OfrlError] = ModelError,
) -> np.ndarray:
    """``value`` as a finite float array of ``shape``; a None axis takes any length >= 1.

    The message names the shape wanted, after its ``meaning`` if given
    (``"A must have shape (n, n) = (2, 2); got (3, 3)."``), then ``fix``.
    Raises ``error`` (default :class:`ModelError`).
    """
    arr = finite_array(name, value, error=error)
    fits = arr.ndim == len(shape) and all(
        got >= 1 if want is None else got == want
        for got, want in zip(arr.shape, shape, strict=True)
    )
    if not fits:
        wanted = "(" + ", ".join("N" if want is None else str(want) for want in shape) + ")"
        if len(shape) == 1:
            wanted = wanted[:-1] + ",)"
        said = f"{meaning} = {wanted}" if meaning else wanted
        raise error(f"{name} must have shape {said}; got {arr.shape}{fix}.")
    return arr


def is_real_number(value: Any) -> bool:
    """Whether ``value`` is one real number: a Python or numpy int or float.

    Not a bool, a string (``"1e-3"``), None or an array: callers that then
    compare it (``math.isfinite(value) and value > 0``) get no TypeError.
    """
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


def integer_at_least(
    name: str, value: Any, least: int = 0, *, error: type[OfrlError] = ModelError
) -> int:
    """``value`` as an int, checked to be an integer (not a bool or a float) ``>= least``.

    For seeds (``least = 0``: numpy refuses negative ones) and counts. Raises
    ``error`` (default :class:`ModelError`), so a module raises its own class.
    """
    if (
        isinstance(value, bool | np.bool_)
        or not isinstance(value, int | np.integer)
        or value < least
    ):
        raise error(f"{name} must be an integer >= {least}; got {value!r}.")
    return int(value)


def deadline_or_none(name: str, value: Any, *, error: type[OfrlError] = ModelError) -> float | None:
    """``value`` as a deadline: a finite ``time.monotonic()`` reading, or None (no limit).

    Raises ``error`` (default :class:`ModelError`), naming ``name`` and the value.
    """
    if value is None:
        return None
    if not (is_real_number(value) and math.isfinite(value)):
        raise error(
            f"{name} must be a time.monotonic() reading or None; got {reprlib.repr(value)}."
        )
    return float(value)


def count_at_most(
    name: str, value: Any, least: int, most: int, fix: str, *, error: type[OfrlError] = ModelError
) -> int:
    """``value`` as an int in ``[least, most]`` (:func:`integer_at_least`, and a limit).

    For counts of work (runs, states, checkpoints) whose each unit costs a
    simulation: a count past ``most`` would take gigabytes or days before
    anything is written. The message names the value, the limit and ``fix``.
    """
    count = integer_at_least(name, value, least, error=error)
    if count > most:
        raise error(f"{name}: {count} is more than the limit of {most}; {fix}.")
    return count


#: The largest seed Drake's ``RandomGenerator`` keeps whole: it reads 32 bits, so
#: ``2**32`` would repeat seed 0's draws.
MAX_DRAKE_SEED = 2**32 - 1


def drake_seed(name: str, value: Any, *, error: type[OfrlError] = ModelError) -> int:
    """``value`` as a seed for Drake's random sources: an integer in ``[0, 2**32 - 1]``.

    Drake keeps 32 bits of a seed (a larger one would repeat a smaller one's
    draws, or fail inside pybind11). Raises ``error`` (default :class:`ModelError`).
    """
    seed = integer_at_least(name, value, 0, error=error)
    if seed > MAX_DRAKE_SEED:
        raise error(
            f"{name} must be at most 2**32 - 1 = {MAX_DRAKE_SEED} (Drake's random sources "
            f"keep 32 bits of a seed); got {value!r}."
        )
    return seed


def positive_number(
    name: str, value: Any, *, allow_zero: bool = False, error: type[OfrlError] = ModelError
) -> float:
    """``value`` as a float, checked finite and ``> 0`` (``>= 0`` with ``allow_zero``).

    A string (``"10"``) or a bool is refused, not read as a number. Raises
    ``error`` (default :class:`ModelError`).
    """
    if isinstance(value, str | bytes | bool | np.bool_):
        raise error(f"{name} must be a number; got {value!r}.")
    arr = finite_array(name, value, error=error)
    if arr.ndim != 0:
        raise error(f"{name} must be a number; got shape {arr.shape}.")
    x = float(arr)
    if x < 0 or (x == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise error(f"{name} must be {bound}; got {x}.")
    return x


def finite_vector(name: str, value: Any, size: int | None = None) -> np.ndarray:
    """``value`` as a finite, non-empty 1-D array, of length ``size`` if given."""
    arr = finite_array(name, value)
    if arr.ndim != 1 or arr.size == 0:
        raise ModelError(f"{name} must be a non-empty 1-D vector; got shape {arr.shape}.")
    if size is not None and arr.size != size:
        raise ModelError(f"{name} must have length {size}; got {arr.size}.")
    return arr


def initial_vector(name: str, value: Any, size: int) -> np.ndarray:
    """A block's default state: zeros of length ``size`` if ``value`` is None, else
    ``value`` as a :func:`finite_vector` of length ``size``.

    Raises
    ------
    ModelError
        If ``value`` is given and is not a finite vector of length ``size``;
        the message starts with ``name`` (``"ControlAffinePlant: initial_state"``).
    """
    if value is None:
        return np.zeros(size)
    return finite_vector(name, value, size)


def positive_vector(name: str, value: Any, size: int | None = None) -> np.ndarray:
    """A :func:`finite_vector` whose entries are all ``> 0``."""
    arr = finite_vector(name, value, size)
    if np.any(arr <= 0):
        raise ModelError(f"{name} must have entries > 0; got {arr.tolist()}.")
    return arr


def _symmetric(name: str, value: Any, size: int | None) -> np.ndarray:
    arr = finite_array(name, value)
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1] or arr.size == 0:
        raise ModelError(f"{name} must be a square matrix; got shape {arr.shape}.")
    if size is not None and arr.shape[0] != size:
        raise ModelError(f"{name} must have shape ({size}, {size}); got {arr.shape}.")
    if not np.allclose(arr, arr.T, rtol=1e-10, atol=1e-12):
        asym = float(np.max(np.abs(arr - arr.T)))
        raise ModelError(f"{name} must be symmetric; max |M - M^T| = {asym:.3g}.")
    return arr


def spd_matrix(name: str, value: Any, size: int | None = None) -> np.ndarray:
    """A finite, symmetric, positive definite square matrix."""
    arr = _symmetric(name, value, size)
    lam = float(np.linalg.eigvalsh(arr)[0])
    if lam <= 0:
        raise ModelError(f"{name} must be positive definite; its smallest eigenvalue is {lam:.3g}.")
    return arr


def nonnegative_matrix(name: str, value: Any, size: int | None = None) -> np.ndarray:
    """A finite, symmetric, positive semidefinite square matrix."""
    arr = _symmetric(name, value, size)
    lam = float(np.linalg.eigvalsh(arr)[0])
    if lam < -1e-12 * max(1.0, float(np.max(np.abs(arr)))):
        raise ModelError(
            f"{name} must be positive semidefinite; its smallest eigenvalue is {lam:.3g}."
        )
    return arr


def number_to_json(value: Any) -> float | None:
    """``value`` as a float for JSON, or None (``null``) if it is None or not finite.

    JSON has no NaN or infinity; :func:`optional_number_from_json` reads it back.
    """
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def point_text(values: Any, digits: int = 4) -> str:
    """``values`` as ``(a, b, ...)`` for a message, each to ``digits`` significant digits."""
    return "(" + ", ".join(f"{v:.{digits}g}" for v in np.asarray(values, float).ravel()) + ")"


def vector_to_json(values: Any) -> list[float | None]:
    """``values`` as a list for JSON, non-finite ones as None.

    :func:`vector_from_json` reads it back.
    """
    return [number_to_json(v) for v in np.asarray(values, dtype=float).ravel()]


def json_ready(value: Any) -> Any:
    """``value`` with every float (numpy's too) through :func:`number_to_json`.

    Dicts, lists, tuples and numpy arrays are walked (tuples and arrays become
    lists, numpy integers and bools Python's), so ``json.dump(json_ready(v),
    allow_nan=False)`` writes strict JSON: a diverged run's NaN state is
    ``null``, not the ``NaN`` token strict parsers (JavaScript, jq) refuse.
    """
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return number_to_json(value)
    return value


def number_from_json(value: Any) -> float:
    """A number read back from JSON (``summary.json``), as a float: not a bool, string or null.

    Raises ``TypeError`` for anything else.
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"expected a number, got {type(value).__name__}")
    return float(value)


def optional_number_from_json(value: Any) -> float | None:
    """A number read back from JSON, or None for ``null`` (a non-finite number, or none)."""
    return None if value is None else number_from_json(value)


def vector_from_json(value: Any, size: int | None = None) -> list[float]:
    """A list of ``size`` numbers (None: any number) read back from JSON, ``null`` as NaN.

    ``null`` is how a non-finite value is written. Raises ``ValueError`` for a
    list of another length, ``TypeError`` for an entry that is not a number.
    """
    if not isinstance(value, list) or (size is not None and len(value) != size):
        raise ValueError(f"expected a list of {'' if size is None else f'{size} '}numbers")
    return [math.nan if v is None else number_from_json(v) for v in value]


def string_from_json(value: Any) -> str:
    """A string read back from JSON; ``TypeError`` for anything else."""
    if not isinstance(value, str):
        raise TypeError(f"expected a string, got {type(value).__name__}")
    return value


def object_from_json(value: Any) -> dict[str, Any]:
    """An object (dict) read back from JSON; ``TypeError`` for anything else."""
    if not isinstance(value, dict):
        raise TypeError(f"expected an object, got {type(value).__name__}")
    return value
