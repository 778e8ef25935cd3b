"""The agents a window is conditioned on (DESIGN.md, Model: the scene the model sees is the whole scene).

A window samples some vehicles (their futures are denoised) and is conditioned on every other agent
near them whose future the simulator knows:

- held vehicles, stationary at the start of an episode: they stand still at their current pose;
- replayed agents (pedestrians, cyclists, static obstacles, vehicles the simulator replays from the
  log): their future as the scene's tracks hold it — the log in a training window; at inference the
  policy builds the window on what a plan knows (:func:`ctgpp.guidance.prediction.known_tracks`: the
  past, and from the current step a constant speed and yaw rate), never the logged future.

Training presents the same kinds of scene (:func:`training_roles`): vehicles at rest at the window's
start that the log keeps there over the window's future are held (standing still) half of the time
and sampled otherwise, so the model learns both to drive around parked cars and to start from rest;
a vehicle at rest that the log moves on within the future is never held, as a held vehicle that the
logged futures of the others drive through would teach the model to drive through held vehicles; a
few moving vehicles are replayed from the log, as vehicles that enter an episode later are; every
other agent type is replayed.
"""

from __future__ import annotations

import enum
import zlib
from dataclasses import dataclass

import numpy as np

from ctgpp.geometry import world_to_local, wrap_angle
from ctgpp.scene.types import AgentType, Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS, controlled_vehicles

STAYS_WITHIN_M = 1.0  # a training window holds a vehicle at rest only if its log stays this close


class Role(enum.IntEnum):
    """What a window does with an agent's future."""

    SAMPLED = 0  # denoised: the model's output
    HELD = 1  # known: standing still at its current pose
    REPLAYED = 2  # known: its future in the window's tracks (logged in training, predicted at inference)


@dataclass(frozen=True)
class ContextConfig:
    """Which agents condition a window, and how training assigns roles.

    max_context: at most this many context agents, nearest to a sampled vehicle first; radius_m: only
    agents this close to a sampled vehicle at the current step (the social radius plus what an agent
    can close in the next seconds). held_prob: the chance that a vehicle at rest at a training window's
    start is held rather than sampled; replay_prob: the chance that a moving one is replayed.
    """

    max_context: int = 24
    radius_m: float = 40.0
    held_prob: float = 0.5
    replay_prob: float = 0.1


@dataclass(frozen=True, eq=False)
class ContextAgents:
    """C conditioning agents of one window, numpy arrays; T = history + future steps.

    index (C,) into ``scene.agents``; role (C,) :class:`Role` (HELD or REPLAYED); type (C,)
    :class:`AgentType`; pose (C, 3) world x, y, yaw at the current step; extent (C, 2) length, width
    m; states (C, T, 4) (x m, y m, speed m/s, yaw rad) in each agent's own current frame — logged
    history, then the known future; valid (C, T).
    """

    index: np.ndarray
    role: np.ndarray
    type: np.ndarray
    pose: np.ndarray
    extent: np.ndarray
    states: np.ndarray
    valid: np.ndarray

    @property
    def num_agents(self) -> int:
        return int(self.index.shape[0])


def training_roles(
    scene: Scene,
    step: int,
    max_sampled: int,
    config: ContextConfig = ContextConfig(),
    future_steps: int = 52,
) -> tuple[np.ndarray, np.ndarray]:
    """Roles of a training window at ``step``: (sampled (M,), held (K,)) agent indices.

    Vehicles present at ``step`` in displayed order; at rest and kept there by the log over the next
    ``future_steps`` (:func:`stays_put`): held with ``held_prob``, else sampled; at rest but moving on:
    sampled; moving: replayed with ``replay_prob``, else sampled; sampled beyond ``max_sampled`` are
    replayed. Every agent neither sampled nor held is replayed. The draws are fixed by the scene id
    and step, so a window is the same in every epoch and after a resumed training.
    """
    rng = np.random.default_rng([zlib.crc32(scene.id.encode()), step])
    vehicles = controlled_vehicles(scene, step)
    at_rest = scene.agents.speed[vehicles, step] < MOVING_SPEED_MPS
    draw = rng.random(len(vehicles))
    held = at_rest & stays_put(scene, vehicles, step, future_steps) & (draw < config.held_prob)
    replayed = ~at_rest & (draw < config.replay_prob)
    sampled = vehicles[~held & ~replayed][:max_sampled]
    return sampled, vehicles[held]


def stays_put(scene: Scene, vehicles: np.ndarray, step: int, future_steps: int) -> np.ndarray:
    """(V,) bool: whether the log keeps each vehicle within ``STAYS_WITHIN_M`` of where it is at
    ``step`` over its logged steps among the next ``future_steps`` (False with none logged)."""
    a = scene.agents
    t = np.arange(step + 1, min(step + 1 + future_steps, a.num_steps))
    if len(vehicles) == 0 or len(t) == 0:
        return np.zeros(len(vehicles), dtype=bool)
    gap = np.linalg.norm(a.xy[vehicles][:, t] - a.xy[vehicles, step][:, None], axis=-1)  # (V, T)
    logged = a.valid[vehicles][:, t]
    far = np.where(logged, gap, 0.0).max(axis=1) > STAYS_WITHIN_M
    return logged.any(axis=1) & ~far


def standing_vehicles(scene: Scene, step: int, exclude: np.ndarray, future_steps: int) -> np.ndarray:
    """The vehicles present at ``step``, not in ``exclude``, at rest and kept within
    ``STAYS_WITHIN_M`` by ``scene``'s tracks over the next ``future_steps``: parked cars the simulator
    replays standing still. A window gives them the held role, as training gives it to every vehicle
    at rest that its log keeps there (:func:`training_roles`), and never to a replayed one."""
    a = scene.agents
    present = np.flatnonzero(a.is_vehicle & a.valid[:, step])
    candidates = present[~np.isin(present, exclude) & (a.speed[present, step] < MOVING_SPEED_MPS)]
    return candidates[stays_put(scene, candidates, step, future_steps)]


def select_context(
    scene: Scene,
    step: int,
    sampled: np.ndarray,
    held: np.ndarray,
    history_steps: int,
    future_steps: int,
    config: ContextConfig = ContextConfig(),
) -> ContextAgents:
    """The context of a window sampling ``sampled`` at ``step``: ``held`` vehicles stand still, every
    other agent present at ``step`` follows ``scene``'s tracks (the log in training; at inference what
    the policy gives: the simulated past and the predicted future).
    """
    a = scene.agents
    present = np.flatnonzero(a.valid[:, step])
    candidates = present[~np.isin(present, sampled)]
    if len(sampled) == 0 or len(candidates) == 0 or config.max_context == 0:
        return _empty(history_steps + future_steps)
    gap = a.xy[candidates, step][:, None] - a.xy[sampled, step][None]  # (K, M, 2)
    dist = np.sqrt((gap**2).sum(-1)).min(axis=1)  # (K,) to the nearest sampled vehicle
    near = np.flatnonzero(dist <= config.radius_m)
    order = near[np.lexsort((candidates[near], dist[near]))][: config.max_context]
    index = candidates[order]
    role = np.where(np.isin(index, held), Role.HELD, Role.REPLAYED).astype(np.int8)
    pose = np.concatenate([a.xy[index, step], a.yaw[index, step][:, None]], axis=-1)  # (C, 3)
    steps = np.arange(step - history_steps + 1, step + future_steps + 1)  # (T,)
    inside = (steps >= 0) & (steps < a.num_steps)
    t = np.clip(steps, 0, a.num_steps - 1)
    valid = a.valid[index][:, t] & inside  # (C, T)
    xy = world_to_local(a.xy[index][:, t], pose[:, None, :2], pose[:, None, 2])  # (C, T, 2)
    yaw = wrap_angle(a.yaw[index][:, t] - pose[:, None, 2])
    states = np.concatenate([xy, a.speed[index][:, t, None], yaw[..., None]], axis=-1)  # (C, T, 4)
    still = role == Role.HELD
    future = slice(history_steps, None)
    states[still, future] = 0.0  # at its current pose, at rest, from the next step on
    valid[still, future] = True
    states = np.where(valid[..., None], states, 0.0)
    return ContextAgents(
        index=index,
        role=role,
        type=a.types[index].astype(np.int8),
        pose=pose,
        extent=a.extent[index].astype(np.float32),
        states=states.astype(np.float32),
        valid=valid,
    )


def _empty(n_steps: int) -> ContextAgents:
    return ContextAgents(
        index=np.zeros(0, dtype=np.int64),
        role=np.zeros(0, dtype=np.int8),
        type=np.zeros(0, dtype=np.int8),
        pose=np.zeros((0, 3)),
        extent=np.zeros((0, 2), dtype=np.float32),
        states=np.zeros((0, n_steps, 4), dtype=np.float32),
        valid=np.zeros((0, n_steps), dtype=bool),
    )


NUM_TYPES = len(AgentType)
NUM_ROLES = len(Role)
