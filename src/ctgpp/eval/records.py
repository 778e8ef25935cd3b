"""Resumable result files: one CSV line per finished unit of work, appended and flushed in one call.

A killed run loses at most the line in flight; :func:`read_records` drops a torn last line, so a
re-run skips exactly the work already in the file.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path


def read_records(path: Path, required: Sequence[str]) -> list[dict[str, str]]:
    """Finished rows of a results CSV: rows with every column present and ``required`` non-empty (a
    torn last line from a killed run is ignored). An absent file has no rows."""
    if not path.exists():
        return []
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return [r for r in rows if None not in r.values() and all(r.get(k) for k in required)]


def record_key(record: dict[str, str], key: Sequence[str]) -> tuple[str, ...]:
    """The identity of a row: its values of the ``key`` columns, in order."""
    return tuple(record[k] for k in key)


@contextmanager
def append_records(path: Path, fields: Sequence[str]) -> Iterator[Callable[[dict[str, str]], None]]:
    """Open ``path`` for appending rows of columns ``fields`` (header written when the file is new
    or empty; a torn last line left by a killed run is cut off first, so that the next row starts a
    line of its own); yields ``write(row)``, which writes one line and flushes it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    _drop_torn_line(path)
    new_file = not path.exists() or path.stat().st_size == 0
    with path.open("a", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(fields), lineterminator="\n")
        if new_file:
            writer.writeheader()
            f.flush()

        def write(row: dict[str, str]) -> None:
            writer.writerow(row)
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
