"""``ctgpp rules``: every behaviour of the vocabulary (:mod:`ctgpp.behaviours`) with its parameters,
defaults and units, its violation's unit, the window its verdict is judged on and a phrasing; and the
``--rule`` syntax that ``ctgpp simulate`` accepts."""

from __future__ import annotations

import argparse

from ctgpp.api.rule_text import RULE_SYNTAX, parse_rule_arg
from ctgpp.cli.common import print_table

__all__ = ["RULE_SYNTAX", "add_parsers", "parse_rule_arg", "run_rules"]  # the --rule syntax lives in the API


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rules", help="list the guidance rules with their parameters, defaults and units")
    p.set_defaults(run=run_rules)


def run_rules(args: argparse.Namespace) -> int:
    from ctgpp.behaviours import behaviours

    for name, b in behaviours().items():
        coupled = "  (couples vehicles: one sample kept for the whole scene)" if b.couples_agents else ""
        print(f"{name}{coupled}\n  {b.summary}")
        rows = [
            [p.name, p.type, "required" if p.required else repr(p.default), p.unit or "-", p.help]
            for p in b.params
        ]
        if rows:
            print_table(["parameter", "type", "default", "unit", "meaning"], rows)
        print(f"  violation: {b.meaning} ({b.unit or 'no unit'})")
        print(f"  judged on: {b.window}")
        print(f"  e.g. \"{b.phrasings[0]}\"")
        print()
    print(f"Use with: ctgpp simulate --rule {RULE_SYNTAX} (repeatable; e.g. --rule speed_limit:limit_mps=3")
    print("--rule no_offroad). Vehicles are the displayed numbers; lists are written 1/2/3; a parameter may")
    print("drop its unit suffix (limit=3). Each rule reports its violation with its unit and a verdict.")
    return 0
