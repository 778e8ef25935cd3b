"""The guidance rules' parameters, read without torch: names, types, defaults, units and help.

The rules themselves are ``torch.nn.Module`` classes (:mod:`ctgpp.guidance`); what their constructors
take is described here as plain data, so that ``ctgpp rules``, the vocabulary
(:mod:`ctgpp.behaviours`) and ``--rule`` can list and check parameters without loading torch.
``assets/rule_params.json`` holds every registered rule's :class:`ParamInfo` list, written by
``scripts/rule_params.py`` from :func:`ctgpp.guidance.describe_rules` (which reads the constructors
with ``inspect``); a test keeps the two equal.

:func:`resolve_params` reads a rule's parameters as the user gives them (names with or without their
unit suffix, text values from the command line) for both.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import cache
from importlib import resources
from typing import Any

UNIT_SUFFIXES = ("_mps2", "_mps", "_m", "_s", "_rad")
MAX_SPEED_MPS = 40.0  # 144 km/h: a speed a user asks for above this is refused, not clipped
SNAPSHOT = "rule_params.json"  # in ctgpp/assets


@dataclass(frozen=True)
class ParamInfo:
    """One constructor parameter of a rule: name, type (as text), default (None when required;
    ``required`` tells), unit and help."""

    name: str
    type: str
    default: Any
    required: bool
    unit: str
    help: str


@dataclass(frozen=True)
class RuleParams:
    """What a registered rule takes (``params``) and whether its cost couples vehicles."""

    name: str
    params: tuple[ParamInfo, ...]
    couples_agents: bool


def snapshot_text(rules: Sequence[RuleParams]) -> str:
    """``rules`` as the JSON text of ``assets/rule_params.json``, sorted by name."""
    table = {r.name: {"couples_agents": r.couples_agents, "params": [asdict(p) for p in r.params]}
             for r in sorted(rules, key=lambda r: r.name)}
    return json.dumps(table, indent=1, ensure_ascii=False) + "\n"


@cache
def rule_params() -> dict[str, RuleParams]:
    """Name -> parameters of every registered guidance rule, from the snapshot (no torch)."""
    text = (resources.files("ctgpp") / "assets" / SNAPSHOT).read_text(encoding="utf-8")
    return {name: RuleParams(name, tuple(ParamInfo(**p) for p in entry["params"]), entry["couples_agents"])
            for name, entry in json.loads(text).items()}


def _resolve_name(given: str, valid: list[str]) -> str | None:
    """A parameter name as given, or its full name when given without the unit suffix (limit -> limit_mps)."""
    if given in valid:
        return given
    matches = [v for v in valid if any(v == given + suffix for suffix in UNIT_SUFFIXES)]
    return matches[0] if len(matches) == 1 else None


def _coerce(value: Any, type_text: str, name: str) -> Any:
    """Convert text values (from the command line) to the parameter's type: int, float, bool, lists."""
    if not isinstance(value, str):
        return value
    if value.lower() == "none" and "None" in type_text:
        return None
    if "Sequence" in type_text and ("/" in value or ";" in value):
        kind = int if type_text.startswith("int") else float
        return [kind(v) for v in value.replace(";", "/").split("/")]
    try:
        if type_text.startswith("int"):
            return int(value)
        if type_text.startswith("float"):
            return float(value)
        if type_text.startswith("bool"):
            if value.lower() in ("1", "true", "yes"):
                return True
            if value.lower() in ("0", "false", "no"):
                return False
            raise ValueError(value)
    except ValueError:
        raise ValueError(f"parameter {name!r} expects {type_text}, got {value!r}") from None
    return value


def check_quantity(what: str, value: Any, unit: str) -> None:
    """Raise ValueError starting with ``what`` when a number (or a list of numbers) given by the user
    is NaN or infinite, or, for a speed (``unit`` m/s), outside 0..``MAX_SPEED_MPS``."""
    values = value if isinstance(value, list | tuple) else [value]
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int | float):
            continue
        if not math.isfinite(v):
            raise ValueError(f"{what} is {v}: expected a finite number")
        if unit == "m/s" and not 0.0 <= v <= MAX_SPEED_MPS:
            raise ValueError(
                f"{what} is {v:g} m/s: speeds must be 0 to {MAX_SPEED_MPS:g} m/s "
                f"({MAX_SPEED_MPS * 3.6:g} km/h)"
            )


def resolve_params(rule: RuleParams, params: Mapping[str, Any]) -> dict[str, Any]:
    """The keyword arguments of ``rule`` for ``params``: full names (a parameter may be named without
    its unit suffix, ``limit=3`` for ``limit_mps``), text values converted to the parameter's type
    (lists as ``1/2/3``) and checked for physical range, defaults filled in. Unknown parameters and
    missing required ones raise ValueError listing the valid choices."""
    table = {p.name: p for p in rule.params}
    valid = list(table)
    kwargs = {}
    for given, value in params.items():
        full = _resolve_name(given, valid)
        if full is None:
            raise ValueError(
                f"rule {rule.name!r} has no parameter {given!r}; its parameters are: {', '.join(valid)}"
            )
        kwargs[full] = _coerce(value, table[full].type, full)
        if isinstance(value, str):  # a value typed by the user: refused when out of physical range
            check_quantity(f"rule {rule.name!r}: parameter {full!r}", kwargs[full], table[full].unit)
    missing = [p.name for p in rule.params if p.required and p.name not in kwargs]
    if missing:
        raise ValueError(
            f"rule {rule.name!r} needs {', '.join(missing)}; its parameters are: {', '.join(valid)}"
        )
    defaults = {p.name: p.default for p in rule.params if not p.required}
    return {**defaults, **kwargs}


__all__ = [
    "MAX_SPEED_MPS",
    "ParamInfo",
    "RuleParams",
    "check_quantity",
    "resolve_params",
    "rule_params",
    "snapshot_text",
]
