"""Leaving the lane: a vehicle farther than 2 m from every centerline running its way.

At each future step where it is valid, a vehicle's centre is compared with the scene's lane
centerlines whose direction lies within ``SAME_DIRECTION_DEG`` (45°) of its simulated heading
(``scene.lanes.centerline_distance``); it leaves its lane at the first step where the nearest of them
is more than ``LANE_LEAVE_M`` (2 m) away. 2 m is about half a lane width plus a margin: a lane
change passes at most ~1.8 m from both centerlines and does not count, a car across the lane
boundary or on the shoulder does. 45° rather than the 90° of "same direction": with 90°, a car going
straight on where its lane curves away, or across an intersection, still finds a centerline of a
crossing road within 2 m and counts as in lane; at 45° it does not, while lane changes (a few
degrees) and real turns (the connector's heading follows the car's) are unaffected.
"""

from __future__ import annotations

import math

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.scene.lanes import centerline_distance

LANE_LEAVE_M = 2.0
SAME_DIRECTION_DEG = 45.0


def lane_leave_steps(rollout: Rollout, agents: np.ndarray) -> np.ndarray:
    """(C,) window index of each vehicle's first future step > 2 m from every same-direction
    centerline, -1 if it never leaves (or the scene has no lanes)."""
    out = np.full(len(agents), -1, dtype=np.int64)
    if rollout.scene.lanes.num_lanes == 0:
        return out
    sim, f = rollout.sim, rollout.future
    index = np.arange(sim.num_steps)[f]  # (T,)
    for c, a in enumerate(agents):
        steps = index[sim.valid[a, f]]
        if steps.size == 0:
            continue
        dist = centerline_distance(
            rollout.scene.lanes,
            sim.xy[a, steps],
            sim.yaw[a, steps],
            max_heading_diff_rad=math.radians(SAME_DIRECTION_DEG),
            max_dist_m=LANE_LEAVE_M,
        )  # (T_valid,) m, inf beyond 2 m of every lane
        away = dist > LANE_LEAVE_M
        if away.any():
            out[c] = steps[np.argmax(away)]
    return out
