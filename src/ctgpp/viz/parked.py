"""Parked agents outside the log's view, so that pictures do not show them popping in and out.

A logged scene holds a parked car only while the sensors see it: in nuScenes scene-0103, all 31
vehicles that first appear in the 10 s after a 3 s start stay within a metre of one place over their
whole track; they are parked, logged only once the ego comes close. The simulator replays
them as logged (present only while seen). Pictures draw such an agent faintly, at its logged place,
over the steps of the window where the log does not hold it, and solid where it does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctgpp.scene.types import AgentTracks, AgentType

PARKED_SPREAD_M = 1.0  # a track whose positions all lie within this of their median is parked


@dataclass(frozen=True, eq=False)
class ParkedAgents:
    """Agents that never move while logged. agents: (P,) indices; xy: (P, 2) m; yaw: (P,) rad."""

    agents: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray

    def unseen_at(self, valid: np.ndarray, indices: np.ndarray | int) -> ParkedAgents:
        """The parked agents that ``valid`` (A, T) does not hold at one of ``indices`` at least."""
        idx = np.atleast_1d(indices)
        keep = ~valid[self.agents][:, idx].all(axis=1)  # (P,)
        return ParkedAgents(self.agents[keep], self.xy[keep], self.yaw[keep])


def parked_agents(
    tracks: AgentTracks, numbers: np.ndarray, spread_m: float = PARKED_SPREAD_M
) -> ParkedAgents:
    """The replayed (``numbers`` < 0) non-pedestrian agents of ``tracks`` (A, T) that are logged at
    some step and stay within ``spread_m`` of their median position; placed at their median
    position and the yaw of their first logged step."""
    agents, xy, yaw = [], [], []
    for a in np.flatnonzero((np.asarray(numbers) < 0) & tracks.valid.any(axis=1)):
        if tracks.types[a] == AgentType.PEDESTRIAN:
            continue
        seen = tracks.valid[a]
        points = tracks.xy[a, seen]  # (n_seen, 2)
        centre = np.median(points, axis=0)
        if np.linalg.norm(points - centre, axis=-1).max() <= spread_m:
            agents.append(int(a))
            xy.append(centre)
            yaw.append(float(tracks.yaw[a, np.argmax(seen)]))
    return ParkedAgents(np.array(agents, dtype=np.int64), np.array(xy).reshape(-1, 2), np.array(yaw))
