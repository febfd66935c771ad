"""Per-run metrics of an ablation, from logged trajectories (pure numpy).

Every function takes arrays with time first, as in
:class:`~ofrl_drake.SimulationResult`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "SETTLING_RADIUS",
    "optimality_ratio",
    "regulated",
    "regulation",
    "rms_estimation_error",
    "run_metrics",
    "settling_time",
    "time_outside_box",
]

#: ``|x|`` below which a run counts as settled.
SETTLING_RADIUS = 1e-2


def settling_time(t: np.ndarray, x: np.ndarray, radius: float = SETTLING_RADIUS) -> float:
    """The first logged time after which ``|x| < radius`` at every sample.

    Returns ``t[0]`` if the run starts and stays inside, and ``inf`` if ``|x|``
    is not below ``radius`` at the last sample (never settled in the horizon).
    """
    outside = np.linalg.norm(np.asarray(x, dtype=float), axis=1) >= radius
    if not outside.any():
        return float(t[0])
    last = int(np.flatnonzero(outside)[-1])
    return float(t[last + 1]) if last + 1 < len(t) else math.inf


def rms_estimation_error(t: np.ndarray, x: np.ndarray, xhat: np.ndarray) -> float:
    """``sqrt((1/T) int |x - xhat|^2 dt)`` by the trapezoid rule."""
    t = np.asarray(t, dtype=float)
    sq = np.sum((np.asarray(x, dtype=float) - np.asarray(xhat, dtype=float)) ** 2, axis=1)
    span = t[-1] - t[0]
    if span <= 0:
        return float(np.sqrt(sq[0]))
    integral = 0.5 * np.sum((sq[1:] + sq[:-1]) * np.diff(t))
    return float(np.sqrt(integral / span))


def time_outside_box(
    t: np.ndarray, x: np.ndarray, xhat: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> float:
    """Seconds during which ``x`` or ``xhat`` was outside ``[lower, upper]``.

    Left-point rule on the logged samples: the interval ``[t_k, t_{k+1})``
    counts as outside if either was outside at ``t_k``.
    """
    lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)

    def outside(z: np.ndarray) -> np.ndarray:
        z = np.asarray(z, dtype=float)
        return np.any((z < lo) | (z > hi), axis=1)

    bad = outside(x) | outside(xhat)
    return float(np.sum(np.diff(np.asarray(t, dtype=float)) * bad[:-1]))


#: ``simulation.regulation_tolerance`` by default: every component of the final
#: state within this fraction of the observer box's half-width of the target.
REGULATION_FRACTION = 0.05


def regulation(
    status: str,
    x_final: np.ndarray,
    box: tuple[np.ndarray, np.ndarray],
    tolerance: float = REGULATION_FRACTION,
    xhat_final: np.ndarray | None = None,
) -> dict:
    """Whether a run reached its target, with the numbers behind the verdict.

    A run is regulated when it ended ``ok``, every ``|x_i(T)|`` (``x`` in the
    method's coordinates, ``x - x*``) is at most ``tolerance`` times the
    observer box's half-width along ``x_i``, and ``x(T)`` (and ``xhat(T)``
    when given) lie inside the observer box. On the cart-pole's box
    (``[-2, 2] m x [-0.4, 0.4] rad x ...``) the default is 0.1 m and 0.02 rad.

    Returns
    -------
    dict
        ``regulated`` (bool), ``tolerance`` (the per-component bound),
        ``final_error`` (``|x_i(T)|``), ``inside_observer_box``, ``status``.
    """
    lower, upper = (np.asarray(b, dtype=float) for b in box)
    bound = tolerance * 0.5 * (upper - lower)
    x = np.asarray(x_final, dtype=float)
    finals = [x] if xhat_final is None else [x, np.asarray(xhat_final, dtype=float)]
    inside = bool(all(np.all((v >= lower) & (v <= upper)) for v in finals))
    close = bool(np.all(np.isfinite(x)) and np.all(np.abs(x) <= bound))
    return {
        "regulated": bool(status == "ok" and close and inside),
        "tolerance": bound.tolist(),
        "final_error": np.abs(x).tolist(),
        "inside_observer_box": inside,
        "status": status,
    }


def regulation_shortfall(
    final_error: Sequence[float], tolerance: Sequence[float], inside_observer_box: bool
) -> str:
    """Why :func:`regulation` failed a run that ended ``ok``, as one phrase.

    The component furthest beyond its tolerance (relative to it), and whether
    ``x(T)`` or ``xhat(T)`` left the observer box; the arguments are
    :func:`regulation`'s ``final_error``, ``tolerance`` and
    ``inside_observer_box``. Empty when neither failed (the run's status did).

    Examples
    --------
    >>> regulation_shortfall([0.05, 0.03], [0.1, 0.02], True)
    '|x_2(T) - x*_2| = 0.03 > 0.02'
    """
    error = np.asarray(final_error, dtype=float)
    bound = np.asarray(tolerance, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        excess = np.where(bound > 0, error / bound, np.where(error > 0, np.inf, 0.0))
    excess = np.where(np.isnan(error), np.inf, excess)  # a non-finite state fails first
    worst = int(np.argmax(excess))
    why = []
    if not error[worst] <= bound[worst]:
        why.append(f"|x_{worst + 1}(T) - x*_{worst + 1}| = {error[worst]:.3g} > {bound[worst]:.3g}")
    if not inside_observer_box:
        why.append("x(T) or xhat(T) is outside the observer box")
    return "; ".join(why)


def regulated(
    status: str,
    x_final: np.ndarray,
    box: tuple[np.ndarray, np.ndarray],
    tolerance: float = REGULATION_FRACTION,
) -> bool:
    """:func:`regulation`'s verdict alone."""
    return regulation(status, x_final, box, tolerance)["regulated"]


def optimality_ratio(cost: float, optimal_cost: float) -> float:
    """``J / J*``; NaN when ``J*`` is unavailable or not positive."""
    if not (math.isfinite(optimal_cost) and optimal_cost > 0 and math.isfinite(cost)):
        return math.nan
    return cost / optimal_cost


def run_metrics(result: Any, box: tuple[np.ndarray, np.ndarray]) -> dict[str, float]:
    """The trajectory metrics of one run.

    Parameters
    ----------
    result : SimulationResult
        The logged run.
    box : (lower, upper)
        The observer's certified box.

    Returns
    -------
    dict
        ``cost``, ``final_state_norm``, ``settling_time``,
        ``rms_estimation_error``, ``min_learning_condition``,
        ``time_outside_box``.
    """
    return {
        "cost": float(result.cost[-1]),
        "final_state_norm": float(np.linalg.norm(result.x[-1])),
        "settling_time": settling_time(result.t, result.x),
        "rms_estimation_error": rms_estimation_error(result.t, result.x, result.xhat),
        "min_learning_condition": float(np.min(result.learning_condition)),
        "time_outside_box": time_outside_box(result.t, result.x, result.xhat, *box),
    }
