"""Turn-balanced sampling of training windows (issue 35): turns are not drowned by straight driving.

Most logged driving is straight (NGSIM's highways and arterials almost entirely; INTERACTION's
intersections 29–58 % of tracks turn, but a turn lasts a few seconds of a long track), so a uniform
draw shows the model few turns and it learns to cut or skip them. A window *turns* when one of its
moving vehicles changes heading by at least :data:`TURN_DEG` over the window's future; the sampler
draws turning windows with a chosen total probability, the rest uniformly.

Data sets can be weighted too (``ctgpp train --train DIR:SPLIT*W``): a split of short scenes gives
few windows for its vehicle-seconds (a 9-s Waymo scene holds 5 windows 1 s apart, a 20-s INTERACTION
scene 17), so its windows are drawn ``W`` times as often as the others'. The turn share is taken over
those weighted draws.
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


def turn_weights(turning: np.ndarray, share: float, base: np.ndarray | None = None) -> torch.Tensor:
    """(N,) float64 sampling weights that draw the windows where ``turning`` (N,) bool with total
    probability ``share`` (when there are any), each group in proportion to ``base`` (N,) positive
    weights (None: uniform within each group). Where turns already make up at least ``share`` of the
    draws, or there are none, the weights are ``base``'s, normalised."""
    n = len(turning)
    n_turn = int(turning.sum())
    if n == 0:
        raise ValueError("no windows to sample")
    if not 0.0 <= share < 1.0:
        raise ValueError(f"turn share {share}: expected at least 0 and below 1")
    if base is None:
        if n_turn == 0 or n_turn >= share * n:
            return torch.full((n,), 1.0 / n, dtype=torch.float64)
        return torch.from_numpy(np.where(turning, share / n_turn, (1.0 - share) / (n - n_turn)))
    base = np.asarray(base, dtype=np.float64)
    if base.shape != (n,) or not (np.isfinite(base).all() and (base > 0).all()):
        raise ValueError(f"window weights: expected {n} positive numbers")
    p = base / base.sum()
    turned = float(p[turning].sum())
    if n_turn == 0 or turned >= share:
        return torch.from_numpy(p)
    return torch.from_numpy(np.where(turning, p * share / turned, p * (1.0 - share) / (1.0 - turned)))


def is_turning(angles: np.ndarray) -> np.ndarray:
    """(N,) bool: heading changes (rad) of at least :data:`TURN_DEG`."""
    return np.asarray(angles) >= math.radians(TURN_DEG)


def window_weights(
    items: list[tuple[int, int]],
    scenes: list[Scene],
    share: float,
    future_steps: int = 52,
    scene_weights: list[float] | None = None,
) -> tuple[torch.Tensor | None, int | None]:
    """Sampling weights of the windows ``items`` ((scene, step) pairs into ``scenes``): each window in
    proportion to its scene's weight in ``scene_weights`` (None: all 1), those where a vehicle turns
    (:func:`window_turns` over ``future_steps``, :func:`is_turning`) with total probability ``share``;
    and how many turn. (None, None) for uniform draws: ``share`` 0 and every scene weighted alike."""
    if scene_weights is not None and len(scene_weights) != len(scenes):
        raise ValueError(f"{len(scene_weights)} scene weights for {len(scenes)} scenes")
    base = None
    if scene_weights is not None and len(set(scene_weights)) > 1:
        base = np.array([scene_weights[s] for s, _ in items], dtype=np.float64)
    if share <= 0:
        if base is None:
            return None, None
        return torch.from_numpy(base / base.sum()), None
    turning = is_turning(np.array([window_turns(scenes[s], step, future_steps) for s, step in items]))
    return turn_weights(turning, share, base), int(turning.sum())
