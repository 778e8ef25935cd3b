"""Structured calls from a small local model (issue 36, item 3), through the real ``openai`` client
against a local OpenAI-compatible server on 127.0.0.1 with canned replies (no network): the schema
generated from the behaviour registry, replies read into the compiler's own parts, refusals with their
reason and the compiler as fallback, the path recorded in metrics.json."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from ctgpp.behaviours import behaviours
from ctgpp.cli.main import main
from ctgpp.language.compiler import QueryError, QueryPart, compile_query
from ctgpp.language.llm.calls import call_params
from ctgpp.language.llm.client import LLMConfig, LLMError
from ctgpp.language.llm.schema import call_schema, reply_schema
from ctgpp.language.llm.structured import (
    StructuredRefused,
    read_structured,
    structure_key,
    structured_messages,
    system_prompt,
)
from ctgpp.language.query import STRUCTURED_PATH, resolve_query
from tests.support.llm_server import MODEL, CannedServer, no_proxy, server
from tests.support.observations import real_observation

__all__ = ["no_proxy", "server"]  # fixtures from tests/support

SCENE_VEHICLES = 12


def calls(*items: dict[str, Any]) -> str:
    return json.dumps({"calls": list(items)})


def config(server: CannedServer, mode: str) -> LLMConfig:
    return LLMConfig(base_url=server.url, model=MODEL, api_key="test-key", timeout_s=20, max_retries=0,
                     mode=mode)


def guidance(part: QueryPart) -> str:
    """Everything a part's loss is built from: its behaviour, every parameter (defaults filled in, the
    compiler's aims included), the vehicles it is restricted to and steers, its window and stage."""
    params = behaviours()[part.rule].resolve(part.params)
    window = None if part.window is None else [part.window.start_s, part.window.end_s, part.window.hold]
    return json.dumps([part.rule, params, part.vehicles, part.steers, part.steers_when_held, window,
                       part.stage], sort_keys=True, default=list)


@pytest.fixture(scope="module")
def obs() -> Any:
    return real_observation()


def test_schema_covers_every_behaviour_and_parameter_of_the_registry() -> None:
    schema = reply_schema(SCENE_VEHICLES)
    alternatives = schema["properties"]["calls"]["items"]["anyOf"]
    entries = {e["properties"]["behaviour"]["const"]: e for e in alternatives}
    assert sorted(entries) == sorted(behaviours())
    for name, behaviour in behaviours().items():
        props, entry = entries[name]["properties"], entries[name]
        for p in behaviour.params:
            assert p.name in props, (name, p.name)
        required = ["behaviour", *(p.name for p in behaviour.params if p.required)]
        assert sorted(entry["required"]) == sorted(required)
        assert entry["additionalProperties"] is False
        names_a_vehicle = any(p.type.startswith("int") for p in behaviour.params)
        assert ("vehicles" in props) == (not names_a_vehicle), name
        extra = set(props) - {p.name for p in behaviour.params}
        assert extra <= {"behaviour", "vehicles", "within_s", "from_s", "until_s", "at_s", "stage"}
    # hand-read from src/ctgpp/assets/rule_params.json
    assert entries["lane_change"]["properties"]["side"] == {"type": "string", "enum": ["left", "right"]}
    turn = entries["turn_at_next_intersection"]["properties"]
    assert turn["direction"]["enum"] == ["left", "right", "straight"]
    assert entries["reach_speed"]["properties"]["bound"]["enum"] == ["below", "above"]
    assert entries["cut_in"]["properties"]["ahead_of"] == {"type": "integer", "enum": list(range(12))}
    assert entries["speed_limit"]["properties"]["limit_mps"] == {"type": "number"}
    assert "at_s" in entries["stop"]["properties"] and "at_s" not in entries["speed_limit"]["properties"]


def test_prompt_is_short_and_its_fixed_part_comes_first() -> None:
    a = structured_messages("vehicle 1 should stop", 12)
    b = structured_messages("vehicle three drives at 36 km/h", 7)
    assert a[0] == b[0] == {"role": "system", "content": system_prompt()}  # the cached prefix
    assert all(f"- {name}(" in a[0]["content"] for name in behaviours())
    assert len(a[0]["content"]) < 7000  # ~1.6k tokens, against ~8.3k for a program
    assert b[1]["content"] == "The scene has vehicles 0 to 6.\nSentence: vehicle 3 drives at 10 m/s"


AGREE = [
    ("vehicle 3 should not exceed 36 km/h and no collisions",
     calls({"behaviour": "speed_limit", "limit_mps": 10, "vehicles": [3]}, {"behaviour": "no_collision"})),
    ("vehicle 2 should change to the left lane then vehicle 3 stops within 5 s",
     calls({"behaviour": "lane_change", "vehicle": 2, "side": "left"},
           {"behaviour": "stop", "vehicles": [3], "within_s": 5, "stage": 1})),
    ("vehicle 2 should follow vehicle 1",
     calls({"behaviour": "keep_distance", "follower": 2, "leader": 1})),
    ("vehicle 3 should stay on the left of vehicle 1",
     calls({"behaviour": "stay_side_of", "vehicle": 3, "other": 1, "side": "left"})),
    ("vehicle 5 comes to a full stop at 4 seconds", calls({"behaviour": "stop", "vehicles": [5], "at_s": 4})),
    ("everyone stays in their lane", calls({"behaviour": "follow_lane"})),
    ("vehicle 2 should drive at 5 m/s for the first 4 s",
     calls({"behaviour": "target_speed", "speed_mps": 5, "vehicles": [2], "until_s": 4})),
]


@pytest.mark.parametrize(("query", "answer"), AGREE)
def test_valid_reply_builds_the_compilers_parts(query: str, answer: str, server: CannedServer) -> None:
    """The same guidance, part for part (rule, parameters with the compiler's aims, vehicles, steering,
    window, stage), as the compiler's reading of a sentence it understands."""
    server.replies = [answer]
    got = read_structured(query, server.client(), SCENE_VEHICLES)
    want = compile_query(query, SCENE_VEHICLES)
    assert sorted(map(guidance, got.compiled.parts)) == sorted(map(guidance, want.parts))
    assert sorted(map(structure_key, got.compiled.parts)) == sorted(map(structure_key, want.parts))
    (request,) = server.requests
    assert request["response_format"]["type"] == "json_schema"
    assert request["response_format"]["json_schema"]["schema"] == reply_schema(SCENE_VEHICLES)
    assert request["cache_prompt"] is True and request["temperature"] == 0.0 and request["max_tokens"] <= 400
    assert got.round.refusal is None and got.round.reply == answer


def test_a_different_reading_is_not_the_compilers(server: CannedServer) -> None:
    query = "vehicle 3 should not exceed 36 km/h"
    # slowing to 10 m/s and staying under, not a limit from the start: another reading that passes the
    # checks (a target speed, a reading that asks for what the "not" denies, no longer does)
    server.replies = [calls({"behaviour": "reach_speed", "speed_mps": 10, "bound": "below", "vehicles": [3]})]
    got = read_structured(query, server.client(), SCENE_VEHICLES)
    want = compile_query(query, SCENE_VEHICLES)
    assert sorted(map(structure_key, got.compiled.parts)) != sorted(map(structure_key, want.parts))
    server.replies = [calls({"behaviour": "speed_limit", "limit_mps": 36, "vehicles": [3]})]  # km/h unread
    with pytest.raises(StructuredRefused, match="limit_mps=36 is a number the sentence does not name"):
        read_structured(query, server.client(), SCENE_VEHICLES)
    server.replies = [calls({"behaviour": "target_speed", "speed_mps": 10, "vehicles": [3]})]
    with pytest.raises(StructuredRefused, match="says what must not happen"):
        read_structured(query, server.client(), SCENE_VEHICLES)


BAD = [
    (calls({"behaviour": "stop", "vehicles": [40]}), "names vehicle 40, which is not in the scene"),
    (calls({"behaviour": "collision", "vehicle_a": 1, "vehicle_b": 99}), "names vehicle 99"),
    (calls({"behaviour": "three_point_turn", "vehicle": 1}), "unknown behaviour 'three_point_turn'"),
    (calls({"behaviour": "speed_limit", "limit_mps": "fast"}),
     "parameter 'limit_mps' is 'fast': expected a finite number"),
    (calls({"behaviour": "lane_change", "vehicle": 1, "side": "up"}), "expected one of left, right"),
    (calls({"behaviour": "lane_change", "vehicle": True}), "expected a vehicle number"),
    (calls({"behaviour": "cut_in", "vehicle": 1}), "cut_in needs ahead_of"),
    (calls({"behaviour": "cut_in", "vehicle": 1, "ahead_of": 2, "gap_m": 10}),
     "ahead_of=2 is a vehicle the sentence does not name"),
    (calls({"behaviour": "stop", "vehicle": 1}), "stop has no parameter 'vehicle'"),
    (calls({"behaviour": "speed_limit", "limit_mps": 400}), "speeds must be 0 to 40 m/s"),
    (calls({"behaviour": "stop", "vehicles": [3]}), "vehicles=3 is a vehicle the sentence does not name"),
    (calls({"behaviour": "stop", "vehicles": [1], "at_s": 0}), "at_s=0 is a time the sentence does not"),
    (calls({"behaviour": "stop", "vehicles": [1], "within_s": 5}), "within_s=5 is a time the sentence"),
    (calls({"behaviour": "speed_limit", "limit_mps": 7, "vehicles": [1]}), "limit_mps=7 is a number"),
    (calls({"behaviour": "no_collision"}), "vehicle 1, which the sentence names, is in no call"),
    (calls({"behaviour": "stop", "vehicles": [1], "from_s": 6, "until_s": 6}), "until_s=6 is not after"),
    (calls({"behaviour": "goal_waypoint", "vehicle": 1, "x": 0, "y": 0}), "x=0 is a number the sentence"),
    ("stop vehicle 1", "the reply is not JSON"),
    (json.dumps({"calls": []}), "no list of calls"),
]


@pytest.mark.parametrize(("answer", "reason"), BAD)
def test_bad_reply_is_refused_with_its_reason(answer: str, reason: str, server: CannedServer) -> None:
    server.replies = [answer]
    with pytest.raises(StructuredRefused) as refused:
        read_structured("vehicle 1 should stop", server.client(), SCENE_VEHICLES)
    assert reason in str(refused.value) and "\n" not in str(refused.value)
    assert refused.value.round is not None and refused.value.round.refusal is not None


def test_a_number_of_the_sentence_left_out_is_refused(server: CannedServer) -> None:
    server.replies = [calls({"behaviour": "lane_change", "vehicle": 4, "side": "left"})]
    with pytest.raises(StructuredRefused, match="the sentence's 5 is in no call"):
        read_structured("vehicle 4 changes to the left lane within 5 s", server.client(), SCENE_VEHICLES)


def test_then_needs_stages(server: CannedServer) -> None:
    query = "vehicle 9 changes to the right lane, then vehicle 10 does the same"
    both = [{"behaviour": "lane_change", "vehicle": v, "side": "right", "stage": 1} for v in (9, 10)]
    server.replies = [calls(*both)]
    with pytest.raises(StructuredRefused, match="says 'then' but every call has the same stage"):
        read_structured(query, server.client(), SCENE_VEHICLES)
    server.replies = [calls(both[0], {**both[1], "stage": 2})]
    got = read_structured(query, server.client(), SCENE_VEHICLES)
    assert [p.stage for p in got.compiled.parts] == [0, 1]
    server.replies = [calls(both[0], {**both[1], "stage": 2})]
    with pytest.raises(StructuredRefused, match="the calls have stages but the sentence says no 'then'"):
        read_structured("vehicles 9 and 10 change to the right lane", server.client(), SCENE_VEHICLES)


def test_calls_in_any_order_are_read_in_stage_order(server: CannedServer) -> None:
    """A reply that lists a later stage's call first is a sequence all the same (it had stopped the
    reading with "InOrder: part 0 may only wait for earlier parts")."""
    query = "vehicle 3 changes into the right lane, then it overtakes the ego"
    server.replies = [calls({"behaviour": "overtake", "vehicle": 3, "other": 0, "stage": 1},
                            {"behaviour": "lane_change", "vehicle": 3, "side": "right", "stage": 0})]
    got = read_structured(query, server.client(), SCENE_VEHICLES)
    assert [(p.rule, p.stage) for p in got.compiled.parts] == [("lane_change", 0), ("overtake", 1)]


def test_a_whole_episode_clause_after_a_sequence_waits_for_nothing() -> None:
    """"...; vehicle 7 stays on the road throughout" after a "then" holds from the start (stage 0), and
    the loss is built whatever order the clauses came in."""
    parts = compile_query("vehicle 7 overtakes vehicle 2, then moves to the rightmost lane; vehicle 7 stays "
                          "on the road throughout", SCENE_VEHICLES).parts
    assert [(p.rule, p.stage) for p in parts] == [("overtake", 0), ("no_offroad", 0),
                                                  ("move_to_rightmost_lane", 1)]


@pytest.mark.parametrize(("answer", "reason"), BAD[:3])
def test_refused_reply_falls_back_to_the_compiler(answer: str, reason: str, server: CannedServer,
                                                   obs: Any) -> None:
    query = "vehicle 1 should come to a stop"
    server.replies = [answer]
    got = resolve_query(query, obs, config(server, "structured"))
    want = compile_query(query, len(obs.controlled))
    assert got.path == "offline query compiler (fallback)" and reason in (got.fallback or "")
    assert [guidance(p) for p in got.compiled.parts] == [guidance(p) for p in want.parts]
    assert got.rounds[0]["refusal"] is not None and reason in got.notes[0]


def test_structured_mode_uses_the_models_reading_and_compares(server: CannedServer, obs: Any) -> None:
    query = "vehicle 1 should come to a stop"
    server.replies = [calls({"behaviour": "stop", "vehicles": [1]})]
    got = resolve_query(query, obs, config(server, "structured"))
    assert got.path.startswith(f"{STRUCTURED_PATH} (language model {MODEL}")
    assert got.notes == ["the offline compiler reads the sentence the same way"]
    # a reading that differs from the compiler's (a part left out) is used, and the difference said
    server.replies = [calls({"behaviour": "no_offroad", "vehicles": [1]})]
    both = "vehicle 1 should come to a stop and stay on the road"
    got = resolve_query(both, obs, config(server, "structured"))
    assert got.path.startswith(STRUCTURED_PATH) and got.compiled.parts[0].rule == "no_offroad"
    assert got.notes[0].startswith("the offline compiler reads the sentence differently")
    # a behaviour the sentence has no word of is made up: refused, the compiler's reading used
    server.replies = [calls({"behaviour": "no_offroad", "vehicles": [1]})]
    got = resolve_query(query, obs, config(server, "structured"))
    assert got.path == "offline query compiler (fallback)"


def test_auto_asks_the_model_only_where_the_compiler_refuses(server: CannedServer, obs: Any) -> None:
    got = resolve_query("vehicle 1 should come to a stop", obs, config(server, "auto"))
    assert got.path == "offline query compiler" and server.requests == []
    refused = "vehicle 2 has to be at a standstill six seconds from now"
    with pytest.raises(QueryError):
        compile_query(refused, len(obs.controlled))
    server.replies = [calls({"behaviour": "stop", "vehicles": [2], "within_s": 6})]
    got = resolve_query(refused, obs, config(server, "auto"))
    assert got.path.startswith(STRUCTURED_PATH) and len(server.requests) == 1
    (part,) = got.compiled.parts
    assert (part.rule, part.vehicles, part.window.start_s, part.window.end_s) == ("stop", (2,), 6.0, None)
    server.replies = [calls({"behaviour": "stop", "vehicles": [77]})]
    with pytest.raises(QueryError, match="not in the scene.*the offline compiler does not read the sentence"):
        resolve_query(refused, obs, config(server, "auto"))


def test_mode_is_checked() -> None:
    with pytest.raises(LLMError, match="--llm-mode must be one of program, structured, auto"):
        LLMConfig.resolve(model="m", base_url="http://127.0.0.1:1/v1", env={"CTGPP_LLM_MODE": "fast"})
    got = LLMConfig.resolve(model="m", base_url="http://127.0.0.1:1/v1", env={"CTGPP_LLM_MODE": "auto"})
    assert got is not None and got.mode == "auto"


def test_path_recorded_in_metrics_json(server: CannedServer, tmp_path: Path,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CTGPP_CACHE_DIR", str(tmp_path / "cache"))
    short = ["--scene", "0103", "--policy", "replay", "--duration", "1", "--animation", "none",
             "--llm-model", MODEL, "--llm-base-url", server.url, "--llm-mode", "auto"]
    query = "vehicle 2 has to be at a standstill six seconds from now"
    server.replies = [calls({"behaviour": "stop", "vehicles": [2], "within_s": 6})]
    assert main(["simulate", query, *short, "--out", str(tmp_path / "ok")]) == 0
    record = json.loads((tmp_path / "ok" / "metrics.json").read_text())["query"]
    assert record["path"].startswith(STRUCTURED_PATH) and record["fallback"] is None
    assert [p["text"] for p in record["parts"]] == ["stop(vehicles=[2], within_s=6)"]
    assert record["rounds"][0]["refusal"] is None and '"stop"' in record["rounds"][0]["reply"]

    server.replies = [calls({"behaviour": "stop", "vehicles": [2], "at_s": "soon"})]
    query = "vehicle 2 should come to a stop"
    assert main(["simulate", query, *short[:-1], "structured", "--out", str(tmp_path / "fb")]) == 0
    record = json.loads((tmp_path / "fb" / "metrics.json").read_text())["query"]
    assert record["path"] == "offline query compiler (fallback)"
    assert "stop: at_s is 'soon': expected a finite number" in record["fallback"]
    assert record["rounds"][0]["refusal"] == "stop: at_s is 'soon': expected a finite number"


def test_benchmark_set_is_refused_by_the_compiler_and_means_registry_calls() -> None:
    """tests/data/structured/refused.jsonl (scripts/structured_bench.py): ≥ 20 sentences the compiler
    refuses, each with the calls it means, in the registry's terms."""
    rows = [json.loads(line) for line in
            (Path(__file__).parent / "data" / "structured" / "refused.jsonl").read_text().splitlines()]
    assert len(rows) >= 20
    for row in rows:
        with pytest.raises(ValueError):
            compile_query(row["query"], SCENE_VEHICLES)
        for part in row["expect"]:
            behaviours()[part["rule"]].resolve(part["params"])  # a behaviour, its parameters


def test_a_word_parameter_with_no_default_choice_is_a_word() -> None:
    """The overtake's side ('left', 'right', or left out: the behaviour chooses) is a word in the schema
    and in a call, never a number (it had been typed as a number: every side the model gave was refused)."""
    assert call_schema("overtake")["properties"]["side"] == {"type": "string", "enum": ["left", "right"]}
    call = {"behaviour": "overtake", "vehicle": 4, "other": 7}
    assert call_params("overtake", {**call, "side": "right"}, 12)["side"] == "right"
    assert "side" not in call_params("overtake", {**call, "side": None}, 12)
    with pytest.raises(ValueError, match="expected one of left, right"):
        call_params("overtake", {**call, "side": "north"}, 12)
