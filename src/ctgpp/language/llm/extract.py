"""The program in a language model's reply: the ```python block (or the whole reply if it is code)
and the name of its loss class.

A reply may define several classes deriving from ``GuidanceLoss`` (the paper's replies sometimes hold
a helper loss that the main one builds). The *loss class* — the one the simulator builds with no
arguments — is :func:`main_class`: the last class that no other part of the program names (a helper
class is named where the main one builds it); when every class is named somewhere, the last class.
"""

from __future__ import annotations

import ast
import re

__all__ = ["ExtractionError", "extract_code", "loss_class_name", "loss_classes", "main_class"]

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


def loss_classes(tree: ast.Module) -> list[ast.ClassDef]:
    """The top-level classes of a module that derive from ``GuidanceLoss``, in order."""
    return [node for node in tree.body if isinstance(node, ast.ClassDef)
            and any(isinstance(b, ast.Name) and b.id == "GuidanceLoss" for b in node.bases)]


def main_class(tree: ast.Module) -> ast.ClassDef | None:
    """The loss class of a module (see the module docstring); None when it defines no loss class."""
    classes = loss_classes(tree)
    named: set[str] = set()
    for node in tree.body:
        for inner in ast.walk(node):
            if isinstance(inner, ast.Name) and not (isinstance(node, ast.ClassDef) and inner.id == node.name):
                named.add(inner.id)
    unnamed = [c for c in classes if c.name not in named]
    if unnamed:
        return unnamed[-1]
    return classes[-1] if classes else None


def loss_class_name(code: str) -> str:
    """The name of the loss class (:func:`main_class`) of ``code``."""
    try:
        tree = ast.parse(code)
    except SyntaxError as err:
        raise ExtractionError(f"line {err.lineno}: syntax error: {err.msg}") from None
    cls = main_class(tree)
    if cls is None:
        raise ExtractionError("the program defines no class deriving from GuidanceLoss")
    return cls.name
