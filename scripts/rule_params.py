"""Write ``src/ctgpp/assets/rule_params.json``: every registered guidance rule's parameters as read
from its constructor (:func:`ctgpp.guidance.describe_rules`), for the commands that describe rules
without torch (:mod:`ctgpp.rule_params`). Run it after changing a rule's parameters or their
``param_doc``; tests/test_rule_params.py fails until the file matches.

    python scripts/rule_params.py
"""

from __future__ import annotations

from pathlib import Path

from ctgpp.guidance.composite import describe_rules, rule_params_of
from ctgpp.rule_params import SNAPSHOT, snapshot_text

if __name__ == "__main__":
    path = Path(__file__).resolve().parents[1] / "src" / "ctgpp" / "assets" / SNAPSHOT
    path.write_text(snapshot_text([rule_params_of(r) for r in describe_rules()]), encoding="utf-8")
    print(f"wrote {path}")
