"""Resumable result files: one line per finished unit of work, appended and flushed in one call.

CSV rows (:func:`append_records`, :func:`read_records`; an undefined metric is an empty cell,
:func:`metric_cell`) and JSON lines (:func:`append_json_lines`, :func:`read_json_lines`; strict JSON,
an undefined value is ``null``). A killed run loses at most the line in flight; readers drop a torn
last line and writers cut it off before appending, so a re-run skips exactly the work already in the
file.
"""

from __future__ import annotations

import csv
import fcntl
import json
import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ctgpp.io.strict_json import dumps_strict


def read_records(path: Path, required: Sequence[str]) -> list[dict[str, str]]:
    """Finished rows of a results CSV: rows with every column present and ``required`` non-empty (a
    torn last line from a killed run is ignored). An absent file has no rows."""
    if not path.exists():
        return []
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return [r for r in rows if None not in r.values() and all(r.get(k) for k in required)]


def metric_cell(value: float, digits: int = 6) -> str:
    """A metric as a results-CSV cell: ``digits`` decimals, empty when undefined (NaN or infinite)."""
    return f"{value:.{digits}f}" if math.isfinite(value) else ""


def record_key(record: dict[str, str], key: Sequence[str]) -> tuple[str, ...]:
    """The identity of a row: its values of the ``key`` columns, in order."""
    return tuple(record[k] for k in key)


@contextmanager
def append_records(path: Path, fields: Sequence[str]) -> Iterator[Callable[[dict[str, str]], None]]:
    """Open ``path`` for appending rows of columns ``fields`` (header written when the file is new
    or empty; a torn last line left by a killed run is cut off first, so that the next row starts a
    line of its own); yields ``write(row)``, which writes one line and flushes it.

    The file is locked for as long as it is open: a second run writing to the same file (two
    ``ctgpp evaluate`` with one ``--out``) is refused before it starts, rather than running the same
    work again and appending it twice."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", newline="", encoding="utf-8") as f:
        _lock_exclusively(f.fileno(), path)
        _drop_torn_line(path)
        new_file = path.stat().st_size == 0
        if not new_file:
            with path.open(newline="", encoding="utf-8") as g:
                header = next(csv.reader(g), [])
            if header != list(fields):
                raise ValueError(
                    f"{path} has the columns {', '.join(header)}, not {', '.join(fields)}: it was written "
                    "by another kind of run or an older ctgpp; write the results to another directory"
                )
        writer = csv.DictWriter(f, fieldnames=list(fields), lineterminator="\n")
        if new_file:
            writer.writeheader()
            f.flush()

        def write(row: dict[str, str]) -> None:
            writer.writerow(row)
            f.flush()

        yield write


def _lock_exclusively(fd: int, path: Path) -> None:
    """Hold an exclusive lock on the open file ``fd`` (released when it is closed), or raise a clear
    error when another process holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise ValueError(
            f"{path} is being written by another run (another ctgpp command with the same --out?): wait for "
            "it to finish or write the results to another directory"
        ) from None


def read_json_lines(path: Path) -> list[dict[str, Any]]:
    """The objects of a JSON-lines file, one a line (a torn or unreadable line is ignored). An absent
    file has none."""
    if not path.exists():
        return []
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            item = json.loads(line)
        except ValueError:
            continue
        if isinstance(item, dict):
            out.append(item)
    return out


@contextmanager
def append_json_lines(path: Path) -> Iterator[Callable[[dict[str, Any]], None]]:
    """Open ``path`` for appending JSON objects, a torn last line cut off first; yields ``write(obj)``,
    which writes one line (compact, strict JSON: an undefined value, NaN or infinite, is ``null``) and
    flushes it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    _drop_torn_line(path)
    with path.open("a", encoding="utf-8") as f:

        def write(item: dict[str, Any]) -> None:
            f.write(dumps_strict(item, separators=(",", ":")) + "\n")
            f.flush()

        yield write


def _drop_torn_line(path: Path) -> None:
    """Cut ``path`` back to its last complete line (one that ends in a newline)."""
    if not path.exists() or path.stat().st_size == 0:
        return
    data = path.read_bytes()
    if not data.endswith(b"\n"):
        with path.open("r+b") as f:
            f.truncate(data.rfind(b"\n") + 1)
