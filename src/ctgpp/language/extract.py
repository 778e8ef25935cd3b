"""The program in a language model's reply: the ```python block (or the whole reply if it is code)
and the name of its loss class."""

from __future__ import annotations

import ast
import re

__all__ = ["ExtractionError", "extract_code", "loss_class_name"]

_FENCE = re.compile(r"^[ \t]*```[ \t]*(?P<lang>[\w+-]*)[^\n]*\n(?P<code>.*?)^[ \t]*```", re.M | re.S)


class ExtractionError(ValueError):
    """The reply holds no Python program."""


def _defines_class(code: str) -> bool:
    return re.search(r"^class\s+\w+\s*\(", code, re.M) is not None


def extract_code(reply: str) -> str:
    """The Python program of a reply.

    Preference: a ```python (or ```py) block that defines a class, then any such block, then an
    unlabelled ``` block that defines a class; without fences, the whole reply when it parses as
    Python. Raises :class:`ExtractionError` otherwise.
    """
    blocks = [(m["lang"].lower(), m["code"]) for m in _FENCE.finditer(reply)]
    python = [code for lang, code in blocks if lang in ("python", "py", "python3")]
    plain = [code for lang, code in blocks if lang == ""]
    preferred = [c for c in python if _defines_class(c)]
    for candidates in (preferred, python, [c for c in plain if _defines_class(c)]):
        if candidates:
            return candidates[0].strip("\n") + "\n"
    text = reply.strip()
    if text and "```" not in text:
        try:
            ast.parse(text)
        except SyntaxError:
            pass
        else:
            return text + "\n"
    raise ExtractionError("the reply contains no Python program: answer with one ```python code block")


def loss_class_name(code: str) -> str:
    """The name of the top-level class deriving from ``GuidanceLoss`` in ``code``."""
    try:
        tree = ast.parse(code)
    except SyntaxError as err:
        raise ExtractionError(f"line {err.lineno}: syntax error: {err.msg}") from None
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and any(
            isinstance(b, ast.Name) and b.id == "GuidanceLoss" for b in node.bases
        ):
            return node.name
    raise ExtractionError("the program defines no class deriving from GuidanceLoss")
