"""A structured reply of the language model read and checked (issue 36, item 3): its calls against
the behaviour registry and the scene (:func:`parse_calls`, :func:`call_params`) and against the
sentence (:func:`check_grounded`). Nothing in a reply is trusted, whatever the server enforced."""

from __future__ import annotations

import json
import math
import re
from typing import Any

from ctgpp.behaviours import behaviours, get_behaviour
from ctgpp.language.llm.generate import Round
from ctgpp.language.llm.schema import TIME_FIELDS, is_vehicle, is_word, scoped, words
from ctgpp.language.llm.sentence import named_vehicles, said_quantities
from ctgpp.rule_params import check_quantity

__all__ = ["StructuredRefused", "call_params", "check_grounded", "is_vehicle_param", "number", "parse_calls",
           "vehicle_number"]


class StructuredRefused(ValueError):
    """A structured reply that cannot be used (the message says why, in one line); ``round``: the
    model's reply with the refusal and seconds, where there was one."""

    def __init__(self, message: str, round: Round | None = None) -> None:
        super().__init__(message)
        self.round = round



def number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise StructuredRefused(f"{what} is {value!r}: expected a finite number")
    return float(value)


def vehicle_number(value: Any, what: str, num_vehicles: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise StructuredRefused(f"{what} is {value!r}: expected a vehicle number")
    if not 0 <= value < num_vehicles:
        raise StructuredRefused(f"{what} names vehicle {value}, which is not in the scene (vehicles 0 to "
                                f"{num_vehicles - 1})")
    return value


def call_params(name: str, call: dict[str, Any], num_vehicles: int) -> dict[str, Any]:
    """The behaviour's parameters of one call, typed and checked against the registry and the scene."""
    table = {p.name: p for p in get_behaviour(name).params}
    params: dict[str, Any] = {}
    for key, value in call.items():
        if key not in table:
            continue
        p, what = table[key], f"{name}: parameter {key!r}"
        if is_vehicle(p):
            ok = value is None and "None" in p.type
            params[key] = None if ok else vehicle_number(value, what, num_vehicles)
        elif is_word(p):
            if value is None and "None" in p.type:  # the behaviour's own choice
                continue
            if value not in words(p):
                raise StructuredRefused(f"{what} is {value!r}: expected one of {', '.join(words(p))}")
            params[key] = value
        elif p.type == "bool":
            if not isinstance(value, bool):
                raise StructuredRefused(f"{what} is {value!r}: expected true or false")
            params[key] = value
        else:
            params[key] = number(value, what)
            try:
                check_quantity(what, params[key], p.unit)
            except ValueError as err:
                raise StructuredRefused(str(err)) from None
    missing = [p.name for p in table.values() if p.required and p.name not in params]
    if missing:
        raise StructuredRefused(f"{name} needs {', '.join(missing)}")
    for p in table.values():  # "every vehicle" said explicitly, as the compiler says it
        if is_vehicle(p) and "None" in p.type and p.name not in params:
            params[p.name] = None
    return {k: params[k] for k in table if k in params}


def check_grounded(calls: list[dict[str, Any]], sentence: str) -> None:
    """Every vehicle of the calls is one the sentence names as a vehicle ("vehicle 3", "cars 1 and 2",
    "the ego"), every other number one it says (a parameter's default, a stage and a lower bound
    ``min_*`` of 0 excepted), and every vehicle and number it says is in a call:
    :class:`StructuredRefused` naming the first that is not. A small model fills fields with numbers
    of its own ("at_s": 0, vehicles 0 to 7 for "no vehicle", "other": 8 for "8 m/s") and leaves out
    a time the sentence gives; a reading that says more or less than the sentence is refused rather
    than used. A number the sentence says with a unit goes into a field of that unit only (a time
    into a time, "2 second gap" is no 2 m distance; a unit no field has, "30 feet", into none), a
    bare number into any. Stages: the sentence's "then" (or "after that", "one by one") and the
    calls' stages go together (one stage for all calls means no order)."""
    named = set(named_vehicles(sentence)) | ({0} if re.search(r"\bego\b", sentence, re.I) else set())
    said = set(said_quantities(sentence))  # (value, unit or None)
    used: set[int] = set()
    numbers: set[tuple[float, str | None]] = set()
    for call in calls:
        name = call["behaviour"]
        defaults = {p.name: p.default for p in get_behaviour(name).params}
        for key, value in call.items():
            values = value if isinstance(value, list) else [value]
            for v in values:
                if key == "stage" or isinstance(v, bool) or not isinstance(v, int | float):
                    continue
                vehicle = key == "vehicles" or is_vehicle_param(name, key)
                timed = key in TIME_FIELDS or key == "at_s"
                if vehicle:
                    used.add(int(v))
                    if v in named:
                        continue
                else:
                    unit = "s" if timed else _unit(name, key)
                    same = {q for q in said if q[0] == float(v)}
                    fits = {q for q in same if q[1] in (None, unit)}
                    numbers |= fits
                    if fits or (key in defaults and defaults[key] == v):
                        continue
                    if v == 0 and key.startswith("min_"):  # a lower bound of nothing ("at most 18 m")
                        continue
                    if same:
                        said_in = sorted(str(q[1]) for q in same)[0]
                        raise StructuredRefused(f"{name}: {key}={v:g} is in {unit or 'no unit'}, but the "
                                                f"sentence's {v:g} is in {said_in}")
                what = "vehicle" if vehicle else "time" if timed else "number"
                raise StructuredRefused(f"{name}: {key}={v:g} is a {what} the sentence does not name")
    stages = {c.get("stage", 0) for c in calls}
    sequence = re.search(r"\bthen\b|\bafter\s+that\b|\bafterwards\b|\bone\s+by\s+one\b", sentence, re.I)
    if sequence and len(calls) > 1 and len(stages) == 1:
        raise StructuredRefused(f"the sentence says {sequence.group(0)!r} but every call has the same stage")
    if not sequence and len(stages) > 1:
        raise StructuredRefused("the calls have stages but the sentence says no 'then'")
    dropped = sorted(named - used)
    if dropped:
        raise StructuredRefused(f"vehicle {dropped[0]}, which the sentence names, is in no call")
    unread = sorted(said - numbers, key=lambda q: (q[0], str(q[1])))
    if unread:
        value, unit = unread[0]
        where = f" as a quantity in {unit}" if unit is not None else ""
        raise StructuredRefused(f"the sentence's {value:g} is in no call{where}")


def is_vehicle_param(name: str, key: str) -> bool:
    return any(p.name == key and is_vehicle(p) for p in get_behaviour(name).params)


def _unit(name: str, key: str) -> str | None:
    """The registry's unit of a behaviour's parameter ("m", "m/s", "m/s²", ...; None: none)."""
    return next((p.unit or None for p in get_behaviour(name).params if p.name == key), None)


def parse_calls(reply: str, num_vehicles: int) -> list[dict[str, Any]]:
    """The reply's calls, each checked (module docstring); :class:`StructuredRefused` otherwise."""
    try:
        data = json.loads(reply)
    except json.JSONDecodeError as err:
        raise StructuredRefused(f"the reply is not JSON ({err.msg} at character {err.pos})") from None
    calls = data.get("calls") if isinstance(data, dict) else None
    if not isinstance(calls, list) or not calls:
        raise StructuredRefused('the reply has no list of calls ({"calls": [...]})')
    known = behaviours()
    for k, call in enumerate(calls):
        if not isinstance(call, dict):
            raise StructuredRefused(f"call {k + 1} is not an object")
        name = call.get("behaviour")
        if name not in known:
            raise StructuredRefused(f"call {k + 1} names an unknown behaviour {name!r}; the behaviours are: "
                                    f"{', '.join(known)}")
        allowed = {p.name for p in known[name].params} | {"behaviour", "stage", *TIME_FIELDS}
        allowed |= ({"vehicles"} if scoped(name) else set()) | ({"at_s"} if name == "stop" else set())
        extra = sorted(set(call) - allowed)
        if extra:
            raise StructuredRefused(f"{name} has no parameter {extra[0]!r}; its parameters are: "
                                    f"{', '.join(sorted(allowed - {'behaviour'}))}")
    return calls
