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
    rf"\(\s*({NUM})\s*,\s*({NUM})\s*\)"
    rf"|\bx\s*=?\s*({NUM})(?:\s*m\b)?\s*,?\s*(?:and\s+)?y\s*=?\s*({NUM})(?:\s*m\b)?"
)
_SPEED_UNIT = (
    r"m/s|mps|m\s*s-1|(?:meters?|metres?)\s+(?:per|a|/)\s+second|km/h|kmh|kph|km\s+per\s+hour"
    r"|(?:kilometers?|kilometres?)\s+(?:per|an|/)\s+hour|mph|miles?\s+(?:per|an|/)\s+hour"
)
_SPEED = re.compile(rf"({NUM})\s*({_SPEED_UNIT})(?![²2^])")
_DIST_UNIT = r"(?:m|meters?|metres?|ft|feet)\b(?!/)"
_RANGE = re.compile(
    rf"\bbetween\s+({NUM})\s*(?:{_DIST_UNIT})?\s*(?:and|to|-)\s*({NUM})\s*({_DIST_UNIT})?"
    rf"|\b({NUM})\s*(?:-|–|to)\s*({NUM})\s*({_DIST_UNIT})"
)
_DIST = re.compile(rf"({NUM})\s*({_DIST_UNIT})")
_BARE = re.compile(rf"(?<![\w.])({NUM})(?![\w.])")
_EVERYONE = re.compile(
    r"\b(?:everyone|everybody|every\s+(?:vehicle|car|agent|one)|each\s+(?:vehicle|car)"
    r"|all\s+(?:the\s+)?(?:vehicles|cars|agents|traffic)|the\s+whole\s+scene)\b(?!\s+(?:else|other))"
)
NEGATION = re.compile(
    r"\b(?:no|not|never|avoid\w*|without|prevent\w*|nobody|none)\b|n't\b|\bdont\b|\bdoesnt\b"
)
_PRONOUN = re.compile(r"\b(?:it|its|itself|they|their|them|he|she|his|her)\b")
_MODAL_START = re.compile(r"^\s*(?:should|must|will|shall|has\s+to|have\s+to|needs?\s+to|then|also)\b")
_VERB_START = re.compile(  # a clause that starts with its verb: "... and stays below 8 m/s"
    r"^\s*(?:never|does|doesn't|is|are"
    r"|(?:stay|keep|driv|go|travel|mov|slow|speed|accelerat|brak|stop|remain|turn|chang|switch|reach|get|head"
    r"|cruis|maintain|hold|obey|follow|come|halt|park|cut|merg|collid|hit|crash|decelerat|arriv)\w*)\b"
)

_OTHERS = re.compile(  # the vehicles not named: "every other car", "the others", "everyone else"
    r"\b(?:every\s+other\s+(?:vehicle|car|agent|one)|(?:all\s+)?(?:the\s+)?other\s+(?:vehicles|cars|agents)"
    r"|all\s+the\s+others|the\s+others|(?:everyone|everybody|all)\s+else|the\s+rest(?:\s+of\s+(?:the\s+)?"
    r"(?:vehicles|cars|traffic))?|(?:every|each|any|all)\s+(?:vehicles?|cars?)\s+(?:other\s+than|except|but)"
    r"|(?:everyone|everybody)\s+(?:except|but|other\s+than))\b"
)
PASSIVE_VERB = r"(?:[\w-]+ed|[\w-]+en|hit|cut|struck|run)"
"""A verb's participle after "is" / "gets" in the passive ("rear-ended", "overtaken", "cut off")."""
_PASSIVE = re.compile(  # "vehicle 1 gets rear-ended by vehicle 2", "is overtaken by", "is cut off by": 2 acts
    r"\b(?:is|are|was|were|be|been|being|gets?|got|getting)\s+(?:\w+\s+){0,2}?"
    rf"{PASSIVE_VERB}\b[^.;]*?"
    r"\bby\s+(?:(?:vehicle|car|agent|truck)s?\s*#?\d|v\d|#\d|(?:the\s+)?ego)"
)
_GROUP = re.compile(r"\b(?:both|they|them|their|all\s+of\s+them|each\s+of\s+them|the\s+two)\b")
_ONE_BY_ONE = re.compile(r"\b(?:one\s+by\s+one|one\s+after\s+(?:the\s+)?other|in\s+turn|in\s+sequence)\b")
_SECONDS = r"(?:s|secs?|seconds?)\b"
_BETWEEN_TIMES = re.compile(  # "between 2 and 6 s", "between t = 2 s and t = 6 s", "from 2 s to 6 s"
    rf"\b(?:between|from)\s+(?:t\s*=\s*)?({NUM})\s*(?:{_SECONDS})?\s*(?:and|to|-|–)\s*(?:t\s*=\s*)?({NUM})\s*{_SECONDS}"
)
_DEADLINE = re.compile(
    rf"\b(?:within(?:\s+the\s+first)?|in(?:\s+(?:under|less\s+than|at\s+most))?|by(?:\s+the\s+time|\s+t\s*=)?"
    rf"|before(?:\s+t\s*=)?|no\s+later\s+than)\s+(?:the\s+|t\s*=\s*)?({NUM})\s*{_SECONDS}"
    rf"(?:\s+mark\b|\s+in\b|\s+(?:are|is|has|have)\s+(?:up|passed|over|elapsed|gone\s+by)\b)?"
)
_START = re.compile(
    rf"\b(?:after(?:\s+the\s+first|\s+the|\s+t\s*=)?|from(?:\s+t\s*=)?|starting(?:\s+(?:at|from|after))?(?:\s+t\s*=)?|once)"
    rf"(?:\s+|(?<==)\s*)({NUM})\s*{_SECONDS}(?:\s+(?:onwards?|on|have\s+passed|passed|in|mark))?"
)
_END = re.compile(
    rf"\b(?:for|during)\s+the\s+first\s+({NUM})\s*{_SECONDS}|\b(?:until|till|up\s+to)\s+(?:t\s*=\s*)?({NUM})\s*{_SECONDS}"
)
_AT = re.compile(  # a time point: "stops at 4 s", "at t = 4 s", "at the 4 s mark", "4 s in"
    rf"\b(?:at|around|about)\s+(?:t\s*=\s*|the\s+)?({NUM})\s*{_SECONDS}(?:\s+mark)?|\b({NUM})\s*{_SECONDS}\s+in\b"
)
_DURATION = re.compile(rf"(?<![\w.])({NUM})\s*{_SECONDS}")
_ALWAYS = re.compile(
    r"\b(?:at\s+all\s+times|always|throughout(?:\s+the\s+(?:episode|scene|drive))?|the\s+whole\s+time"
    r"|all\s+the\s+time|for\s+the\s+(?:whole|entire)\s+(?:episode|scene|drive|scenario|simulation|run|time)"
    r"|the\s+entire\s+time|at\s+any\s+time)\b"
)
_SPEED_RANGE = re.compile(
    rf"\bbetween\s+({NUM})\s*(?:and|to|-)\s*({NUM})\s*({_SPEED_UNIT})|\b({NUM})\s*(?:-|–|to)\s*({NUM})\s*({_SPEED_UNIT})"
)

# protected spans: separators inside them do not split clauses
PROTECTED = (_POINT, _BETWEEN_TIMES,
             re.compile(rf"\bbetween\s+{NUM}\s*(?:{_DIST_UNIT}|{_SPEED_UNIT})?\s*and\s+{NUM}"), _ONE_BY_ONE)
SEPARATOR = re.compile(
    r"\s*[,;]\s*(?:and\s+|while\s+|but\s+|then\s+|after\s+that,?\s+|afterwards,?\s+)*|\.\s+"
    r"|\s+(?:and\s+then|and\s+after\s+that|after\s+that|afterwards|and\s+also|and|while|whilst|then|but|also"
    r"|as\s+well\s+as|plus)\s+"
)


@dataclass(frozen=True)
class Clause:
    """One conjunct of a query. text: lower-case, with its time phrases blanked; start/end: its span in
    the query; vehicles: displayed numbers named, in order of appearance; subjects: the leading group
    of them (the clause's subject, "vehicles 1, 2 and 3 follow vehicle 4": 1, 2, 3) and objects the
    rest (4); speeds m/s; speed_ranges (lo, hi) m/s; distances m; ranges (lo, hi) m; points (x, y) m;
    bare: numbers without a unit (not vehicle numbers). Times (s from the episode start): deadline_s
    ("within 5 s"), start_s ("after 3 s"), end_s ("for the first 4 s", "until 4 s"; both: "between 2 and
    6 s"), at_s ("at 4 s": a
    time point), always ("at all times"); durations: times in seconds no time phrase reads ("a 2 s
    gap"). Flags: everyone, others ("every other car", "the others"), group ("both", "they"),
    one_by_one, negated, pronoun, modal_start ("should ..."), verb_start ("stays below ..."), passive
    (the vehicle after "by" acts: "vehicle 1 is overtaken by vehicle 2")."""

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
    subjects: tuple[int, ...] = ()
    objects: tuple[int, ...] = ()
    speed_ranges: tuple[tuple[float, float], ...] = ()
    deadline_s: float | None = None
    start_s: float | None = None
    end_s: float | None = None
    at_s: float | None = None
    durations: tuple[float, ...] = ()
    always: bool = False
    others: bool = False
    group: bool = False
    one_by_one: bool = False
    verb_start: bool = False
    passive: bool = False

    def has(self, pattern: str) -> re.Match[str] | None:
        """The first match of a regular expression in the clause's text."""
        return re.search(pattern, self.text)

    @property
    def timed(self) -> bool:
        """Whether the clause names a time window."""
        return (self.deadline_s is not None or self.start_s is not None or self.end_s is not None
                or self.at_s is not None)


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


_LIST_GLUE = re.compile(r"^(?:\s|,|&|\band\b|\bor\b|\bas\s+well\s+as\b|\bvehicles?\b|\bcars?\b)*$")


def _vehicles(text: str) -> tuple[list[tuple[int, int, int]], str]:
    """Displayed vehicle numbers with their spans (start, end, number), and the text with them blanked."""
    found: list[tuple[int, int, int]] = []
    for pattern in (_VEHICLE_LIST, _BARE_PAIR):
        for m in pattern.finditer(text):
            for d in re.finditer(r"\d+", m.group(0)):
                found.append((m.start() + d.start(), m.start() + d.end(), int(d.group(0))))
            text = _mask(text, m)
    for m in _VEHICLE.finditer(text):
        digits = next((g for g in m.groups() if g is not None), None)
        found.append((m.start(), m.end(), 0 if digits is None else int(digits)))
        text = _mask(text, m)
    found.sort()
    return found, text


_LEAD = re.compile(
    r"^(?:\s|,|#|\b(?:the|make|let|have|get|keep|for|both|and|then|also|now|please|that|i|we|want|would|like"
    r"|can|could|you|will|may|shall|should|must"
    r"|vehicles?|cars?|agents?"
    r"|trucks?|number|no\.?)\b)*$"
)


def _groups(refs: list[tuple[int, int, int]], low: str) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The leading group of vehicle references (joined by "and", ",", "&" only), when only filler
    precedes it (else no subject: "stay within 20 m of vehicle 4"), and the rest."""
    if not refs:
        return (), ()
    if not _LEAD.match(low[: refs[0][0]]):
        return (), tuple(dict.fromkeys(v for _, _, v in refs))
    lead = [refs[0][2]]
    k = 1
    while k < len(refs) and _LIST_GLUE.match(low[refs[k - 1][1] : refs[k][0]]):
        lead.append(refs[k][2])
        k += 1
    rest = [v for _, _, v in refs[k:] if v not in lead]
    return tuple(dict.fromkeys(lead)), tuple(dict.fromkeys(rest))


def _times(low: str) -> tuple[str, float | None, float | None, float | None, float | None, bool]:
    """The text with its time phrases blanked, and deadline_s, start_s, end_s, at_s, always."""
    deadline = start = end = at = None
    m = _BETWEEN_TIMES.search(low)
    if m:
        start, end, low = float(m.group(1)), float(m.group(2)), _mask(low, m)
    m = _DEADLINE.search(low)
    if m:
        deadline, low = float(m.group(1)), _mask(low, m)
    m = _START.search(low)
    if m:
        start, low = float(m.group(1)), _mask(low, m)
    m = _END.search(low)
    if m:
        end, low = float(m.group(1) or m.group(2)), _mask(low, m)
    m = _AT.search(low)
    if m:
        at, low = float(m.group(1) or m.group(2)), _mask(low, m)
    m = _ALWAYS.search(low)
    if m:
        low = _mask(low, m)
    return low, deadline, start, end, at, m is not None


def analyse(text: str, start: int) -> Clause:
    """The :class:`Clause` of ``text`` (any case), which starts at ``start`` in the query."""
    low, deadline, start_s, end_s, at_s, always = _times(text.lower())
    refs, rest = _vehicles(low)
    vehicles: list[int] = []
    for _, _, v in refs:
        if v not in vehicles:
            vehicles.append(v)
    subjects, objects = _groups(refs, low)
    points, speeds, ranges, dists, speed_ranges = [], [], [], [], []
    for m in _POINT.finditer(rest):
        g = [v for v in m.groups() if v is not None]
        points.append((float(g[0]), float(g[1])))
        rest = _mask(rest, m)
    durations = []
    for m in _DURATION.finditer(rest):  # a time no time phrase read: never a distance or a plain number
        durations.append(float(m.group(1)))
        rest = _mask(rest, m)
    for m in _SPEED_RANGE.finditer(rest):
        lo, hi, unit = (m.group(1), m.group(2), m.group(3)) if m.group(1) else m.group(4, 5, 6)
        a, b = sorted((_speed_mps(float(lo), unit), _speed_mps(float(hi), unit)))
        speed_ranges.append((a, b))
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
    others = bool(_OTHERS.search(low))
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
        everyone=bool(_EVERYONE.search(low)) and not others,
        negated=bool(NEGATION.search(low)),
        pronoun=bool(_PRONOUN.search(low)),
        modal_start=bool(_MODAL_START.search(low)),
        subjects=subjects,
        objects=objects,
        speed_ranges=tuple(speed_ranges),
        deadline_s=deadline,
        start_s=start_s,
        end_s=end_s,
        at_s=at_s,
        durations=tuple(durations),
        always=always,
        others=others,
        group=bool(_GROUP.search(low)),
        one_by_one=bool(_ONE_BY_ONE.search(low)),
        verb_start=bool(_VERB_START.search(low)),
        passive=bool(_PASSIVE.search(low)),
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
