"""Where a result came from: package versions, the command line, the start time.

:func:`provenance` is stored in every ``summary.json`` (key ``provenance``)
beside ``scenario.yaml``, the scenario as run, so an output folder says how to
reproduce itself.
"""

from __future__ import annotations

import datetime
import functools
import importlib.metadata
import platform
import shlex
import sys
from typing import Any

__all__ = ["provenance", "utc_now", "versions"]

#: Distribution name -> key in :func:`versions`.
_PACKAGES = {"ofrl_drake": "ofrl_drake", "drake": "drake", "numpy": "numpy", "scipy": "scipy"}


def utc_now() -> str:
    """The current time in UTC, ISO 8601 to the second (``2026-12-01T02:00:00+00:00``)."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def versions() -> dict[str, str]:
    """Versions of ofrl_drake, Drake, numpy, scipy and Python (``"not installed"`` if absent).

    Read from the installed distributions' metadata; ofrl_drake's is
    ``version`` in pyproject.toml, and ``ofrl_drake.__version__`` is this entry.
    """
    return dict(_installed_versions())


@functools.cache
def _installed_versions() -> dict[str, str]:
    # Read once per process (about 4 ms a package): the modules in use cannot change.
    out = {}
    for dist, key in _PACKAGES.items():
        try:
            out[key] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[key] = "not installed"
    out["python"] = platform.python_version()
    return out


def provenance(started: str | None = None) -> dict[str, Any]:
    """``started`` (UTC, default now), the command line of this process, and :func:`versions`."""
    argv = getattr(sys, "orig_argv", None) or [sys.executable, *sys.argv]
    return {
        "started": started or utc_now(),
        "command_line": shlex.join(argv),
        "versions": versions(),
    }
