"""Running the command-line tool as a user does: ``python -m ofrl_drake`` in a subprocess."""

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
