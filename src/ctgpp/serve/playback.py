"""A simulated episode as the data the page animates: every agent's track over the episode's window
(logged history, then the simulated future), its colour, and the collisions and off-road moments
with where and when they happen (the same events ``scene.png`` marks)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ctgpp.api.result import Result
from ctgpp.scene.types import AgentType
from ctgpp.serve.scenes import TYPE_NAMES, agent_color
from ctgpp.viz.events import distinct_events, rollout_events


def playback(result: Result) -> dict[str, Any]:
    """``result``'s rollout for the page.

    time_s: (T,) s, 0 at the simulation start (index ``current``); agents: one record per agent
    present at some step, with its number (-1: replayed), type, colour, box (m), whether it moves at
    the start, and per step x, y (m), yaw (rad), speed (m/s), null where the agent is absent; events:
    each vehicle's first collision and off-road moment (time, where, who, with whom, a line of text);
    named: the vehicles the query names.
    """
    rollout, sim = result.rollout, result.rollout.sim
    moving = {int(e["vehicle"]): bool(e.get("moving", False)) for e in result.events}
    agents = []
    for a in np.flatnonzero(sim.valid.any(axis=1)):
        valid = sim.valid[a]
        number = int(rollout.number[a])
        agents.append({
            "number": number,
            "type": TYPE_NAMES[AgentType(int(sim.types[a]))],
            "color": agent_color(number, int(sim.types[a])),
            "length": round(float(sim.extent[a, 0]), 2),
            "width": round(float(sim.extent[a, 1]), 2),
            "moving": moving.get(number, False),
            "x": _series(sim.xy[a, :, 0], valid, 2),
            "y": _series(sim.xy[a, :, 1], valid, 2),
            "yaw": _series(sim.yaw[a], valid, 3),
            "speed": _series(sim.speed[a], valid, 2),
        })
    events = [
        {"kind": e.kind, "vehicle": e.agent_number, "partner_number": e.partner_number,
         "partner": e.partner, "time_s": e.time_s, "x": round(float(e.xy[0]), 2),
         "y": round(float(e.xy[1]), 2), "text": e.text.strip()}
        for e in distinct_events(rollout_events(rollout))
    ]
    time_s = np.round((np.arange(sim.num_steps) - rollout.current) * rollout.dt_s, 3)
    named = (result.query or {}).get("vehicles") or []
    return {"scene": result.scene.id, "policy": result.policy, "dt_s": rollout.dt_s,
            "current": rollout.current, "time_s": time_s.tolist(), "agents": agents, "events": events,
            "named": named}


def _series(values: np.ndarray, valid: np.ndarray, digits: int) -> list[float | None]:
    """(T,) values rounded to ``digits``, None where not ``valid``."""
    rounded = np.round(values.astype(np.float64), digits)
    return [float(v) if ok else None for v, ok in zip(rounded, valid, strict=True)]
