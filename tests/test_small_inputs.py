"""Small inputs are refused before any work starts, naming the flag (issue 36, item 7): a negative
seed, a query over the playground's 300 characters, an --out where nothing can be written; a language
model's reply is capped in size and what the run records of it is cut; a reply that is not JSON is
reported as such."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from ctgpp.cli.common import MAX_QUERY_CHARS
from ctgpp.language.compiler import compile_query
from ctgpp.language.llm.client import LLMError
from ctgpp.language.llm.generate import MAX_REPLY_CHARS, RECORD_CHARS, GenerationFailed, generate_loss
from ctgpp.serve.schema import MAX_SENTENCE_CHARS
from tests.support.llm_server import GOOD, QUERY, CannedServer, no_proxy, reply, server
from tests.support.loss_checks import checker, scene
from tests.support.refusals import no_simulation, refused

__all__ = ["checker", "no_proxy", "no_simulation", "scene", "server"]  # fixtures from tests/support
pytestmark = pytest.mark.usefixtures("no_simulation")  # every input here is refused before the work


@pytest.mark.parametrize("seed", ["-1", str(2**32)])
def test_seed_out_of_range(seed: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    refused(["simulate", "--seed", seed, "--out", str(tmp_path / "o")], capsys, "--seed", seed)
    assert not (tmp_path / "o").exists()


def test_query_over_the_cap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert MAX_QUERY_CHARS == MAX_SENTENCE_CHARS == 300  # the command line and the playground agree
    long = "vehicle 1 should collide with vehicle 2 " * 3000  # about 120 kB
    refused(["simulate", long, "--out", str(tmp_path / "o")], capsys, "query", f"{len(long)} characters",
            "300")
    refused(["simulate", "   ", "--out", str(tmp_path / "o")], capsys, "query is empty")


def test_out_where_nothing_can_be_written(capsys: pytest.CaptureFixture[str]) -> None:
    """/proc takes no new files, whoever runs this (root included)."""
    refused(["simulate", "vehicle 1 should stop", "--out", "/proc/ctgpp-out"], capsys,
            "--out /proc/ctgpp-out", "cannot write into /proc")


@pytest.mark.parametrize(("body", "words"), [
    (b"<html><body>502 Bad Gateway</body></html>", "not JSON (41 characters: '<html><body>502 Bad Gateway"),
    (b"this is not json", "a body that is not JSON"),
    (b'{"status": "ok"}', "not a chat completion (no 'choices')"),
])
def test_a_reply_that_is_not_json(body: bytes, words: str, server: CannedServer) -> None:
    server.replies = [body]
    with pytest.raises(LLMError) as failed:
        server.client().complete([{"role": "user", "content": QUERY}])
    assert words in str(failed.value) and "empty" not in str(failed.value)


def test_a_huge_reply_is_refused_and_recorded_cut(server: CannedServer, checker: Any, scene: Any) -> None:
    batch, x = scene
    huge = reply(GOOD) + "# " + "x" * (10 * MAX_REPLY_CHARS)  # about 650 kB
    server.replies = [huge, huge]
    with pytest.raises(GenerationFailed) as failed:
        generate_loss(QUERY, server.client(), batch, x, max_repairs=1, cache=False, checker=checker,
                      reference=compile_query(QUERY, batch.num_vehicles))
    assert f"characters long, more than the {MAX_REPLY_CHARS} allowed" in str(failed.value)
    sent_back = server.requests[1]["messages"][-2]["content"]  # the reply as the repair round saw it
    assert len(sent_back) == MAX_REPLY_CHARS
    for record in (r.record() for r in failed.value.transcript):
        assert len(record["reply"]) < RECORD_CHARS + 100
        assert f"{len(huge)} characters in all" in record["reply"]
