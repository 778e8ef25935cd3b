"""The LLM path through the real ``openai`` client against a local OpenAI-compatible server on
127.0.0.1 (canned replies; no network): accepted, repaired, refused, unreachable, cached."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

import pytest

from ctgpp.language.llm.cache import CACHE_FILE, LossCache
from ctgpp.language.llm.client import LLMClient, LLMConfig, LLMError
from ctgpp.language.llm.extract import ExtractionError, extract_code, loss_class_name
from ctgpp.language.llm.generate import GenerationFailed, generate_loss
from ctgpp.language.llm.prompt import PROMPT_VERSION, build_messages, examples, helper_descriptions
from ctgpp.language.sandbox.checks import LossChecker
from ctgpp.language.sandbox.vocabulary import BATCH_ATTRIBUTES, HELPER_NAMES
from tests.support.llm_server import GOOD, MODEL, QUERY, CannedServer, no_proxy, reply, server
from tests.support.loss_checks import checker, scene

__all__ = ["checker", "no_proxy", "scene", "server"]  # fixtures from tests/support

WRONG_SHAPE = GOOD.replace("return (gap * weights).sum(-1) / weights.sum()  # (N,)", "return gap.sum()")
SYNTAX_ERROR = GOOD.replace("def forward(self, x, data_batch, agt_mask=None):", "def forward(self, x,:")
HOSTILE = [
    "import os\n\nclass L(GuidanceLoss):\n    def forward(self, x, data_batch, agt_mask=None):\n"
    "        os.system('rm -rf /')\n        return x.sum((2, 3))\n",
    "class L(GuidanceLoss):\n    def forward(self, x, data_batch, agt_mask=None):\n"
    "        k = ().__class__.__bases__[0].__subclasses__()\n        return x.sum((2, 3))\n",
    "class L(GuidanceLoss):\n    def forward(self, x, data_batch, agt_mask=None):\n"
    "        torch.save(x, '/tmp/x.pt')\n        return x.sum((2, 3))\n",
]


def test_good_program_accepted_in_round_1(server: CannedServer, checker: LossChecker, scene: Any) -> None:
    server.replies = [reply(GOOD)]
    result = generate_loss(QUERY, server.client(), *scene, cache=False, checker=checker)
    assert result.rounds == 1 and result.errors == () and result.path == "llm" and not result.cached
    assert result.code == GOOD and result.name == "CollisionLoss"
    assert result.report.output_shape == (scene[1].shape[1],)
    (request,) = server.requests
    assert request["model"] == MODEL and request["temperature"] == 0.0
    system, user = request["messages"]
    assert system["role"] == "system" and "GuidanceLoss" in system["content"]
    assert user["content"].rstrip().endswith("in one ```python code block.")
    assert QUERY in user["content"] and "The scene has 12 vehicles" in user["content"]
    assert "transform_coord_agents_to_world" in user["content"]


@pytest.mark.parametrize(("broken", "error"), [
    (WRONG_SHAPE, "forward returned shape ()"),
    (SYNTAX_ERROR, "syntax error"),
])
def test_broken_program_repaired_in_round_2(broken: str, error: str, server: CannedServer,
                                            checker: LossChecker, scene: Any) -> None:
    server.replies = [reply(broken), reply(GOOD)]
    result = generate_loss(QUERY, server.client(), *scene, cache=False, checker=checker)
    assert result.rounds == 2 and len(result.errors) == 1 and error in result.errors[0]
    first, second = server.requests
    assert len(second["messages"]) == len(first["messages"]) + 2
    assert second["messages"][-2] == {"role": "assistant", "content": reply(broken)}
    feedback = second["messages"][-1]
    assert feedback["role"] == "user" and error in feedback["content"] and "refused" in feedback["content"]


def test_hostile_program_refused_every_round(server: CannedServer, checker: LossChecker, scene: Any) -> None:
    server.replies = [reply(code) for code in HOSTILE]
    with pytest.raises(GenerationFailed) as failed:
        generate_loss(QUERY, server.client(), *scene, max_repairs=2, cache=False, checker=checker)
    errors = failed.value.errors
    assert len(errors) == 3 and len(server.requests) == 3
    assert "import os is not allowed" in errors[0]
    assert "attributes starting with '_' are not allowed" in errors[1]
    assert "torch.save is not on the allow list" in errors[2]
    assert "failed the checks in all 3 rounds" in str(failed.value)


def test_cache_hit_avoids_a_second_request(server: CannedServer, checker: LossChecker, scene: Any,
                                           tmp_path: Path) -> None:
    cache = LossCache(tmp_path)
    server.replies = [reply(GOOD)]
    first = generate_loss(QUERY, server.client(), *scene, cache=cache, checker=checker)
    again = generate_loss("  Vehicle 1 should collide with vehicle 2 ", server.client(), *scene, cache=cache,
                          checker=checker)
    assert len(server.requests) == 1 and first.rounds == 1
    assert again.cached and again.rounds == 0 and again.code == GOOD
    stored = json.loads((tmp_path / CACHE_FILE).read_text())
    (entry,) = stored["entries"].values()
    assert entry["model"] == MODEL and entry["prompt_version"] == PROMPT_VERSION and entry["code"] == GOOD


def test_tampered_cache_is_checked_again(server: CannedServer, checker: LossChecker, scene: Any,
                                         tmp_path: Path) -> None:
    cache = LossCache(tmp_path)
    cache.put(QUERY, MODEL, HOSTILE[0], rounds=1)
    server.replies = [reply(GOOD)]
    result = generate_loss(QUERY, server.client(), *scene, cache=cache, checker=checker)
    assert not result.cached and result.rounds == 1 and len(server.requests) == 1
    assert cache.get(QUERY, MODEL) == GOOD


def test_unreachable_port_is_a_clear_error(scene: Any) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # closed again below: nothing listens there
    url = f"http://127.0.0.1:{port}/v1"
    client = LLMClient(LLMConfig(base_url=url, model=MODEL, api_key="k", timeout_s=2, max_retries=0))
    with pytest.raises(LLMError, match=f"cannot reach the language model at {url}"):
        generate_loss(QUERY, client, *scene, cache=False)


@pytest.mark.parametrize(("status", "message"), [
    (401, "refused the API key (HTTP 401)"),
    (404, f"has no model '{MODEL}'"),
    (500, "answered HTTP 500"),
])
def test_http_errors_are_clear(status: int, message: str, server: CannedServer) -> None:
    server.replies = [(status, "canned failure")]
    with pytest.raises(LLMError) as failed:
        server.client().complete(build_messages(QUERY))
    assert message in str(failed.value) and server.url in str(failed.value)


def test_config_from_flags_and_environment() -> None:
    env = {"OPENAI_BASE_URL": "http://127.0.0.1:8000/v1/", "CTGPP_LLM_MODEL": "llama", "OPENAI_API_KEY": "s3"}
    cfg = LLMConfig.resolve(env=env)
    assert cfg == LLMConfig("http://127.0.0.1:8000/v1", "llama", "s3")
    assert "s3" not in repr(cfg)
    assert LLMConfig.resolve(model="qwen", timeout_s=5, env=env).model == "qwen"
    assert LLMConfig.resolve(env={}) is None  # no model anywhere: the offline compiler
    local = LLMConfig.resolve(base_url="http://127.0.0.1:11434/v1", model="m", env={})
    assert local is not None and local.api_key  # local servers need no key
    with pytest.raises(LLMError, match="needs an API key"):
        LLMConfig.resolve(model="gpt-4o", env={})


def test_extraction() -> None:
    assert extract_code(reply(GOOD)) == GOOD
    assert extract_code("```py\nprint(1)\n```\n```python\n" + GOOD + "```") == GOOD  # the block with a class
    assert extract_code(GOOD) == GOOD  # a bare program
    assert loss_class_name(GOOD) == "CollisionLoss"
    with pytest.raises(ExtractionError, match="no Python program"):
        extract_code("I cannot help with that.")
    with pytest.raises(ExtractionError, match="no class deriving from GuidanceLoss"):
        loss_class_name("x = 1\n")


def test_prompt_describes_every_helper_and_field() -> None:
    text = helper_descriptions()
    for name in HELPER_NAMES:
        assert f"- `{name}(" in text
    assert "(B, N, T, 2)" in text and ":func:" not in text
    user = build_messages(QUERY, num_vehicles=5)[1]["content"]
    for field in BATCH_ATTRIBUTES:
        assert f"data_batch.{field}" in user
    assert "{{" not in user and user.index(examples()[-1].query) < user.rindex(QUERY)
    assert len(PROMPT_VERSION) == 16 and int(PROMPT_VERSION, 16) >= 0
