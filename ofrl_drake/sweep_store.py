"""A sweep's folder: its plan, its table of rows streamed as runs finish, its runs' arrays.

Shared by :func:`ofrl_drake.ablation.ablate` and
:func:`ofrl_drake.monte_carlo.montecarlo`; :class:`SweepFiles` names what
differs between them (file names, columns, the command, the exception).

* The plan (``ablation.json``, ``montecarlo.json``) records what defines the
  sweep, written whole (:func:`~ofrl_drake.atomic.atomic_write_text`). A
  ``resume`` compares it with the new sweep's and refuses another sweep by name.
* The table (``ablation.csv``, ``montecarlo.csv``) gets one line per finished
  row, flushed and fsynced (:class:`RowWriter`), so a killed sweep loses no
  finished row. Numbers are written with ``repr`` (``nan``, ``inf``), so they
  read back exactly (:func:`read_table`). A ``resume`` drops a torn last line
  and, with ``retry_failed``, the rows whose status is not ``ok``.
* ``runs/`` holds each run's trajectories, one ``.npz`` file per run, written whole.
  A run's file belongs to its row in the table: it is written (or, for a run
  that ended before it had logs, removed) with its row
  (:meth:`SweepStore.save_run`, :meth:`SweepStore.remove_run`), and the files
  a sweep finds in ``runs/`` of a folder without a table (rows of no table)
  are removed when it writes its first row.
* A sweep that stops before its first row (an error, an interrupt) leaves
  nothing to resume, so nothing of it stays: :meth:`SweepStore.recording`
  removes what of the folder :meth:`SweepStore.open` found absent (the folder
  itself, the plan, the table, ``runs/``...), and leaves a folder that was
  there as it was found.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import shutil
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ofrl_drake.atomic import (
    atomic_file,
    atomic_write_text,
    check_output_folder,
    ensure_parent,
    sigint_held,
)
from ofrl_drake.errors import OfrlError, OutputError

__all__ = [
    "RowWriter",
    "SweepFiles",
    "SweepStore",
    "TableError",
    "describe_difference",
    "first_difference",
    "format_row",
    "load_arrays",
    "read_table",
]


class TableError(OfrlError):
    """A CSV table that is not the one expected (header or a malformed row)."""


def format_row(row: Mapping[str, Any], columns: Sequence[str], text: Sequence[str]) -> str:
    """One CSV line: ``text`` columns as they are, the others as ``repr(float)``."""
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\n").writerow(
        [row[c] if c in text else repr(float(row[c])) for c in columns]
    )
    return buffer.getvalue()


def read_table(
    path: str | os.PathLike[str],
    columns: Sequence[str],
    text: Sequence[str],
    *,
    repair: bool = False,
    kind: str = "table",
) -> list[dict[str, Any]]:
    """The rows of a CSV table with header ``columns``, numbers as floats.

    ``repair`` truncates the file after its last complete line (a sweep killed
    while writing can leave a torn one).

    Raises
    ------
    TableError
        If the header is not ``columns``, or a line is malformed, is not
        UTF-8 text or cannot be read as CSV (the line named).
    """
    path = Path(path)
    data = path.read_bytes()
    if not data.endswith(b"\n"):
        data = data[: data.rfind(b"\n") + 1]
        if repair:
            with open(path, "r+b") as fh:
                fh.truncate(len(data))
    if not data and repair:
        return []  # killed before the header was complete; the writer adds it
    try:
        decoded = data.decode()
    except UnicodeDecodeError as err:
        line = data.count(b"\n", 0, err.start) + 1
        raise _bad_line(
            path, line, f"is not UTF-8 text (byte {data[err.start]:#04x} at offset {err.start})"
        ) from None
    reader = csv.reader(io.StringIO(decoded))
    try:
        lines = list(reader)
    except csv.Error as err:
        raise _bad_line(path, reader.line_num, f"cannot be read as CSV ({err})") from None
    columns = tuple(columns)
    if not lines or tuple(lines[0]) != columns:
        got = f"the header {_shortened(tuple(lines[0]))}" if lines else "an empty file"
        raise TableError(
            f"{path}: not a valid {kind}: expected the header {columns}; got {got}. Move it "
            "away, or choose another --out."
        )
    rows = []
    for i, values in enumerate(lines[1:], start=2):
        try:
            rows.append(
                {c: (v if c in text else float(v)) for c, v in zip(columns, values, strict=True)}
            )
        except ValueError:
            raise _bad_line(path, i, f"is malformed: {_shortened(values)}") from None
    return rows


def _shortened(value: Any, limit: int = 200) -> str:
    """``repr(value)``, cut to ``limit`` characters (a corrupt line can be megabytes long)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _bad_line(path: Path, line: int, problem: str) -> TableError:
    """The error for line ``line`` of the table ``path`` (the file is corrupt)."""
    if line <= 1:
        fix = "the header is damaged: move the file away, or choose another --out"
    else:
        fix = "delete that line (--resume then runs its row again), or choose another --out"
    return TableError(f"{path}: line {line} {problem}; the file is corrupt: {fix}.")


class RowWriter:
    """Appends rows to a CSV file, each flushed and fsynced before returning."""

    def __init__(self, path: Path, columns: Sequence[str], text: Sequence[str]) -> None:
        self.path = path
        self.columns = tuple(columns)
        self.text = tuple(text)
        fresh = not path.exists() or path.stat().st_size == 0
        self._fh = open(path, "a", encoding="utf-8", newline="")
        if fresh:
            self._write(",".join(self.columns) + "\n")

    def _write(self, line: str) -> None:
        try:
            self._fh.write(line)
            self._fh.flush()
            os.fsync(self._fh.fileno())
        except OSError as err:
            problem = (err.strerror or type(err).__name__).lower()
            raise TableError(
                f"{problem} writing {self.path}; the rows written before are kept: free the "
                "problem and rerun with --resume."
            ) from None

    def write(self, row: Mapping[str, Any]) -> None:
        """Append ``row`` (every column) and make it durable."""
        self._write(format_row(row, self.columns, self.text))

    def close(self) -> None:
        self._fh.close()


class _Absent:
    """A key one of two plans does not have, as :func:`describe_difference` shows it."""

    def __repr__(self) -> str:
        return "absent"


_ABSENT = _Absent()


def _difference(old: Any, new: Any, path: str) -> tuple[str, Any, Any] | None:
    """The key path of the first difference and the two values there, or None."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            where = f"{path}.{key}" if path else str(key)
            found = _difference(old.get(key, _ABSENT), new.get(key, _ABSENT), where)
            if found is not None:
                return found
        return None
    if old is _ABSENT or new is _ABSENT:
        return path, old, new
    return None if old == new else (path or "value", old, new)


def first_difference(old: Any, new: Any, path: str = "") -> str | None:
    """The key path of the first difference between two JSON-like values, or None."""
    found = _difference(old, new, path)
    return None if found is None else found[0]


def describe_difference(old: Any, new: Any) -> str | None:
    """The first difference between a folder's plan ``old`` and a command's ``new``, or None.

    ``"runs (3 in the folder, 2 now)"``: the key path (:func:`first_difference`)
    and both values, so a refused ``--resume`` says what to pass.
    """
    found = _difference(old, new, "")
    if found is None:
        return None
    where, before, now = found
    return f"{where} ({before!r} in the folder, {now!r} now)"


#: The key of a plan that holds :func:`~ofrl_drake.plants.dynamics_fingerprints`.
#: :class:`SweepStore` compares it itself, after the sweep's own ``mismatch``,
#: which never sees it.
DYNAMICS_KEY = "dynamics"


#: The key of a plan that holds how the sweep's ``J*`` is had: solved (the
#: ``Mesh`` with its check, and the solver) or given. :class:`SweepStore`
#: compares it itself, like :data:`DYNAMICS_KEY`: rows scored against two
#: different ``J*`` must not share a table.
OPTIMAL_KEY = "optimal"

#: What a refused ``--resume`` suggests, unless the difference has its own fix.
RESUME_FIX = "resume with the sweep's own arguments, or choose another --out"


def _without_store_keys(plan: Mapping[str, Any]) -> dict[str, Any]:
    """``plan`` without the keys :class:`SweepStore` compares itself (dynamics, J*)."""
    return {k: v for k, v in plan.items() if k not in (DYNAMICS_KEY, OPTIMAL_KEY)}


def _optimal_difference(old: Mapping[str, Any], new: Mapping[str, Any]) -> str | None:
    """Why the rows of plan ``new`` would be scored against another ``J*`` than ``old``'s."""
    if OPTIMAL_KEY not in new or old.get(OPTIMAL_KEY) == new[OPTIMAL_KEY]:
        return None
    if OPTIMAL_KEY not in old:
        return (
            "the folder's sweep was written by an ofrl_drake that did not record how J* is "
            "had (before J* was checked on a finer grid), so its rows' J* may differ from "
            "this sweep's; start the sweep again in another --out"
        )
    return (
        f"the folder's sweep had J* {_how(old[OPTIMAL_KEY])}, this one {_how(new[OPTIMAL_KEY])}: "
        f"rows would be scored against different J*; {RESUME_FIX}"
    )


def _how(optimal: Mapping[str, Any]) -> str:
    """How a plan's :data:`OPTIMAL_KEY` had ``J*``, in words."""
    if "optimal_cost" in optimal:
        return f"given as {optimal['optimal_cost']!r}"
    mesh = ", ".join(f"{k}={v!r}" for k, v in optimal["mesh"].items())
    return f"solved by {optimal['solver']} on Mesh({mesh})"


def _dynamics_difference(old: Mapping[str, Any], new: Mapping[str, Any]) -> str | None:
    """Why the plant's code of plan ``new`` is not that of the folder's plan ``old``, or None.

    Both plans hold :data:`DYNAMICS_KEY` (an older folder's plan, without it, is
    not compared): the model and truth fingerprints.
    """
    if DYNAMICS_KEY not in old or DYNAMICS_KEY not in new:
        return None
    if old[DYNAMICS_KEY] == new[DYNAMICS_KEY]:
        return None
    which = [k for k, v in new[DYNAMICS_KEY].items() if old[DYNAMICS_KEY].get(k) != v]
    return (
        f"the {' and '.join(which) or 'plant'} dynamics differ from the folder's sweep: "
        "f, g or C give other values at the same states (was the plant's code edited?)"
    )


def load_arrays(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The arrays of one ``runs/*.npz`` file, or None if there is none."""
    path = Path(path)
    if not path.is_file():
        return None
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def _has_rows(table: Path) -> bool:
    """Whether ``table`` holds a line after its header."""
    try:
        with open(table, encoding="utf-8") as fh:
            fh.readline()  # the header
            return fh.readline() != ""
    except OSError:
        return False


def _remove(path: Path) -> None:
    """Remove ``path``: a folder with its files, or a file (a link, not its target)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


def _remove_stale_run(path: Path) -> None:
    """Remove ``path``, a file of ``runs/`` that belongs to no row, if it is there.

    Raises
    ------
    OutputError
        If it is there and cannot be removed (the figures would draw it as a row's).
    """
    try:
        _remove(path)
    except FileNotFoundError:
        pass
    except OSError as err:
        problem = (err.strerror or type(err).__name__).lower()
        raise OutputError(
            f"--out: cannot remove {path} ({problem}): it holds a run that is not the one in "
            "the table, and the figures would draw it; remove it yourself, or choose another "
            "--out."
        ) from None


@dataclass(frozen=True)
class SweepFiles:
    """What one kind of sweep keeps in its folder, and how its errors are named.

    Attributes
    ----------
    table : str
        File name of the CSV table, e.g. ``ablation.csv``.
    plan : str
        File name of the plan (what defines the sweep), e.g. ``ablation.json``.
    columns : tuple of str
        The table's header, in order.
    text : tuple of str
        The columns kept as text; the others are floats.
    command : str
        The ``ofrl-drake`` command that writes such folders, e.g. ``ablate``.
    kind : str
        The table in messages, e.g. ``ablation table``.
    error : type
        The exception raised for bad input (an :class:`~ofrl_drake.errors.OfrlError`).
    folders : tuple of str
        The sub-folders the sweep writes (``runs/`` and, e.g., a cache), removed
        with their files by :meth:`SweepStore.discard` when it created them.
    """

    table: str
    plan: str
    columns: tuple[str, ...]
    text: tuple[str, ...]
    command: str
    kind: str
    error: type[OfrlError]
    folders: tuple[str, ...] = ("runs",)

    def read(self, path: str | os.PathLike[str], *, repair: bool = False) -> list[dict[str, Any]]:
        """The rows of a table of this kind (:func:`read_table`), errors as :attr:`error`."""
        try:
            return read_table(path, self.columns, self.text, repair=repair, kind=self.kind)
        except TableError as err:
            raise self.error(str(err)) from None


class SweepStore:
    """The folder of one sweep: plan, streamed table and ``runs/``.

    Parameters
    ----------
    files : SweepFiles
        The kind of sweep.
    folder : Path
        The ``--out`` folder (created if absent).

    Attributes
    ----------
    written : int
        Rows this store appended to the table since it was opened.

    Examples
    --------
    >>> store = SweepStore(files, Path("out"))                          # doctest: +SKIP
    >>> with store.recording(plan, resume=True, mismatch=why_not) as done:  # doctest: +SKIP
    ...     store.write(row)                                            # doctest: +SKIP
    """

    def __init__(self, files: SweepFiles, folder: Path) -> None:
        self.files = files
        self.folder = folder
        self.written = 0
        self._writer: RowWriter | None = None
        self._absent: list[Path] = []  # what open() found absent, outermost first
        self._found: dict[Path, set[str]] = {}  # files of each sub-folder open() found
        self._table_before: str | None = None  # the table retry_failed rewrote, as found
        self._stale: set[str] = set()  # runs/ files of no row, removed at the first row

    @property
    def table(self) -> Path:
        """The table's path."""
        return self.root / self.files.table

    @property
    def runs(self) -> Path:
        """The folder of the runs' arrays."""
        return self.root / "runs"

    def open(
        self,
        plan: Mapping[str, Any],
        *,
        resume: bool,
        mismatch: Callable[[Mapping[str, Any], Mapping[str, Any]], str | None],
        retry_failed: bool = False,
    ) -> list[dict[str, Any]]:
        """Check the folder, check or write the plan; return the rows already done.

        Parameters
        ----------
        plan : mapping
            What defines this sweep (JSON-ready), compared with the folder's
            on ``resume`` and written otherwise.
        resume : bool
            Complete the table in the folder instead of refusing it.
        mismatch : callable
            ``mismatch(old_plan, new_plan)``: why the folder's sweep cannot
            be continued by this one (one clause), or None if it can. It sees
            the plans without :data:`DYNAMICS_KEY`: when they otherwise agree,
            the store compares the plant's fingerprints itself.
        retry_failed : bool
            Drop the rows whose status is not ``ok`` from the table (rewritten
            whole) so that their runs are done again.

        Without a table in the folder, the files in ``runs/`` belong to no
        row: they are removed when the first row is written (:meth:`write`;
        a sweep that stops before it leaves them, as :meth:`discard` does).

        Raises
        ------
        OfrlError
            (:attr:`SweepFiles.error`) For a folder another command wrote, a
            table without its plan, a table without ``resume``, a plan cut
            short, or a ``resume`` of another sweep (named by ``mismatch``).
        """
        self._table_before = None
        self._stale = set()
        self._absent = self._absent_paths()
        self._found = {
            path: {entry.name for entry in path.iterdir()}
            for path in self._sub_folders()
            if path.is_dir() and not path.is_symlink()
        }
        self.written = 0
        files, error = self.files, self.files.error
        table, plan_path = self.table, self.root / files.plan
        if table.exists() and not plan_path.exists():
            raise error(
                f"--out: {plan_path} is missing; it records the sweep that "
                f"{files.table} belongs to, so it cannot be resumed. Restore it, or move "
                f"{files.table} away to start a new sweep in {self.folder}."
            )
        check_output_folder(self.root, marker=files.plan, command=files.command, error=error)
        ensure_parent(plan_path)
        if table.exists() and not resume:
            raise error(f"{table} exists; pass --resume to complete it, or choose another --out.")
        self._check_or_write_plan(plan, resume, mismatch)
        if not table.exists():
            runs = self.runs
            if runs.is_dir() and not runs.is_symlink():
                self._stale = {entry.name for entry in runs.iterdir()}
            return []
        rows = files.read(table, repair=True)
        if retry_failed:
            kept = [r for r in rows if r["status"] == "ok"]
            if len(kept) < len(rows):
                self._table_before = table.read_text()  # restored by discard()
                text = ",".join(files.columns) + "\n"
                text += "".join(format_row(r, files.columns, files.text) for r in kept)
                atomic_write_text(table, text)
            rows = kept
        return rows

    def _check_or_write_plan(
        self,
        plan: Mapping[str, Any],
        resume: bool,
        mismatch: Callable[[Mapping[str, Any], Mapping[str, Any]], str | None],
    ) -> None:
        path = self.root / self.files.plan
        if resume and path.is_file():
            try:
                old = json.loads(path.read_text())
            except (ValueError, UnicodeDecodeError):
                raise self.files.error(
                    f"--resume: {path} is not valid JSON (cut short?); it records the sweep that "
                    f"{self.files.table} belongs to. Restore it, or move the folder away and "
                    "start again."
                ) from None
            new = json.loads(json.dumps(plan))
            why = mismatch(_without_store_keys(old), _without_store_keys(new))
            why = why if why is not None else _dynamics_difference(old, new)
            if why is not None:
                raise self.files.error(f"--resume: {why}; {RESUME_FIX}.")
            why = _optimal_difference(old, new)  # a message with its own fix
            if why is not None:
                raise self.files.error(f"--resume: {why}.")
            return
        atomic_write_text(path, json.dumps(plan, indent=2) + "\n")

    def start(self) -> None:
        """Open the table for appending (with its header if it is new)."""
        self._writer = RowWriter(self.table, self.files.columns, self.files.text)

    def write(self, row: Mapping[str, Any]) -> None:
        """Append ``row`` to the table and make it durable (after :meth:`start`).

        The first row removes the files :meth:`open` found in ``runs/`` of a
        folder without a table (but those written since, by :meth:`save_run`).

        Raises
        ------
        OfrlError
            (:class:`TableError`) If the row cannot be written;
            (:class:`~ofrl_drake.errors.OutputError`) if such a file cannot be removed.
        """
        if self._writer is None:
            raise RuntimeError("SweepStore.write: call start() first.")
        for name in sorted(self._stale):
            _remove_stale_run(self.runs / name)
        self._stale = set()
        self._writer.write(row)
        self.written += 1

    @property
    def root(self) -> Path:
        """The folder as the file system names it: ``~``, links and ``..`` resolved.

        Every path of the store is made from it, so a spelling such as
        ``build/../out`` (``build`` absent) neither creates ``build`` nor makes
        an existing folder look absent to :meth:`discard`.
        """
        return self.folder.expanduser().resolve()

    def _sub_folders(self) -> list[Path]:
        """The paths of :attr:`SweepFiles.folders`."""
        return [self.root / name for name in self.files.folders]

    def _absent_paths(self) -> list[Path]:
        """What of the folder does not exist now, outermost first.

        Of the folder's parents, the folder, the plan, the table and
        :attr:`SweepFiles.folders`: what :meth:`open` and the sweep may create.
        """
        folder = self.root
        files = [folder / self.files.plan, folder / self.files.table]
        parents = reversed(folder.parents)  # outermost first; open() creates the missing ones
        paths = [*parents, folder, *files, *self._sub_folders()]
        return [p for p in paths if not (p.exists() or p.is_symlink())]

    def discard(self) -> None:
        """Remove what :meth:`open` found absent, unless a row was written since.

        For a sweep that stopped before its first row (an error, an interrupt):
        there is nothing to resume, so nothing of it stays, not a folder
        holding only the plan and the table's header. Files and
        :attr:`SweepFiles.folders` created since :meth:`open` are removed (the
        folders with their files, and the files added to such a folder that
        was there); the folder itself only if it did not exist and is then
        empty, and so for the parents it created. What existed is left as it
        was found: a table that ``retry_failed`` rewrote is put back, and a
        table this store created but finds with rows in it (another process's
        sweep) keeps the folder whole.
        Once a row is written (:attr:`written`) nothing is removed: the folder
        can be resumed.
        """
        if self.written:
            return
        self.close()
        if self._table_before is not None:  # retry_failed dropped rows: put them back
            atomic_write_text(self.table, self._table_before)
            self._table_before = None
        table = self.root / self.files.table
        if table in self._absent and _has_rows(table):
            return  # rows this store did not write: another process's sweep, kept whole
        for folder, found in self._found.items():
            with contextlib.suppress(OSError):
                for entry in folder.iterdir():
                    if entry.name not in found:
                        _remove(entry)
        folders = set(self._sub_folders())
        for path in reversed(self._absent):  # deepest first
            with contextlib.suppress(OSError):
                if path in folders or not path.is_dir():
                    _remove(path)
                else:
                    path.rmdir()  # the sweep's folder or a parent: only if empty
        self._absent, self._found = [], {}

    @contextlib.contextmanager
    def recording(
        self,
        plan: Mapping[str, Any],
        *,
        resume: bool,
        mismatch: Callable[[Mapping[str, Any], Mapping[str, Any]], str | None],
        retry_failed: bool = False,
    ) -> Iterator[list[dict[str, Any]]]:
        """:meth:`open` and :meth:`start` the store for the block; :meth:`close` it after.

        Yields the rows already done (:meth:`open`'s arguments and result). If
        :meth:`open` or the block raises, or is interrupted, before the first
        row is written, what the sweep created in the folder is removed
        (:meth:`discard`, with a SIGINT held until it is done) and the
        exception goes on.

        Raises
        ------
        OfrlError
            (:attr:`SweepFiles.error`) As :meth:`open`.
        """
        try:
            rows = self.open(plan, resume=resume, mismatch=mismatch, retry_failed=retry_failed)
            self.start()
            yield rows
        except BaseException:
            with sigint_held():  # a second Ctrl-C must not cut the clean-up short
                self.discard()
            raise
        finally:
            self.close()

    def save_run(self, name: str, arrays: Mapping[str, Any]) -> None:
        """Write ``runs/<name>`` (an ``.npz`` file of ``arrays``) whole or not at all.

        Call it just before :meth:`write` of the run's row: the file is that row's.
        """
        with atomic_file(self.runs / name, "wb") as fh:
            np.savez(fh, **arrays)
        self._stale.discard(name)

    def remove_run(self, name: str) -> None:
        """Remove ``runs/<name>`` if it is there: the row about to be written has no logs.

        A run done again (``retry_failed``, or a row the table lost) that ends
        before it has logs must not leave the file of an earlier attempt, which
        the figures would draw as the row's.

        Raises
        ------
        OutputError
            If the file is there and cannot be removed.
        """
        _remove_stale_run(self.runs / name)
        self._stale.discard(name)

    def close(self) -> None:
        """Close the table."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
