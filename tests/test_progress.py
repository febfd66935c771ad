"""The one progress bar: in percent for a simulation, in runs for a sweep (pure Python)."""

import io
import re

import numpy as np

from ofrl_drake.progress import ProgressBar


def test_progress_bar_draws_each_percent_once():
    stream = io.StringIO()
    bar = ProgressBar(2.0, stream)
    for t in np.linspace(0.0, 2.0, 1001):
        bar.update(t)
    bar.close()
    frames = stream.getvalue().split("\r")[1:]
    assert len(frames) == 101
    assert frames[-1].startswith("[" + "#" * 30 + "] 100%")


def test_progress_bar_in_runs_draws_each_count_once_from_a_resumed_start():
    stream = io.StringIO()
    bar = ProgressBar(4, stream, unit="runs")
    bar.update(1)  # one row already on disk
    bar.advance(0)  # a run whose row waits for J*: nothing to redraw
    bar.advance()
    bar.advance()
    bar.advance()
    bar.close()
    frames = stream.getvalue().split("\r")[1:]
    assert [f.split("]")[1].split("  ")[0] for f in frames] == [
        " 1/4 runs",
        " 2/4 runs",
        " 3/4 runs",
        " 4/4 runs",
    ]
    assert frames[0].startswith("[" + "#" * 8 + "." * 22 + "]")  # round(30 / 4)
    assert re.fullmatch(r"\[#{30}\] 4/4 runs  +\d+\.\d s\n", frames[-1])


def test_a_hidden_bar_writes_nothing_but_counts():
    stream = io.StringIO()
    bar = ProgressBar(3, stream, unit="runs", show=False)
    bar.update(1)
    bar.advance()
    bar.close()
    assert stream.getvalue() == ""
    assert bar.done == 2
