"""A cache of accepted generated losses, keyed by (query, model, prompt version), in one JSON file.

The directory is ``$CTGPP_CACHE_DIR``, else ``$XDG_CACHE_HOME/ctgpp``, else ``~/.cache/ctgpp``; the
file is ``llm_losses.json``, rewritten atomically on every change. Cached code is as untrusted as a
fresh reply: :func:`ctgpp.language.llm.generate.generate_loss` runs the sandbox and the checks on it
again before using it. A damaged file is treated as empty.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from ctgpp.io.atomic import write_text_atomic
from ctgpp.language.llm.prompt import PROMPT_VERSION

__all__ = ["CACHE_FILE", "LossCache", "default_cache_dir"]

CACHE_FILE = "llm_losses.json"
FORMAT = 1
log = logging.getLogger(__name__)


def default_cache_dir(env: dict[str, str] | None = None) -> Path:
    """``$CTGPP_CACHE_DIR``, else ``$XDG_CACHE_HOME/ctgpp``, else ``~/.cache/ctgpp``."""
    env = dict(os.environ) if env is None else env
    if env.get("CTGPP_CACHE_DIR"):
        return Path(env["CTGPP_CACHE_DIR"]).expanduser()
    base = Path(env["XDG_CACHE_HOME"]).expanduser() if env.get("XDG_CACHE_HOME") else Path.home() / ".cache"
    return base / "ctgpp"


def normalize_query(query: str) -> str:
    """Whitespace collapsed and lower case: the same request typed twice hits the same entry."""
    return " ".join(query.split()).lower()


class LossCache:
    """Accepted programs by (query, model, prompt version) in ``directory / CACHE_FILE``."""

    def __init__(self, directory: Path | None = None, prompt_version: str = PROMPT_VERSION) -> None:
        self.path = Path(directory if directory is not None else default_cache_dir()) / CACHE_FILE
        self.prompt_version = prompt_version

    def key(self, query: str, model: str) -> str:
        text = json.dumps([normalize_query(query), model, self.prompt_version])
        return hashlib.sha256(text.encode()).hexdigest()

    def _entries(self) -> dict[str, Any]:
        if not self.path.is_file():
            return {}
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            log.warning("ignoring the unreadable loss cache %s: %s", self.path, err)
            return {}
        entries = data.get("entries") if isinstance(data, dict) and data.get("format") == FORMAT else None
        return entries if isinstance(entries, dict) else {}

    def _write(self, entries: dict[str, Any]) -> None:
        text = json.dumps({"format": FORMAT, "entries": entries}, indent=1, sort_keys=True)
        write_text_atomic(self.path, text + "\n")

    def get(self, query: str, model: str) -> str | None:
        """The cached program for (query, model) under this prompt version, or None."""
        entry = self._entries().get(self.key(query, model))
        code = entry.get("code") if isinstance(entry, dict) else None
        return code if isinstance(code, str) else None

    def put(self, query: str, model: str, code: str, rounds: int,
            cpu_s_per_call: float | None = None) -> None:
        """Remember an accepted program and its measured CPU seconds per call (its trial's)."""
        entries = self._entries()
        entries[self.key(query, model)] = {
            "query": query, "model": model, "prompt_version": self.prompt_version, "code": code,
            "rounds": int(rounds), "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        if cpu_s_per_call is not None:
            entries[self.key(query, model)]["cpu_s_per_call"] = float(cpu_s_per_call)
        self._write(entries)

    def cost(self, query: str, model: str) -> float | None:
        """The CPU seconds per call measured when the program for (query, model) was cached (None:
        no entry, or an entry without it)."""
        entry = self._entries().get(self.key(query, model))
        value = entry.get("cpu_s_per_call") if isinstance(entry, dict) else None
        return float(value) if isinstance(value, int | float) else None

    def discard(self, query: str, model: str) -> None:
        """Forget the entry for (query, model) (e.g. when it no longer passes the checks)."""
        entries = self._entries()
        if entries.pop(self.key(query, model), None) is not None:
            self._write(entries)
