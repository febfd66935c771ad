"""The package's one progress bar: a line of ``#`` redrawn in place on a stream.

A simulation draws its simulated time in whole percent (`` 17%     3.2 s``
after the bar, from the run guard, :mod:`ofrl_drake.guard`); a sweep draws its
finished runs (``3/17 runs    41.0 s``, from the engine,
:mod:`ofrl_drake.sweep`). The bar is redrawn only when its label changes, so a
monitor may update it at every integrator step.
"""

from __future__ import annotations

import time
from typing import IO

__all__ = ["ProgressBar"]

#: Characters between the brackets.
WIDTH = 30


class ProgressBar:
    """A one-line bar of an amount done out of ``total``, with the elapsed wall time.

    Parameters
    ----------
    total : float
        The amount at 100 %: a horizon in seconds, a number of runs.
    stream : file object
        Where to draw (``sys.stderr``).
    unit : str, optional
        Label the bar ``done/total unit`` (``3/17 runs``), redrawn at each new
        count; without it, in whole percent (`` 17%``), redrawn at each new
        percent.
    show : bool
        Draw nothing when False (the amount is still tracked).

    Examples
    --------
    >>> bar = ProgressBar(2.0, sys.stderr)                   # doctest: +SKIP
    >>> bar.update(0.5); bar.close()                         # doctest: +SKIP
    >>> runs = ProgressBar(17, sys.stderr, unit="runs")      # doctest: +SKIP
    >>> runs.update(3); runs.advance(); runs.close()         # doctest: +SKIP
    """

    def __init__(
        self, total: float, stream: IO[str], *, unit: str | None = None, show: bool = True
    ) -> None:
        self.total = total
        self.stream = stream
        self.unit = unit
        self.show = show
        self.done: float = 0
        self._start = time.perf_counter()
        self._shown: float | None = None  # the count or percent last drawn

    def update(self, done: float) -> None:
        """Set the amount done; redraw if the label changed."""
        self.done = done
        if self.unit is None:
            shown: float = int(100 * min(max(done / self.total, 0.0), 1.0))
        else:
            shown = done
        if shown == self._shown:
            return
        self._shown = shown
        if self.show:
            self._draw(shown)

    def advance(self, step: float = 1) -> None:
        """Add ``step`` to the amount done (one finished run by default)."""
        self.update(self.done + step)

    def _draw(self, shown: float) -> None:
        if self.unit is None:
            filled = round(WIDTH * shown / 100)
            label = f"{shown:3d}%"
        else:
            filled = round(WIDTH * shown / max(self.total, 1))
            label = f"{shown}/{self.total} {self.unit}"
        elapsed = time.perf_counter() - self._start
        self.stream.write(f"\r[{'#' * filled}{'.' * (WIDTH - filled)}] {label}  {elapsed:6.1f} s")
        self.stream.flush()

    def close(self) -> None:
        """End the line."""
        if self.show:
            self.stream.write("\n")
            self.stream.flush()
