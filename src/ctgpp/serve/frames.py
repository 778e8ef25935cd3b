"""The guided episode's frames as each re-plan finishes, for the page to draw before the run ends.

The closed loop (:func:`ctgpp.sim.closed_loop.simulate`) writes each re-plan's executed steps into the
tracks its policy observes. :class:`FrameTap` keeps the last :class:`~ctgpp.policies.base.Observation`
the policy was given (:meth:`FrameTap.watch` wraps the policy's ``plan``) and, after each re-plan,
reads the steps executed since the last call: the first call also says which agents there are (the
agents of ``playback.json``'s header; the finished run's ``playback.json`` replaces what was streamed).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ctgpp.interfaces import Observation, Policy
from ctgpp.scene.types import AgentType
from ctgpp.scene.vehicles import MOVING_SPEED_MPS
from ctgpp.serve.scenes import TYPE_NAMES, agent_color
from ctgpp.sim.closed_loop import SimConfig

Frame = list[list[float] | None]  # per agent of the header: [x m, y m, yaw rad, speed m/s] or None


class FrameTap:
    """Reads an episode's executed steps as they are simulated (module docstring); ``config`` is the
    episode's (:func:`~ctgpp.sim.closed_loop.episode_config`)."""

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        self.obs: Observation | None = None
        self.sent = 0  # window steps already read
        self._rows: list[int] = []  # the header's agents: their rows of the tracks

    def watch(self, policy: Policy) -> Policy:
        """``policy``, its ``plan`` remembering each observation (the object and its class unchanged);
        a new episode (a language model's loss replaced by the compiler's) is read from its start."""
        plan = policy.plan
        self.obs, self.sent = None, 0

        def watched(obs: Observation) -> Any:
            self.obs = obs
            return plan(obs)

        setattr(policy, "plan", watched)  # noqa: B010  (an instance attribute over the method)
        return policy

    def frames(self, done: int) -> dict[str, Any] | None:
        """The steps executed up to re-plan ``done`` not read yet: ``start`` (window index of the first),
        ``frames`` (one :data:`Frame` per step), and on the first call ``header``: ``dt_s``, ``current``
        (the window index of the start), ``steps`` (the window's length), ``agents`` (number, -1:
        replayed; type, colour, box in m, moving at the start). None before the first plan."""
        obs, cfg = self.obs, self.config
        if obs is None:
            return None
        first = obs.start_step - (cfg.history_steps - 1)
        last = min(obs.start_step + done * cfg.replan_every, obs.start_step + cfg.duration_steps)
        header = self._header(obs, first) if self.sent == 0 else None
        rows = self._rows
        start, stop = self.sent, last - first + 1
        tracks = obs.tracks
        frames: list[Frame] = []
        for k in range(start, stop):
            t = first + k
            frames.append([[round(float(tracks.xy[a, t, 0]), 2), round(float(tracks.xy[a, t, 1]), 2),
                            round(float(tracks.yaw[a, t]), 3), round(float(tracks.speed[a, t]), 2)]
                           if tracks.valid[a, t] else None for a in rows])
        self.sent = max(self.sent, stop)
        return {"start": start, "frames": frames, **({"header": header} if header else {})}

    def _header(self, obs: Observation, first: int) -> dict[str, Any]:
        cfg, tracks = self.config, obs.tracks
        window = slice(first, first + cfg.history_steps + cfg.duration_steps)
        number = np.full(tracks.num_agents, -1)
        number[obs.controlled] = np.arange(len(obs.controlled))
        present = tracks.valid[:, window].any(axis=1) | (number >= 0)  # (A,)
        self._rows = [int(a) for a in np.flatnonzero(present)]
        agents = []
        for a in self._rows:
            kind = int(tracks.types[a])
            agents.append({
                "number": int(number[a]), "type": TYPE_NAMES[AgentType(kind)],
                "color": agent_color(int(number[a]), kind),
                "length": round(float(tracks.extent[a, 0]), 2), "width": round(float(tracks.extent[a, 1]), 2),
                "moving": bool(number[a] >= 0 and tracks.speed[a, obs.start_step] >= MOVING_SPEED_MPS),
            })
        return {"dt_s": obs.scene.dt_s, "current": cfg.history_steps - 1,
                "steps": cfg.history_steps + cfg.duration_steps, "agents": agents}


def on_replan_frames(tap: FrameTap, send: Callable[[dict[str, Any]], None]) -> Callable[[int], None]:
    """A callback for re-plan ``done`` that sends the new frames (nothing before the first plan)."""

    def after(done: int) -> None:
        payload = tap.frames(done)
        if payload is not None and payload["frames"]:
            send(payload)

    return after
