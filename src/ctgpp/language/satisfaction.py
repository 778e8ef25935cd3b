"""Was the query satisfied? An independent check of a rollout, one verdict per compiled part.

Each part of a compiled query is a behaviour of the vocabulary (:mod:`ctgpp.behaviours`); its verdict
is that behaviour's check, which reads only the simulated tracks, the boxes, the drivable raster and
the lane graph — never the guidance loss that steered the sampler — on the window the behaviour
states (a speed limit from when the vehicle could be under it, "slow down to" as reach and stay, ...).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from ctgpp.behaviours import get_behaviour
from ctgpp.language.compiler import CompiledQuery, QueryPart
from ctgpp.sim.rollout import Rollout


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
    """The verdict and violation of one compiled part, by its behaviour."""
    behaviour = get_behaviour(part.rule)
    verdict = behaviour.verdict(rollout, part.params, part.vehicles, part.window)
    violation = behaviour.violation(rollout, part.params, part.vehicles, part.window)
    return PartReport(part.text, verdict.satisfied, verdict.measured, verdict.window, violation.value,
                      violation.unit)


def check_satisfied(
    rollout: Rollout, compiled_or_parts: CompiledQuery | Sequence[QueryPart]
) -> list[PartReport]:
    """One :class:`PartReport` per part of a compiled query, measured on the rollout."""
    parts = compiled_or_parts.parts if isinstance(compiled_or_parts, CompiledQuery) else compiled_or_parts
    return [check_part(rollout, part) for part in parts]
