"""Where a query splits into clauses: the shortest runs of pieces (:func:`split_points`, at "and",
",", ";", "while", "then", ...) that some family recognises (:func:`recognise`), each with its family
and handler.

A piece that only names vehicles or times ("vehicle 1" in "vehicle 1 and vehicle 2 collide", "for car
3", "within 5 s", "one by one") joins its neighbour; any other piece that no family recognises makes the
query unsupported (:class:`UnsupportedQuery`).
"""

from __future__ import annotations

import re
from typing import Any

from ctgpp.language.compiler.families import recognise
from ctgpp.language.compiler.patterns import Clause, analyse, split_points
from ctgpp.language.compiler.refusals import unsupported

_FILLER = re.compile(
    r"\b(?:vehicles?|cars?|agents?|trucks?|veh|ego|the|and|or|both|each|other|for|make|let|have|get|also|please"
    r"|should|must|will|number|no)\b|\bv?\d+\b|[#.,;&!?]"
)


def segments(query: str) -> list[tuple[Clause, str, Any]]:
    """Clauses of the query with their family and handler: the shortest run of atoms that some family
    recognises; a trailing run that none recognises joins the previous clause."""
    atoms = split_points(query)
    if not atoms:
        raise unsupported(query, query)
    out: list[tuple[Clause, str, Any]] = []
    i = 0
    while i < len(atoms):
        for j in range(i, len(atoms)):
            start, end = atoms[i][0], atoms[j][1]
            clause = analyse(query[start:end], start)
            found = recognise(clause)
            if found is not None:
                out.append((clause, *found))
                i = j + 1
                break
            if not is_filler(query[atoms[j][0] : atoms[j][1]]):  # only vehicle lists join the next piece
                raise unsupported(query[start:end], query)
        else:
            rest = query[atoms[i][0] : atoms[-1][1]]
            if not out or not is_filler(rest):
                raise unsupported(rest, query)
            start = out[-1][0].start
            clause = analyse(query[start : atoms[-1][1]], start)
            found = recognise(clause)
            if found is None:
                raise unsupported(rest, query)
            out[-1:] = [(clause, *found)]
            i = len(atoms)
    return out


def is_filler(text: str) -> bool:
    """Whether a piece of a query only names vehicles or times ("vehicle 1", "for car 3", "make 2",
    "within 5 s", "one by one"): such a piece joins its neighbour; any other word that no family
    recognises makes the query unsupported."""
    blank = analyse(text, 0).text  # time phrases blanked
    blank = re.sub(r"\b(?:one\s+by\s+one|one\s+after\s+(?:the\s+)?other|in\s+turn)\b", " ", blank)
    return not _FILLER.sub(" ", blank).strip()
