"""Running the command-line tool as a user does: ``python -m ofrl_drake`` in a subprocess."""

import re
import subprocess
import sys


def run_cli(*args, cwd=None, timeout=1200):
    """``python -m ofrl_drake ARGS`` (each argument through ``str``), output captured as text.

    The timeout turns a hang into a test failure (``subprocess.TimeoutExpired``).
    """
    return subprocess.run(
        [sys.executable, "-m", "ofrl_drake", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
    )


#: A dask scheduler address where nothing listens (port 1).
UNREACHABLE_SCHEDULER = "tcp://127.0.0.1:1"


def run_sweep_against_unreachable_scheduler(command, scenario, out, timeout_option, timeout):
    """``ablate`` or ``montecarlo`` (one run) of ``scenario`` into ``out``, with
    ``--scheduler`` where nothing listens and ``--scheduler-timeout timeout_option``."""
    runs = ("--runs", 1) if command == "montecarlo" else ()
    return run_cli(
        command,
        scenario,
        *runs,
        "--out",
        out,
        "--scheduler",
        UNREACHABLE_SCHEDULER,
        "--scheduler-timeout",
        timeout_option,
        timeout=timeout,
    )


def assert_one_line(proc, code, pattern):
    """``proc`` exited with ``code`` and printed one line on stderr that matches ``pattern``."""
    assert proc.returncode == code, (proc.returncode, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert re.search(pattern, lines[0]), lines[0]
