"""Structured calls from a small local model (issue 36, item 3, beyond the paper).

Instead of writing a loss program, the language model maps the sentence to calls of the behaviour
registry, as JSON that the schema of :mod:`ctgpp.language.llm.schema` constrains (llama.cpp's server
and OpenAI's take it as ``response_format``), and the calls become the same
:class:`~ctgpp.language.compiler.QueryPart` values the offline compiler makes, so the loss, the code
shown and the independent satisfaction check are the compiler's.

The prompt is short (about 900 tokens) and its fixed part comes first: the system message (the
behaviours, their sentence parameters, the reply's form, a few examples) is the same for every
sentence, so a server with a prompt cache (llama.cpp's ``cache_prompt``, asked for) reads it once and
then only the sentence: a 1.5B model on one core answers in seconds. The sentence is sent as the
compiler reads it (numbers in words as digits, typos corrected) with speeds and distances in SI units.

Nothing in the reply is trusted: whatever the server enforced, :mod:`ctgpp.language.llm.calls` checks
every call against the registry and the scene (a behaviour that exists, its parameters by name and
type, vehicle numbers the scene has, speeds in range), against the sentence (vehicles it names,
numbers it says in their units, none of its vehicles left out), :mod:`ctgpp.language.llm.qualifiers`
against what no call can express (a manoeuvre the vocabulary lacks, a time gap, a U-turn's place; two
vehicles in the other order) and :func:`build_parts` the times (a window that is not empty);
:class:`StructuredRefused` says what was wrong, in one line.
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import dataclass
from typing import Any

from ctgpp.behaviours import behaviours, get_behaviour
from ctgpp.behaviours.timing import TimeWindow
from ctgpp.language.compiler import CompiledQuery, QueryPart, compose, render_code
from ctgpp.language.compiler.compiled import in_stage_order
from ctgpp.language.compiler.handlers import (
    DISTANCE_MARGIN_M,
    MOVING_BEFORE_STOP_MPS,
    SPEED_MARGIN_MPS,
    STOP_AT_TOLERANCE_S,
    TARGET_SPEED_DECAY,
)
from ctgpp.language.compiler.normalise import normalise
from ctgpp.language.compiler.patterns import _SPEED, _speed_mps  # the compiler's own unit reading
from ctgpp.language.llm.calls import (
    StructuredRefused,
    call_params,
    check_grounded,
    number,
    parse_calls,
    vehicle_number,
)
from ctgpp.language.llm.client import LLMClient
from ctgpp.language.llm.generate import Round
from ctgpp.language.llm.prompt import Message
from ctgpp.language.llm.qualifiers import check_evidence, check_expressible
from ctgpp.language.llm.schema import TIME_FIELDS, TUNING, is_vehicle, reply_schema, scoped, words

__all__ = ["StructuredReading", "StructuredRefused", "build_parts", "parse_calls", "read_structured",
           "structure_key", "structured_messages", "system_prompt"]

MAX_REPLY_TOKENS = 400  # eight calls of a few parameters each fit in ~250 tokens
AIMS = {"speed_limit": {"margin_mps": SPEED_MARGIN_MPS}, "keep_distance": {"margin_m": DISTANCE_MARGIN_M},
        "stay_away": {"margin_m": DISTANCE_MARGIN_M}, "target_speed": {"decay": TARGET_SPEED_DECAY}}
"""What the compiler aims for where a sentence says nothing (:mod:`~ctgpp.language.compiler.handlers`)."""
STEERS = {"keep_distance": ("follower", "leader"), "stay_away": ("vehicle", "other"),
          "stay_side_of": ("vehicle", None), "same_direction": ("vehicle", None)}
"""A relation steers only its subject (and the other when the subject is held), as the compiler's."""

EXAMPLES = (
    ("vehicle 2 should follow vehicle 1 and no collisions",
     {"calls": [{"behaviour": "keep_distance", "follower": 2, "leader": 1, "min_m": 10, "max_m": 30},
                {"behaviour": "no_collision"}]}),
    ("vehicles 3 and 4 stop within 5 s, then vehicle 1 changes to the left lane",
     {"calls": [{"behaviour": "stop", "vehicles": [3, 4], "within_s": 5},
                {"behaviour": "lane_change", "vehicle": 1, "side": "left", "stage": 1}]}),
    ("keep vehicle 6 under 10 m/s for the first 4 s",
     {"calls": [{"behaviour": "speed_limit", "limit_mps": 10, "vehicles": [6], "until_s": 4}]}),
    ("vehicle 0 comes to a full stop at 6 s",
     {"calls": [{"behaviour": "stop", "vehicles": [0], "at_s": 6}]}),
)


@dataclass(frozen=True)
class StructuredReading:
    """The sentence read by the model: the ``compiled`` query (its parts, loss and code) and the
    model's ``round`` (reply, seconds)."""

    compiled: CompiledQuery
    round: Round


def _signature(name: str) -> str:
    b = behaviours()[name]
    args = []
    for p in b.params:
        if p.name in TUNING:
            continue
        plain = "number" if p.type != "bool" else "bool"
        kind = "vehicle" if is_vehicle(p) else "|".join(words(p)) or plain
        unit = f" {p.unit}" if p.unit and not is_vehicle(p) else ""
        if is_vehicle(p) and not p.required:
            args.append(f"{p.name}?: vehicle (left out: every vehicle)")
            continue
        default = "" if p.required else f"={p.default!r}" if p.default is not None else "?"
        args.append(f"{p.name}: {kind}{unit}{default}")
    if scoped(name):
        args.append("vehicles?: [vehicle, ...] (left out: every vehicle)")
    summary = re.split(r"[:;(]|\. ", b.summary)[0].strip().rstrip(".")
    return f"- {name}({', '.join(args)}): {summary}. E.g. \"{b.phrasings[0]}\"."


def system_prompt() -> str:
    """The fixed part of the prompt, the same for every sentence (the server caches it)."""
    lines = [
        "You turn a traffic instruction into calls of the behaviours below. Reply with JSON only: "
        '{"calls": [{"behaviour": NAME, PARAMETER: VALUE, ...}, ...]}, one call per behaviour and vehicle '
        "(pair) the sentence asks for, nothing it does not ask for. Vehicles are the numbers the sentence "
        "names (\"the ego\" is 0). Speeds in m/s (km/h / 3.6, mph * 0.447), distances in m. A parameter "
        "with a default (=value) or ? may be left out.",
        "Times, on any call: within_s (\"within 5 s\", \"by 5 s\"), from_s and until_s (\"after 3 s\", "
        "\"for the first 4 s\"); stop also takes at_s (\"stops at 6 s\"). stage: 0, 1, ... for \"then\" / "
        "\"after that\" only (left out: 0). Leave out every time and number the sentence does not say.",
        "\"follows vehicle N\" is keep_distance (follow_lane is about a lane); \"stays away from\" or "
        "\"keeps clear of\" is stay_away; \"at most N m behind\" is keep_distance with min_m 0, max_m N.",
        "Behaviours:",
        *(_signature(name) for name in behaviours()),
        "Examples:",
        *(f"{q}\n{json.dumps(reply, separators=(',', ':'))}" for q, reply in EXAMPLES),
    ]
    return "\n".join(lines)


def si_units(text: str) -> str:
    """Speeds in km/h or mph rewritten in m/s, as the compiler reads them."""
    return _SPEED.sub(lambda m: f"{_speed_mps(float(m.group(1)), m.group(2)):g} m/s", text)


def structured_messages(query: str, num_vehicles: int) -> list[Message]:
    """The chat messages for ``query`` in a scene of ``num_vehicles``: the fixed system message first."""
    sentence = si_units(normalise(query))
    user = f"The scene has vehicles 0 to {num_vehicles - 1}.\nSentence: {sentence}"
    return [{"role": "system", "content": system_prompt()}, {"role": "user", "content": user}]


def _window(name: str, call: dict[str, Any]) -> TimeWindow | None:
    times = {t: number(call[t], f"{name}: {t}") for t in (*TIME_FIELDS, "at_s") if call.get(t) is not None}
    if any(v < 0 for v in times.values()):
        raise StructuredRefused(f"{name}: a time is negative ({times})")
    if "within_s" in times and len(times) > 1:
        raise StructuredRefused(f"{name}: a deadline (within_s) with another time is not supported")
    if "within_s" in times:
        return get_behaviour(name).within(times["within_s"])
    if "from_s" not in times and "until_s" not in times:
        return None
    if times.get("until_s", math.inf) <= times.get("from_s", 0.0):
        raise StructuredRefused(f"{name}: until_s={times['until_s']:g} is not after from_s")
    try:
        return TimeWindow(times.get("from_s", 0.0), times.get("until_s"))
    except ValueError as err:
        raise StructuredRefused(f"{name}: {err}") from None


def build_parts(calls: list[dict[str, Any]], num_vehicles: int) -> list[QueryPart]:
    """The compiler's parts for checked ``calls``: its aims where the sentence says nothing, a relation
    steering its subject, a stop "at" a time as the compiler's two parts, stages numbered 0, 1, ..."""
    stages = sorted({int(number(c.get("stage", 0), "stage")) for c in calls})
    parts: list[QueryPart] = []
    for call in calls:
        name = call["behaviour"]
        params = call_params(name, call, num_vehicles)
        params |= {k: v for k, v in AIMS.get(name, {}).items() if k not in params}
        only = None
        if scoped(name) and call.get("vehicles") is not None:
            given = call["vehicles"] if isinstance(call["vehicles"], list) else [call["vehicles"]]
            only = tuple(dict.fromkeys(vehicle_number(v, f"{name}: vehicles", num_vehicles) for v in given))
        steers = held = None
        if name in STEERS:
            subject, other = STEERS[name]
            steers = (params[subject],)
            held = (params[other],) if other else None
        stage = stages.index(int(call.get("stage", 0)))
        text = f"{name}({', '.join(f'{k}={v}' for k, v in call.items() if k != 'behaviour')})"
        at = call.get("at_s")
        if at is not None:
            at = number(at, "stop: at_s")
            if any(call.get(t) is not None for t in TIME_FIELDS):
                raise StructuredRefused("stop: at_s with another time is not supported")
            if at - STOP_AT_TOLERANCE_S >= 1.0:  # still moving before, as the compiler reads "at"
                moving = TimeWindow(0.0, at - STOP_AT_TOLERANCE_S)
                parts.append(QueryPart("reach_speed", {"speed_mps": MOVING_BEFORE_STOP_MPS, "bound": "above"},
                                       text, (0, 0), "stop", only, None, moving, stage))
            window: TimeWindow | None = TimeWindow(at, None, hold=True)
        else:
            window = _window(name, call)
        parts.append(QueryPart(name, params, text, (0, 0), name, only, steers, window, stage, held or ()))
    return parts


def structure_key(part: QueryPart) -> str:
    """What a part means, for comparing two readings: behaviour, parameters with the defaults filled
    in (the aims left out), vehicles, window and stage."""
    params = {k: v for k, v in get_behaviour(part.rule).resolve(part.params).items() if k not in TUNING}
    window = None if part.window is None else [part.window.start_s, part.window.end_s]
    return json.dumps({"rule": part.rule, "params": params, "vehicles": part.vehicles, "window": window,
                       "stage": part.stage}, sort_keys=True, default=list)


def read_structured(query: str, client: LLMClient, num_vehicles: int) -> StructuredReading:
    """Ask the model for the calls of ``query`` (one request, the reply constrained to the registry's
    schema) and build the compiled query; :class:`StructuredRefused` (with the round in ``round``)
    when the reply cannot be used. LLMError when the model cannot be reached."""
    schema = reply_schema(num_vehicles)
    constrained = {"name": "behaviour_calls", "strict": True, "schema": schema}
    request = {"response_format": {"type": "json_schema", "json_schema": constrained},
               "max_tokens": MAX_REPLY_TOKENS, "extra_body": {"cache_prompt": True}}
    started = time.perf_counter()
    reply = client.complete(structured_messages(query, num_vehicles), request)
    seconds = time.perf_counter() - started
    try:
        calls = parse_calls(reply, num_vehicles)
        parts = in_stage_order(build_parts(calls, num_vehicles))
        sentence = si_units(normalise(query))
        check_expressible(calls, sentence)
        check_grounded(calls, sentence)
        check_evidence(calls, sentence)
        for part in parts:
            get_behaviour(part.rule).resolve(part.params)
    except (StructuredRefused, ValueError) as err:
        raise StructuredRefused(f"the language model's structured reply was refused: {err}",
                                Round(reply, str(err), seconds)) from None
    loss = compose(parts)
    compiled = CompiledQuery(query, loss, parts, render_code(parts), si_units(normalise(query)))
    return StructuredReading(compiled, Round(reply, None, seconds))

