"""Atomic file writes: write to a temporary file beside the target, then rename over it; a set of
output files staged in a temporary directory and moved into place only when all of them are done."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(target: Path) -> Iterator[Path]:
    """Yield a temporary path in ``target``'s directory; on success it replaces ``target``.

    On an exception the temporary file is removed and ``target`` is left as it was. The temporary
    name keeps the target's suffix so that writers which dispatch on it (numpy, Pillow) behave.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp makes 0600 files (and some writers recreate the file): give the usual permissions
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, target)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def check_output_dir(path: Path, option: str = "--out") -> None:
    """Raise a one-line error naming ``option`` when ``path`` cannot become an output directory: it
    is an existing file, or the nearest existing folder above it is not a writable directory."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"{option} {path} is an existing file, not a directory")
    parent = path
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise NotADirectoryError(f"{option} {path}: {parent} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(f"{option} {path}: {parent} is not writable")
    try:  # what os.access cannot tell (a read-only mount, root, ACLs): a file really created there
        fd, probe = tempfile.mkstemp(prefix=".ctgpp-write-check-", dir=parent)
    except OSError as err:
        raise PermissionError(f"{option} {path}: cannot write into {parent} ({err.strerror})") from None
    os.close(fd)
    os.unlink(probe)


class StagedFiles:
    """Files written into ``staging`` that :func:`staged_dir` moves into ``target`` at the end."""

    def __init__(self, staging: Path, target: Path) -> None:
        self.staging = staging
        self.target = target

    def path(self, name: str) -> Path:
        """Where to write the output file ``name`` now (inside the staging directory)."""
        return self.staging / name

    def final(self, written: Path) -> Path:
        """The path a file written into the staging directory will have in the target directory."""
        return self.target / Path(written).name


@contextlib.contextmanager
def staged_dir(target: Path) -> Iterator[StagedFiles]:
    """Stage a command's output files: they are written into a temporary directory beside ``target``
    and moved into ``target`` (created) only when the block succeeds; on an exception nothing of them
    reaches ``target`` and the temporary directory is removed."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    try:
        yield StagedFiles(staging, target)
        target.mkdir(exist_ok=True)
        for item in sorted(staging.iterdir()):
            os.replace(item, target / item.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def write_text_atomic(target: Path, text: str) -> Path:
    """Write ``text`` to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(target)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
