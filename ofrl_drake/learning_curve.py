"""Is the critic learning? Policy-quality checkpoints and learning-health logs of a run.

A run's closed-loop cost mixes the observer's transient with the learning. To
see what learning buys, :func:`learning_curve` takes the policy in force at
checkpoints ``t_k`` along the run and evaluates each one alone
(:func:`evaluate_policy`): the critic frozen at ``W_pi(t_k)``, the **true
state** fed back, from the scenario's ``x0`` over its horizon. Its cost, and
its ratio to ``J*`` when that is known, is the learning curve. Each
checkpoint is a simulation over the whole horizon, so the curve can take as
long as the run: ``max_wall_time`` bounds it (:class:`~ofrl_drake.errors.WallTimeExceeded`,
as ``run --max-wall`` does).

:func:`learning_health` reads the logs: the learning condition ``c(t)``,
``||Gamma||_2`` and ``cond(Gamma)``, for bases with quadratic monomials the
eigenvalues of the value's quadratic part ``P(W)``, the spectral abscissa of
the linearized loop ``A + B K`` under the policy in force, and when each
policy update was accepted or rejected (:class:`~ofrl_drake.systems.PolicyGate`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus
from pydrake.systems.primitives import ConstantVectorSource

from ofrl_drake.ablation_metrics import optimality_ratio
from ofrl_drake.checks import (
    count_at_most,
    number_from_json,
    number_to_json,
    optional_number_from_json,
    positive_number,
    string_from_json,
    vector_to_json,
)
from ofrl_drake.diagram import ClosedLoop, symbolic_blocks
from ofrl_drake.errors import (
    ModelError,
    ScenarioError,
    WallTimeExceeded,
    is_domain_error,
    one_line,
)
from ofrl_drake.guard import StallDetector
from ofrl_drake.learning import (
    linear_policy_gain,
    spectral_abscissa,
    value_matrix,
    value_weights,
)
from ofrl_drake.limits import CHECKPOINTS_FIX, MAX_CHECKPOINTS
from ofrl_drake.scenario import Scenario, abort_box
from ofrl_drake.simulation import (
    SUMMARY_FILE,
    SimulationResult,
    damaged_run_file,
    read_run_series,
    simulator_config,
    summary_entry,
)
from ofrl_drake.variants import controller_block, plant_block, running_cost_block

__all__ = [
    "DEFAULT_CHECKPOINTS",
    "LEARNING_HEALTH_FILE",
    "LearningHealth",
    "LearningReport",
    "PolicyEvaluator",
    "PolicyRun",
    "evaluate_policy",
    "learning_curve",
    "learning_health",
    "learning_report",
    "lqr_weights",
]

#: Checkpoints of the learning curve by default (``run --checkpoints``).
DEFAULT_CHECKPOINTS = 10

#: The file of a run folder holding :meth:`LearningHealth.arrays` (``ofrl-drake run``).
LEARNING_HEALTH_FILE = "learning_health.npz"


@dataclass(frozen=True)
class PolicyRun:
    """One policy fed the true state from ``x0`` (:func:`evaluate_policy`).

    ``cost`` is ``J(T)``, or NaN when the run left the abort box (``status``
    then says ``diverged`` and when).
    """

    cost: float
    final_state_norm: float
    status: str


class PolicyEvaluator:
    """The policy-evaluation diagram of a loop, built once and run for any ``W`` and ``x0``.

    A Drake diagram of the loop's plant model, its controller and running cost
    (no observer, no learning): the saturated policy of weights ``W``, critic
    frozen, the true state fed back, integrated with the scenario's integrator
    settings. ``W`` is the value of a ``ConstantVectorSource`` (a numeric
    parameter) and ``x0`` the plant's state, both written into the context of
    each run, so evaluating many policies builds one diagram. Each run starts
    from a fresh ``Simulator``: the same numbers as a diagram built for it.

    Parameters
    ----------
    loop : ClosedLoop
        The loop whose plant model, basis, cost and input bound are used.

    Examples
    --------
    >>> evaluate = PolicyEvaluator(loop)                                 # doctest: +SKIP
    >>> [evaluate(W).cost for W in result.W_policy[::100]]               # doctest: +SKIP
    """

    def __init__(self, loop: ClosedLoop) -> None:
        self.loop = loop
        parts = loop.parts
        scenario: Scenario = parts.scenario
        system = parts.system
        symbolic = symbolic_blocks(scenario, system)
        builder = DiagramBuilder()
        self._plant = builder.AddSystem(plant_block(system, scenario.x0, symbolic))
        controller = builder.AddSystem(
            controller_block(system, parts.basis, parts.r, scenario.input_bound, symbolic)
        )
        self._cost = builder.AddSystem(
            running_cost_block(parts.Q, parts.r, scenario.input_bound, symbolic)
        )
        self._weights = builder.AddSystem(ConstantVectorSource(np.zeros(parts.basis.size)))  # type: ignore[arg-type]  # pydrake array stub
        plant, cost = self._plant, self._cost
        builder.Connect(plant.GetOutputPort("state"), controller.GetInputPort("estimated_state"))
        builder.Connect(self._weights.get_output_port(), controller.GetInputPort("policy_weights"))
        builder.Connect(controller.GetOutputPort("u"), plant.GetInputPort("u"))
        builder.Connect(plant.GetOutputPort("state"), cost.GetInputPort("state"))
        builder.Connect(controller.GetOutputPort("u"), cost.GetInputPort("u"))
        self.diagram = builder.Build()

    def __call__(
        self,
        W: np.ndarray,
        *,
        x0: np.ndarray | None = None,
        duration: float | None = None,
        deadline: float | None = None,
    ) -> PolicyRun:
        """The cost of the policy of weights ``W`` from ``x0`` (default: the scenario's).

        Parameters
        ----------
        W : ndarray, shape (L,)
        x0 : ndarray, optional
            Initial state (default: the scenario's).
        duration : float, optional
            Horizon (default: the scenario's).
        deadline : float, optional
            A ``time.monotonic()`` reading: the run stops when it passes
            (checked after every step by the simulator's monitor, which
            changes no step). None: no limit.

        Returns
        -------
        PolicyRun
            Stopped as ``diverged`` when the state leaves the scenario's abort box.

        Raises
        ------
        ScenarioError
            If ``deadline`` is not a number >= 0.
        WallTimeExceeded
            If ``deadline`` passed before the horizon (step ``"policy evaluation"``).
        """
        if deadline is not None:
            deadline = positive_number(
                "PolicyEvaluator: deadline (a time.monotonic() reading)",
                deadline,
                allow_zero=True,
                error=ScenarioError,
            )
        scenario: Scenario = self.loop.parts.scenario
        start = np.asarray(scenario.x0 if x0 is None else x0, dtype=float)
        horizon = float(scenario.simulation.duration if duration is None else duration)
        diagram, plant, cost = self.diagram, self._plant, self._cost
        simulator = Simulator(diagram)
        ApplySimulatorConfig(simulator_config(scenario), simulator)
        root = simulator.get_mutable_context()
        weights_context = self._weights.GetMyMutableContextFromRoot(root)
        self._weights.get_mutable_source_value(weights_context).SetFromVector(  # type: ignore[attr-defined]  # AddSystem returns System
            np.asarray(W, dtype=float)
        )
        plant.set_state(plant.GetMyMutableContextFromRoot(root), start)  # type: ignore[attr-defined]  # a plant block (PlantStateSetter)
        lower, upper = abort_box(scenario)
        state_port = plant.GetOutputPort("state")
        left: list[tuple[float, bool]] = []  # when the state left the box, and if non-finite
        late: list[float] = []
        stall = StallDetector()
        stalled = [""]  # why the run stalled, once it has

        def watch(root) -> EventStatus:
            x = np.asarray(state_port.Eval(plant.GetMyContextFromRoot(root)))
            if not np.all(np.isfinite(x)) or np.any((x < lower) | (x > upper)):
                left.append((root.get_time(), not np.all(np.isfinite(x))))
                return EventStatus.ReachedTermination(diagram, "left the abort box")
            stalled[0] = stall.reason(root.get_time())
            if stalled[0]:
                return EventStatus.ReachedTermination(diagram, stalled[0])
            if deadline is not None and time.monotonic() > deadline:
                late.append(root.get_time())
                return EventStatus.ReachedTermination(diagram, "past its deadline")
            return EventStatus.Succeeded()

        simulator.set_monitor(watch)
        simulator.Initialize()
        try:
            simulator.AdvanceTo(horizon)
        except RuntimeError as err:  # an integrator that gives up: the policy diverged
            return PolicyRun(float("nan"), float("nan"), f"diverged: {one_line(err)}")
        except ValueError as err:  # f or g outside its domain (sqrt(-1)): the state left it
            if not is_domain_error(err):
                raise
            cause = one_line(err, 200)
            return PolicyRun(
                float("nan"),
                float("nan"),
                f"diverged: the model's f or g was evaluated outside its domain ({cause}), "
                "or another function of the diagram was (Drake does not say which; the "
                "running cost, for one)",
            )
        if late:
            raise WallTimeExceeded(
                f"the policy evaluation passed its deadline at t = {late[0]:.6g} s of "
                f"{horizon:g} s; allow more wall time.",
                step="policy evaluation",
            )
        context = simulator.get_context()
        x = np.asarray(state_port.Eval(plant.GetMyContextFromRoot(context)))
        if left:
            when, non_finite = left[0]
            what = "the state turned NaN or infinite" if non_finite else "left the abort box"
            status = f"diverged: {what} at t = {when:.6g}"
            return PolicyRun(float("nan"), float(np.linalg.norm(x)), status)
        if stalled[0]:
            return PolicyRun(float("nan"), float(np.linalg.norm(x)), f"diverged: {stalled[0]}")
        J = np.asarray(cost.GetOutputPort("cost").Eval(cost.GetMyContextFromRoot(context)))[0]
        return PolicyRun(float(J), float(np.linalg.norm(x)), "ok")


def evaluate_policy(
    loop: ClosedLoop,
    W: np.ndarray,
    *,
    x0: np.ndarray | None = None,
    duration: float | None = None,
) -> PolicyRun:
    """The cost of the saturated policy of weights ``W``, critic frozen, true state fed back.

    One run of a :class:`PolicyEvaluator` of ``loop`` (build one to evaluate
    many policies).

    Parameters
    ----------
    loop : ClosedLoop
        The loop whose plant model, basis, cost and input bound are used.
    W : ndarray, shape (L,)
    x0 : ndarray, optional
        Initial state (default: the scenario's).
    duration : float, optional
        Horizon (default: the scenario's).

    Returns
    -------
    PolicyRun
    """
    return PolicyEvaluator(loop)(W, x0=x0, duration=duration)


@dataclass(frozen=True)
class _Budget:
    """The wall time of a learning curve: ``seconds`` from ``start`` (``time.monotonic()``)."""

    seconds: float
    start: float
    began: float  # when the curve began (``time.monotonic()``), for the message

    def evaluate(self, evaluate: PolicyEvaluator, W: np.ndarray, what: str) -> PolicyRun:
        """``evaluate(W)`` before the deadline, or :class:`WallTimeExceeded` naming ``what``."""
        deadline = self.start + self.seconds
        if time.monotonic() < deadline:
            try:
                return evaluate(W, deadline=deadline)
            except WallTimeExceeded:
                pass
        before = self.began - self.start  # what the run used before the curve began
        if before >= self.seconds:
            where = (
                f"the run had used {before:.3g} s of it before the curve began (the "
                "simulation and the checks after it), so no checkpoint was evaluated; allow "
                "more wall time (a larger --max-wall)"
            )
        else:
            where = (
                f"it stopped at {what}, {time.monotonic() - self.began:.3g} s into the curve "
                f"(the run had used {before:.3g} s before it); allow more wall time (a larger "
                "--max-wall) or evaluate fewer checkpoints"
            )
        raise WallTimeExceeded(
            f"the learning curve did not finish within max_wall_time (--max-wall) = "
            f"{self.seconds:g} s: {where} (--checkpoints 0 switches the learning curve off).",
            step="learning curve",
        ) from None


def _budget(owner: str, max_wall_time: Any, started: Any) -> _Budget | None:
    """The curve's :class:`_Budget` (None without ``max_wall_time``), its values checked.

    Raises
    ------
    ScenarioError
        If ``max_wall_time`` is not a number > 0, ``started`` not a number >= 0,
        or ``started`` is given without ``max_wall_time``.
    """
    now = time.monotonic()
    if max_wall_time is None:
        if started is not None:
            raise ScenarioError(
                f"{owner}: started ({started!r}) is when max_wall_time starts counting; "
                "give max_wall_time too, or leave started out."
            )
        return None
    seconds = positive_number(
        f"{owner}: max_wall_time (seconds, --max-wall)", max_wall_time, error=ScenarioError
    )
    if started is None:
        return _Budget(seconds, now, now)
    start = positive_number(
        f"{owner}: started (a time.monotonic() reading)",
        started,
        allow_zero=True,
        error=ScenarioError,
    )
    return _Budget(seconds, start, now)


def learning_curve(
    loop: ClosedLoop,
    result: SimulationResult,
    *,
    checkpoints: int = DEFAULT_CHECKPOINTS,
    optimal_cost: float | None = None,
    evaluator: PolicyEvaluator | None = None,
    max_wall_time: float | None = None,
    started: float | None = None,
) -> list[dict[str, Any]]:
    """The policy in force at ``checkpoints + 1`` times ``0, T/K, ..., T``, each evaluated alone.

    Parameters
    ----------
    loop : ClosedLoop
        The loop ``result`` was simulated from.
    result : SimulationResult
    checkpoints : int
        ``K >= 1``: the number of intervals between checkpoints.
    optimal_cost : float, optional
        ``J*`` of the scenario from ``x0``; then each entry has its ratio.
    evaluator : PolicyEvaluator, optional
        The loop's evaluator (built here if omitted): one diagram for every checkpoint.
    max_wall_time : float, optional
        Seconds of wall time the curve may take, counted from ``started``; an
        evaluation under way stops when they are used up. None: no limit.
    started : float, optional
        When ``max_wall_time`` starts counting, a ``time.monotonic()``
        reading (default: now). ``run`` passes the start of its simulation,
        so that the simulation and the curve share ``--max-wall``.

    Returns
    -------
    list of dict
        One entry per checkpoint: ``t`` (the logged sample nearest ``t_k``;
        for a policy held as discrete state, such as the policy gate's,
        ``t_k`` itself, evaluated at the first sample after it: Drake logs
        before the gate's decision at ``t_k``, so that sample holds the policy
        in force from ``t_k`` on; a stopped run has none after its stop),
        ``policy_cost``,
        ``optimality_ratio`` (None without ``J*``), ``final_state_norm`` and
        ``status`` of the evaluation.

    Raises
    ------
    ScenarioError
        If ``checkpoints`` is not an integer >= 1, ``max_wall_time`` not a
        number > 0, or ``started`` not a number >= 0 (or given without
        ``max_wall_time``).
    WallTimeExceeded
        If ``max_wall_time`` is used up before the last checkpoint is
        evaluated (step ``"learning curve"``; the message names the
        checkpoint it stopped at, the budget and how to allow more).
    """
    count_at_most(
        "learning_curve: checkpoints (the intervals between checkpoints; "
        "learning_report(checkpoints=0) switches the curve off)",
        checkpoints,
        1,
        MAX_CHECKPOINTS,
        CHECKPOINTS_FIX,
        error=ScenarioError,
    )
    budget = _budget("learning_curve", max_wall_time, started)
    evaluate = PolicyEvaluator(loop) if evaluator is None else evaluator
    return _curve(loop, result, checkpoints, optimal_cost, evaluate, budget)


def _within(
    budget: _Budget | None, evaluate: PolicyEvaluator, W: np.ndarray, what: str
) -> PolicyRun:
    """``evaluate(W)``, within ``budget`` when there is one (:meth:`_Budget.evaluate`)."""
    return evaluate(W) if budget is None else budget.evaluate(evaluate, W, what)


def _curve(
    loop: ClosedLoop,
    result: SimulationResult,
    checkpoints: int,
    optimal_cost: float | None,
    evaluate: PolicyEvaluator,
    budget: _Budget | None,
) -> list[dict[str, Any]]:
    """:func:`learning_curve` with its arguments checked and its budget made (one clock)."""
    horizon = float(loop.parts.scenario.simulation.duration)
    entries = []
    seen: set[int] = set()
    times = np.linspace(0.0, horizon, checkpoints + 1)
    # A policy held as discrete state (the policy gate) is logged before its update at
    # t_k: what is in force from t_k on is at the next sample.
    held = loop.policy.num_discrete_state_groups() > 0
    for k, t_k in enumerate(times, start=1):
        if t_k > result.t[-1] + 1e-9:
            break
        if held:
            after = int(np.searchsorted(result.t, t_k + 1e-9 * max(1.0, horizon), side="right"))
            i = min(after, result.t.size - 1)
            t_entry = float(t_k)
        else:
            i = int(np.argmin(np.abs(result.t - t_k)))
            t_entry = float(result.t[i])
        if i in seen:
            continue
        seen.add(i)
        where = f"checkpoint {k} of {times.size} (t = {t_entry:.6g} s)"
        run = _within(budget, evaluate, result.W_policy[i], where)
        ratio = None if optimal_cost is None else optimality_ratio(run.cost, optimal_cost)
        entries.append(
            {
                "t": t_entry,
                "policy_cost": number_to_json(run.cost),
                "optimality_ratio": number_to_json(ratio),
                "final_state_norm": number_to_json(run.final_state_norm),
                "status": run.status,
            }
        )
    return entries


@dataclass
class LearningHealth:
    """Learning-health series of a run (:func:`learning_health`), time first.

    Attributes
    ----------
    t : ndarray, shape (T,)
    learning_condition : ndarray, shape (T,)
        ``c(t)`` for the policy in force.
    gamma_norm, gamma_condition : ndarray, shape (T,)
        ``||Gamma||_2`` and ``cond(Gamma)``.
    value_eigenvalues : ndarray, shape (T, n) or None
        Eigenvalues of the quadratic part ``P(W)`` of the critic's value
        (None when the basis has no quadratic monomial).
    spectral_abscissa : ndarray, shape (T,) or None
        Of ``A + B K(W_pi)``, the linearized loop under the policy in force
        (None without a linearization or quadratic monomials).
    accepted_times, rejected_times : list of float
        When the policy gate accepted or rejected an update (empty under the
        paper's law, which has no gate): one entry per decision, the first
        log sample at or after it (the gate decides at multiples of
        ``policy_period``; when that is at most the log period, several
        decisions share a sample time and the time repeats).
    """

    t: np.ndarray
    learning_condition: np.ndarray
    gamma_norm: np.ndarray
    gamma_condition: np.ndarray
    value_eigenvalues: np.ndarray | None = None
    spectral_abscissa: np.ndarray | None = None
    accepted_times: list[float] = field(default_factory=list)
    rejected_times: list[float] = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        """The series for ``learning_health.npz``."""
        out = {
            "t": self.t,
            "learning_condition": self.learning_condition,
            "gamma_norm": self.gamma_norm,
            "gamma_condition": self.gamma_condition,
        }
        if self.value_eigenvalues is not None:
            out["value_eigenvalues"] = self.value_eigenvalues
        if self.spectral_abscissa is not None:
            out["spectral_abscissa"] = self.spectral_abscissa
        return out

    @classmethod
    def load(
        cls,
        path: str | Path,
        result: SimulationResult,
        accepted_times: Sequence[float] = (),
        rejected_times: Sequence[float] = (),
    ) -> LearningHealth:
        """The series :meth:`arrays` wrote into ``path``, of the run ``result`` read back.

        The policy updates are not in the file (``summary.json`` ->
        ``learning_health`` holds them): pass them as ``accepted_times``,
        ``rejected_times``.

        Raises
        ------
        RunFolderError
            As :func:`~ofrl_drake.simulation.read_run_series` (a missing or
            damaged file, another run's samples); if a series of
            :meth:`arrays` is missing (but the optional two), the file holds
            another, or one has the wrong shape: ``value_eigenvalues`` is
            ``(T, n)`` for the ``n`` states of ``result``, the others ``(T,)``.
        """
        path = Path(path)
        series = read_run_series(path, result.t, required=_HEALTH_SERIES[:3])
        unknown = sorted(set(series) - set(_HEALTH_SERIES))
        if unknown:
            raise damaged_run_file(
                path, f"holds {unknown}, no series of a run's learning health {_HEALTH_SERIES}"
            )
        n = result.x.shape[1]
        for key, value in series.items():
            shape = (result.t.size, n) if key == "value_eigenvalues" else (result.t.size,)
            if value.shape != shape:
                raise damaged_run_file(
                    path, f"{key} has shape {value.shape}; expected {shape} (from trajectories.npz)"
                )
        return cls(
            t=result.t,
            learning_condition=series["learning_condition"],
            gamma_norm=series["gamma_norm"],
            gamma_condition=series["gamma_condition"],
            value_eigenvalues=series.get("value_eigenvalues"),
            spectral_abscissa=series.get("spectral_abscissa"),
            accepted_times=list(accepted_times),
            rejected_times=list(rejected_times),
        )

    def summary(self) -> dict[str, Any]:
        """Extremes and final values, for ``summary.json`` → ``learning_health``."""
        out: dict[str, Any] = {
            "min_learning_condition": number_to_json(_extreme(np.nanmin, self.learning_condition)),
            "final_learning_condition": number_to_json(self.learning_condition[-1]),
            "max_gamma_norm": number_to_json(_extreme(np.nanmax, self.gamma_norm)),
            "final_gamma_norm": number_to_json(self.gamma_norm[-1]),
            "max_gamma_condition": number_to_json(_extreme(np.nanmax, self.gamma_condition)),
            "policy_updates_accepted": len(self.accepted_times),
            "policy_updates_rejected": len(self.rejected_times),
            "accepted_times": self.accepted_times,
            "rejected_times": self.rejected_times,
        }
        if self.value_eigenvalues is not None:
            smallest = self.value_eigenvalues[:, 0]
            indefinite = np.flatnonzero(smallest <= 0.0)
            out["min_value_eigenvalue"] = number_to_json(np.nanmin(smallest))
            out["final_value_eigenvalues"] = vector_to_json(self.value_eigenvalues[-1])
            out["value_indefinite_from"] = float(self.t[indefinite[0]]) if indefinite.size else None
        if self.spectral_abscissa is not None:
            unstable = np.flatnonzero(self.spectral_abscissa >= 0.0)
            out["max_spectral_abscissa"] = number_to_json(np.nanmax(self.spectral_abscissa))
            out["final_spectral_abscissa"] = number_to_json(self.spectral_abscissa[-1])
            out["linearized_loop_unstable_from"] = (
                float(self.t[unstable[0]]) if unstable.size else None
            )
        return out


def learning_health(loop: ClosedLoop, result: SimulationResult) -> LearningHealth:
    """The learning-health series of ``result``, simulated from ``loop``."""
    G = 0.5 * (result.Gamma + np.swapaxes(result.Gamma, 1, 2))
    finite = np.all(np.isfinite(G), axis=(1, 2))
    gamma_norm = np.full(result.t.size, np.nan)
    gamma_condition = np.full(result.t.size, np.nan)
    if np.any(finite):
        eig = np.linalg.eigvalsh(G[finite])
        gamma_norm[finite] = np.abs(eig).max(axis=1)
        with np.errstate(divide="ignore"):
            gamma_condition[finite] = np.abs(eig).max(axis=1) / np.abs(eig).min(axis=1)
    basis = loop.parts.basis
    has_quadratic = bool(np.any(basis.exponents.sum(axis=1) == 2))
    eigenvalues = abscissa = None
    if has_quadratic:
        P = value_matrix(basis, result.W)
        ok = np.all(np.isfinite(P), axis=(1, 2))
        eigenvalues = np.full((result.t.size, basis.n), np.nan)
        if np.any(ok):
            eigenvalues[ok] = np.linalg.eigvalsh(P[ok])
        critic = loop.parts.critic
        if critic is not None and critic.linearization is not None:
            A, B = critic.linearization
            P_pi = value_matrix(basis, result.W_policy)
            K = linear_policy_gain(B, loop.parts.r, P_pi)
            abscissa = spectral_abscissa(A[None, :, :] + B[None, :, :] @ K)
    accepted: list[float] = []
    rejected: list[float] = []
    updates = result.extra.get("policy_updates")
    if updates is not None:
        # Decisions per log interval: more than one when policy_period <= log_period.
        steps = np.diff(np.asarray(updates, float), axis=0, prepend=np.zeros((1, 2)))
        counts = np.rint(steps).astype(int)
        accepted = [float(t) for t in np.repeat(result.t, counts[:, 0])]
        rejected = [float(t) for t in np.repeat(result.t, counts[:, 1])]
    return LearningHealth(
        t=result.t,
        learning_condition=result.learning_condition,
        gamma_norm=gamma_norm,
        gamma_condition=gamma_condition,
        value_eigenvalues=eigenvalues,
        spectral_abscissa=abscissa,
        accepted_times=accepted,
        rejected_times=rejected,
    )


def lqr_weights(loop: ClosedLoop) -> np.ndarray | None:
    """The LQR value of the linearization at the target, in the loop's basis.

    Drake's ``LinearQuadraticRegulator`` with the scenario's ``Q`` and ``R``;
    None when the loop has no linearization or the basis no quadratic monomial.
    """
    from pydrake.systems.controllers import LinearQuadraticRegulator

    critic = loop.parts.critic
    if critic is None or critic.linearization is None:
        return None
    A, B = critic.linearization
    try:
        _, P = LinearQuadraticRegulator(A, B, loop.parts.Q, np.diag(loop.parts.r))  # type: ignore[arg-type]  # pydrake array stub
        return value_weights(loop.parts.basis, P)  # type: ignore[arg-type]  # pydrake array stub
    except (ModelError, RuntimeError):
        return None


@dataclass
class LearningReport:
    """What ``run`` reports on learning: the curve, the health, and the yardsticks.

    Attributes
    ----------
    curve : list of dict or None
        :func:`learning_curve` (None when switched off, or cut: ``curve_stop``).
    health : LearningHealth
    optimal_cost : float or None
        ``J*`` from ``x0`` when asked for.
    lqr_policy_cost : float or None
        The cost of the LQR policy of the linearization, evaluated like the
        checkpoints (true state, from ``x0``).
    curve_stop : str or None
        Why the curve is missing when it did not finish in time (the message
        of its :class:`~ofrl_drake.errors.WallTimeExceeded`, as ``run`` records
        it); None otherwise.
    """

    curve: list[dict[str, Any]] | None
    health: LearningHealth
    optimal_cost: float | None = None
    lqr_policy_cost: float | None = None
    curve_stop: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """For ``summary.json``: ``learning_health``, ``learning_curve``, ``learning_curve_stop``.

        The last two only when there is a curve, or a reason why there is none.
        """
        health = self.health.summary()
        health["optimal_cost"] = number_to_json(self.optimal_cost)
        health["lqr_policy_cost"] = number_to_json(self.lqr_policy_cost)
        if self.curve:
            first, last = self.curve[0]["policy_cost"], self.curve[-1]["policy_cost"]
            health["initial_policy_cost"] = first
            health["final_policy_cost"] = last
        out: dict[str, Any] = {"learning_health": health}
        if self.curve is not None:
            out["learning_curve"] = self.curve
        if self.curve_stop is not None:
            out["learning_curve_stop"] = self.curve_stop
        return out

    @classmethod
    def load(cls, directory: str | Path, result: SimulationResult) -> LearningReport | None:
        """The report ``run`` saved in the run folder ``directory``; None if it saved none.

        ``result`` is the run read back (:meth:`SimulationResult.load`): its
        :attr:`~SimulationResult.reports` hold what :meth:`to_dict` wrote into
        ``summary.json`` (the curve, the policy updates, ``J*``, the LQR
        policy's cost); the series are read from :data:`LEARNING_HEALTH_FILE`
        (:meth:`LearningHealth.load`). A folder written before the learning
        health (no ``learning_health`` entry) gives None.

        Raises
        ------
        RunFolderError
            If an entry of ``summary.json`` has the wrong type (a time or
            cost that is not a number, a checkpoint without one), or as
            :meth:`LearningHealth.load`.
        """
        reports = result.reports
        if "learning_health" not in reports:
            return None
        directory = Path(directory)
        summary = directory / SUMMARY_FILE

        def entry(key: str, convert: Any) -> Any:
            return summary_entry(summary, reports, key, convert)

        saved = entry("learning_health", _saved_health)
        return cls(
            curve=entry(
                "learning_curve", lambda value: _saved_curve(value, result.t[0], result.t[-1])
            ),
            health=LearningHealth.load(
                directory / LEARNING_HEALTH_FILE,
                result,
                saved["accepted_times"],
                saved["rejected_times"],
            ),
            optimal_cost=saved["optimal_cost"],
            lqr_policy_cost=saved["lqr_policy_cost"],
            curve_stop=entry("learning_curve_stop", string_from_json),
        )


#: The series of :meth:`LearningHealth.arrays` (but ``t``): three always, two optional.
_HEALTH_SERIES = (
    "learning_condition",
    "gamma_norm",
    "gamma_condition",
    "value_eigenvalues",
    "spectral_abscissa",
)


def _saved_health(value: Any) -> dict[str, Any]:
    """``summary.json`` -> ``learning_health``: what :meth:`LearningReport.load` reads of it."""
    return {
        "accepted_times": [number_from_json(t) for t in value["accepted_times"]],
        "rejected_times": [number_from_json(t) for t in value["rejected_times"]],
        "optimal_cost": optional_number_from_json(value.get("optimal_cost")),
        "lqr_policy_cost": optional_number_from_json(value.get("lqr_policy_cost")),
    }


def _saved_curve(value: Any, start: float, end: float) -> list[dict[str, Any]]:
    """``summary.json`` -> ``learning_curve``, each checkpoint's time and cost checked.

    A checkpoint's time is one of the run's, within ``[start, end]`` (the logs' first and
    last times), as :func:`learning_curve` labels them.
    """
    if not isinstance(value, list):
        raise TypeError(f"expected a list of checkpoints, got {type(value).__name__}")
    slack = 1e-9 * max(1.0, abs(end))
    for k, checkpoint in enumerate(value):
        t = number_from_json(checkpoint["t"])
        if not start - slack <= t <= end + slack:
            raise ValueError(
                f"checkpoint {k} is at t = {t!r}, outside the run's times [{start:g}, {end:g}]"
            )
        optional_number_from_json(checkpoint["policy_cost"])
    return value


def learning_report(
    loop: ClosedLoop,
    result: SimulationResult,
    *,
    checkpoints: int = DEFAULT_CHECKPOINTS,
    optimal_cost: float | None = None,
    max_wall_time: float | None = None,
    started: float | None = None,
) -> LearningReport:
    """The learning curve (``checkpoints`` intervals; 0 switches it off) and health of a run.

    Parameters
    ----------
    loop : ClosedLoop
        The loop ``result`` was simulated from.
    result : SimulationResult
    checkpoints : int
        ``K >= 0`` intervals between the curve's checkpoints (:func:`learning_curve`).
    optimal_cost : float, optional
        ``J*`` of the scenario from ``x0``.
    max_wall_time : float, optional
        Seconds of wall time the curve (its checkpoints, then the LQR policy's
        cost) may take, counted from ``started``. None: no limit.
    started : float, optional
        When ``max_wall_time`` starts counting (a ``time.monotonic()``
        reading; default: now).

    Raises
    ------
    ScenarioError
        If ``checkpoints`` is not an integer >= 0, ``max_wall_time`` not a
        number > 0, or ``started`` not a number >= 0 (or given without
        ``max_wall_time``).
    WallTimeExceeded
        If ``max_wall_time`` is used up before the curve is done (step
        ``"learning curve"``, the message naming where it stopped, the budget
        and the fix: a larger ``--max-wall`` or fewer ``--checkpoints``).
    """
    count_at_most(
        "learning_report: checkpoints (0 switches the learning curve off)",
        checkpoints,
        0,
        MAX_CHECKPOINTS,
        CHECKPOINTS_FIX,
        error=ScenarioError,
    )
    budget = _budget("learning_report", max_wall_time, started)
    curve = None
    lqr_cost = None
    if checkpoints > 0:
        evaluate = PolicyEvaluator(loop)
        curve = _curve(loop, result, checkpoints, optimal_cost, evaluate, budget)
        W_lqr = lqr_weights(loop)
        if W_lqr is not None:
            what = "the LQR policy's cost, after the checkpoints"
            lqr_cost = _within(budget, evaluate, W_lqr, what).cost
    return LearningReport(
        curve=curve,
        health=learning_health(loop, result),
        optimal_cost=optimal_cost,
        lqr_policy_cost=lqr_cost,
    )


def _extreme(reduce: Any, values: np.ndarray) -> float:
    """``reduce`` (nanmin or nanmax) of ``values``; NaN, without a warning, when all are NaN."""
    values = np.asarray(values, dtype=float)
    return float(reduce(values)) if np.isfinite(values).any() else float("nan")
