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

The same monitor draws the optional :class:`~ofrl_drake.progress.ProgressBar`,
so a run with the bar on and a run with it off take the same steps and give the
same numbers, bit for bit. A condition is seen only after the step that produced it (the monitor
does not localize it), which is all a guard needs.
"""

from __future__ import annotations

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
    "STALL_STEPS",
    "STATUSES",
    "STATUS_DIVERGED",
    "STATUS_OK",
    "STATUS_TIMEOUT",
    "RunGuard",
    "StallDetector",
    "StopReport",
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
    ) -> None:
        self.diagram = diagram
        self.plant = plant
        self.observer = observer
        self.box = box
        self.max_wall_time = max_wall_time
        self.progress = progress
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
        # one compiled call per step
        if _all_inside(state, x, xhat, self._lower, self._upper):  # type: ignore[arg-type]  # pydrake array stub
            return self._check_progress(root_context)
        t = root_context.get_time()
        if not np.all(np.isfinite(state)):
            bad = int(np.flatnonzero(~np.isfinite(state))[0])
            return STATUS_DIVERGED, f"continuous state {bad} is {state[bad]} at t = {t:.6g} s"
        for name, v in (("x", x), ("xhat", xhat)):
            outside = (v < self._lower) | (v > self._upper) | ~np.isfinite(v)
            if np.any(outside):
                i = int(np.flatnonzero(outside)[0])
                return STATUS_DIVERGED, (
                    f"{name}_{i + 1} = {v[i]:.6g} left the abort box "
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
        if self.progress is not None:
            self.progress.update(root_context.get_time())
        status, reason = self.check(root_context)
        if status == STATUS_OK:
            return EventStatus.Succeeded()
        self.status, self.reason = status, reason
        return EventStatus.ReachedTermination(self.diagram, f"{status}: {reason}")

    def fail(self, reason: str) -> None:
        """Record that the integrator gave up (status ``diverged``)."""
        self.status, self.reason = STATUS_DIVERGED, reason

    def report(self, root_context: Context) -> StopReport:
        """How the run ended, read from the simulator's final context."""
        if self.progress is not None:
            self.progress.close()
        x, xhat = self.states(root_context)
        return StopReport(
            status=self.status,
            reason=self.reason,
            time=float(root_context.get_time()),
            x=x.tolist(),
            xhat=xhat.tolist(),
            wall_time=time.perf_counter() - self._start,
        )
