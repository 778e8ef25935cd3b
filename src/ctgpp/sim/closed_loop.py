"""The closed-loop simulator (DESIGN.md, Closed loop): 10 s, re-plan every 5 steps, others replayed."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from ctgpp.interfaces import Observation, Policy, Rollout, StageChange
from ctgpp.scene.parked import fill_parked, parked_agents, parked_at_start
from ctgpp.scene.types import AgentTracks, Scene
from ctgpp.scene.vehicles import controlled_vehicles


class EpisodeError(ValueError):
    """An episode that the scene cannot host (too little history or future)."""


@dataclass(frozen=True)
class SimConfig:
    """history_steps includes the current step; duration_steps are simulated after it (0.1 s steps);
    :func:`episode_config` fits them to a scene."""

    history_steps: int = 31
    duration_steps: int = 100
    replan_every: int = 5
    horizon_steps: int = 52


HISTORY_S = 3.0  # the log an episode starts from: the model's whole history window
MIN_HISTORY_S = 1.0  # the least history a short scene may give its episode
DURATION_S = 10.0


def episode_config(
    scene: Scene, duration_s: float = DURATION_S, history_s: float | None = None
) -> SimConfig:
    """The episode of ``duration_s`` simulated seconds that ``scene`` can host.

    ``history_s`` is the logged history before the start (the policy still looks 3 s back; steps
    before the scene's first are missing to it). None: 3 s, or less where the scene is too short for
    3 s and the duration, down to 1 s. ValueError for a duration or history that is not positive, or
    a scene too short for the episode, saying what would fit.
    """
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"--duration must be positive (got {duration_s:g})")
    if history_s is not None and not (math.isfinite(history_s) and history_s >= 0):
        raise ValueError(f"--history must be ≥ 0 (got {history_s:g})")
    dt = scene.dt_s
    duration_steps = int(round(duration_s / dt))
    if duration_steps < 1:
        raise ValueError(f"--duration {duration_s:g} is shorter than one step ({dt:g} s)")
    room = scene.agents.num_steps - 1 - duration_steps  # steps of log before the start
    if history_s is None:
        history = min(int(round(HISTORY_S / dt)), room)
        if history < int(round(MIN_HISTORY_S / dt)):
            raise EpisodeError(
                f"{scene.id} is {scene.duration_s:.1f} s long: too short for {MIN_HISTORY_S:g} s of history "
                f"and {duration_steps * dt:.1f} s of simulation (--duration "
                f"{max(scene.duration_s - MIN_HISTORY_S, 0):.1f} would fit)"
            )
    else:
        history = int(round(history_s / dt))
    return SimConfig(history_steps=history + 1, duration_steps=duration_steps)


def episode_bounds(scene: Scene, config: SimConfig = SimConfig()) -> tuple[float, float]:
    """Earliest and latest start time in seconds of an episode in ``scene``."""
    first = (config.history_steps - 1) * scene.dt_s
    last = (scene.agents.num_steps - 1 - config.duration_steps) * scene.dt_s
    return round(first, 6), round(last, 6)


def episode_starts(scene: Scene, spacing_s: float = 1.0, config: SimConfig = SimConfig()) -> list[float]:
    """Every start time with the full history and the full duration of log, ``spacing_s`` apart."""
    first, last = episode_bounds(scene, config)
    if last < first:
        return []
    return [round(float(t), 6) for t in np.arange(first, last + 1e-9, spacing_s)]


def start_step(scene: Scene, start_s: float, config: SimConfig = SimConfig()) -> int:
    """The scene step of an episode start, checked against the scene's length."""
    first, last = episode_bounds(scene, config)
    if last < first:
        raise EpisodeError(
            f"{scene.id} is {scene.duration_s:.1f} s long: too short for {first:.1f} s of history and "
            f"{config.duration_steps * scene.dt_s:.1f} s of simulation"
        )
    if not first - 1e-6 <= start_s <= last + 1e-6:
        raise EpisodeError(
            f"--start {start_s:g} is outside {first:.1f}-{last:.1f} s, the episode starts of {scene.id}"
        )
    return int(round(start_s / scene.dt_s))


def simulate(
    scene: Scene,
    policy: Policy,
    start_s: float,
    seed: int = 0,
    config: SimConfig = SimConfig(),
    on_replan: Callable[[int, int], None] | None = None,
    drive: Iterable[int] = (),
) -> Rollout:
    """Run one closed-loop episode of ``scene`` from ``start_s`` with ``policy``.

    Every ``replan_every`` steps the policy plans ``horizon_steps`` from the simulated history; the
    first ``replan_every`` planned states are executed. Vehicles present at the start are controlled;
    with ``policy.hold_stationary`` the parked ones (:func:`held_numbers`) stay where they are, except
    ``drive`` (displayed numbers: the vehicles a rule or query steers, which the policy plans).
    ``on_replan(done, total)`` reports progress.
    """
    obs = initial_observation(scene, start_s, config)
    step0, tracks, controlled = obs.step, obs.tracks, obs.controlled
    first = step0 - (config.history_steps - 1)
    window = config.history_steps + config.duration_steps
    still = controlled[held_numbers(scene, tracks, step0, controlled, policy.hold_stationary, drive)]
    rng = np.random.default_rng(seed)
    n_replans = -(-config.duration_steps // config.replan_every)
    changes: list[tuple[float, StageChange]] = []  # what the plan stages did, re-plan by re-plan
    for k in range(n_replans):
        step = step0 + k * config.replan_every
        obs = Observation(
            scene, tracks, step, controlled, config.horizon_steps, rng, held=still, start_step=step0
        )
        plan = policy.plan(obs)
        changes.extend((round((step - step0) * scene.dt_s, 6), change) for change in plan.changes)
        n = min(config.replan_every, step0 + config.duration_steps - step)
        exe = slice(step + 1, step + 1 + n)
        tracks.xy[controlled, exe] = plan.states[:, :n, :2]
        tracks.speed[controlled, exe] = plan.states[:, :n, 2]
        tracks.yaw[controlled, exe] = plan.states[:, :n, 3]
        tracks.valid[controlled, exe] = plan.valid[:, :n]
        if len(still):
            tracks.xy[still, exe] = tracks.xy[still, step0, None]
            tracks.yaw[still, exe] = tracks.yaw[still, step0, None]
            tracks.speed[still, exe] = 0.0
            tracks.valid[still, exe] = True
        if on_replan is not None:
            on_replan(k + 1, n_replans)
    sim = _slice(tracks, first, first + window)
    number = np.full(scene.agents.num_agents, -1)
    number[controlled] = np.arange(len(controlled))
    is_controlled = number >= 0
    return Rollout(scene, first, config.history_steps - 1, sim, is_controlled, number, policy.name,
                   tuple(changes))


def held_numbers(
    scene: Scene,
    tracks: AgentTracks,
    step: int,
    controlled: np.ndarray,
    hold_stationary: bool,
    drive: Iterable[int] = (),
) -> np.ndarray:
    """The displayed numbers (H,) of the ``controlled`` vehicles (V,) the simulator holds still: with
    ``hold_stationary``, those parked at ``step`` (:func:`~ctgpp.scene.parked.parked_at_start`: from
    ``tracks`` up to ``step`` over the model's 3 s history and ``scene``'s lanes) and not in ``drive``."""
    if not hold_stationary:
        return np.zeros(0, dtype=np.int64)
    history = int(round(HISTORY_S / scene.dt_s)) + 1
    parked = parked_at_start(tracks, scene.lanes, step, controlled, history)  # (V,)
    parked[np.asarray(sorted({int(v) for v in drive} & set(range(len(controlled)))), dtype=np.int64)] = False
    return np.flatnonzero(parked)


def initial_observation(scene: Scene, start_s: float, config: SimConfig = SimConfig()) -> Observation:
    """What a policy sees at the start of an episode: the log up to the start for the controlled
    vehicles (in displayed order), the whole log for the others, padded past the scene's end, with
    parked agents held at their place where the log has not seen them (:func:`fill_parked`)."""
    step0 = start_step(scene, start_s, config)
    first = step0 - (config.history_steps - 1)
    window = config.history_steps + config.duration_steps
    tracks = _padded(scene.agents, first + window + config.horizon_steps)
    controlled = controlled_vehicles(scene, step0)
    number = np.full(scene.agents.num_agents, -1)
    number[controlled] = np.arange(len(controlled))
    fill_parked(tracks, scene.agents, parked_agents(scene.agents, number))
    tracks.valid[controlled, step0 + 1 :] = False
    return Observation(
        scene, tracks, step0, controlled, config.horizon_steps, np.random.default_rng(0), start_step=step0
    )


def _padded(a: AgentTracks, n_steps: int) -> AgentTracks:
    """A writable copy of ``a`` padded (invalid) to at least ``n_steps`` steps."""
    pad = max(n_steps - a.num_steps, 0)

    def grow(x: np.ndarray) -> np.ndarray:
        return np.pad(x, [(0, 0), (0, pad)] + [(0, 0)] * (x.ndim - 2)).copy()

    return AgentTracks(a.ids, a.types, grow(a.xy), grow(a.yaw), grow(a.speed), a.extent.copy(), grow(a.valid))


def _slice(a: AgentTracks, lo: int, hi: int) -> AgentTracks:
    s = slice(lo, hi)
    return AgentTracks(a.ids, a.types, a.xy[:, s], a.yaw[:, s], a.speed[:, s], a.extent, a.valid[:, s])
