"""Per-vehicle events of a rollout, as plain JSON-ready records: who hit whom and when, who left the
road and when, who left its lane and when (DESIGN.md, Metrics). Times are seconds after the start.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.metrics.outcomes import VehicleOutcomes, vehicle_outcomes
from ctgpp.scene.types import AgentType


def _time(rollout: Rollout, step: int) -> float:
    return round((int(step) - rollout.current) * rollout.dt_s, 3)


def _at(rollout: Rollout, step: int) -> dict[str, float] | None:
    return None if step < 0 else {"time_s": _time(rollout, step)}


def _collision(rollout: Rollout, o: VehicleOutcomes, c: int) -> dict[str, Any] | None:
    if o.hit_step[c] < 0:
        return None
    j = int(o.partner[c])
    return {
        "time_s": _time(rollout, o.hit_step[c]),
        "partner": o.partner_kind(rollout, c),
        "vehicle": int(rollout.number[j]) if rollout.controlled[j] else None,
        "kind": AgentType(int(rollout.sim.types[j])).name.lower(),
        "track": str(rollout.sim.ids[j]),
    }


def _beyond_map(rollout: Rollout, o: VehicleOutcomes, c: int) -> dict[str, Any] | None:
    step = int(o.beyond_step[c])
    if step < 0:
        return None
    a = o.agents[c]
    log = rollout.log
    log_off = log.valid[a, step] and not rollout.scene.drivable.is_drivable(log.xy[a, step])
    if log_off:
        reason = "its log leaves the mapped area"
    elif rollout.scene.drivable.covers(rollout.sim.xy[a, step]):
        reason = "it drives on past the end of the mapped road"
    else:
        reason = "it drives off the edge of the map"
    return {"time_s": _time(rollout, step), "reason": reason}


def vehicle_events(rollout: Rollout) -> list[dict[str, Any]]:
    """One record per controlled vehicle, by displayed number.

    ``vehicle``, ``track`` (its track id), ``moving`` (faster than 0.5 m/s at the start) and, each
    null when it does not happen: ``collision`` (the first: ``time_s``, ``partner`` held / moving /
    replayed, the partner's ``vehicle`` number (null for a replayed agent), ``kind`` and ``track``),
    ``offroad`` (``time_s`` of the first off-road step on the mapped area), ``beyond_map``
    (``time_s``, ``reason``: the log or the vehicle left the mapped area; not an off-road), and for
    the moving vehicles ``lane_leave`` and ``stop`` (``time_s``).
    """
    o = vehicle_outcomes(rollout)
    out = []
    for c in np.argsort(rollout.number[o.agents], kind="stable"):
        a = int(o.agents[c])
        moving = bool(o.moving[c])
        out.append(
            {
                "vehicle": int(rollout.number[a]),
                "track": str(rollout.sim.ids[a]),
                "moving": moving,
                "collision": _collision(rollout, o, c),
                "offroad": _at(rollout, o.offroad_step[c]),
                "beyond_map": _beyond_map(rollout, o, c),
                "lane_leave": _at(rollout, o.lane_step[c]) if moving else None,
                "stop": _at(rollout, o.stop_step[c]) if moving else None,
            }
        )
    return out
