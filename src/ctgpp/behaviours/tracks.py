"""What the measures and checks read of a rollout: one vehicle's start state and simulated future,
and the windows a verdict is judged on.

The start (t = 0, the state the guidance loss plans from) is the reference of every check that needs
one (the lane a vehicle starts on, its heading, its speed); the verdict is judged on the simulated
future (t > 0), from the step the sentence allows (:func:`earliest_speed_step`, :func:`held_from`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ctgpp.behaviours.base import MissingVehicle, Vehicles
from ctgpp.interfaces import Rollout
from ctgpp.metrics.collision import controlled_vehicle_indices
from ctgpp.metrics.offroad import off_the_map


@dataclass(frozen=True)
class Track:
    """One controlled vehicle: its ``number``, agent index, start state (xy0 (2,) m, yaw0 rad, speed0
    m/s at t = 0) and future (t > 0): xy (T, 2) m, yaw (T,) rad, speed (T,) m/s, valid (T,), extent (2,)
    length, width m; ``dt_s`` the step. In a time window (:mod:`~ctgpp.behaviours.timing`) the start is the
    window's, ``shift_steps`` steps after the episode's, ``hold`` asks the behaviour to hold from
    the window's first step and ``once`` only to reach and hold a state for
    :data:`~ctgpp.scene.holds.HOLD_S` (a sequence's earlier stage)."""

    number: int
    agent: int
    xy0: np.ndarray
    yaw0: float
    speed0: float
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    valid: np.ndarray
    extent: np.ndarray
    dt_s: float
    shift_steps: int = 0
    hold: bool = False
    once: bool = False

    def time(self, k: int) -> float:
        """Episode time (s) of future index k (index 0 is t = 0.1 s; in a time window,
        :mod:`~ctgpp.behaviours.timing`, ``shift_steps`` steps later)."""
        return (k + 1 + self.shift_steps) * self.dt_s

    def valid_part(self) -> Track:
        """The track with its invalid future steps dropped."""
        keep = self.valid
        return Track(self.number, self.agent, self.xy0, self.yaw0, self.speed0, self.xy[keep], self.yaw[keep],
                     self.speed[keep], self.valid[keep], self.extent, self.dt_s, self.shift_steps, self.hold,
                     self.once)


def on_the_map(rollout: Rollout, t: Track) -> Track:
    """``t`` (its valid part) up to its first step beyond the mapped area, as the metrics find it for
    a simulated vehicle (:func:`~ctgpp.metrics.offroad.beyond_map_steps`): off the drivable area where
    the raster ends, or just past the end of a lane where the mapped road stops. Where a vehicle ends
    is judged there (the map says nothing of the lanes beyond); the whole track when it never leaves
    the map or is beyond it from its first step."""
    t = t.valid_part()
    if not t.xy.size:
        return t
    beyond = ~rollout.scene.drivable.is_drivable(t.xy) & off_the_map(rollout.scene, t.xy)
    k = int(np.argmax(beyond)) if beyond.any() else len(beyond)
    if k in (0, len(beyond)):
        return t
    return Track(t.number, t.agent, t.xy0, t.yaw0, t.speed0, t.xy[:k], t.yaw[:k], t.speed[:k], t.valid[:k],
                 t.extent, t.dt_s, t.shift_steps, t.hold, t.once)


def track(rollout: Rollout, number: int) -> Track:
    """Displayed vehicle ``number``'s track; :class:`MissingVehicle` when it is not controlled."""
    hit = np.flatnonzero(rollout.number == int(number))
    if hit.size == 0:
        raise MissingVehicle(f"vehicle {number} is not controlled in this episode")
    a, sim, f, c = int(hit[0]), rollout.sim, rollout.future, rollout.current
    return Track(int(number), a, sim.xy[a, c], float(sim.yaw[a, c]), float(sim.speed[a, c]), sim.xy[a, f],
                 sim.yaw[a, f], sim.speed[a, f], sim.valid[a, f], sim.extent[a], rollout.dt_s,
                 int(getattr(rollout, "shift_steps", 0)), bool(getattr(rollout, "hold", False)),
                 bool(getattr(rollout, "once", False)))


def tracks(rollout: Rollout, vehicles: Vehicles | Sequence[int]) -> list[Track]:
    """Tracks of ``vehicles`` (displayed numbers), or of every controlled vehicle in order when None."""
    if vehicles is None:
        agents = controlled_vehicle_indices(rollout)
        numbers = sorted(int(rollout.number[a]) for a in agents)
        return [track(rollout, n) for n in numbers]
    return [track(rollout, v) for v in vehicles]


def both_valid(a: Track, b: Track) -> np.ndarray:
    """(T,) steps at which both tracks are valid."""
    return a.valid & b.valid


def earliest_speed_step(speed0: float, bound_mps: float, below: bool, dt_s: float) -> int:
    """The first future index (0: t = 0.1 s) at which a vehicle starting at ``speed0`` could be at or
    below (``below``) / at or above ``bound_mps``, at the action bounds (braking 10 m/s², accelerating
    8 m/s², DESIGN.md Dynamics). 0 when it already is."""
    from ctgpp.dynamics.unicycle import ACC_MAX_MPS2, ACC_MIN_MPS2  # torch, when a measure first runs

    gap = speed0 - bound_mps if below else bound_mps - speed0
    if gap <= 0:
        return 0
    rate = -ACC_MIN_MPS2 if below else ACC_MAX_MPS2
    return max(math.ceil(gap / rate / dt_s - 1e-9) - 1, 0)


def wrapped_deg(a: float) -> float:
    """An angle in rad wrapped to (-180, 180] degrees."""
    return math.degrees(math.atan2(math.sin(a), math.cos(a)))
