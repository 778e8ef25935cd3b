"""Off-road driving and the fail metric (DESIGN.md, Metrics; paper appendix E).

A vehicle is off-road at a step when its centre lies outside the scene's drivable area. Only
vehicles whose centre is on the drivable area at the simulation start are checked: a car parked off
the mapped road (driveways, car parks, kerbside slots the map leaves out) cannot "go" off-road, and
counting it would charge every policy for the map's gaps. Such a vehicle counts as not off-road; the
rates still divide by all controlled vehicles, so that ``fail`` is the union of the two failures over
the same vehicles.

Beyond the mapped area (:func:`beyond_map_steps`): the drivable raster is a crop around the scene and
the map has gaps, so a vehicle whose log leaves the drivable area, that drives off the edge of the
raster, or that drives on past the end of a lane where the mapped road stops (a lane with no successor
whose road ends there: NGSIM Peachtree's map is a crossroads with four cut-off arms) tells about the
map rather than about the policy. Such vehicles are reported apart, as the per-vehicle events do
(``beyond_map``, not ``offroad``): ``offroad_rate`` counts the vehicles off the road on the mapped
area, ``beyond_map_rate`` those beyond the map, both over every controlled vehicle, and the figures
over the vehicles moving at the start (``metrics.moving``) likewise. ``fail`` and the ``no_offroad``
rule's violation keep the paper's definition (any step with the centre off the drivable area, beyond
the map or not: :func:`paper_offroad_vehicles`), so that Table 1 stays comparable with the paper's.
"""

from __future__ import annotations

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.metrics.collision import collided_vehicles, controlled_vehicle_indices
from ctgpp.metrics.registry import MetricValue, register_metric
from ctgpp.scene.map_ends import map_end_points
from ctgpp.scene.types import Scene

# a vehicle first off the road within these of such an end (past it, beside its centerline) drove off the map
MAP_END_ALONG_M = (-1.0, 6.0)
MAP_END_LATERAL_M = 2.5


def offroad_steps(rollout: Rollout, agents: np.ndarray | None = None) -> np.ndarray:
    """Which of ``agents`` (default: the controlled vehicles) are off-road at each future step.

    Returns (C, T_future) bool. False at steps where the agent is invalid and for every step of an
    agent whose centre is off the drivable area at the simulation start (see the module docstring).
    """
    if agents is None:
        agents = controlled_vehicle_indices(rollout)
    sim = rollout.sim
    drivable = rollout.scene.drivable
    start = rollout.current
    on_road_at_start = sim.valid[agents, start] & drivable.is_drivable(sim.xy[agents, start])  # (C,)
    future = rollout.future
    off = ~drivable.is_drivable(sim.xy[agents, future])  # (C, T_future)
    return off & sim.valid[agents, future] & on_road_at_start[:, None]


def first_step(flags: np.ndarray, steps: slice, num_steps: int) -> np.ndarray:
    """(C,) the window index of each row's first True in ``flags`` (C, T) over ``steps``; -1 if none."""
    index = np.arange(num_steps)[steps]  # (T,)
    return np.where(flags.any(axis=1), index[np.argmax(flags, axis=1)], -1)


def beyond_map_steps(rollout: Rollout, agents: np.ndarray | None = None) -> np.ndarray:
    """When each of ``agents`` (default: the controlled vehicles) is first found beyond the mapped area.

    A vehicle is beyond the map from the first step (t ≥ 0) at which its logged centre is off the
    drivable area or off the raster (the log never drives off the road: the map does not cover where
    it went), or from its first off-road step (:func:`offroad_steps`) when its simulated centre is
    off the raster there (it drove off the edge of the crop, not off the road) or just past the end
    of a lane where the mapped road stops (:func:`map_end_points`). Returns (C,) window indices, -1
    for a vehicle that stays on the map.
    """
    if agents is None:
        agents = controlled_vehicle_indices(rollout)
    log, n = rollout.log, rollout.sim.num_steps
    from_start = slice(rollout.current, n)
    log_off = log.valid[agents, from_start] & ~rollout.scene.drivable.is_drivable(log.xy[agents, from_start])
    log_step = first_step(log_off, from_start, n)  # (C,)
    off_step = first_step(offroad_steps(rollout, agents), rollout.future, n)  # (C,)
    xy_then = rollout.sim.xy[agents, np.maximum(off_step, 0)]  # (C, 2)
    sim_step = np.where((off_step >= 0) & off_the_map(rollout.scene, xy_then), off_step, -1)
    both = np.stack([log_step, sim_step])  # (2, C)
    return np.where((both >= 0).any(axis=0), np.where(both >= 0, both, n).min(axis=0), -1)


def off_the_map(scene: Scene, xy: np.ndarray) -> np.ndarray:
    """(N, 2) world points -> (N,) bool: where the map says nothing, off the raster or just past a lane
    end where the mapped road stops (:func:`past_map_end`); a point off the road there is beyond the
    map, not off-road."""
    return np.asarray(~scene.drivable.covers(xy) | past_map_end(scene, xy))


def past_map_end(scene: Scene, xy: np.ndarray) -> np.ndarray:
    """(C, 2) world points -> (C,) bool: just past a lane end where the mapped road stops
    (:func:`map_end_points`; within :data:`MAP_END_ALONG_M` along its direction and
    :data:`MAP_END_LATERAL_M` beside it)."""
    end, unit = map_end_points(scene)
    if len(end) == 0:
        return np.zeros(len(xy), dtype=bool)
    d = np.asarray(xy, dtype=np.float64)[:, None, :] - end[None]  # (C, K, 2)
    along = (d * unit[None]).sum(-1)
    lateral = np.abs(d[..., 0] * unit[None, :, 1] - d[..., 1] * unit[None, :, 0])
    near = (along >= MAP_END_ALONG_M[0]) & (along <= MAP_END_ALONG_M[1]) & (lateral <= MAP_END_LATERAL_M)
    return np.asarray(near.any(axis=1))


def paper_offroad_vehicles(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """The controlled vehicles and whether each is off-road at any future step, as the paper counts
    it (vehicles beyond the map included). Returns (agents (C,) int, offroad (C,) bool)."""
    agents = controlled_vehicle_indices(rollout)
    return agents, np.asarray(offroad_steps(rollout, agents).any(axis=1))


def offroad_vehicles(rollout: Rollout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The controlled vehicles, whether each goes off-road on the mapped area, and whether each goes
    beyond the map (:func:`beyond_map_steps`; such a vehicle is never off-road here, as in the
    per-vehicle events). Returns (agents (C,) int, offroad (C,) bool, beyond (C,) bool)."""
    agents, offroad = paper_offroad_vehicles(rollout)
    beyond = beyond_map_steps(rollout, agents) >= 0
    return agents, offroad & ~beyond, beyond


def failed_vehicles(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """The controlled vehicles and whether each collides or goes off-road as the paper counts it
    (:func:`paper_offroad_vehicles`). (agents (C,), failed (C,))."""
    agents, collided = collided_vehicles(rollout)
    _, offroad = paper_offroad_vehicles(rollout)
    return agents, collided | offroad


@register_metric("offroad_rate")
def offroad_rate(rollout: Rollout) -> MetricValue:
    """Fraction of the controlled vehicles that go off-road on the mapped area at any future step
    (the vehicles beyond the map are counted apart: ``beyond_map_rate``)."""
    agents, offroad, _ = offroad_vehicles(rollout)
    if agents.size == 0:
        return MetricValue.invalid()
    return MetricValue(float(offroad.mean()), True)


@register_metric("beyond_map_rate")
def beyond_map_rate(rollout: Rollout) -> MetricValue:
    """Fraction of the controlled vehicles that go beyond the mapped area (:func:`beyond_map_steps`)."""
    agents, _, beyond = offroad_vehicles(rollout)
    if agents.size == 0:
        return MetricValue.invalid()
    return MetricValue(float(beyond.mean()), True)


def paper_offroad_rate(rollout: Rollout) -> MetricValue:
    """Fraction of the controlled vehicles off the drivable area at any future step, beyond the map
    or not: the paper's off-road rate, the ``no_offroad`` rule's violation."""
    agents, offroad = paper_offroad_vehicles(rollout)
    if agents.size == 0:
        return MetricValue.invalid()
    return MetricValue(float(offroad.mean()), True)


@register_metric("fail")
def fail_rate(rollout: Rollout) -> MetricValue:
    """Fraction of the controlled vehicles with any collision or off-road step (paper Table 1, fail).

    Per episode; averages over scenes are the caller's.
    """
    agents, failed = failed_vehicles(rollout)
    if agents.size == 0:
        return MetricValue.invalid()
    return MetricValue(float(failed.mean()), True)
