"""The query of an episode as pictures show it: its words and verdict in the title, the vehicles it
names highlighted."""

from __future__ import annotations

import textwrap
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

VERDICT_COLORS = {True: "#1a7f37", False: "#c62828", None: "#555555"}


@dataclass(frozen=True)
class QueryCaption:
    """text: the query as typed. satisfied: the verdict of its independent checks (None: no check
    exists, e.g. a query only the language model understood). vehicles: the displayed numbers of the
    vehicles it names (drawn highlighted)."""

    text: str
    satisfied: bool | None = None
    vehicles: frozenset[int] = frozenset()

    @classmethod
    def of(cls, text: str, satisfied: object, vehicles: Iterable[int] | None) -> QueryCaption:
        """From a ``metrics.json`` query report's ``satisfied`` (True, False or an "unknown ..." text)
        and a loss scope's vehicles (None, "every vehicle", highlights none)."""
        verdict = satisfied if isinstance(satisfied, bool) else None
        return cls(text, verdict, frozenset(int(v) for v in vehicles or ()))

    @classmethod
    def from_report(cls, report: Mapping[str, Any] | None) -> QueryCaption | None:
        """From a query report of ``metrics.json`` (``text``, ``satisfied``, ``vehicles``); None for None."""
        if report is None:
            return None
        return cls.of(str(report["text"]), report.get("satisfied"), report.get("vehicles"))

    @property
    def verdict(self) -> str:
        if self.satisfied is None:
            return "not checked (no independent check)"
        return "met ✓" if self.satisfied else "not met ✗"

    @property
    def color(self) -> str:
        """The title colour of the verdict: green met, red not met, grey unchecked."""
        return VERDICT_COLORS[self.satisfied]

    def line(self, width: int = 110) -> str:
        """``query "...": verdict``, the query shortened to fit ``width`` characters."""
        room = max(width - len(self.verdict) - 12, 20)
        return f'query "{textwrap.shorten(self.text, room, placeholder=" ...")}": {self.verdict}'
