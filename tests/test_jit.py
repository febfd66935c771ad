"""ofrl_drake._jit: cached numba kernels are dropped when a kernel module changes."""

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

from ofrl_drake import _jit
from ofrl_drake._jit import KERNEL_MODULES, STAMP_FILE, drop_stale_caches

PACKAGE = Path(_jit.__file__).parent


def test_the_kernel_modules_are_every_module_that_compiles_a_kernel():
    uses_njit = {
        path.stem
        for path in PACKAGE.rglob("*.py")
        if path.stem != "_jit" and re.search(r"@njit\b", path.read_text())
    }
    assert uses_njit == set(KERNEL_MODULES)


def _edit(path, text):
    """Rewrite ``path`` with a modification time a second later (coarse file systems)."""
    before = path.stat().st_mtime_ns if path.exists() else 0
    path.write_text(text)
    os.utime(path, ns=(before + 10**9, before + 10**9))


def test_caches_are_dropped_once_after_a_kernel_module_changes(tmp_path):
    for name in ("a", "b", "other"):
        (tmp_path / f"{name}.py").write_text("x = 1\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    kept = [cache / "other.k-1.py311.nbi", cache / "a.pyc"]  # not of the kernel modules

    def fill():
        paths = [cache / "a.k-3.py311.nbi", cache / "a.k-3.py311.1.nbc", cache / "b.g-1.py311.nbi"]
        for path in paths + kept:
            path.write_bytes(b"cached")
        return paths

    cached = fill()
    assert drop_stale_caches(tmp_path, ("a", "b"))  # no stamp yet: of unknown files
    assert not any(p.exists() for p in cached) and all(p.exists() for p in kept)
    assert (cache / STAMP_FILE).is_file()
    cached = fill()
    assert not drop_stale_caches(tmp_path, ("a", "b"))  # unchanged: kept
    assert all(p.exists() for p in cached)
    _edit(tmp_path / "other.py", "x = 2\n")  # not a kernel module
    assert not drop_stale_caches(tmp_path, ("a", "b"))
    _edit(tmp_path / "b.py", "x = 2\n")
    assert drop_stale_caches(tmp_path, ("a", "b"))
    assert not any(p.exists() for p in cached) and all(p.exists() for p in kept)


def test_a_kernel_sees_an_edit_of_the_kernel_it_inlines_from_another_module(tmp_path):
    """Before: numba checked only a.py, so a.outer kept returning the old b.inner's value."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text(
        "from pathlib import Path\n"
        "from ofrl_drake._jit import drop_stale_caches\n"
        "drop_stale_caches(Path(__file__).parent, ('a', 'b'))\n"
    )
    (package / "a.py").write_text(
        textwrap.dedent(
            """
            from numba import njit
            from ofrl_drake._jit import JIT
            from pkg.b import inner

            @njit(**JIT)
            def outer(x):
                return inner(x) + 1.0
            """
        )
    )
    inner = "from numba import njit\nfrom ofrl_drake._jit import JIT\n\n@njit(**JIT)\n"
    _edit(package / "b.py", inner + "def inner(x):\n    return 2.0 * x\n")

    def outer_of_one():
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(PACKAGE.parent)])}
        code = "from pkg.a import outer; print(outer(1.0))"
        done = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
        )
        return float(done.stdout)

    assert outer_of_one() == 3.0
    assert list((package / "__pycache__").glob("a.outer-*.nbi"))  # compiled and cached
    _edit(package / "b.py", inner + "def inner(x):\n    return 10.0 * x\n")
    assert outer_of_one() == 11.0
