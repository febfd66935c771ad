"""The tasks of an ablation: one variant from many initial states, and ``J*`` from one state.

Each task runs inside a worker (:mod:`ofrl_drake.sweep`) and does not raise
for a run or a solve that fails (:func:`solve_optimal_task` only refuses a
``warm`` of the wrong kind, with an
:class:`~ofrl_drake.ablation_grid.AblationError`). It
carries only picklable data (the :class:`~ofrl_drake.scenario.Scenario`
dataclass, the :class:`~ofrl_drake.ablation_grid.Variant`, the initial states)
and builds its Drake diagram where it runs. :func:`run_variant_states` builds
one variant once (its observer design, Jacobian bounds and LMI included) and
simulates it from each initial state, writing only the context
(:meth:`~ofrl_drake.diagram.ClosedLoop.set_initial_values`), then measures
each run (:mod:`ofrl_drake.ablation_metrics`); the runs are the same, bit for
bit, as runs of a loop built for each state. :func:`solve_optimal_task`
solves ``J*`` (:mod:`ofrl_drake.optimal`), warm-started from a run with the
learned controller. An error becomes the status of the rows it concerns, on
one line.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ofrl_drake.ablation_grid import AblationError, Variant, initial_state_label
from ofrl_drake.ablation_metrics import run_metrics
from ofrl_drake.errors import WallTimeExceeded, one_line, status_line
from ofrl_drake.optimal import Mesh, OptimalControlResult, Trajectory, optimal_control
from ofrl_drake.plants import check_dynamics
from ofrl_drake.scenario import Scenario, variant_choices

__all__ = [
    "METRICS",
    "RunOutcome",
    "failed_optimum",
    "run_variant",
    "run_variant_states",
    "solve_optimal_task",
]

#: The trajectory metrics of a run (NaN if it failed or was stopped).
METRICS = (
    "cost",
    "final_state_norm",
    "settling_time",
    "rms_estimation_error",
    "min_learning_condition",
    "time_outside_box",
    "initial_policy_cost",
    "final_policy_cost",
)


def _scenario_for(
    scenario: Scenario, variant: Variant, x0: Sequence[float], duration: float | None
) -> Scenario:
    """The scenario of one run: the variant's choices, from ``x0``, over ``duration``.

    The rest of the scenario's ``variant`` (``constant_input``) is kept.
    """
    start = np.asarray(x0, dtype=float)
    offset = np.asarray(scenario.xhat0, dtype=float) - np.asarray(scenario.x0, dtype=float)
    choices = variant.full_choices(scenario)
    simulation = scenario.simulation
    if duration is not None:
        simulation = dataclasses.replace(simulation, duration=float(duration))
    return dataclasses.replace(
        scenario,
        x0=start.tolist(),
        xhat0=(start + offset).tolist(),
        variant=dataclasses.replace(
            scenario.variant,
            observer=choices["observer"],
            controller=choices["controller"],
            points=choices["points"],
            gamma=choices["gamma"],
        ),
        simulation=simulation,
    )


@dataclass(frozen=True)
class RunOutcome:
    """What one run returns from its worker: metrics, status and trajectories.

    Attributes
    ----------
    variant, initial_state : str
        The row's key.
    metrics : dict of str to float
        The trajectory metrics (:func:`~ofrl_drake.ablation_metrics.run_metrics`);
        NaN if the run failed.
    status : str
        ``"ok"`` or the error, on one line.
    wall_time : float
        Seconds to simulate and measure this run, plus its share of the
        variant's build (built once for all the initial states of its task).
    learned : bool
        True if the variant uses the learned controller (a J* warm start).
    logs : dict of str to ndarray
        ``t, x, xhat, u, cost`` (empty if the run failed).
    regulated : bool
        The run's verdict (:func:`~ofrl_drake.ablation_metrics.regulation`).
    """

    variant: str
    initial_state: str
    metrics: dict[str, float]
    status: str
    wall_time: float
    learned: bool
    logs: dict[str, np.ndarray] = field(default_factory=dict)
    regulated: bool = False

    def warm_start(self) -> Trajectory | None:
        """The run as a :class:`~ofrl_drake.optimal.Trajectory`, if it reached its horizon."""
        if not self.logs or self.status.startswith(("diverged", "timeout")):
            return None
        return Trajectory(
            t=self.logs["t"], x=self.logs["x"], u=self.logs["u"], cost=self.logs["cost"]
        )


def run_variant_states(
    scenario: Scenario,
    variant: Variant,
    states: Sequence[Sequence[float]],
    duration: float | None = None,
    dynamics: Mapping[str, str | None] | None = None,
) -> list[RunOutcome]:
    """Build one variant once and simulate it from each of ``states``; never raises.

    Runs inside a worker: the Drake diagram, and the policy-evaluation
    diagram of the policy costs, are built here from the scenario data, then
    each run writes its initial state into a fresh context. An error in the
    build is the status of every run; an error in a run, of that run. With
    ``dynamics`` (the client's :func:`~ofrl_drake.plants.dynamics_fingerprints`),
    a worker whose plant's code differs runs nothing: that is every run's
    status (:func:`~ofrl_drake.plants.check_dynamics`).

    Returns
    -------
    list of RunOutcome
        One per initial state, in order.
    """
    from ofrl_drake.diagram import build_closed_loop
    from ofrl_drake.learning_curve import PolicyEvaluator

    if len(states) == 0:
        return []
    choices = variant.full_choices(scenario)
    learned = choices["controller"] == "learned"
    start = time.perf_counter()
    try:
        check_dynamics(scenario, dynamics)
        loop = build_closed_loop(_scenario_for(scenario, variant, states[0], duration))
        acts_on_critic = choices["controller"] in ("learned", "frozen_critic")
        evaluator = PolicyEvaluator(loop) if acts_on_critic else None
    except Exception as err:
        share = (time.perf_counter() - start) / len(states)
        nan = dict.fromkeys(METRICS, math.nan)
        return [
            RunOutcome(variant.name, initial_state_label(x0), nan, status_line(err), share, learned)
            for x0 in states
        ]
    share = (time.perf_counter() - start) / len(states)
    return [
        _run(loop, evaluator, _scenario_for(scenario, variant, x0, duration), variant, share)
        for x0 in states
    ]


def run_variant(
    scenario: Scenario, variant: Variant, x0: Sequence[float], duration: float | None = None
) -> RunOutcome:
    """Build and simulate one variant from ``x0``; never raises (:func:`run_variant_states`)."""
    return run_variant_states(scenario, variant, [x0], duration)[0]


def _run(
    loop: Any, evaluator: Any, s: Scenario, variant: Variant, build_share: float
) -> RunOutcome:
    """Simulate the built ``loop`` from the initial values of ``s`` and measure the run."""
    from ofrl_drake.simulation import simulate

    label = initial_state_label(s.x0)
    learned = variant_choices(s)["controller"] == "learned"
    start = time.perf_counter()
    budget = s.simulation.max_wall_time  # the run and its policy evaluations share it
    deadline = None if budget is None else time.monotonic() + budget
    regulated = False
    try:
        result = simulate(s, loop=loop, progress=False)
        box = (np.asarray(s.observer.box.lower), np.asarray(s.observer.box.upper))
        metrics = run_metrics(result, box)
        regulated = bool(result.regulated)
        status = "ok"
        try:
            metrics.update(_policy_costs(evaluator, result, s, deadline))
        except WallTimeExceeded as err:  # the run is whole; its policies were not evaluated
            metrics.update(initial_policy_cost=math.nan, final_policy_cost=math.nan)
            status = f"timeout: {one_line(err)} (max_wall_time = {budget:g} s)"
        if result.stopped is not None:
            # Stopped by the guard: the metrics of a truncated run are not comparable.
            status = result.stopped
            metrics = dict.fromkeys(METRICS, math.nan)
        elif not (np.all(np.isfinite(result.x)) and np.all(np.isfinite(result.cost))):
            status = "diverged: non-finite state or cost"
        logs = {k: np.asarray(getattr(result, k)) for k in ("t", "x", "xhat", "u", "cost")}
    except Exception as err:
        metrics = dict.fromkeys(METRICS, math.nan)
        status = status_line(err)
        logs = {}
    return RunOutcome(
        variant=variant.name,
        initial_state=label,
        metrics=metrics,
        status=status,
        wall_time=time.perf_counter() - start + build_share,
        learned=learned,
        logs=logs,
        regulated=regulated,
    )


def _policy_costs(
    evaluator: Any, result: Any, scenario: Scenario, deadline: float | None = None
) -> dict[str, float]:
    """The policy in force at 0 and at the run's end, each fed the true state from x0.

    What learning buys, apart from the observer: the critic frozen at
    ``W_pi(0)`` and ``W_pi(T)``, over the scenario's horizon
    (:class:`ofrl_drake.learning_curve.PolicyEvaluator`, built once per
    variant). NaN for a controller that does not act on the critic (``lqr``,
    ``constant``): no ``evaluator``. Each evaluation stops at ``deadline`` (a
    ``time.monotonic()`` reading) with :class:`~ofrl_drake.errors.WallTimeExceeded`.
    """
    if evaluator is None:
        return {"initial_policy_cost": math.nan, "final_policy_cost": math.nan}
    x0 = np.asarray(scenario.x0, dtype=float)
    return {
        "initial_policy_cost": evaluator(result.W_policy[0], x0=x0, deadline=deadline).cost,
        "final_policy_cost": evaluator(result.W_policy[-1], x0=x0, deadline=deadline).cost,
    }


def solve_optimal_task(
    scenario: Scenario,
    x0: Sequence[float],
    warm: RunOutcome | Sequence[RunOutcome] | Trajectory | None,
    duration: float | None = None,
    mesh: Mesh | None = None,
    solver: str | None = None,
    dynamics: Mapping[str, str | None] | None = None,
) -> OptimalControlResult:
    """``J*`` from ``x0``, warm-started from a run; a failed solve is returned, not raised.

    ``warm`` is that run, or the runs of a :func:`run_variant_states` task
    (the one from ``x0`` is used), or a trajectory, or None. ``dynamics`` is
    checked as by :func:`run_variant_states`.

    Raises
    ------
    AblationError
        If ``warm`` is none of these (a call to fix, not a solve that failed).
    """
    if isinstance(warm, (list, tuple)):
        label = initial_state_label(x0)
        warm = next((run for run in warm if run.initial_state == label), None)
    if duration is not None:
        scenario = dataclasses.replace(
            scenario,
            simulation=dataclasses.replace(scenario.simulation, duration=float(duration)),
        )
    warm_start = warm.warm_start() if isinstance(warm, RunOutcome) else warm
    if not (warm_start is None or isinstance(warm_start, Trajectory)):
        raise AblationError(
            f"solve_optimal_task: warm must be a RunOutcome, the runs of a "
            f"run_variant_states task, an optimal.Trajectory or None; got "
            f"{type(warm).__name__} {warm!r:.80}. Pass the run to warm-start from, or None "
            "for a cold start."
        )
    try:
        check_dynamics(scenario, dynamics)
        return optimal_control(scenario, x0, warm_start=warm_start, mesh=mesh, solver=solver)
    except Exception as err:
        return failed_optimum(x0, scenario.simulation.duration, status_line(err))


def failed_optimum(x0: Iterable[float], duration: float, status: str) -> OptimalControlResult:
    """A ``J*`` that is not available (NaN, not converged), with why in its ``status``."""
    return OptimalControlResult(
        x0=tuple(float(v) for v in x0),
        cost=math.nan,
        converged=False,
        status=status,
        duration=float(duration),
        solver="",
        solve_time=0.0,
    )
