"""Stop a run that diverges or overruns its time, and show progress, without changing its steps.

:class:`RunGuard` is installed as the ``Simulator``'s monitor
(``Simulator.set_monitor``). Drake calls a monitor at the end of
``Initialize()`` and after every integrator step, and "the presence of a
monitor has no effect on the step sizes taken" (Drake's documentation), unlike
a periodic event or a sequence of ``AdvanceTo`` calls, both of which cut the
steps at their times. The guard returns ``EventStatus.ReachedTermination`` to
end ``AdvanceTo`` early when

* a continuous state is non-finite, or x or xhat leaves the abort box
  (status ``diverged``);
* the integrator stalls: :data:`STALL_STEPS` steps in a row each advance time
  by less than Drake's smallest working step, ``max(1e-14, 1e-14 t)``
  (status ``diverged``). Drake's error control answers a NaN or infinite
  time derivative by shrinking the step, and at this size it keeps taking
  steps that round to no time at all, so without this check such a run would
  never end;
* the wall time since :meth:`RunGuard.start` exceeds ``max_wall_time``
  (status ``timeout``).

A monitor cannot see a step that never ends. Drake's error control answers a
NaN or infinite error estimate by shrinking the step tenfold with no floor
(``IntegratorBase::CalcAdjustedStepSize``), so when the time derivative at
the current state is not finite no step ever succeeds and ``AdvanceTo`` never
returns. :class:`StallWatchdog` is a thread that watches the guard's steps and
the integrator's derivative evaluations; when :func:`stall_limit` evaluations
pass without a step, or ``max_wall_time`` without one, it raises
:class:`IntegratorStalled` in the simulating thread. Python delivers it at the
next line of a Python block's calc (every loop has some: the critic, Gamma,
the Bellman sums), and it unwinds ``AdvanceTo`` like any exception of a block.

The same monitor draws the optional :class:`~ofrl_drake.progress.ProgressBar`,
so a run with the bar on and a run with it off take the same steps and give the
same numbers, bit for bit. A condition is seen only after the step that produced it (the monitor
does not localize it), which is all a guard needs.
"""

from __future__ import annotations

import ctypes
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydrake.systems.framework import Context, Diagram, EventStatus, System

from ofrl_drake._jit import kernel
from ofrl_drake.checks import (
    number_from_json,
    object_from_json,
    string_from_json,
    vector_from_json,
    vector_to_json,
)
from ofrl_drake.progress import ProgressBar

__all__ = [
    "STALL_EVALUATIONS",
    "STALL_STEPS",
    "STATUSES",
    "STATUS_DIVERGED",
    "STATUS_OK",
    "STATUS_TIMEOUT",
    "IntegratorStalled",
    "RunGuard",
    "StallDetector",
    "StallWatchdog",
    "StopReport",
    "stall_limit",
]

#: The run reached its horizon.
STATUS_OK = "ok"
#: A state turned non-finite or x or xhat left the abort box.
STATUS_DIVERGED = "diverged"
#: The run used up its wall-time budget.
STATUS_TIMEOUT = "timeout"
#: Every status a run can end with.
STATUSES = (STATUS_OK, STATUS_DIVERGED, STATUS_TIMEOUT)
#: Steps in a row, each shorter than Drake's smallest step, that stop a run as
#: stalled. Drake documents that its integrators never shrink a step below
#: ``h_floor`` (below); with a NaN error estimate they do, and a stalled run
#: takes hundreds of thousands of such steps a second.
STALL_STEPS = 100
#: Drake's ``h_floor`` is ``max(STALL_TOLERANCE, STALL_TOLERANCE * |t|)``
#: (``IntegratorBase::get_working_minimum_step_size``), the shortest step that
#: still advances time.
STALL_TOLERANCE = 1e-14
#: Derivative evaluations without a finished step that make a stall: at least
#: this many, and 20 per continuous state (an implicit scheme forms its
#: Jacobian by differences over every state, some times per step).
STALL_EVALUATIONS = 10_000
#: Seconds between two looks of :class:`StallWatchdog`.
WATCH_PERIOD = 0.1


@dataclass(frozen=True)
class StopReport:
    """How a run ended.

    Attributes
    ----------
    status : str
        :data:`STATUS_OK`, :data:`STATUS_DIVERGED` or :data:`STATUS_TIMEOUT`.
    reason : str
        One line: what stopped the run ("" when it reached its horizon).
    time : float
        Simulated time at the end of the run.
    x, xhat : list of float
        True and estimated state at that time.
    wall_time : float
        Wall-clock seconds from :meth:`RunGuard.start` to the end.
    """

    status: str
    reason: str
    time: float
    x: list[float]
    xhat: list[float]
    wall_time: float

    @property
    def ok(self) -> bool:
        """True if the run reached its horizon."""
        return self.status == STATUS_OK

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (non-finite numbers become None)."""
        return {
            "status": self.status,
            "reason": self.reason,
            "time": self.time,
            "x": vector_to_json(self.x),
            "xhat": vector_to_json(self.xhat),
            "wall_time": self.wall_time,
        }

    @classmethod
    def from_dict(cls, data: Any, size: int | None = None) -> StopReport:
        """The report :meth:`to_dict` wrote (``None`` in x, xhat read back as NaN).

        ``size`` is the number of states x and xhat must hold (None: any).

        Raises
        ------
        TypeError, ValueError, KeyError
            If ``data`` is not an object with every entry of :meth:`to_dict`,
            an entry has the wrong type, a status is not one of
            :data:`STATUS_OK`, :data:`STATUS_DIVERGED`, :data:`STATUS_TIMEOUT`,
            or x, xhat do not hold ``size`` numbers (a reader of a file, such
            as :meth:`ofrl_drake.SimulationResult.load`, names the file).
        """
        data = object_from_json(data)
        status = string_from_json(data["status"])
        if status not in STATUSES:
            raise ValueError(f"status {status!r} is not one of {list(STATUSES)}")
        x = vector_from_json(data["x"], size)
        return cls(
            status=status,
            reason=string_from_json(data["reason"]),
            time=number_from_json(data["time"]),
            x=x,
            xhat=vector_from_json(data["xhat"], len(x)),
            wall_time=number_from_json(data["wall_time"]),
        )


class StallDetector:
    """Tells a simulation whose steps no longer advance time.

    Feed it the time after every step (a ``Simulator`` monitor does). It
    reports a stall after :data:`STALL_STEPS` steps in a row that each advanced
    time by less than Drake's smallest working step, ``max(1e-14, 1e-14 t)``.

    Examples
    --------
    >>> detector = StallDetector()
    >>> [detector.reason(1.0) for _ in range(STALL_STEPS)][-1][:33]
    'the integrator stalled at t = 1 s'
    """

    def __init__(self) -> None:
        self._last_time = -np.inf
        self._short_steps = 0

    def reason(self, t: float) -> str:
        """One line on the stall at time ``t``; "" while the steps advance time."""
        shortest = STALL_TOLERANCE * max(1.0, abs(t))
        self._short_steps = self._short_steps + 1 if t - self._last_time < shortest else 0
        self._last_time = t
        if self._short_steps < STALL_STEPS:
            return ""
        return (
            f"the integrator stalled at t = {t:.6g} s: {STALL_STEPS} steps in a row "
            f"each advanced time by less than {shortest:.1e} s; a time derivative is "
            "probably NaN or infinite just past this state (check the plant's f(x) "
            "and g(x) there)"
        )


@kernel
def _all_inside(
    state: np.ndarray, x: np.ndarray, xhat: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> bool:
    """Every state finite, and x and xhat inside ``[lower, upper]`` (NaN is outside)."""
    for v in state:
        if not np.isfinite(v):
            return False
    for i in range(x.shape[0]):
        if not (lower[i] <= x[i] <= upper[i] and lower[i] <= xhat[i] <= upper[i]):
            return False
    return True


class RunGuard:
    """The monitor of one simulation: divergence and wall-time checks, progress.

    Parameters
    ----------
    diagram : Diagram
        The simulated diagram (named in the termination status).
    plant, observer : System
        Blocks of ``diagram`` with output ports ``state`` and ``estimated_state``.
    box : tuple of ndarray
        ``(lower, upper)``: the abort box for x and xhat.
    max_wall_time : float or None
        Seconds of wall time before the run stops; None for no limit.
    progress : ProgressBar, optional
        Updated after every step.
    relative : bool, optional
        The plant's ``state`` and the box are relative to an equilibrium
        ``x*``: a stop names ``x_i - x*_i`` (default False: ``x_i``).

    Examples
    --------
    >>> guard = RunGuard(diagram, plant, observer, box, 60.0)        # doctest: +SKIP
    >>> simulator.set_monitor(guard)                                 # doctest: +SKIP
    >>> guard.start(); simulator.Initialize()                        # doctest: +SKIP
    >>> if not guard.stopped: simulator.AdvanceTo(30.0)              # doctest: +SKIP
    >>> guard.report(simulator.get_context()).status                 # doctest: +SKIP
    """

    def __init__(
        self,
        diagram: Diagram,
        plant: System,
        observer: System,
        box: tuple[np.ndarray, np.ndarray],
        max_wall_time: float | None = None,
        progress: ProgressBar | None = None,
        relative: bool = False,
    ) -> None:
        self.diagram = diagram
        self.plant = plant
        self.observer = observer
        self.box = box
        self.max_wall_time = max_wall_time
        self.progress = progress
        self.relative = relative
        self._state_port = plant.GetOutputPort("state")
        self._estimate_port = observer.GetOutputPort("estimated_state")
        self._lower = np.asarray(box[0], dtype=float)
        self._upper = np.asarray(box[1], dtype=float)
        self._start = time.perf_counter()
        self.status = STATUS_OK
        self.reason = ""
        self._root: Context | None = None  # the simulator's context, as last seen
        self._stall = StallDetector()
        self._subcontexts: tuple[Context, Context] | None = None
        self.steps = 0  # monitor calls: what StallWatchdog watches
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None  # at the last step
        self._within_step = False  # stopped inside a step: report the last step's end

    def elapsed(self) -> float:
        """Wall-clock seconds since :meth:`start`."""
        return time.perf_counter() - self._start

    @property
    def within_step(self) -> bool:
        """True if the run was stopped inside a step (:meth:`fail` said so)."""
        return self._within_step

    @property
    def last_time(self) -> float:
        """Simulated time of the last step the monitor saw (0 before any)."""
        return 0.0 if self._last is None else float(self._last[0])

    @property
    def stopped(self) -> bool:
        """True once the guard has ended the run."""
        return self.status != STATUS_OK

    def start(self) -> None:
        """Start the wall clock (call right before ``Simulator.Initialize``)."""
        self._start = time.perf_counter()

    def states(self, root_context: Context) -> tuple[np.ndarray, np.ndarray]:
        """x and xhat in ``root_context``."""
        # the monitor sees one context at every step
        if root_context is not self._root or self._subcontexts is None:
            self._root = root_context
            self._subcontexts = (
                self.plant.GetMyContextFromRoot(root_context),
                self.observer.GetMyContextFromRoot(root_context),
            )
        plant_context, observer_context = self._subcontexts
        x = self._state_port.Eval(plant_context)
        xhat = self._estimate_port.Eval(observer_context)
        return np.asarray(x, dtype=float), np.asarray(xhat, dtype=float)

    def check(self, root_context: Context) -> tuple[str, str]:
        """``(status, reason)`` of the run at ``root_context``; ``("ok", "")`` if it may go on."""
        state = root_context.get_continuous_state_vector().CopyToVector()
        x, xhat = self.states(root_context)
        t = root_context.get_time()
        self._last = (t, x, xhat)
        # one compiled call per step
        if _all_inside(state, x, xhat, self._lower, self._upper):  # type: ignore[arg-type]  # pydrake array stub
            return self._check_progress(root_context)
        if not np.all(np.isfinite(state)):
            bad = int(np.flatnonzero(~np.isfinite(state))[0])
            return STATUS_DIVERGED, f"continuous state {bad} is {state[bad]} at t = {t:.6g} s"
        for name, v in (("x", x), ("xhat", xhat)):
            outside = (v < self._lower) | (v > self._upper) | ~np.isfinite(v)
            if np.any(outside):
                i = int(np.flatnonzero(outside)[0])
                shift = f" - x*_{i + 1}" if self.relative else ""
                return STATUS_DIVERGED, (
                    f"{name}_{i + 1}{shift} = {v[i]:.6g} left the abort box "
                    f"[{self._lower[i]:g}, {self._upper[i]:g}] at t = {t:.6g} s"
                )
        return self._check_progress(root_context)

    def _check_progress(self, root_context: Context) -> tuple[str, str]:
        """Stop a run whose steps no longer advance time, then check the wall time."""
        stalled = self._stall.reason(root_context.get_time())
        if stalled:
            return STATUS_DIVERGED, stalled
        return self._check_wall_time(root_context)

    def _check_wall_time(self, root_context: Context) -> tuple[str, str]:
        if self.max_wall_time is None:
            return STATUS_OK, ""
        wall = time.perf_counter() - self._start
        if wall > self.max_wall_time:
            return STATUS_TIMEOUT, (
                f"wall time {wall:.3g} s exceeded max_wall_time = {self.max_wall_time:g} s "
                f"at t = {root_context.get_time():.6g} s"
            )
        return STATUS_OK, ""

    def __call__(self, root_context: Context) -> EventStatus:
        """The monitor: check the run, draw progress, stop the run if needed."""
        self.steps += 1
        if self.progress is not None:
            self.progress.update(root_context.get_time())
        status, reason = self.check(root_context)
        if status == STATUS_OK:
            return EventStatus.Succeeded()
        self.status, self.reason = status, reason
        return EventStatus.ReachedTermination(self.diagram, f"{status}: {reason}")

    def fail(
        self, reason: str, status: str = STATUS_DIVERGED, *, within_step: bool = False
    ) -> None:
        """Record that the integrator gave up (status ``diverged`` unless given).

        ``within_step``: the run was stopped inside a step (:class:`StallWatchdog`),
        whose context holds a stage of it, not a state of the run; the report
        then gives the time and states of the last finished step.
        """
        self.status, self.reason = status, reason
        self._within_step = within_step

    def report(self, root_context: Context) -> StopReport:
        """How the run ended, read from the simulator's final context."""
        if self.progress is not None:
            self.progress.close()
        x, xhat = self.states(root_context)
        t = float(root_context.get_time())
        if self._within_step and self._last is not None:
            t, x, xhat = self._last
        return StopReport(
            status=self.status,
            reason=self.reason,
            time=float(t),
            x=x.tolist(),
            xhat=xhat.tolist(),
            wall_time=time.perf_counter() - self._start,
        )


def stall_limit(states: int) -> int:
    """Derivative evaluations without a step that :class:`StallWatchdog` calls a stall."""
    return max(STALL_EVALUATIONS, 20 * int(states))


class IntegratorStalled(BaseException):
    """Raised by :class:`StallWatchdog` in the thread that runs ``AdvanceTo``.

    A ``BaseException``, as ``KeyboardInterrupt`` is, so that no ``except
    Exception`` in a block's calc keeps it from unwinding ``AdvanceTo``.
    """


def _raise_in(thread_id: int, exc: type[BaseException]) -> None:
    """Have the thread ``thread_id`` raise ``exc`` at its next line of Python."""
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id), ctypes.py_object(exc))


class StallWatchdog:
    """Stop an ``AdvanceTo`` whose integrator step never ends (module docstring).

    Use it as a context manager around ``Simulator.AdvanceTo``, and catch
    :class:`IntegratorStalled` around both: :attr:`fired` then holds the
    status and reason, for :meth:`RunGuard.fail`.

    Parameters
    ----------
    guard : RunGuard
        The simulator's monitor; its ``steps`` count the finished steps.
    integrator : IntegratorBase
        The simulator's integrator; it counts the derivative evaluations.
    limit : int
        Evaluations without a step that make a stall (:func:`stall_limit`).
    period : float
        Seconds between two looks.

    Attributes
    ----------
    fired : tuple of str or None
        ``(status, reason)`` once the watchdog has stopped the run.

    Examples
    --------
    >>> watchdog = StallWatchdog(guard, simulator.get_integrator(), limit)  # doctest: +SKIP
    >>> try:                                                              # doctest: +SKIP
    ...     with watchdog:
    ...         simulator.AdvanceTo(duration)
    ... except IntegratorStalled:
    ...     guard.fail(watchdog.fired[1], watchdog.fired[0])
    """

    def __init__(
        self, guard: RunGuard, integrator: Any, limit: int, period: float = WATCH_PERIOD
    ) -> None:
        self.guard = guard
        self.integrator = integrator
        self.limit = limit
        self.period = period
        self.fired: tuple[str, str] | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._armed = False
        self._target = 0
        self._thread: threading.Thread | None = None

    def __enter__(self) -> StallWatchdog:
        self._target = threading.get_ident()
        self._armed = True
        self._thread = threading.Thread(target=self._watch, name="ofrl-stall-watchdog", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc_info: Any) -> None:
        # Once fired, the exception is raised at the simulating thread's next line of
        # Python, so within the block or on leaving it: catch it around the block.
        with self._lock:
            self._armed = False
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _watch(self) -> None:
        steps, evaluations = self.guard.steps, self.integrator.get_num_derivative_evaluations()
        while not self._stop.wait(self.period):
            now = self.integrator.get_num_derivative_evaluations()
            if self.guard.steps != steps:
                steps, evaluations = self.guard.steps, now
                continue
            # The context holds a stage of the step that does not end: its time is no
            # state's; the last finished step's is.
            t = self.guard.last_time
            fired = None
            if now - evaluations > self.limit:
                fired = (
                    STATUS_DIVERGED,
                    f"the integrator made no step in {now - evaluations} derivative "
                    f"evaluations at t = {t:.6g} s: a time derivative is NaN or infinite "
                    "at this state (check the plant's f(x) and g(x) there), and Drake's error "
                    "control would shrink the step forever",
                )
            elif (
                self.guard.max_wall_time is not None
                and self.guard.elapsed() > self.guard.max_wall_time
            ):
                fired = (
                    STATUS_TIMEOUT,
                    f"wall time {self.guard.elapsed():.3g} s exceeded max_wall_time = "
                    f"{self.guard.max_wall_time:g} s at t = {t:.6g} s, within a step "
                    f"({now - evaluations} derivative evaluations since the last one)",
                )
            if fired is not None:
                with self._lock:
                    if self._armed:
                        self.fired = fired
                        self._armed = False
                        _raise_in(self._target, IntegratorStalled)
                return
