"""A local OpenAI-compatible server on 127.0.0.1 with canned replies (no network), the fixtures that
start it and clear the proxies, and ``ctgpp simulate`` against it (the ``llm_env`` fixture of
tests/conftest.py serves the same server)."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest

from ctgpp.cli.main import main
from ctgpp.language.llm.client import LLMClient, LLMConfig
from ctgpp.language.llm.prompt import examples

MODEL = "canned-model"
QUERY = "vehicle 1 should collide with vehicle 2"
GOOD = examples()[0].code  # the collision example


def reply(code: str) -> str:
    return f"Here is the loss.\n\n```python\n{code}```\n\nIt pulls the two vehicles together."


class CannedServer:
    """POST /v1/chat/completions answers the queued replies in order (text, (status, message), or
    bytes sent as the body itself), each after ``delay_s`` seconds."""

    def __init__(self) -> None:
        self.replies: list[Any] = []
        self.requests: list[dict[str, Any]] = []
        self.delay_s = 0.0
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                server.requests.append(body)
                time.sleep(server.delay_s)
                item = server.replies.pop(0) if server.replies else (500, "no canned reply left")
                if isinstance(item, bytes):  # a body that is not a chat completion, sent as is
                    self.send_response(200)
                    kind = "text/html" if item.startswith(b"<") else "application/json"
                    self.send_header("Content-Type", kind)
                    self.send_header("Content-Length", str(len(item)))
                    self.end_headers()
                    self.wfile.write(item)
                    return
                if isinstance(item, tuple):
                    error = {"message": item[1], "type": "invalid_request_error"}
                    status, payload = item[0], {"error": error}
                else:
                    status, payload = 200, {
                        "id": f"chatcmpl-{len(server.requests)}", "object": "chat.completion", "created": 0,
                        "model": body["model"],
                        "choices": [{"index": 0, "finish_reason": "stop",
                                     "message": {"role": "assistant", "content": item}}],
                        "usage": {"prompt_tokens": 1, "completion_tokens": 1, "total_tokens": 2},
                    }
                data = json.dumps(payload).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def log_message(self, *args: Any) -> None:
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def client(self) -> LLMClient:
        return LLMClient(LLMConfig(base_url=self.url, model=MODEL, api_key="test-key", timeout_s=20,
                                   max_retries=0))

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture(autouse=True)
def no_proxy(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")


@pytest.fixture()
def server() -> Iterator[CannedServer]:
    canned = CannedServer()
    yield canned
    canned.close()


def model_argv(query: str, server: CannedServer, out: Path, *flags: str) -> list[str]:
    """``ctgpp simulate QUERY`` with the canned model, ``flags`` and ``--out out``."""
    return ["simulate", query, "--llm-model", MODEL, "--llm-base-url", server.url, *flags, "--out", str(out)]


def simulate_with_model(query: str, server: CannedServer, out: Path, *flags: str) -> dict:
    """Run :func:`model_argv` (exit 0 asserted); returns metrics.json."""
    assert main(model_argv(query, server, out, *flags)) == 0
    return json.loads((out / "metrics.json").read_text())
