"""The package type-checks: ``python -m mypy`` (configured in pyproject.toml) succeeds.

mypy is in the ``test`` extra, so this runs wherever the tests do. Modules still being
typed are listed in pyproject.toml's ``ignore_errors`` override, not skipped here.
"""

import subprocess
import sys

from .conftest import ROOT


def test_mypy_reports_no_errors():
    run = subprocess.run(
        [sys.executable, "-m", "mypy"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert run.returncode == 0, (
        f"`python -m mypy` exited with {run.returncode}:\n{run.stdout}{run.stderr}"
    )
    assert "Success: no issues found" in run.stdout, run.stdout
