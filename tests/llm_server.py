"""``ctgpp simulate`` against the local OpenAI-compatible model of the ``llm_env`` fixture
(tests/conftest.py)."""

from __future__ import annotations

import json
from pathlib import Path

from ctgpp.cli.main import main
from tests.test_llm_client import MODEL, CannedServer


def model_argv(query: str, server: CannedServer, out: Path, *flags: str) -> list[str]:
    """``ctgpp simulate QUERY`` with the canned model, ``flags`` and ``--out out``."""
    return ["simulate", query, "--llm-model", MODEL, "--llm-base-url", server.url, *flags, "--out", str(out)]


def simulate_with_model(query: str, server: CannedServer, out: Path, *flags: str) -> dict:
    """Run :func:`model_argv` (exit 0 asserted); returns metrics.json."""
    assert main(model_argv(query, server, out, *flags)) == 0
    return json.loads((out / "metrics.json").read_text())
