"""The machinery of a sweep: engines that run tasks, a progress bar, a streamed CSV table.

Shared by :mod:`ofrl_drake.ablation` and :mod:`ofrl_drake.monte_carlo`. A task
carries only picklable data and builds its own Drake diagram, so it runs in
this process (:class:`SerialEngine`) or on a Dask cluster (:class:`DaskEngine`).
Rows are appended to a CSV file and fsynced as they finish
(:class:`RowWriter`), so a killed sweep loses no finished row, and
:func:`read_table` reads them back exactly (``repr`` of floats), dropping a
torn last line when asked to repair.
"""

from __future__ import annotations

import csv
import io
import os
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ofrl_drake.errors import OfrlError

__all__ = [
    "DaskEngine",
    "Progress",
    "RowWriter",
    "SerialEngine",
    "TableError",
    "first_difference",
    "format_row",
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
        If the header is not ``columns`` or a row is malformed.
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
    lines = list(csv.reader(io.StringIO(data.decode())))
    columns = tuple(columns)
    if not lines or tuple(lines[0]) != columns:
        raise TableError(f"{path}: not an {kind}; expected the header {columns}.")
    rows = []
    for i, values in enumerate(lines[1:], start=2):
        try:
            rows.append(
                {c: (v if c in text else float(v)) for c, v in zip(columns, values, strict=True)}
            )
        except ValueError:
            raise TableError(f"{path}: line {i} is malformed: {values}.") from None
    return rows


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


class SerialEngine:
    """Runs tasks in this process, in submission order, when results are asked for."""

    def __init__(self) -> None:
        self._queue: list[tuple[int, Callable[..., Any], tuple]] = []

    def submit(self, fn: Callable[..., Any], *args: Any) -> int:
        handle = len(self._queue)
        self._queue.append((handle, fn, args))
        return handle

    def completed(self) -> Iterator[tuple[int, Any, BaseException | None]]:
        results: dict[int, Any] = {}
        for handle, fn, args in self._queue:
            resolved = tuple(results[a.handle] if isinstance(a, _Ref) else a for a in args)
            try:
                results[handle] = fn(*resolved)
                yield handle, results[handle], None
            except Exception as err:  # tasks catch their own errors; this is a safety net
                results[handle] = None
                yield handle, None, err

    def ref(self, handle: int) -> Any:
        return _Ref(handle)


@dataclass(frozen=True)
class _Ref:
    handle: int


class DaskEngine:
    """Submits tasks to a ``distributed.Client`` and yields them as they finish."""

    def __init__(self, client: Any) -> None:
        self._client = client
        self._futures: list[Any] = []

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        future = self._client.submit(fn, *args, pure=False)
        self._futures.append(future)
        return future

    def completed(self) -> Iterator[tuple[Any, Any, BaseException | None]]:
        from distributed import as_completed

        for future in as_completed(self._futures):
            try:
                yield future, future.result(), None
            except Exception as err:
                yield future, None, err

    def ref(self, handle: Any) -> Any:
        return handle


class Progress:
    """A one-line bar of finished runs on stderr (nothing when ``show`` is False)."""

    def __init__(self, total: int, done: int, show: bool) -> None:
        self.total, self.done, self.show = total, done, show
        self.start = time.perf_counter()
        self._draw()

    def advance(self) -> None:
        self.done += 1
        self._draw()

    def _draw(self) -> None:
        if not self.show:
            return
        width = 30
        filled = round(width * self.done / max(self.total, 1))
        sys.stderr.write(
            f"\r[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} runs  "
            f"{time.perf_counter() - self.start:6.1f} s"
        )
        sys.stderr.flush()

    def close(self) -> None:
        if self.show:
            sys.stderr.write("\n")
            sys.stderr.flush()


def first_difference(old: Any, new: Any, path: str = "") -> str | None:
    """The key path of the first difference between two JSON-like values, or None."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            where = f"{path}.{key}" if path else str(key)
            if key not in old or key not in new:
                return where
            found = first_difference(old[key], new[key], where)
            if found is not None:
                return found
        return None
    return None if old == new else (path or "value")
