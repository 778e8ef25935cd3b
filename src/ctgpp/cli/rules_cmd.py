"""``ctgpp rules``: every guidance rule with its parameters, defaults and units; and the ``--rule``
syntax that ``ctgpp simulate`` accepts."""

from __future__ import annotations

import argparse

from ctgpp.cli.common import print_table

RULE_SYNTAX = "NAME[:KEY=VALUE,...]"


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rules", help="list the guidance rules with their parameters, defaults and units")
    p.set_defaults(run=run_rules)


def parse_rule_arg(text: str) -> tuple[str, dict[str, str]]:
    """``"speed_limit:limit_mps=3,..."`` -> ("speed_limit", {"limit_mps": "3", ...}).

    Values stay text (``make_loss`` converts them; lists as ``1/2/3``). Raises ValueError on an empty
    name, a parameter without ``=``, an empty key or value, or a repeated key.
    """
    name, _, rest = text.partition(":")
    name = name.strip()
    if not name:
        raise ValueError(f"--rule {text!r}: expected {RULE_SYNTAX}, e.g. speed_limit:limit_mps=3")
    params: dict[str, str] = {}
    items = [item.strip() for item in rest.split(",")] if ":" in text else []
    for item in items:
        key, eq, value = (s.strip() for s in item.partition("="))
        if not eq or not key or not value:
            raise ValueError(f"--rule {text!r}: parameter {item!r} is not KEY=VALUE ({RULE_SYNTAX})")
        if key in params:
            raise ValueError(f"--rule {text!r}: parameter {key!r} is given twice")
        params[key] = value
    return name, params


def run_rules(args: argparse.Namespace) -> int:
    from ctgpp.guidance import describe_rules

    rows = []
    for rule in describe_rules():
        summary = rule.doc.split("\n\n")[0].replace("\n", " ")
        coupled = "  (couples vehicles: one sample kept for the whole scene)" if rule.couples_agents else ""
        print(f"{rule.name}{coupled}\n  {summary}")
        rows = [
            [p.name, p.type, "required" if p.required else repr(p.default), p.unit or "-", p.help]
            for p in rule.params
        ]
        if rows:
            print_table(["parameter", "type", "default", "unit", "meaning"], rows)
        print()
    print(f"Use with: ctgpp simulate --rule {RULE_SYNTAX} (repeatable; e.g. --rule speed_limit:limit_mps=3")
    print("--rule no_offroad). Vehicles are the displayed numbers; lists are written 1/2/3; a parameter may")
    print("drop its unit suffix (limit=3).")
    return 0
