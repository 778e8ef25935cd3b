"""Which vehicles an episode controls, and the numbers users see and type in queries."""

from __future__ import annotations

import numpy as np

from ctgpp.scene.types import Scene

MOVING_SPEED_MPS = 0.5
"""A vehicle at this speed (m/s) or faster is moving, a slower one is at rest: the one definition
the simulator (holding vehicles at rest at the start), the training windows, the metrics and
evaluation rules over the vehicles moving at the start, the turns (a heading counts only while
moving) and the ``stop`` behaviours (stopped: not moving) use. Readers keep their own side of the
boundary (``>`` or ``>=``)."""


def controlled_vehicles(scene: Scene, step: int) -> np.ndarray:
    """Agent indices of the vehicles present at ``step``, in displayed order.

    Vehicle number k (as drawn on scene pictures and used in queries, from 0) is agent
    ``controlled_vehicles(scene, step)[k]``: the ego first when it is a vehicle, then the others by
    increasing distance to the ego (to the mean vehicle position when there is no ego), ties by index.
    """
    agents = scene.agents
    present = np.flatnonzero(agents.is_vehicle & agents.valid[:, step])
    if present.size == 0:
        return present
    if scene.ego >= 0 and scene.ego in present:
        centre = agents.xy[scene.ego, step]
    else:
        centre = agents.xy[present, step].mean(axis=0)
    dist = np.linalg.norm(agents.xy[present, step] - centre, axis=-1)
    if scene.ego >= 0:
        dist = np.where(present == scene.ego, -1.0, dist)
    order = np.lexsort((present, dist))
    return present[order]
