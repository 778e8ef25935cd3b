"""The result of a closed-loop episode: simulated tracks beside the log they started from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctgpp.scene.types import AgentTracks, Scene


@dataclass(frozen=True, eq=False)
class Rollout:
    """One simulated episode of a scene.

    The episode's window covers scene steps ``[first_step, first_step + num_steps)``; index
    ``current`` of the window is the simulation start (t = 0 s), earlier indices are the logged
    history, later ones the simulated future. ``sim`` holds every agent of the scene over the window
    (controlled vehicles simulated, the others replayed from the log). ``controlled``: (A,) bool.
    ``number``: (A,) int, the displayed vehicle number of controlled agents, -1 for the others.
    """

    scene: Scene
    first_step: int
    current: int
    sim: AgentTracks
    controlled: np.ndarray
    number: np.ndarray
    policy: str

    @property
    def log(self) -> AgentTracks:
        """The logged tracks over the same window."""
        a = self.scene.agents
        window = slice(self.first_step, self.first_step + self.sim.num_steps)
        return AgentTracks(
            ids=a.ids,
            types=a.types,
            xy=a.xy[:, window],
            yaw=a.yaw[:, window],
            speed=a.speed[:, window],
            extent=a.extent,
            valid=a.valid[:, window],
        )

    @property
    def dt_s(self) -> float:
        return self.scene.dt_s

    @property
    def start_s(self) -> float:
        """Scene time of the simulation start in seconds."""
        return (self.first_step + self.current) * self.scene.dt_s

    @property
    def future(self) -> slice:
        """Window indices of the simulated future (t > 0)."""
        return slice(self.current + 1, self.sim.num_steps)
