"""How the package's numba kernels are compiled: ``@njit(**JIT)``.

``cache``: compiled once per machine, then loaded from ``__pycache__``.
numba checks a cached kernel only against its own source file, but a kernel
inlines the kernels it calls from other modules (the Bellman kernel calls
:mod:`ofrl_drake.cost`'s), so an edit of ``cost.py`` alone (a ``git pull`` into
an editable install) would keep running the old cost. On import, this module
compares the kernel modules' files (:data:`KERNEL_MODULES`) with those the
caches were compiled from, and drops every cached kernel when one changed
(:func:`drop_stale_caches`).

``error_model="numpy"``: numba's default ("python") model tests every float
division for a zero divisor, to raise ``ZeroDivisionError``, and that branch
keeps LLVM from vectorizing a loop that divides (measured 4x slower per
division in the Bellman kernel). No kernel here divides by zero, and IEEE
``inf``/``nan`` would be the right answer if one did.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path
from typing import Literal, TypedDict

#: The modules of the package that define numba kernels (a test keeps this list whole).
KERNEL_MODULES = ("basis", "bellman", "cost", "guard", "observer", "policy")
#: The file in ``__pycache__`` that records the kernel modules' files the caches are of.
STAMP_FILE = "numba_kernels.stamp"


class JitOptions(TypedDict):
    """The keyword arguments of ``numba.njit`` used here, typed so ``njit(**JIT)`` type-checks."""

    cache: bool
    error_model: Literal["python", "numpy"]


JIT: JitOptions = {"cache": True, "error_model": "numpy"}


def _sources_stamp(package: Path, modules: tuple[str, ...]) -> str:
    """A hash of the modification time and size of each ``package/<module>.py``."""
    parts = []
    for name in modules:
        try:
            stat = (package / f"{name}.py").stat()
            parts.append(f"{name}:{stat.st_mtime_ns}:{stat.st_size}")
        except OSError:
            parts.append(f"{name}:missing")
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def drop_stale_caches(
    package: Path = Path(__file__).parent, modules: tuple[str, ...] = KERNEL_MODULES
) -> bool:
    """Remove numba's cached kernels of ``modules`` if one of their files changed.

    Compares :func:`_sources_stamp` with ``package/__pycache__/STAMP_FILE``
    (none: the caches are of unknown files, also dropped) and records the new
    stamp. A folder that cannot be written (a read-only install, whose files
    change only with a reinstall, which numba sees) is left as it is.

    Returns
    -------
    bool
        True if the caches were dropped.
    """
    cache = package / "__pycache__"
    stamp = _sources_stamp(package, modules)
    with contextlib.suppress(OSError):
        if (cache / STAMP_FILE).read_text() == stamp:
            return False
    try:
        cache.mkdir(exist_ok=True)
        for name in modules:
            for path in cache.glob(f"{name}.*.nb[ic]"):
                path.unlink(missing_ok=True)  # another process may have removed it
        temporary = cache / f"{STAMP_FILE}.{os.getpid()}"
        temporary.write_text(stamp)
        temporary.replace(cache / STAMP_FILE)
    except OSError:
        return False
    return True


drop_stale_caches()
