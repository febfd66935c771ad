"""Wall-clock statistics over repeated runs, and a description of the machine."""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

__all__ = ["Timing", "interleaved", "machine_info", "measure", "speed_probe"]

T = TypeVar("T")


@dataclass(frozen=True)
class Timing:
    """Wall-clock seconds of repeated runs (the warm-up run is not included).

    Attributes
    ----------
    runs : tuple of float
        Seconds of each timed run, in order.
    """

    runs: tuple[float, ...]

    @property
    def median(self) -> float:
        """Median seconds."""
        return statistics.median(self.runs)

    @property
    def min(self) -> float:
        """Fastest run, seconds."""
        return min(self.runs)

    @property
    def max(self) -> float:
        """Slowest run, seconds."""
        return max(self.runs)

    def to_dict(self) -> dict[str, Any]:
        """``{"median", "min", "max", "runs"}`` in seconds."""
        return {
            "median": self.median,
            "min": self.min,
            "max": self.max,
            "runs": list(self.runs),
        }


def measure(fn: Callable[[], T], repeats: int, *, warmup: int = 1) -> tuple[Timing, T]:
    """Time ``fn()`` ``repeats`` times after ``warmup`` untimed calls.

    Returns
    -------
    timing : Timing
    result
        What the last call returned.
    """
    result = None
    for _ in range(warmup):
        result = fn()
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        runs.append(time.perf_counter() - start)
    return Timing(tuple(runs)), result


def interleaved(
    fns: dict[str, Callable[[], Any]], repeats: int, *, warmup: int = 1
) -> tuple[dict[str, Timing], dict[str, Any]]:
    """Time several functions in alternation, so that drift in machine load
    falls on all of them alike.

    Returns
    -------
    timings : dict of Timing
    results : dict
        What each function's last call returned.
    """
    results: dict[str, Any] = {}
    for _ in range(warmup):
        for key, fn in fns.items():
            results[key] = fn()
    runs: dict[str, list[float]] = {key: [] for key in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            start = time.perf_counter()
            results[key] = fn()
            runs[key].append(time.perf_counter() - start)
    return {key: Timing(tuple(r)) for key, r in runs.items()}, results


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _git(*args: str) -> str | None:
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        done = subprocess.run(
            ["git", *args], cwd=root, capture_output=True, text=True, check=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip()


def _load_average() -> list[float] | None:
    try:
        return list(os.getloadavg())
    except OSError:
        return None


def machine_info() -> dict[str, Any]:
    """CPU model, core count, load average, the versions that matter and the commit run.

    ``tree_clean`` is whether the working tree matched the commit, but for
    ``benchmarks/RESULTS.md`` and ``benchmarks/results.json`` (None outside git).
    """
    from importlib.metadata import PackageNotFoundError, version

    import numpy
    import scipy

    try:
        drake = version("drake")
    except PackageNotFoundError:
        drake = "unknown"

    # The run's own outputs do not count: a run rewrites them.
    status = _git(
        "status", "--porcelain", "--", ".", ":!benchmarks/RESULTS.md", ":!benchmarks/results.json"
    )
    return {
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "load_average": _load_average(),
        "commit": _git("rev-parse", "--short", "HEAD"),
        "tree_clean": None if status is None else status == "",
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "drake": drake,
        "platform": platform.platform(),
    }


def speed_probe(calls: int = 20_000) -> dict[str, Any]:
    """Microseconds of two fixed tiny workloads, to show how fast the machine
    ran at a given moment (a shared virtual machine drifts): a 3 x 3 numpy
    product and a call of an empty Python function; and the load average
    (1, 5 and 15 minutes) then."""
    import numpy as np

    A = np.arange(9.0).reshape(3, 3)

    def noop() -> None:
        return None

    def best(fn: Callable[[], Any]) -> float:
        times = []
        for _ in range(5):
            start = time.perf_counter()
            for _ in range(calls):
                fn()
            times.append(time.perf_counter() - start)
        return 1e6 * min(times) / calls

    return {
        "numpy_matmul_3x3_us": best(lambda: A @ A),
        "python_call_us": best(noop),
        "load_average": _load_average(),
    }
