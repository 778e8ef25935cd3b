"""Hand-built rollouts whose rule values can be computed by hand: cars driving straight along +x on a
road without lanes, drivable up to a chosen x."""

from __future__ import annotations

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.scene.types import AgentTracks, DrivableArea, LaneGraph, Scene

DT = 0.1
CAR = (4.0, 2.0)
T = 21  # current index 0, 20 future steps (2 s)


def no_lanes() -> LaneGraph:
    edges = np.zeros((0, 2), dtype=np.int64)
    empty = np.zeros(0, dtype=np.int64)
    offsets = np.zeros(1, dtype=np.int64)
    return LaneGraph(np.array([], dtype=str), np.zeros((0, 2)), offsets, edges, edges, empty, empty)


def hand_rollout(xy: np.ndarray, speed: np.ndarray, road_x_max: float = 1e9) -> Rollout:
    """Cars (A, T, 2) heading +x, all controlled (vehicle i = agent i), drivable where x < road_x_max."""
    n_a, n_t = speed.shape
    tracks = AgentTracks(
        ids=np.array([f"v{i}" for i in range(n_a)]),
        types=np.zeros(n_a, dtype=np.int8),
        xy=xy,
        yaw=np.zeros((n_a, n_t)),
        speed=speed,
        extent=np.array([CAR] * n_a),
        valid=np.ones((n_a, n_t), dtype=bool),
    )
    cols = np.arange(400) * 0.5 - 100.0
    mask = np.broadcast_to(cols[None, :] < road_x_max, (400, 400)).copy()
    area = DrivableArea(mask=mask, origin_xy=np.array([-100.0, -100.0]), resolution_m=0.5)
    scene = Scene("hand", "none", "hand", DT, tracks, no_lanes(), area)
    return Rollout(scene, 0, 0, tracks, np.ones(n_a, dtype=bool), np.arange(n_a), "hand")


def straight(x0: float, y: float, speed_mps: float) -> np.ndarray:
    return np.stack([x0 + speed_mps * DT * np.arange(T), np.full(T, y)], axis=-1)  # (T, 2)
