"""What a generated program takes from the sentence itself (issue 36, item 1): the vehicles it names
(the paper's ``agt_mask``) and the values of loss parameters the program leaves without a default
(the paper's ``AccLimitLoss(acc_limit)``, instantiated with the sentence's value).

Rules, in order:

- the *named vehicles* are the numbers after "vehicle"/"vehicles"/"car"/"agent" (lists such as
  "vehicles 1, 2 and 3" included), within the scene's vehicle count;
- the *quantities* are the other numbers of the sentence (units such as "m/s^2" do not count: their
  exponent is no value), each with the unit written after it where there is one
  (:func:`said_quantities`: "s", "m", "m/s", "m/s²", or another word such as "ft", "km", "min");
- a parameter of the main loss class's ``__init__`` without a default whose name reads as a vehicle
  (``ind``, ``idx``, ``vehicle``, ``agent``, ``target``, ``ref``, ``ego``, ``other``, ``leader``,
  ``follower``) takes the named vehicles in order; any other takes the quantities in order. Where the
  sentence gives fewer values of a kind than the program leaves open, or more (which one is meant?),
  the program is refused naming the parameter.

The value is written into the program as the parameter's default, so the program that runs, is
shown and is cached is the one that was checked.
"""

from __future__ import annotations

import ast
import re

from ctgpp.language.llm.extract import main_class
from ctgpp.language.sandbox.nodes import SandboxError

__all__ = ["bind_parameters", "named_vehicles", "quantities", "said_quantities"]

_VEHICLE_WORDS = r"(?:vehicles?|cars?|agents?)"
_LIST = re.compile(rf"\b{_VEHICLE_WORDS}\s+(\d+(?:\s*(?:,|and|&|or)\s*(?:{_VEHICLE_WORDS}\s+)?\d+)*)", re.I)
_NUMBER = re.compile(r"(?<![\w^.])(\d+(?:\.\d+)?)(?![\w.]*\d)")
_UNIT_POWER = re.compile(r"\^\s*-?\d+|[²³]")
_UNIT = re.compile(  # the unit right after a number, in the compiler's wording (normalise, si_units)
    r"\s*-?\s*(m/s(?:\^\s*2|²)|m/s|(?:s|secs?|seconds?)\b|(?:m|meters?|metres?)\b(?!/)"
    r"|(?:km|kilometers?|kilometres?|ft|feet|foot|miles?|mi|min(?:s|utes?)?|h(?:rs?|ours?)?|degrees?|deg)\b"
    r"|%)", re.I)
_UNIT_NAMES = {"m/s": "m/s", "m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m", "s": "s",
               "sec": "s", "secs": "s", "second": "s", "seconds": "s"}
_VEHICLE_PARAM = re.compile(r"ind|idx|vehicle|agent|target|ref|ego|other|leader|follower", re.I)


def named_vehicles(query: str, num_vehicles: int | None = None) -> tuple[int, ...]:
    """The vehicle numbers the sentence names, in order of first mention (within ``num_vehicles``)."""
    found: list[int] = []
    for match in _LIST.finditer(query):
        for number in re.findall(r"\d+", match.group(1)):
            v = int(number)
            if v not in found and (num_vehicles is None or v < num_vehicles):
                found.append(v)
    return tuple(found)


def quantities(query: str) -> tuple[float, ...]:
    """The numbers of the sentence that are not vehicle numbers nor unit exponents, in order."""
    return tuple(value for value, _ in said_quantities(query))


def _blank(match: re.Match[str]) -> str:
    """Spaces in place of a match: the positions after it are kept, to read the units there."""
    return " " * len(match.group(0))


def said_quantities(query: str) -> tuple[tuple[float, str | None], ...]:
    """:func:`quantities` with the unit each is said in: "s", "m", "m/s", "m/s²", another unit word as
    written (lower case: "ft", "km", "min"), or None (a bare number, a point's coordinate)."""
    text = _LIST.sub(_blank, query)
    found = []
    for m in _NUMBER.finditer(_UNIT_POWER.sub(_blank, text)):
        unit = _UNIT.match(text, m.end())
        word = None if unit is None else unit.group(1).lower()
        if word is not None and word.startswith("m/s") and word != "m/s":
            word = "m/s²"
        found.append((float(m.group(1)), None if word is None else _UNIT_NAMES.get(word, word)))
    return tuple(found)


def _open_parameters(tree: ast.Module) -> tuple[str, list[ast.arg]]:
    """The main class's name and the parameters of its ``__init__`` without a default (after self)."""
    cls = main_class(tree)
    if cls is None:
        return "", []
    for node in cls.body:
        if isinstance(node, ast.FunctionDef) and node.name == "__init__":
            args = node.args
            positional = args.posonlyargs + args.args
            open_args = positional[1:len(positional) - len(args.defaults)]
            open_args += [a for a, d in zip(args.kwonlyargs, args.kw_defaults, strict=True) if d is None]
            return cls.name, open_args
    return cls.name, []


def _format(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(float(value))


def bind_parameters(code: str, query: str, num_vehicles: int | None = None) -> tuple[str, dict[str, float]]:
    """``code`` with every parameter of its main loss class's ``__init__`` that has no default given
    the sentence's value as its default (module docstring), and the values given by name. Raises
    :class:`SandboxError` naming the parameter when the sentence does not say which value it takes.
    A program that does not parse is returned unchanged (the sandbox reports it)."""
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return code, {}
    name, open_args = _open_parameters(tree)
    if not open_args:
        return code, {}
    vehicles = [float(v) for v in named_vehicles(query, num_vehicles)]
    numbers = list(quantities(query))
    wanted = {"vehicle": [a for a in open_args if _VEHICLE_PARAM.search(a.arg)]}
    wanted["quantity"] = [a for a in open_args if a not in wanted["vehicle"]]
    values: dict[str, float] = {}
    for kind, args in wanted.items():
        given = vehicles if kind == "vehicle" else numbers
        if not args:
            continue
        if len(given) != len(args):
            arg = args[min(len(given), len(args) - 1)]
            says = (f"gives {len(given)} ({', '.join(_format(g) for g in given)})" if given
                    else "gives none")
            raise SandboxError(
                f"{name}.__init__ has no default value for its parameter {arg.arg!r} and the sentence does "
                f"not say which value it takes (the program leaves {len(args)} {kind} parameter(s) open, the "
                f"sentence {says}): give {arg.arg} the value the query states as its default",
                arg.lineno)
        values.update({a.arg: g for a, g in zip(args, given, strict=True)})
    lines = code.splitlines(keepends=True)
    last_first = sorted(open_args, key=lambda a: (a.end_lineno or a.lineno, a.end_col_offset or 0),
                        reverse=True)
    for arg in last_first:
        row, col = (arg.end_lineno or arg.lineno) - 1, arg.end_col_offset or 0
        text = values[arg.arg]
        literal = str(int(text)) if _VEHICLE_PARAM.search(arg.arg) and text in vehicles else _format(text)
        line = lines[row].encode()  # ast's columns count UTF-8 bytes
        glue = "=" if arg.annotation is None else " = "
        lines[row] = (line[:col] + (glue + literal).encode() + line[col:]).decode()
    return "".join(lines), values
