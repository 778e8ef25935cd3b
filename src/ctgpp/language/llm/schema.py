"""The JSON schema of a structured reading (issue 36, item 3), generated from the behaviour registry.

A small language model does not write a loss program here: it maps the sentence to calls of the
registry's behaviours, ``{"calls": [{"behaviour": "stop", "vehicles": [1]}, ...]}``, and a server that
constrains its answer to a JSON schema (llama.cpp's ``response_format``) can only answer calls that
exist. One call is an object with:

- ``behaviour``: a behaviour's name (a constant per alternative of ``anyOf``);
- every parameter of that behaviour (:attr:`Behaviour.params`), typed from the registry: a displayed
  vehicle number (an ``int`` parameter, "displayed number" in its help) as an integer among the
  scene's vehicles when their count is known, a word parameter (``side``, ``bound``, ``direction``) as
  one of the words its help quotes, numbers as numbers; required where the registry requires them;
- ``vehicles``: for a behaviour that names no vehicle of its own (a speed limit, a stop), the vehicles
  it is restricted to (left out: every vehicle);
- the times of :mod:`ctgpp.behaviours.timing`: ``within_s`` ("within 5 s"), ``from_s`` / ``until_s``
  (a window), and for ``stop`` ``at_s`` ("stops at 4 s"); ``stage``: its place in a sequence
  ("then": 0, 1, ...).

Everything here is plain data (no torch): the prompt (:mod:`ctgpp.language.llm.structured`) reads the
same table.
"""

from __future__ import annotations

import re
from typing import Any

from ctgpp.behaviours import behaviours
from ctgpp.rule_params import ParamInfo

__all__ = ["TIME_FIELDS", "TUNING", "call_schema", "is_vehicle", "is_word", "reply_schema", "scoped", "words"]

TIME_FIELDS = ("within_s", "from_s", "until_s")
"""The time fields every call may carry (``at_s`` only ``stop``'s)."""

TUNING = frozenset({"margin_m", "margin_mps", "decay", "buffer_m", "contact_m", "min_gap_m",
                    "speed_weight", "absolute_steps"})
"""Parameters that tune a guidance loss rather than say what a sentence means: in the schema (a reply
may set them) but not in the prompt; left out, the compiler's own aims are used."""

MAX_CALLS = 8  # a sentence of more parts than this is not a query the playground takes
MAX_STAGE = 7


def is_vehicle(param: ParamInfo) -> bool:
    """Whether a parameter is a displayed vehicle number (an ``int`` parameter, by its help)."""
    return param.type.startswith("int") and "displayed" in param.help


def is_word(param: ParamInfo) -> bool:
    """Whether ``param`` takes a word (``str``, or ``str | None`` where None is its default: the
    overtake's side)."""
    return param.type in ("str", "str | None")


def words(param: ParamInfo) -> list[str]:
    """The words a word parameter takes, as its help quotes them (``'left' or 'right'``)."""
    return re.findall(r"'([a-z_]+)'", param.help) if is_word(param) else []


def scoped(name: str) -> bool:
    """Whether behaviour ``name`` names no vehicle of its own (a call restricts it with ``vehicles``)."""
    return not any(is_vehicle(p) for p in behaviours()[name].params)


def _vehicle(num_vehicles: int | None) -> dict[str, Any]:
    if num_vehicles is None:
        return {"type": "integer", "minimum": 0}
    return {"type": "integer", "enum": list(range(num_vehicles))}


def _param(param: ParamInfo, num_vehicles: int | None) -> dict[str, Any]:
    if is_vehicle(param):
        return _vehicle(num_vehicles)
    if is_word(param):
        return {"type": "string", "enum": words(param)}
    if param.type == "bool":
        return {"type": "boolean"}
    return {"type": "number"}


def call_schema(name: str, num_vehicles: int | None = None) -> dict[str, Any]:
    """The schema of one call of behaviour ``name`` (module docstring)."""
    params = behaviours()[name].params
    props: dict[str, Any] = {"behaviour": {"const": name}}
    props |= {p.name: _param(p, num_vehicles) for p in params}
    if scoped(name):
        props["vehicles"] = {"type": "array", "items": _vehicle(num_vehicles), "minItems": 1}
    props |= {t: {"type": "number", "minimum": 0} for t in TIME_FIELDS}
    if name == "stop":
        props["at_s"] = {"type": "number", "minimum": 0}
    props["stage"] = {"type": "integer", "minimum": 0, "maximum": MAX_STAGE}
    required = ["behaviour", *(p.name for p in params if p.required)]
    return {"type": "object", "properties": props, "required": required, "additionalProperties": False}


def reply_schema(num_vehicles: int | None = None) -> dict[str, Any]:
    """The schema of a whole reply: ``{"calls": [call, ...]}``, one to :data:`MAX_CALLS` calls of any
    behaviour of the registry (vehicle numbers among ``num_vehicles`` when given)."""
    calls = {"anyOf": [call_schema(name, num_vehicles) for name in behaviours()]}
    return {"type": "object", "properties": {"calls": {"type": "array", "items": calls, "minItems": 1,
                                                       "maxItems": MAX_CALLS}},
            "required": ["calls"], "additionalProperties": False}
