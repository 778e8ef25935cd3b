"""Was the query satisfied? An independent check of a rollout, one verdict per compiled part.

Each part of a compiled query is a behaviour of the vocabulary (:mod:`ctgpp.behaviours`); its verdict
is that behaviour's check, which reads only the simulated tracks, the boxes, the drivable raster and
the lane graph — never the guidance loss that steered the sampler — on the window the behaviour
states (a speed limit from when the vehicle could be under it, "slow down to" as reach and stay, ...).

A sequence ("one by one", "then": the parts' ``stage``) is judged in its order too: a part achieved
at a time (its verdict's ``done_s``: a lane reached, a turn made) before a part it waits for was
achieved (the earlier parts about its vehicles, else the stage just before:
:func:`~ctgpp.language.compiler.compiled.prerequisites`, what guidance waits for too) is not
satisfied (one that held from t = 0 asked for no move and is in order). Where either part does not
say when it was achieved, the order is not judged, and the report says so. A part whose vehicle a
later stage takes elsewhere ("move to the rightmost lane and then turn right": after the turn it
drives in another street's lane) is judged up to the time that later manoeuvre began (its verdict's
``began_s``: entering the intersection), not at the end of the episode; and a state it reaches need
only be held once, for the hold time, not to the end (``TimeWindow.once``: "slows down to 5 m/s and
then stops" holds 5 m/s for a second, then the stop takes over, as guidance hands it over:
:meth:`~ctgpp.guidance.sequence.InOrder.guiding`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

from ctgpp.behaviours import get_behaviour
from ctgpp.behaviours.timing import TimeWindow
from ctgpp.interfaces import Rollout
from ctgpp.language.compiler import CompiledQuery, QueryPart
from ctgpp.language.compiler.compiled import part_subjects, prerequisites


@dataclass(frozen=True)
class PartReport:
    """The verdict on one part of a query: its ``text``, whether it was ``satisfied``, what was
    ``measured`` (numbers with units, in words), the ``window`` it was judged on, and its measured
    ``violation`` in ``unit``."""

    text: str
    satisfied: bool
    measured: str
    window: str = ""
    violation: float = float("nan")
    unit: str = ""


def check_part(rollout: Rollout, part: QueryPart) -> PartReport:
    """The verdict and violation of one compiled part, by its behaviour (on its own, without the
    order of a sequence: :func:`check_satisfied`)."""
    return _checked(rollout, part)[0]


def check_satisfied(
    rollout: Rollout, compiled_or_parts: CompiledQuery | Sequence[QueryPart]
) -> list[PartReport]:
    """One :class:`PartReport` per part of a compiled query, measured on the rollout, a sequence's
    stages in their order (module docstring)."""
    parts = compiled_or_parts.parts if isinstance(compiled_or_parts, CompiledQuery) else compiled_or_parts
    checked = [_checked(rollout, part) for part in parts]
    found = [_until_later_stage(rollout, k, parts, checked) for k in range(len(parts))]
    reports = []
    waits = prerequisites(list(parts))
    for k, (report, done) in enumerate(found):
        earlier = [(parts[j], found[j][1]) for j in waits[k]]
        reports.append(in_order(report, done, earlier))
    return reports


def in_order(report: PartReport, done_s: float | None, earlier: Sequence[tuple[QueryPart, float | None]]
             ) -> PartReport:
    """``report`` of a part achieved at ``done_s`` (s; None: not said), judged against the parts of
    earlier stages and the times they were achieved: not satisfied when achieved before one of them
    (a part that already held at t = 0, a vehicle already in the rightmost lane, asked nothing to
    happen and is in order), "order not judged" where a time is missing."""
    if not earlier or not report.satisfied:
        return report
    unknown = [p.text for p, d in earlier if d is None]
    before = [(p.text, d) for p, d in earlier if d is not None and done_s is not None and 0.0 < done_s < d]
    if before:
        text, d = before[0]
        said = f"{report.measured}; achieved at t = {done_s:.1f} s, before '{text}' (t = {d:.1f} s)"
        return replace(report, satisfied=False, measured=said)
    if done_s is None or unknown:
        return replace(report, measured=f"{report.measured}; order not judged (no time for "
                                        f"{'this part' if done_s is None else repr(unknown[0])})")
    last = max(d for _, d in earlier if d is not None)
    return replace(report, measured=f"{report.measured}; achieved at t = {done_s:.1f} s, after the earlier "
                                    f"stage (t = {last:.1f} s)")


def _until_later_stage(
    rollout: Rollout, index: int, parts: Sequence[QueryPart],
    checked: Sequence[tuple[PartReport, float | None, float | None]],
) -> tuple[PartReport, float | None]:
    """The report and time achieved of ``parts[index]`` (``checked[index]`` on its own), judged up to
    the earliest time a part of a later stage for one of its vehicles began its manoeuvre (module
    docstring); as checked when there is none, or when the part names a time window of its own."""
    part = parts[index]
    report, done, _ = checked[index]
    later = [(q, b) for q, (_, _, b) in zip(parts, checked, strict=True)
             if q.stage > part.stage and part_subjects(q) & part_subjects(part)]
    if not later or part.window is not None:
        return report, done
    began = [b for _, b in later if b is not None]
    until = min(began) if began else None
    report, done, _ = _checked(rollout, part, TimeWindow(0.0, until, once=True))
    if until is None:
        return replace(report, measured=f"{report.measured} (a later stage takes over)"), done
    return replace(report, measured=f"{report.measured} (judged up to t = {until:.1f} s, when a later "
                                    f"stage began)"), done


def _checked(rollout: Rollout, part: QueryPart, window: TimeWindow | None = None
             ) -> tuple[PartReport, float | None, float | None]:
    """The report of ``part`` on its own (in ``window`` instead of the part's own, when given), the
    time it was achieved (None: not said or not satisfied) and the time its manoeuvre began."""
    behaviour = get_behaviour(part.rule)
    window = part.window if window is None else window
    verdict = behaviour.verdict(rollout, part.params, part.vehicles, window)
    violation = behaviour.violation(rollout, part.params, part.vehicles, window)
    report = PartReport(part.text, verdict.satisfied, verdict.measured, verdict.window, violation.value,
                        violation.unit)
    return report, verdict.done_s if verdict.satisfied else None, verdict.began_s
