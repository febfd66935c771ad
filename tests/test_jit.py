"""ofrl_drake._jit: numba caches in a folder per version of the kernel modules' files."""

import importlib
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ofrl_drake import _jit
from ofrl_drake._jit import KERNEL_MODULES, STALE_AFTER, cache_folder, sources_stamp

PACKAGE = Path(_jit.__file__).parent


#: A line that compiles a kernel through ofrl_drake._jit.
_COMPILES = re.compile(r"^(@kernel|@ufunc|.*= kernel\()", re.M)
#: A line that compiles with numba directly, around the version folders.
_DIRECT = re.compile(r"^\s*@(njit|vectorize)\b|=\s*(njit|vectorize)\(", re.M)


def test_the_kernel_modules_are_every_module_that_compiles_a_kernel():
    sources = {p: p.read_text() for p in PACKAGE.rglob("*.py") if p.stem != "_jit"}
    assert {p.stem for p, text in sources.items() if _COMPILES.search(text)} == set(KERNEL_MODULES)
    assert not [p for p, text in sources.items() if _DIRECT.search(text)]


def _edit(path, text):
    """Rewrite ``path`` with a modification time a second later (coarse file systems)."""
    before = path.stat().st_mtime_ns if path.exists() else 0
    path.write_text(text)
    os.utime(path, ns=(before + 10**9, before + 10**9))


def test_the_folder_follows_the_kernel_modules_files_and_old_ones_go(tmp_path, monkeypatch):
    monkeypatch.setattr(_jit._CONFIG, "CACHE_DIR", "")
    for name in ("a", "b", "other"):
        (tmp_path / f"{name}.py").write_text("x = 1\n")
    (tmp_path / "__pycache__").mkdir()
    old_style = tmp_path / "__pycache__" / "a.k-3.py311.nbi"  # numba's own folder
    kept = tmp_path / "__pycache__" / "other.k-1.py311.nbi"
    old_style.write_bytes(b"")
    kept.write_bytes(b"")
    first = cache_folder(tmp_path, ("a", "b"))
    assert first.parent == tmp_path / "__pycache__" / "numba"
    assert not old_style.exists() and kept.exists()
    first.mkdir(parents=True)
    _edit(tmp_path / "other.py", "x = 2\n")  # not a kernel module
    assert cache_folder(tmp_path, ("a", "b")) == first
    _edit(tmp_path / "b.py", "x = 2\n")
    second = cache_folder(tmp_path, ("a", "b"))
    assert second != first and first.exists()  # a process may still use the old one
    os.utime(first, (0, 0))  # untouched for longer than STALE_AFTER
    assert STALE_AFTER <= 7 * 86400
    cache_folder(tmp_path, ("a", "b"))  # second is new: the cleanup runs
    assert not first.exists()
    second.mkdir(parents=True)
    stale = second.parent / "0123456789abcdef"
    stale.mkdir()
    os.utime(stale, (0, 0))
    assert cache_folder(tmp_path, ("a", "b")) == second and stale.exists()  # found: no more
    # NUMBA_CACHE_DIR is respected: the folders go under it.
    monkeypatch.setattr(_jit._CONFIG, "CACHE_DIR", str(tmp_path / "cluster_cache"))
    folder = cache_folder(tmp_path, ("a", "b"))
    assert folder == tmp_path / "cluster_cache" / "ofrl_drake" / sources_stamp(tmp_path, "ab")


_INIT = """
from pathlib import Path
from ofrl_drake._jit import cache_folder, compiler
kernel, ufunc = compiler(cache_folder(Path(__file__).parent, ("a", "b")))
"""
_OUTER = """
from pkg import kernel
from pkg.b import inner

@kernel
def outer(x):
    return inner(x) + 1.0
"""
_INNER = "from pkg import kernel\n\n@kernel\ndef inner(x):\n    return {k} * x\n"


@pytest.fixture
def package(tmp_path):
    """``pkg.a.outer`` inlines ``pkg.b.inner`` (``2 x``), as bellman's kernel inlines cost's."""
    folder = tmp_path / "pkg"
    folder.mkdir()
    (folder / "__init__.py").write_text(_INIT)
    (folder / "a.py").write_text(_OUTER)
    _edit(folder / "b.py", _INNER.format(k="2.0"))
    return folder


def _outer_of_one(package, **env):
    """``pkg.a.outer(1.0)`` in a new process."""
    paths = os.pathsep.join([str(package.parent), str(PACKAGE.parent)])
    done = subprocess.run(
        [sys.executable, "-c", "from pkg.a import outer; print(outer(1.0))"],
        env={**os.environ, "PYTHONPATH": paths, **env},
        capture_output=True,
        text=True,
        check=True,
    )
    return float(done.stdout)


@pytest.mark.parametrize("numba_cache_dir", [False, True])
def test_a_kernel_sees_an_edit_of_the_kernel_it_inlines_from_another_module(
    package, numba_cache_dir
):
    """Before: numba checked only a.py, so outer kept returning the old inner's value
    (and with NUMBA_CACHE_DIR set, the first fix dropped nothing)."""
    env = {"NUMBA_CACHE_DIR": str(package.parent / "nbcache")} if numba_cache_dir else {}
    assert _outer_of_one(package, **env) == 3.0
    cached = package.parent / "nbcache" if numba_cache_dir else package / "__pycache__"
    assert list(cached.rglob("a.outer-*.nbi"))  # compiled and cached
    _edit(package / "b.py", _INNER.format(k="10.0"))
    assert _outer_of_one(package, **env) == 11.0
    assert _outer_of_one(package, **env) == 11.0  # and cached as such


def test_a_process_still_running_the_old_files_caches_nothing_new_ones_read(package, monkeypatch):
    """Before: a process that imported the old b and compiled after the edit wrote its
    cache where the next processes read it."""
    monkeypatch.syspath_prepend(str(package.parent))
    try:
        old = importlib.import_module("pkg.a")  # imports pkg.b as it is now: 2 x
        _edit(package / "b.py", _INNER.format(k="10.0"))
        assert old.outer(1.0) == 3.0  # compiled now, from the b it imported
        assert _outer_of_one(package) == 11.0
    finally:
        for name in [m for m in sys.modules if m == "pkg" or m.startswith("pkg.")]:
            del sys.modules[name]
