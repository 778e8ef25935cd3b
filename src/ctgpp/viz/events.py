"""Failure events of a rollout for pictures: each vehicle's first collision and first off-road step,
read from the same per-vehicle outcomes as the metrics (``metrics.outcomes``, the ``events`` of
``metrics.json``), with where they happen and a one-line text for the event list."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.metrics.outcomes import vehicle_outcomes
from ctgpp.scene.types import AgentType

EVENT_KINDS = ("collision", "offroad")
AGENT_NOUNS = {
    AgentType.VEHICLE: "vehicle",
    AgentType.PEDESTRIAN: "pedestrian",
    AgentType.CYCLIST: "cyclist",
    AgentType.STATIC: "static object",
    AgentType.OTHER: "agent",
}


@dataclass(frozen=True, eq=False)
class Event:
    """Something to mark on a picture: a collision (drawn ⋆) or an off-road moment (drawn △).

    xy: (2,) world position in m (for a collision, midway between the two boxes' centres).
    agent_number: the displayed vehicle number. time_s: seconds since the simulation start (t = 0 at
    ``Rollout.current``); animations show an event from that time on. For a collision, the partner:
    ``partner_number`` its displayed number (None for a replayed agent) and ``partner`` its words
    ("vehicle 2", "vehicle 4 (held)", "a replayed pedestrian").
    """

    kind: Literal["collision", "offroad"]
    xy: np.ndarray
    agent_number: int
    time_s: float
    partner_number: int | None = None
    partner: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in EVENT_KINDS:
            raise ValueError(f"unknown event kind {self.kind!r}")
        object.__setattr__(self, "xy", np.asarray(self.xy, dtype=np.float64).reshape(2))

    @property
    def text(self) -> str:
        """One line of the event list: time, kind, who (and with whom)."""
        if self.kind == "offroad":
            return f"{self.time_s:4.1f} s  off-road   vehicle {self.agent_number}"
        partner = f" × {self.partner}" if self.partner else ""
        return f"{self.time_s:4.1f} s  collision  vehicle {self.agent_number}{partner}"

    def mirrors(self, other: Event) -> bool:
        """Whether ``other`` is the same collision seen from the other vehicle."""
        return (
            self.kind == other.kind == "collision"
            and self.partner_number == other.agent_number
            and other.partner_number == self.agent_number
            and abs(self.time_s - other.time_s) < 1e-6
        )


def distinct_events(events: Sequence[Event], until_s: float | None = None) -> list[Event]:
    """The events up to ``until_s`` (all when None) by time, a collision of two numbered vehicles once."""
    shown = [e for e in events if until_s is None or e.time_s <= until_s + 1e-9]
    shown.sort(key=lambda e: (e.time_s, EVENT_KINDS.index(e.kind), e.agent_number))
    out: list[Event] = []
    for e in shown:
        if not any(e.mirrors(kept) for kept in out):
            out.append(e)
    return out


def event_lines(events: Sequence[Event], until_s: float | None = None, max_lines: int = 12) -> list[str]:
    """The event list of a picture: one line per distinct event (see :func:`distinct_events`), at most
    ``max_lines`` of them, then how many more there are; ["none"] when there is no event."""
    shown = distinct_events(events, until_s)
    if not shown:
        return ["none"]
    lines = [e.text for e in shown[:max_lines]]
    if len(shown) > max_lines:
        lines.append(f"... and {len(shown) - max_lines} more (metrics.json)")
    return lines


def rollout_events(rollout: Rollout) -> list[Event]:
    """One ⋆ per vehicle at its first collision, one △ at its first off-road step (future only; a
    vehicle beyond the mapped area, ``offroad.beyond_map_steps``, is not marked off-road)."""
    o = vehicle_outcomes(rollout)
    sim = rollout.sim
    events = []
    for c, agent in enumerate(o.agents):
        number = int(rollout.number[agent])
        t = int(o.hit_step[c])
        if t >= 0:
            j = int(o.partner[c])
            if rollout.controlled[j]:
                partner_number: int | None = int(rollout.number[j])
                held = o.partner_kind(rollout, c) == "held"
                partner = f"vehicle {partner_number}" + (" (held)" if held else "")
            else:
                partner_number = None
                partner = "a replayed " + AGENT_NOUNS[AgentType(int(sim.types[j]))]
            xy = (sim.xy[agent, t] + sim.xy[j, t]) / 2.0
            events.append(Event("collision", xy, number, _time_s(rollout, t), partner_number, partner))
        t = int(o.offroad_step[c])
        if t >= 0:
            events.append(Event("offroad", sim.xy[agent, t], number, _time_s(rollout, t)))
    return events


def _time_s(rollout: Rollout, step: int) -> float:
    return round((step - rollout.current) * rollout.dt_s, 3)
