"""Rollouts as files people can replay: Parquet (or CSV), one row per agent per valid step."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from ctgpp.interfaces import Rollout
from ctgpp.io.atomic import atomic_path
from ctgpp.scene.types import AgentType


def rollout_table(rollout: Rollout) -> pa.Table:
    """Columns: time_s (0 at the simulation start, negative for history), agent (displayed vehicle
    number, -1 for agents that are not controlled), role (moving, at_rest or replayed:
    :attr:`Rollout.roles`), track_id, type, controlled, x, y, yaw, speed, length, width (metres,
    radians, m/s)."""
    sim = rollout.sim
    n_agents, n_steps = sim.valid.shape
    agent, step = np.nonzero(sim.valid)  # row order: agent by agent, time ascending
    time_s = (step - rollout.current) * rollout.dt_s
    type_names = np.array([t.name.lower() for t in AgentType])
    return pa.table(
        {
            "time_s": np.round(time_s, 3),
            "agent": rollout.number[agent].astype(np.int32),
            "role": rollout.roles[agent],
            "track_id": sim.ids[agent].astype(str),
            "type": type_names[sim.types[agent]],
            "controlled": rollout.controlled[agent],
            "x": sim.xy[agent, step, 0],
            "y": sim.xy[agent, step, 1],
            "yaw": sim.yaw[agent, step],
            "speed": sim.speed[agent, step],
            "length": sim.extent[agent, 0],
            "width": sim.extent[agent, 1],
        }
    )


def write_rollout(rollout: Rollout, path: Path) -> Path:
    """Write the rollout table to ``path`` (.parquet or .csv) atomically."""
    table = rollout_table(rollout)
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.suffix == ".csv":
            pacsv.write_csv(table, tmp)
        else:
            pq.write_table(table, tmp)
    return path
