"""The policy interface of the closed-loop simulator, and the two simple policies."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ctgpp.scene.types import AgentTracks, Scene


@dataclass(frozen=True, eq=False)
class Observation:
    """What a policy sees when it re-plans.

    tracks: every agent over the whole (padded) scene time; controlled vehicles are valid only up
    to ``step`` (their simulated past), other agents hold the log. controlled: (V,) agent indices in
    displayed order. horizon_steps: how many future steps to plan. held: the controlled vehicles the
    simulator keeps still whatever is planned for them (stationary at the start, with a policy that
    ``hold_stationary``), agent indices: a policy may plan them as standing still and spend nothing on
    them.
    """

    scene: Scene
    tracks: AgentTracks
    step: int
    controlled: np.ndarray
    horizon_steps: int
    rng: np.random.Generator
    held: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


@dataclass(frozen=True, eq=False)
class Plan:
    """Planned world states of the controlled vehicles for the next ``horizon_steps`` steps.

    states: (V, F, 4) x m, y m, speed m/s, yaw rad. valid: (V, F) bool — an invalid step removes the
    vehicle from the scene at that step (used by log replay when a track ends).
    """

    states: np.ndarray
    valid: np.ndarray


class Policy(Protocol):
    """Plans the next seconds for every controlled vehicle from the simulated history."""

    name: str
    hold_stationary: bool  # whether the simulator keeps vehicles that are stationary at the start still

    def plan(self, obs: Observation) -> Plan: ...


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

