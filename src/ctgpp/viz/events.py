"""Failure events of a rollout for pictures: each vehicle's first collision and first off-road step."""

from __future__ import annotations

import numpy as np

from ctgpp.metrics.collision import collision_steps, controlled_vehicle_indices
from ctgpp.metrics.offroad import offroad_steps
from ctgpp.sim.rollout import Rollout
from ctgpp.viz.scene_plot import Event


def rollout_events(rollout: Rollout) -> list[Event]:
    """One ⋆ per vehicle at its first collision, one △ at its first off-road step (future only)."""
    agents = controlled_vehicle_indices(rollout)
    future = rollout.future
    events = []
    for kind, hits in (
        ("collision", collision_steps(rollout.sim, agents, future)),
        ("offroad", offroad_steps(rollout, agents)),
    ):
        for c in np.flatnonzero(hits.any(axis=1)):
            t = future.start + int(np.argmax(hits[c]))
            agent = agents[c]
            time_s = (t - rollout.current) * rollout.dt_s
            events.append(Event(kind, rollout.sim.xy[agent, t], int(rollout.number[agent]), round(time_s, 3)))
    return events
