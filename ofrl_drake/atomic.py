"""Files written whole or not at all: a temporary file beside the target, then a rename.

Every file ofrl_drake writes goes through :func:`atomic_file`, so a crash, a
full disk or a bad value half-way through never leaves a half-written file,
and the finished file gets the permissions the user's umask asks for (as a
plain ``open`` would), not the ``0600`` of :func:`tempfile.mkstemp`.
:func:`output_lock` keeps two commands from writing one output (or one from
writing what another reads).
"""

from __future__ import annotations

import contextlib
import os
import signal
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from ofrl_drake.errors import OutputError

__all__ = [
    "atomic_file",
    "atomic_write_text",
    "check_output_folder",
    "check_output_target",
    "check_writable",
    "ensure_parent",
    "file_version",
    "output_lock",
    "sigint_handled_here",
    "sigint_held",
    "umask_mode",
]


#: What :func:`file_version` gives: the absolute path, then mtime (ns) and size, or None.
FileVersion = tuple[str, int, int] | tuple[str, None]


def file_version(path: str | Path) -> FileVersion:
    """``(absolute path, mtime in ns, size)`` of a file; ``(path, None)`` if it cannot be read.

    A relative path is taken from the working folder. Like Python's own
    ``.pyc`` check, an edited file is told by its modification time and size
    (here to the nanosecond): what the caches of files read (a user's plant
    module, a model file, the numba kernels' sources) are keyed by.
    """
    resolved = Path(path).resolve()
    try:
        stat = resolved.stat()
    except OSError:
        return (str(resolved), None)
    return (str(resolved), stat.st_mtime_ns, stat.st_size)


def umask_mode(base: int = 0o666) -> int:
    """``base`` with the process umask applied (``0o644`` under the usual ``022``)."""
    umask = os.umask(0)
    os.umask(umask)
    return base & ~umask


def ensure_parent(target: Path, what: str = "--out") -> Path:
    """Create ``target``'s parent folders, or raise :class:`OutputError` naming the path.

    Raises
    ------
    OutputError
        If a parent of ``target`` is a file or cannot be created.
    """
    target = Path(target).expanduser()
    for parent in reversed(target.parents):
        if parent.exists() and not parent.is_dir():
            raise OutputError(
                f"{what}: {parent} is a file, so {target} cannot be created; choose another path."
            )
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"{what}: cannot create {target.parent} ({err.strerror}).") from err
    return target


def check_writable(target: Path, what: str = "--out") -> Path:
    """Raise :class:`OutputError` now if ``target`` could not be created later.

    Probes the nearest existing folder above ``target`` by creating and removing
    a temporary folder in it (so it also catches read-only file systems, which
    ``os.access`` misses for root). Creates nothing that stays.

    Raises
    ------
    OutputError
        If a parent of ``target`` is a file, or the nearest existing one cannot
        be written.
    """
    target = Path(target).expanduser().absolute()
    ancestor = target.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputError(
            f"{what}: {ancestor} is a file, so {target} cannot be created; choose another path."
        )
    try:
        tempfile.TemporaryDirectory(prefix=".ofrl_drake_probe.", dir=ancestor).cleanup()
    except OSError as err:
        raise OutputError(
            f"{what}: cannot write in {ancestor} ({err.strerror}), so {target} cannot be "
            "created; choose a folder you can write to."
        ) from None
    return target


def check_output_folder(
    target: Path, *, marker: str, command: str, error: type[Exception] = OutputError
) -> Path:
    """Refuse an output folder that a command of ours did not write.

    ``target`` may be absent, an empty folder, or a folder holding ``marker``
    (written there by an earlier ``ofrl-drake <command>``). Anything else, a
    file or someone else's non-empty folder, raises ``error`` naming it.
    """
    target = Path(target).expanduser()
    if target.exists() and not target.is_dir():
        raise error(f"--out: {target} exists and is not a folder; choose another path.")
    if target.is_dir() and any(target.iterdir()) and not (target / marker).exists():
        raise error(
            f"--out: {target} is not empty and was not written by ofrl-drake {command} "
            f"(no {marker}); choose a new folder or empty this one."
        )
    return target


def check_output_target(target: str | Path, what: str = "--out", *, folder: bool = False) -> Path:
    """Refuse an output path that a rename would mistreat.

    ``target`` must be a non-empty path that, if it exists, is a regular file
    (or, with ``folder``, a folder) and not a symbolic link: replacing a
    device, a FIFO, a socket or a link by renaming a file onto it would
    destroy it (``--out /dev/null`` would replace the machine's ``/dev/null``).

    Raises
    ------
    OutputError
        Naming the path and what it is.
    """
    if str(target) == "":
        kind = "folder" if folder else "file"
        raise OutputError(f"{what}: the path is empty; name an output {kind}.")
    path = Path(target).expanduser()
    if path.is_symlink():
        raise OutputError(
            f"{what}: {path} is a symbolic link; ofrl-drake writes only regular files and "
            "folders it creates. Name the link's target, or another path."
        )
    if path.exists():
        if folder and path.is_dir():
            return path
        if not folder and path.is_file():
            return path
        if path.is_dir():
            raise OutputError(f"{what}: {path} is a folder; name a file inside it.")
        kind = "a file" if path.is_file() else "not a regular file (a device, FIFO or socket)"
        want = "a folder" if folder else "a file"
        raise OutputError(f"{what}: {path} is {kind}; name {want} ofrl-drake may replace.")
    return path


@contextlib.contextmanager
def output_lock(target: str | Path, what: str = "--out", *, shared: bool = False) -> Iterator[None]:
    """Hold a lock on ``target`` for the block; refuse if another process holds a clashing one.

    The lock is ``flock`` on a file named by a hash of ``target``'s absolute
    path (links and ``..`` resolved) in ``<tmp>/ofrl_drake-locks`` (nothing is
    added beside the output), released when the block ends or the process
    dies. A writer takes it exclusive (the default), so two ``ofrl-drake``
    commands writing the same output cannot interleave; a reader takes it
    ``shared`` (``plot`` reading a run folder), so any number of readers may
    hold it together, but none while a writer does, and no writer while one
    reads.

    Raises
    ------
    OutputError
        If another process holds the lock exclusive, or (not ``shared``) at all.
    """
    import fcntl
    import hashlib

    path = Path(target).expanduser().resolve()  # one lock whatever the spelling (.., links)
    folder = Path(tempfile.gettempdir()) / "ofrl_drake-locks"
    folder.mkdir(mode=0o777, exist_ok=True)
    name = hashlib.sha256(str(path).encode()).hexdigest()[:32]
    with open(folder / f"{name}.lock", "a+") as fh:
        try:
            fcntl.flock(fh.fileno(), (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            doing = "writing" if shared else "writing or reading"
            raise OutputError(
                f"{what}: another ofrl-drake command is {doing} {path} now; wait for it to "
                "finish, or choose another path."
            ) from None
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


@contextlib.contextmanager
def atomic_file(target: str | Path, mode: str = "w", *, what: str = "output") -> Iterator[IO[Any]]:
    """Open a temporary file next to ``target``; rename it onto ``target`` on success.

    On any exception the temporary file is removed and ``target`` is left as
    it was. A target that is not a regular file (a device, FIFO, socket,
    folder or symbolic link) is refused (:func:`check_output_target`).
    """
    target = check_output_target(target, what)
    target = ensure_parent(target, what)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
    except OSError as err:
        raise OutputError(
            f"{what}: cannot write in {target.parent} ({err.strerror}); choose a folder you "
            "can write to."
        ) from None
    try:
        os.chmod(tmp, umask_mode())
        with os.fdopen(fd, mode) as fh:
            yield fh
        os.replace(tmp, target)
    except OSError as err:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise OutputError(
            f"{what}: {_os_error(err)} writing {target}; nothing was written."
        ) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _os_error(err: OSError) -> str:
    """An ``OSError`` in a few words: "no space left on device", "permission denied"..."""
    return (err.strerror or type(err).__name__).lower()


def atomic_write_text(target: str | Path, text: str, *, what: str = "--out") -> None:
    """Write ``text`` to ``target`` whole or not at all (see :func:`atomic_file`)."""
    with atomic_file(target, "w", what=what) as fh:
        fh.write(text)


def sigint_handled_here() -> bool:
    """True if a SIGINT would interrupt this thread: the main thread, SIGINT not ignored.

    Signals are handled in the main thread only; and a process started with
    SIGINT ignored (a shell script's background job, ``cmd &``) was told not
    to stop on it. Elsewhere :func:`sigint_held` leaves the handler alone.
    """
    return (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN
    )


@contextlib.contextmanager
def sigint_held() -> Iterator[None]:
    """Hold a SIGINT until the block ends, then raise ``KeyboardInterrupt``.

    For work a Ctrl-C must not cut in two: a clean-up that removes what an
    interrupted command wrote (a terminal sends the interrupt to the whole
    process group, and ``timeout`` sends it again to the child, so a second one
    can land in the clean-up of the first), or an import during which pydrake's
    C++ initialization would turn a ``KeyboardInterrupt`` into an
    ``ImportError`` with a 30-line trace. Outside the main thread (where
    signals cannot be handled), or with SIGINT ignored, the block runs as is
    (:func:`sigint_handled_here`).
    """
    if not sigint_handled_here():
        yield
        return
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt
