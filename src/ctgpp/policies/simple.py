"""The two simple policies of the closed-loop simulator: log replay and constant velocity.

They implement the policy interface of :mod:`ctgpp.interfaces` (:class:`~ctgpp.interfaces.Policy`)."""

from __future__ import annotations

import numpy as np

from ctgpp.interfaces import Observation, Plan

__all__ = ["ConstantVelocityPolicy", "ReplayPolicy"]


class ReplayPolicy:
    """Log replay: every vehicle follows its recorded track."""

    name = "replay"
    hold_stationary = False

    def plan(self, obs: Observation) -> Plan:
        a = obs.scene.agents
        steps = np.arange(obs.step + 1, obs.step + 1 + obs.horizon_steps)
        inside = steps < a.num_steps
        t = np.clip(steps, 0, a.num_steps - 1)
        idx = obs.controlled
        states = np.concatenate([a.xy[idx][:, t], a.speed[idx][:, t, None], a.yaw[idx][:, t, None]], axis=-1)
        return Plan(states=states, valid=a.valid[idx][:, t] & inside[None])


class ConstantVelocityPolicy:
    """Every vehicle keeps its current speed and heading."""

    name = "constvel"
    hold_stationary = True

    def plan(self, obs: Observation) -> Plan:
        tr, idx, step = obs.tracks, obs.controlled, obs.step
        xy, speed, yaw = tr.xy[idx, step], tr.speed[idx, step], tr.yaw[idx, step]  # (V, 2), (V,), (V,)
        t_s = np.arange(1, obs.horizon_steps + 1) * obs.scene.dt_s  # (F,)
        heading = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)  # (V, 2)
        pos = xy[:, None] + (speed[:, None] * t_s[None])[..., None] * heading[:, None]  # (V, F, 2)
        n = obs.horizon_steps
        states = np.concatenate(
            [pos, np.repeat(speed[:, None, None], n, 1), np.repeat(yaw[:, None, None], n, 1)], axis=-1
        )
        return Plan(states=states, valid=np.ones(states.shape[:2], dtype=bool))

