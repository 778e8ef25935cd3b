"""Rules written as text, ``NAME[:KEY=VALUE,...]``: what ``ctgpp simulate --rule`` and
:func:`ctgpp.simulate`'s ``rules`` take."""

from __future__ import annotations

RULE_SYNTAX = "NAME[:KEY=VALUE,...]"


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
