"""Turn-balanced sampling of training windows (issue 35): turns are not drowned by straight driving.

Most logged driving is straight (NGSIM's highways and arterials almost entirely; INTERACTION's
intersections 29–58 % of tracks turn, but a turn lasts a few seconds of a long track), so a uniform
draw shows the model few turns and it learns to cut or skip them. A window *turns* when one of its
moving vehicles changes heading by at least :data:`TURN_DEG` over the window's future; the sampler
draws turning windows with a chosen total probability, the rest uniformly.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

# a heading change this large within the 5.2 s future is a turn at an intersection or a roundabout
# entry, not a lane change (a lane change turns by about 5–15°) nor a gentle curve
TURN_DEG = 45.0


def window_turns(scene: Scene, step: int, future_steps: int) -> float:
    """The largest heading change (rad, absolute) of a vehicle moving at ``step`` between ``step`` and
    its last logged step within ``future_steps``; 0 when no vehicle moves."""
    a = scene.agents
    end = min(step + future_steps, a.num_steps - 1)
    moving = a.is_vehicle & a.valid[:, step] & (a.speed[:, step] >= MOVING_SPEED_MPS)
    best = 0.0
    for i in np.flatnonzero(moving):
        logged = np.flatnonzero(a.valid[i, step : end + 1])
        last = step + int(logged[-1])
        best = max(best, abs(float(wrap_angle(a.yaw[i, last] - a.yaw[i, step]))))
    return best


def turn_weights(turning: np.ndarray, share: float) -> torch.Tensor:
    """(N,) float64 sampling weights that draw the windows where ``turning`` (N,) bool with total
    probability ``share`` (when there are any; uniform within each group). Where turns already make
    up at least ``share`` of the windows, or there are none, the weights are uniform."""
    n = len(turning)
    n_turn = int(turning.sum())
    if n == 0:
        raise ValueError("no windows to sample")
    if not 0.0 <= share < 1.0:
        raise ValueError(f"turn share {share}: expected at least 0 and below 1")
    if n_turn == 0 or n_turn >= share * n:
        return torch.full((n,), 1.0 / n, dtype=torch.float64)
    weights = np.where(turning, share / n_turn, (1.0 - share) / (n - n_turn))
    return torch.from_numpy(weights)


def is_turning(angles: np.ndarray) -> np.ndarray:
    """(N,) bool: heading changes (rad) of at least :data:`TURN_DEG`."""
    return np.asarray(angles) >= math.radians(TURN_DEG)


def window_weights(
    items: list[tuple[int, int]], scenes: list[Scene], share: float, future_steps: int = 52
) -> tuple[torch.Tensor | None, int | None]:
    """Sampling weights of the windows ``items`` ((scene, step) pairs into ``scenes``) that draw those
    where a vehicle turns (:func:`window_turns` over ``future_steps``, :func:`is_turning`) with total
    probability ``share``, and how many turn; (None, None) for ``share`` 0: uniform draws."""
    if share <= 0:
        return None, None
    turning = is_turning(np.array([window_turns(scenes[s], step, future_steps) for s, step in items]))
    return turn_weights(turning, share), int(turning.sum())
