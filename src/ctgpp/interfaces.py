"""The types every layer shares: what a policy observes and plans (:class:`Observation`,
:class:`Plan`), the :class:`Policy` protocol, and the :class:`Rollout` of an episode.

They live here, apart from the simulator (:mod:`ctgpp.sim`), so that guidance, language, policies,
metrics and pictures can name them without importing the simulator; every module imports them from
here. Only NumPy and the scene types are imported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ctgpp.scene.types import AgentTracks, Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

__all__ = ["Observation", "Plan", "Policy", "Rollout", "StageChange"]


@dataclass(frozen=True, eq=False)
class Observation:
    """What a policy sees when it re-plans.

    tracks: every agent over the whole (padded) scene time; controlled vehicles are valid only up
    to ``step`` (their simulated past), other agents hold the log, which the simulator replays; a
    planner reads every agent only up to ``step`` and predicts the rest
    (:mod:`ctgpp.guidance.prediction`). controlled: (V,) agent indices in displayed order.
    horizon_steps: how many future steps to plan. held: the controlled vehicles the simulator keeps
    still whatever is planned for them (parked at the start,
    :func:`~ctgpp.scene.parked.parked_at_start`, with a policy that ``hold_stationary``), agent
    indices: a policy may plan them as standing still and spend nothing on them. start_step: the
    episode's first simulated step (the step of its first re-plan; ``step`` at that re-plan),
    keyword only: what a rule fixes at the start of the episode ("within 5 s", "the
    point 20 m ahead of it", the lane it changes to) is read at this step of ``tracks``.
    """

    scene: Scene
    tracks: AgentTracks
    step: int
    controlled: np.ndarray
    horizon_steps: int
    rng: np.random.Generator
    held: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    start_step: int = field(kw_only=True)

    def __repr__(self) -> str:
        return (f"Observation({self.scene.id}, step {self.step} (start {self.start_step}), "
                f"{len(self.controlled)} controlled of which {len(self.held)} held, "
                f"horizon {self.horizon_steps} steps)")

    def __post_init__(self) -> None:
        if not 0 <= self.start_step <= self.step:
            raise ValueError(f"start_step must lie in [0, step = {self.step}], got {self.start_step}")


@dataclass(frozen=True)
class StageChange:
    """What one plan stage changed at one re-plan: the ``vehicles`` (displayed numbers) whose plans
    it changed, the largest change of a planned speed (``speed_mps``) and of a planned position
    (``shift_m``) it made among them, over the plan's samples and horizon."""

    stage: str
    vehicles: tuple[int, ...]
    speed_mps: float
    shift_m: float


@dataclass(frozen=True, eq=False)
class Plan:
    """Planned world states of the controlled vehicles for the next ``horizon_steps`` steps.

    states: (V, F, 4) x m, y m, speed m/s, yaw rad. valid: (V, F) bool — an invalid step removes the
    vehicle from the scene at that step (used by log replay when a track ends). changes: what each
    plan stage changed to make it (:mod:`ctgpp.policies.stages`; empty for a policy without stages).
    """

    states: np.ndarray
    valid: np.ndarray
    changes: tuple[StageChange, ...] = ()

    def __repr__(self) -> str:
        v, f = self.states.shape[:2]
        return f"Plan({v} vehicles × {f} steps, {len(self.changes)} stage changes)"


class Policy(Protocol):
    """Plans the next seconds for every controlled vehicle from the simulated history."""

    name: str
    hold_stationary: bool  # whether the simulator keeps the vehicles parked at the start still

    def plan(self, obs: Observation) -> Plan: ...


@dataclass(frozen=True, eq=False)
class Rollout:
    """One simulated episode of a scene.

    The episode's window covers scene steps ``[first_step, first_step + num_steps)``; index
    ``current`` of the window is the simulation start (t = 0 s), earlier indices are the logged
    history, later ones the simulated future. ``sim`` holds every agent of the scene over the window
    (controlled vehicles simulated, the others replayed from the log). ``controlled``: (A,) bool.
    ``number``: (A,) int, the displayed vehicle number of controlled agents, -1 for the others
    (:attr:`roles` says what each of those is).
    ``stage_changes``: what the policy's plan stages changed, as (episode time s of the re-plan,
    change) in order (empty for a policy without stages).
    """

    scene: Scene
    first_step: int
    current: int
    sim: AgentTracks
    controlled: np.ndarray
    number: np.ndarray
    policy: str
    stage_changes: tuple[tuple[float, StageChange], ...] = ()

    def __repr__(self) -> str:
        steps = self.sim.num_steps - 1 - self.current
        return (f"Rollout({self.scene.id}, policy {self.policy}, from {self.start_s:g} s for "
                f"{steps * self.dt_s:g} s, {int(self.controlled.sum())} vehicles simulated, "
                f"{int((~self.controlled).sum())} agents replayed)")

    @property
    def roles(self) -> np.ndarray:
        """(A,) str, each agent's role in the episode, fixed at the start: "moving" (a simulated
        vehicle faster than 0.5 m/s), "at_rest" (a simulated vehicle slower than that: parked or
        waiting; the policies that hold parked vehicles keep the parked ones still) or "replayed"
        (played from the log: pedestrians, cyclists, static objects, vehicles absent at the start;
        vehicle number -1)."""
        start = self.current
        fast = self.sim.valid[:, start] & (self.sim.speed[:, start] > MOVING_SPEED_MPS)
        return np.where(self.controlled, np.where(fast, "moving", "at_rest"), "replayed")

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
