"""The engine of a sweep: tasks run in this process or on a Dask cluster, a bar of rows.

Shared by :func:`ofrl_drake.ablation.ablate` and
:func:`ofrl_drake.monte_carlo.montecarlo`. A task is a function and picklable
arguments (a :class:`~ofrl_drake.scenario.Scenario` dataclass, the choices,
the initial states); it builds its own Drake diagram where it runs, so nothing
of Drake is pickled. Without a Dask ``distributed.Client`` the
:class:`Engine` runs the tasks one after another in this process, in
submission order; with one, they run on the cluster and are handed back as
they finish. A task may take another task's result as an argument
(:meth:`Engine.ref`), e.g. ``J*`` warm-started from a run.

:func:`execute` submits a sweep's tasks, hands each finished task to the
sweep, and advances the progress bar by the rows that task completed: none
while a row waits for another task, one or more otherwise (a task of one
variant from many initial states would complete several). What the rows are
and where they go is the sweep's business (:mod:`ofrl_drake.sweep_store`).

On a cluster, the warnings a task raises (in a worker process, where Python
prints them in its own format, two lines with the source line) are recorded
with its result (:func:`_warnings_recorded`) and warned again in this process
as the task is handed back: they reach the command's one-line printer
(``ofrl_drake.cli``), as those of a task run serially do.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ofrl_drake.progress import ProgressBar

__all__ = ["Engine", "execute", "split_consecutive", "worker_threads"]


@dataclass(frozen=True)
class _Ref:
    """The result of the serial task ``handle``, as an argument of a later task."""

    handle: int


@dataclass(frozen=True)
class _Warned:
    """What a task returned on a cluster, and the warnings it raised there.

    ``warned`` holds ``(category, message, filename, lineno)`` of each, the
    message as text (a warning's own class may not survive pickling).
    """

    value: Any
    warned: tuple[tuple[type[Warning], str, str, int], ...]


def _warnings_recorded(fn: Callable[..., Any], *args: Any) -> _Warned:
    """``fn(*args)`` on a cluster's worker, with the warnings it raised (:class:`_Warned`).

    A task's argument that is an earlier task's result (:meth:`Engine.ref`)
    arrives as that task's :class:`_Warned`: its value is passed on.
    """
    args = tuple(a.value if isinstance(a, _Warned) else a for a in args)
    with warnings.catch_warnings(record=True) as caught:
        value = fn(*args)
    warned = tuple((w.category, str(w.message), w.filename, w.lineno) for w in caught)
    return _Warned(value, warned)


#: Where :func:`_warn_again` keeps the warnings shown, as Python keeps a module's: a
#: warning that the filters show once per place is shown once, not once per task.
_WARNED_AGAIN: dict[Any, Any] = {}


def _warn_again(result: Any) -> Any:
    """The value of a cluster task's ``result`` (:class:`_Warned`), its warnings warned here.

    They go through this process's filters and ``warnings.showwarning`` (the
    command's one-line printer), as the warnings of a task run here do.
    """
    if not isinstance(result, _Warned):
        return result
    for category, message, filename, lineno in result.warned:
        try:
            warning = category(message)
        except Exception:  # a class that takes more than the message: its text, as is
            warning = UserWarning(message)
        warnings.warn_explicit(warning, type(warning), filename, lineno, registry=_WARNED_AGAIN)
    return result.value


class Engine:
    """Runs a sweep's tasks: serially in this process, or on a Dask cluster.

    Parameters
    ----------
    client : distributed.Client, optional
        Submit the tasks to this cluster; without one, run them here, in
        submission order, when :meth:`completed` is iterated.
    """

    def __init__(self, client: Any = None) -> None:
        self.client = client
        self._submitted: list[Any] = []  # (handle, fn, args) serially, else futures

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Queue ``fn(*args)``; return its handle (an int serially, else a Dask future)."""
        if self.client is None:
            handle = len(self._submitted)
            self._submitted.append((handle, fn, args))
            return handle
        future = self.client.submit(_warnings_recorded, fn, *args, pure=False)
        self._submitted.append(future)
        return future

    def ref(self, handle: Any) -> Any:
        """The result of task ``handle``, to pass as an argument of a task submitted later."""
        return handle if self.client is not None else _Ref(handle)

    def completed(self) -> Iterator[tuple[Any, Any, BaseException | None]]:
        """``(handle, result, None)`` or ``(handle, None, error)`` for each task as it ends."""
        if self.client is not None:
            from distributed import as_completed

            for future in as_completed(self._submitted):
                try:
                    yield future, _warn_again(future.result()), None
                except Exception as err:
                    yield future, None, err
            return
        results: dict[int, Any] = {}
        for handle, fn, args in self._submitted:
            resolved = tuple(results[a.handle] if isinstance(a, _Ref) else a for a in args)
            try:
                results[handle] = fn(*resolved)
                yield handle, results[handle], None
            except Exception as err:  # tasks catch their own errors; this is a safety net
                results[handle] = None
                yield handle, None, err


def execute(
    submit: Callable[[Engine], Mapping[Any, Any]],
    finish: Callable[[Any, Any, BaseException | None], Sequence[Any]],
    *,
    client: Any,
    total: int,
    done: int,
    progress: bool | None,
) -> None:
    """Run a sweep's tasks and hand each one, as it ends, to the sweep.

    Parameters
    ----------
    submit : callable
        ``submit(engine)`` submits the tasks (:meth:`Engine.submit`) and
        returns ``handle -> task`` (the sweep's own description of each).
    finish : callable
        ``finish(task, result, error)``: records a finished task (``error``
        set if it raised or its worker was lost) and returns the rows it
        completed; it may raise to stop the sweep.
    client : distributed.Client or None
        Where the tasks run (:class:`Engine`).
    total, done : int
        Rows in the whole sweep, and already done (resumed).
    progress : bool or None
        The bar of finished rows on stderr; None: only on a terminal.
    """
    engine = Engine(client)
    show = sys.stderr.isatty() if progress is None else progress
    bar = ProgressBar(total, sys.stderr, unit="runs", show=show)
    bar.update(done)
    try:
        tasks = submit(engine)
        for handle, value, err in engine.completed():
            for _ in finish(tasks[handle], value, err):
                bar.advance()
    finally:
        bar.close()


def worker_threads(client: Any) -> int:
    """How many tasks ``client``'s cluster runs at once (1 without a cluster)."""
    if client is None:
        return 1
    try:
        return max(1, int(sum(client.nthreads().values())))
    except Exception:  # a client that cannot tell: as if it ran one task at a time
        return 1


def split_consecutive(items: Sequence[Any], parts: int) -> list[list[Any]]:
    """``items`` in at most ``parts`` consecutive runs of nearly equal length, none empty.

    >>> split_consecutive([1, 2, 3, 4, 5], 2)
    [[1, 2, 3], [4, 5]]
    """
    count = max(1, min(parts, len(items)))
    size, extra = divmod(len(items), count)
    out, start = [], 0
    for k in range(count):
        stop = start + size + (1 if k < extra else 0)
        out.append(list(items[start:stop]))
        start = stop
    return [part for part in out if part]
