"""Failure events of a rollout for pictures: each vehicle's first collision and first off-road step,
read from the same per-vehicle outcomes as the metrics (``metrics.outcomes``)."""

from __future__ import annotations

from ctgpp.metrics.outcomes import vehicle_outcomes
from ctgpp.sim.rollout import Rollout
from ctgpp.viz.scene_plot import Event


def rollout_events(rollout: Rollout) -> list[Event]:
    """One ⋆ per vehicle at its first collision, one △ at its first off-road step (future only; a
    vehicle beyond the mapped area, ``offroad.beyond_map_steps``, is not marked off-road)."""
    o = vehicle_outcomes(rollout)
    events = []
    for kind, steps in (("collision", o.hit_step), ("offroad", o.offroad_step)):
        for agent, t in zip(o.agents, steps, strict=True):
            if t < 0:
                continue
            time_s = (int(t) - rollout.current) * rollout.dt_s
            events.append(Event(kind, rollout.sim.xy[agent, t], int(rollout.number[agent]), round(time_s, 3)))
    return events
