"""A compiled query: its parts (one registered rule each, with its vehicles, steering, time window and
stage), the loss each part builds, and the readable Python code of the whole composition.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ctgpp.behaviours.timing import TimeWindow
from ctgpp.guidance import CompositeLoss, GuidanceLoss, InOrder, make_loss
from ctgpp.guidance.rules.relative import ForVehicles, SteerOnly
from ctgpp.guidance.rules.timing import During


@dataclass(frozen=True)
class QueryPart:
    """One rule of a compiled query.

    rule: registered rule name; params: its keyword parameters (units in the names: m, m/s; points
    in scene world metres); text: the clause of the query it came from and span (start, end) its
    position in the query; family: the query family ("lane_change", "keep_within", "stop", ...,
    what :mod:`ctgpp.language.satisfaction` checks); vehicles: the vehicles a global rule is
    restricted to (None: the rule's own scope, every vehicle for speed limits and the like);
    steers: the only vehicles the rule's gradient moves (None: every vehicle it involves), the
    subject of a relation to another vehicle, which then keeps driving as sampled; window: the
    episode time the clause names ("within 5 s", "after 3 s", :mod:`ctgpp.behaviours.timing`; None:
    the behaviour's own window); stage: the part's place in a sequence ("then", "one by one": 0, 1,
    ...; parts of one stage have no order among them); steers_when_held: the vehicles steered
    instead of ``steers`` when those are held still by the simulator (:class:`SteerOnly`).
    """

    rule: str
    params: dict[str, Any]
    text: str
    span: tuple[int, int]
    family: str
    vehicles: tuple[int, ...] | None = None
    steers: tuple[int, ...] | None = None
    window: TimeWindow | None = None
    stage: int = 0
    steers_when_held: tuple[int, ...] = ()

    def build(self) -> GuidanceLoss:
        """The loss of this part: the registered rule, on the steps of ``window``, restricted to
        ``vehicles`` and steering only ``steers`` when given."""
        loss = make_loss(self.rule, **self.params)
        if self.window is not None:
            loss = During(loss, self.window.start_s, self.window.end_s)
        if self.vehicles is not None:
            loss = ForVehicles(loss, list(self.vehicles))
        if self.steers is None:
            return loss
        return SteerOnly(loss, list(self.steers), list(self.steers_when_held))

    def code(self) -> str:
        """Python source of :meth:`build`."""
        args = "".join(f", {k}={v!r}" for k, v in self.params.items())
        call = f"make_loss({self.rule!r}{args})".replace("'", '"')
        if self.window is not None:
            call = f"During({call}, start_s={self.window.start_s!r}, end_s={self.window.end_s!r})"
        if self.vehicles is not None:
            call = f"ForVehicles({call}, vehicles={list(self.vehicles)})"
        if self.steers is None:
            return call
        held = f", when_held={list(self.steers_when_held)}" if self.steers_when_held else ""
        return f"SteerOnly({call}, vehicles={list(self.steers)}{held})"


@dataclass(frozen=True, eq=False)
class CompiledQuery:
    """A compiled query: the ``loss`` (a :class:`CompositeLoss` of every part, weight 1 each), its
    ``parts`` and ``code``, a readable Python rendering of the composition; ``read_as``: the query
    after normalisation (:mod:`ctgpp.language.compiler.normalise`), which the parts' spans index."""

    query: str
    loss: GuidanceLoss
    parts: list[QueryPart] = field(default_factory=list)
    code: str = ""
    read_as: str = ""


def prerequisites(parts: list[QueryPart]) -> list[tuple[int, ...]]:
    """For each part, the parts (indices) of earlier stages it waits for: those about one of its
    vehicles; a part about none of the vehicles of earlier stages waits for the whole stage just
    before it. "Vehicles 20 and 21 move to the rightmost lane one by one and then both turn right":
    vehicle 21's lane change waits for vehicle 20's, and each turn for its own vehicle's lane change
    (vehicle 20 does not stop short of its turn until vehicle 21 is in lane). "Vehicle 1 stops; after
    that vehicle 2 stops": vehicle 2's stop waits for vehicle 1's."""
    out = []
    for part in parts:
        earlier = [k for k, p in enumerate(parts) if p.stage < part.stage]
        own = [k for k in earlier if part_subjects(parts[k]) & part_subjects(part)]
        if not own and earlier:
            last = max(parts[k].stage for k in earlier)
            own = [k for k in earlier if parts[k].stage == last]
        out.append(tuple(own))
    return out


def part_subjects(part: QueryPart) -> set[int]:
    """The vehicles a part is about: its ``vehicles``, else its rule's ``vehicle`` parameter."""
    if part.vehicles is not None:
        return set(part.vehicles)
    vehicle = part.params.get("vehicle")
    return {int(vehicle)} if isinstance(vehicle, int) else set()


def in_stage_order(parts: list[QueryPart]) -> list[QueryPart]:
    """``parts`` ordered by stage, in their order within a stage: a part waits only for parts before
    it (:func:`prerequisites`), whichever order a reader listed them in ("...; all stay on the road
    throughout" after a sequence, a model's calls in any order)."""
    return sorted(parts, key=lambda p: p.stage)


def compose(parts: list[QueryPart]) -> GuidanceLoss:
    """The loss of a query's ``parts``: all of them together (:class:`CompositeLoss`), or, for a
    sequence (parts of more than one stage), each part once those it waits for are reached
    (:class:`InOrder`, :func:`prerequisites`)."""
    if len({p.stage for p in parts}) == 1:
        return CompositeLoss([(part.build(), 1.0) for part in parts])
    return InOrder([p.build() for p in parts], prerequisites(parts))


def render_code(parts: list[QueryPart]) -> str:
    """Readable Python source that builds the same loss as the compiled ``parts`` (:func:`compose`)."""
    if len({p.stage for p in parts}) > 1:
        return _render_sequence(parts)
    lines = ["from ctgpp.guidance import CompositeLoss, make_loss", *_wrapper_imports(parts)]
    lines += ["", "loss = CompositeLoss(["]
    for p in parts:
        lines.append(f"    ({p.code()}, 1.0),  # {p.text}")
    lines.append("])")
    return "\n".join(lines) + "\n"


def _render_sequence(parts: list[QueryPart]) -> str:
    waits = prerequisites(parts)
    lines = ["from ctgpp.guidance import InOrder, make_loss", *_wrapper_imports(parts), "",
             "# each part guides once the parts it waits for (waits[k]) are reached", "loss = InOrder(["]
    lines += [f"    {p.code()},  # {k}: {p.text}" for k, p in enumerate(parts)]
    lines.append(f"], waits={[list(w) for w in waits]})")
    return "\n".join(lines) + "\n"


def _wrapper_imports(parts: list[QueryPart]) -> list[str]:
    lines = []
    wrappers = [name for name, used in (("ForVehicles", any(p.vehicles is not None for p in parts)),
                                        ("SteerOnly", any(p.steers is not None for p in parts))) if used]
    if wrappers:
        lines.append(f"from ctgpp.guidance.rules.relative import {', '.join(wrappers)}")
    if any(p.window is not None for p in parts):
        lines.append("from ctgpp.guidance.rules.timing import During")
    return lines
