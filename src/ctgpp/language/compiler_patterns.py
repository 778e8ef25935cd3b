"""The lexicon of the offline query compiler: vehicle references, quantities and clause analysis.

Everything works on lower-case text. A :class:`Clause` is one conjunct of a query ("vehicle 3
should change to the left lane") with what was found in it: the vehicles it names (in order),
speeds (m/s), distances (m), distance ranges (m), points (x, y) (scene world m), and flags for
"everyone", negation and pronouns. Unit conversions: km/h ÷ 3.6, mph × 0.44704, ft × 0.3048; a
number without a unit in a speed or distance phrase is taken in m/s or m (the project's units).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

NUM = r"-?\d+(?:\.\d+)?(?:e[+-]?\d+)?"  # 12, -3.5, 1e12 (read whole: never as 12 of 1e12)
_VEHICLE_LIST = re.compile(  # "vehicles 1, 2 and 3", "vehicle 1, 3, and 2", "cars 4 & 5"
    r"\b(?:vehicles?|cars?|agents?)\s+(#?\d+(?:(?:\s*,\s*(?:and\s+)?|\s*(?:and|&|or)\s+)#?\d+)+)"
)
_VEHICLE = re.compile(
    r"\b(?:vehicle|car|agent|truck|veh\.?)\s*(?:#|no\.?\s*|number\s+)?(\d+)\b"
    r"|\bv(\d+)\b|#(\d+)\b"
    r"|\b(?:the\s+)?ego(?:[- ](?:vehicle|car))?\b"
)
_BARE_PAIR = re.compile(r"\b(?:make|let|have|get)\s+(\d+)\s*(?:and|&|,)\s*(\d+)\b")
_POINT = re.compile(
    rf"\(\s*({NUM})\s*,\s*({NUM})\s*\)|\bx\s*=\s*({NUM})\s*,?\s*(?:and\s+)?y\s*=\s*({NUM})"
)
_SPEED = re.compile(
    rf"({NUM})\s*(m/s|mps|m\s*s-1|(?:meters?|metres?)\s+(?:per|a|/)\s+second|km/h|kmh|kph|km\s+per\s+hour"
    r"|(?:kilometers?|kilometres?)\s+(?:per|an|/)\s+hour|mph|miles?\s+(?:per|an|/)\s+hour)"
)
_DIST_UNIT = r"(?:m|meters?|metres?|ft|feet)\b(?!/)"
_RANGE = re.compile(
    rf"\bbetween\s+({NUM})\s*(?:{_DIST_UNIT})?\s*(?:and|to|-)\s*({NUM})\s*({_DIST_UNIT})?"
    rf"|\b({NUM})\s*(?:-|–|to)\s*({NUM})\s*({_DIST_UNIT})"
)
_DIST = re.compile(rf"({NUM})\s*({_DIST_UNIT})")
_BARE = re.compile(rf"(?<![\w.])({NUM})(?![\w.])")
_EVERYONE = re.compile(
    r"\b(?:everyone|everybody|every\s+(?:vehicle|car|agent|one)|each\s+(?:vehicle|car)"
    r"|all\s+(?:the\s+)?(?:vehicles|cars|agents|traffic)|all\s+of\s+them|the\s+whole\s+scene)\b"
)
_NEGATION = re.compile(
    r"\b(?:no|not|never|avoid\w*|without|prevent\w*|nobody|none)\b|n't\b|\bdont\b|\bdoesnt\b"
)
_PRONOUN = re.compile(r"\b(?:it|its|itself|they|their|them|he|she|his|her)\b")
_MODAL_START = re.compile(r"^\s*(?:should|must|will|shall|has\s+to|have\s+to|needs?\s+to|then|also)\b")

# protected spans: separators inside them do not split clauses
PROTECTED = (_POINT, re.compile(rf"\bbetween\s+{NUM}\s*(?:{_DIST_UNIT})?\s*and\s+{NUM}"))
SEPARATOR = re.compile(
    r"\s*[,;]\s*(?:and\s+|while\s+|but\s+|then\s+)*|\.\s+"
    r"|\s+(?:and\s+then|and\s+also|and|while|whilst|then|but|also|as\s+well\s+as|plus)\s+"
)


@dataclass(frozen=True)
class Clause:
    """One conjunct of a query. text: lower-case; start/end: its span in the query; vehicles:
    displayed numbers named, in order of appearance; speeds m/s; distances m; ranges (lo, hi) m;
    points (x, y) m; bare: numbers without a unit (not vehicle numbers)."""

    text: str
    start: int
    end: int
    vehicles: tuple[int, ...]
    speeds: tuple[float, ...]
    distances: tuple[float, ...]
    ranges: tuple[tuple[float, float], ...]
    points: tuple[tuple[float, float], ...]
    bare: tuple[float, ...]
    everyone: bool
    negated: bool
    pronoun: bool
    modal_start: bool

    def has(self, pattern: str) -> re.Match[str] | None:
        """The first match of a regular expression in the clause's text."""
        return re.search(pattern, self.text)


def _mask(text: str, m: re.Match[str]) -> str:
    return text[: m.start()] + " " * (m.end() - m.start()) + text[m.end() :]


def _speed_mps(value: float, unit: str) -> float:
    unit = unit.replace(" ", "")
    if unit.startswith(("km", "kilo")) or unit == "kph":
        return round(value / 3.6, 4)
    if unit.startswith(("mph", "mile")):
        return round(value * 0.44704, 4)
    return value


def _metres(value: float, unit: str | None) -> float:
    return value * 0.3048 if unit and unit.startswith(("ft", "feet")) else value


def _vehicles(text: str) -> tuple[list[tuple[int, int]], str]:
    """Displayed vehicle numbers with their positions, and the text with them blanked."""
    found: list[tuple[int, int]] = []
    for pattern in (_VEHICLE_LIST, _BARE_PAIR):
        for m in pattern.finditer(text):
            for d in re.finditer(r"\d+", m.group(0)):
                found.append((m.start() + d.start(), int(d.group(0))))
            text = _mask(text, m)
    for m in _VEHICLE.finditer(text):
        digits = next((g for g in m.groups() if g is not None), None)
        found.append((m.start(), 0 if digits is None else int(digits)))
        text = _mask(text, m)
    found.sort()
    return found, text


def analyse(text: str, start: int) -> Clause:
    """The :class:`Clause` of ``text`` (any case), which starts at ``start`` in the query."""
    low = text.lower()
    refs, rest = _vehicles(low)
    vehicles: list[int] = []
    for _, v in refs:
        if v not in vehicles:
            vehicles.append(v)
    points, speeds, ranges, dists = [], [], [], []
    for m in _POINT.finditer(rest):
        g = [v for v in m.groups() if v is not None]
        points.append((float(g[0]), float(g[1])))
        rest = _mask(rest, m)
    for m in _SPEED.finditer(rest):
        speeds.append(_speed_mps(float(m.group(1)), m.group(2)))
        rest = _mask(rest, m)
    for m in _RANGE.finditer(rest):
        lo, hi, unit = (m.group(1), m.group(2), m.group(3)) if m.group(1) else m.group(4, 5, 6)
        a, b = sorted((_metres(float(lo), unit), _metres(float(hi), unit)))
        ranges.append((a, b))
        rest = _mask(rest, m)
    for m in _DIST.finditer(rest):
        dists.append(_metres(float(m.group(1)), m.group(2)))
        rest = _mask(rest, m)
    bare = tuple(float(m.group(1)) for m in _BARE.finditer(rest))
    return Clause(
        text=low,
        start=start,
        end=start + len(text),
        vehicles=tuple(vehicles),
        speeds=tuple(speeds),
        distances=tuple(dists),
        ranges=tuple(ranges),
        points=tuple(points),
        bare=bare,
        everyone=bool(_EVERYONE.search(low)),
        negated=bool(_NEGATION.search(low)),
        pronoun=bool(_PRONOUN.search(low)),
        modal_start=bool(_MODAL_START.search(low)),
    )


def split_points(query: str) -> list[tuple[int, int]]:
    """Spans (start, end) of the atoms of a query between separators ("and", ",", "while", "then",
    ...), ignoring separators inside protected spans (points, "between A and B")."""
    low = query.lower()
    protected = [m.span() for p in PROTECTED for m in p.finditer(low)]
    atoms, last = [], 0
    for m in SEPARATOR.finditer(low):
        if any(a < m.end() and m.start() < b for a, b in protected):
            continue
        if m.start() > last:
            atoms.append((last, m.start()))
        last = m.end()
    if last < len(query):
        atoms.append((last, len(query)))
    return [(a, b) for a, b in atoms if query[a:b].strip(" .!?")]
