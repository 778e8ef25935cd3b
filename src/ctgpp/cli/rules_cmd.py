"""``ctgpp rules``: every guidance rule with its parameters, defaults and units; and the ``--rule``
syntax that ``ctgpp simulate`` accepts."""

from __future__ import annotations

import argparse

from ctgpp.api.rule_text import RULE_SYNTAX, parse_rule_arg
from ctgpp.cli.common import print_table

__all__ = ["RULE_SYNTAX", "add_parsers", "parse_rule_arg", "run_rules"]  # the --rule syntax lives in the API


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rules", help="list the guidance rules with their parameters, defaults and units")
    p.set_defaults(run=run_rules)


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
