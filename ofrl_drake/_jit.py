"""How the package's numba kernels are compiled: ``@kernel`` and ``@ufunc``.

Both compile in nopython mode and cache the machine code, compiled once per
machine and then loaded, in a folder of their own for each version of the
kernel modules' files (:data:`KERNEL_MODULES`; their modification times and
sizes, read when this module is imported). numba checks a cached kernel only
against its own source file, but a kernel inlines the kernels it calls from
other modules (the Bellman kernel calls :mod:`ofrl_drake.cost`'s), so with
numba's default folder an edit of ``cost.py`` alone (a ``git pull`` into an
editable install) kept running the old cost. With a folder per version, a
process compiles and loads only kernels of the files it imported; one still
running the old files writes to the old folder, which no new process reads.

The folders are under ``NUMBA_CACHE_DIR/ofrl_drake`` when that variable is set,
else ``ofrl_drake/__pycache__/numba`` when the package folder can be written,
else ``~/.cache/ofrl_drake/numba``; when the files change, folders of other
versions untouched for a day are removed.

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
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar, cast

import numba.core.config
from numba import njit, vectorize

from ofrl_drake.atomic import file_version

__all__ = ["KERNEL_MODULES", "cache_folder", "kernel", "ufunc"]

#: The modules of the package that define numba kernels (a test keeps this list whole).
KERNEL_MODULES = ("basis", "bellman", "cost", "guard", "observer", "policy")
#: Seconds after which a cache folder of another version of the files is removed.
STALE_AFTER = 86400.0

F = TypeVar("F", bound=Callable[..., Any])
#: numba's settings (its attributes are made at run time, hence Any).
_CONFIG: Any = numba.core.config


def sources_stamp(package: Path, modules: Sequence[str]) -> str:
    """16 hex digits of a hash of the :func:`~ofrl_drake.atomic.file_version` of each module."""
    versions = [file_version(package / f"{name}.py") for name in modules]
    return hashlib.sha256(repr(versions).encode()).hexdigest()[:16]


def _cache_base(package: Path) -> Path:
    """Where the version folders live (see the module's docstring)."""
    if _CONFIG.CACHE_DIR:
        return Path(_CONFIG.CACHE_DIR) / "ofrl_drake"
    if os.access(package, os.W_OK):
        return package / "__pycache__" / "numba"
    return Path.home() / ".cache" / "ofrl_drake" / "numba"


def cache_folder(package: Path, modules: Sequence[str]) -> Path:
    """The cache folder of the kernels of ``modules`` as their files are now.

    When the folder is new (the files changed), folders of other versions
    not modified for :data:`STALE_AFTER` seconds are removed (best effort:
    one in use is recreated by numba), and so are numba's own caches of
    ``modules`` in ``package/__pycache__`` (written before there were
    folders); an import that finds its folder does no more than that lookup.
    """
    base = _cache_base(package)
    folder = base / sources_stamp(package, modules)
    if folder.exists():
        return folder
    with contextlib.suppress(OSError):
        for other in base.iterdir():
            if time.time() - other.stat().st_mtime > STALE_AFTER:
                shutil.rmtree(other, ignore_errors=True)
    with contextlib.suppress(OSError):  # numba's own caches, of versions before the folders
        for name in modules:
            for path in (package / "__pycache__").glob(f"{name}.*.nb[ic]"):
                path.unlink(missing_ok=True)
    return folder


@contextlib.contextmanager
def _caching_in(folder: Path) -> Iterator[None]:
    """numba places the caches of the functions decorated inside the block in ``folder``.

    numba reads ``config.CACHE_DIR`` when a function is decorated (its cache
    locator is chosen then), so the setting holds for those functions only.
    """
    previous = _CONFIG.CACHE_DIR
    _CONFIG.CACHE_DIR = str(folder)
    try:
        yield
    finally:
        _CONFIG.CACHE_DIR = previous


def compiler(
    folder: Path,
) -> tuple[Callable[[F], F], Callable[[Sequence[str]], Callable[[Callable[..., Any]], Any]]]:
    """``(kernel, ufunc)`` decorators that cache in ``folder`` (for a package's own modules)."""

    def kernel(function: F) -> F:
        """``function`` compiled by ``numba.njit``, cached in the version's folder."""
        with _caching_in(folder):
            return cast(F, njit(cache=True, error_model="numpy")(function))

    def ufunc(signatures: Sequence[str]) -> Callable[[Callable[..., Any]], Any]:
        """A decorator: a numpy ufunc of ``signatures`` by ``numba.vectorize``, cached alike."""

        def decorate(function: Callable[..., Any]) -> Any:
            with _caching_in(folder):
                return vectorize(list(signatures), cache=True)(function)

        return decorate

    return kernel, ufunc


#: This package's decorators.
kernel, ufunc = compiler(cache_folder(Path(__file__).parent, KERNEL_MODULES))
