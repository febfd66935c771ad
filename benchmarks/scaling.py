"""Scaling rows: whole ``simulate()`` per simulated second as N, L and n grow.

Three groups, each row a scenario run by ``simulate()`` whole (observer
design, build, simulation, logs), ``repeats`` times after one warm-up:

* ``points``: the cart-pole with N = 100, 1,000, 10,000 uniformly drawn
  points (its own box and seed);
* ``basis``: the cart-pole with basis degrees [2] (L = 10) and [2, 4] (L = 45);
* ``state_dimension``: n = 2, 4, 6 -- the upright pendulum; the cart-pole and
  the acrobot; the planar quadrotor of ``benchmarks/scenarios/`` and the
  cart double pendulum. The two multi-link robots (Drake's multibody plants)
  take their certified bounds from the mass-matrix structure, which costs
  seconds, so their whole ``simulate()`` is mostly design at this horizon:
  each row also gives the simulation alone.

The learning gains of every row are resolved at its scenario's own horizon
(:func:`~benchmarks.cases.gains_resolved`), then the row runs a shorter
horizon: the start of the same loop. Each row reports seconds per simulated
second, derivative evaluations (per simulated second too), microseconds per
evaluation (``AdvanceTo`` over evaluations) and the growth ratios over the
first row of its group. No baseline: these plants have no hand-written loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.cases import gains_resolved, with_basis, with_duration, with_point_count
from benchmarks.timing import Timing, measure
from ofrl_drake.scenario import Scenario

__all__ = ["CART_POLE", "DIMENSION_SCENARIOS", "ScalingSettings", "scaling_rows"]

_ROOT = Path(__file__).resolve().parents[1]

#: The scenario of the N and L rows.
CART_POLE = _ROOT / "diagrams" / "cart_pole.yaml"

#: Name -> the scenario of an n row, in the table's order (n grows).
DIMENSION_SCENARIOS = {
    "pendulum_upright": _ROOT / "diagrams" / "pendulum_upright.yaml",
    "cart_pole": CART_POLE,
    "acrobot": _ROOT / "diagrams" / "acrobot.yaml",
    "planar_quadrotor": _ROOT / "benchmarks" / "scenarios" / "planar_quadrotor.yaml",
    "cart_double_pendulum": _ROOT / "diagrams" / "cart_double_pendulum.yaml",
}
#: The n rows whose single run takes seconds (multibody design): fewer repeats.
_MULTILINK = ("acrobot", "cart_double_pendulum")


@dataclass(frozen=True)
class ScalingSettings:
    """What the scaling rows run.

    Attributes
    ----------
    point_counts : tuple of int
        N of the ``points`` rows.
    basis_degrees : tuple of tuple of int
        Degrees of the ``basis`` rows.
    dimensions : tuple of str
        The ``state_dimension`` rows (keys of :data:`DIMENSION_SCENARIOS`).
    duration : float
        Simulated seconds of the ``points`` and ``state_dimension`` rows.
    basis_duration : float
        Simulated seconds of the ``basis`` rows: shorter, since the derived
        gains of the quartic basis make the critic stiff (many more steps).
    repeats : int
        Timed runs per row.
    multilink_repeats : int
        Timed runs of the acrobot and cart double pendulum rows (at most
        ``repeats``): one run takes 7 and 30 s at a 2 s horizon.
    """

    point_counts: tuple[int, ...] = (100, 1000, 10_000)
    basis_degrees: tuple[tuple[int, ...], ...] = ((2,), (2, 4))
    dimensions: tuple[str, ...] = tuple(DIMENSION_SCENARIOS)
    duration: float = 2.0
    basis_duration: float = 0.25
    repeats: int = 3
    multilink_repeats: int = 3


def _run(scenario: Scenario, repeats: int) -> dict[str, Any]:
    """Whole ``simulate()`` of ``scenario``, timed; its evaluations and their cost."""
    from ofrl_drake.simulation import simulate

    advance: list[float] = []

    def run() -> Any:
        result = simulate(scenario, progress=False)
        advance.append(result.wall_time)
        return result

    timing, result = measure(run, repeats)
    duration = scenario.simulation.duration
    evals = int(result.integrator["num_derivative_evaluations"])
    simulation = Timing(tuple(advance[-repeats:]))
    return {
        **timing.to_dict(),
        "duration": duration,
        "seconds_per_simulated_second": timing.median / duration,
        "advance": simulation.to_dict(),
        "num_derivative_evaluations": evals,
        "evaluations_per_simulated_second": evals / duration,
        "num_steps": int(result.integrator["num_steps"]),
        "us_per_evaluation": 1e6 * simulation.median / evals,
        "status": result.status,
    }


def _growth(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each row's ratios over the first row of its group."""
    first = rows[0]
    for row in rows:
        for key in ("seconds_per_simulated_second", "us_per_evaluation"):
            row[f"{key}_growth"] = row[key] / first[key]
        row["evaluations_growth"] = (
            row["evaluations_per_simulated_second"] / first["evaluations_per_simulated_second"]
        )
    return rows


def scaling_rows(settings: ScalingSettings) -> dict[str, list[dict[str, Any]]]:
    """The three groups of rows: ``points``, ``basis`` and ``state_dimension``."""
    from ofrl_drake.basis import PolynomialBasis
    from ofrl_drake.scenario import load_scenario

    cart_pole = load_scenario(CART_POLE)
    out: dict[str, list[dict[str, Any]]] = {"points": [], "basis": [], "state_dimension": []}
    for N in settings.point_counts:
        case = with_duration(gains_resolved(with_point_count(cart_pole, N)), settings.duration)
        out["points"].append(
            {"scenario": cart_pole.name, "N": int(N), **_run(case, settings.repeats)}
        )
    for degrees in settings.basis_degrees:
        case = with_duration(
            gains_resolved(with_basis(cart_pole, list(degrees))), settings.basis_duration
        )
        size = PolynomialBasis(len(cart_pole.x0), list(degrees)).size
        row = {"scenario": cart_pole.name, "degrees": list(degrees), "L": size}
        out["basis"].append({**row, **_run(case, settings.repeats)})
    for name in settings.dimensions:
        scenario = load_scenario(DIMENSION_SCENARIOS[name])
        case = with_duration(gains_resolved(scenario), settings.duration)
        n = len(scenario.x0)
        size = PolynomialBasis(n, list(scenario.critic.basis_degrees)).size
        row = {"scenario": scenario.name, "n": n, "L": size, "N": _point_count(scenario)}
        repeats = settings.repeats
        if name in _MULTILINK:
            repeats = min(repeats, settings.multilink_repeats)
        out["state_dimension"].append({**row, **_run(case, repeats)})
    return {key: _growth(rows) for key, rows in out.items() if rows}


def _point_count(scenario: Scenario) -> int:
    from ofrl_drake.diagram import extrapolation_points

    return int(extrapolation_points(scenario).shape[1])
