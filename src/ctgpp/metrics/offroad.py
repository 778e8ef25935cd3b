"""Off-road driving and the fail metric (DESIGN.md, Metrics; paper appendix E).

A vehicle is off-road at a step when its centre lies outside the scene's drivable area. Only
vehicles whose centre is on the drivable area at the simulation start are checked: a car parked off
the mapped road (driveways, car parks, kerbside slots the map leaves out) cannot "go" off-road, and
counting it would charge every policy for the map's gaps. Such a vehicle counts as not off-road; the
rates still divide by all controlled vehicles, so that ``fail`` is the union of the two failures over
the same vehicles.
"""

from __future__ import annotations

import numpy as np

from ctgpp.metrics.collision import collided_vehicles, controlled_vehicle_indices
from ctgpp.metrics.registry import MetricValue, register_metric
from ctgpp.sim.rollout import Rollout


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


def offroad_vehicles(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """The controlled vehicles and whether each goes off-road at any future step.

    Returns (agents (C,) int, offroad (C,) bool).
    """
    agents = controlled_vehicle_indices(rollout)
    return agents, offroad_steps(rollout, agents).any(axis=1)


def failed_vehicles(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """The controlled vehicles and whether each collides or goes off-road. (agents (C,), failed (C,))."""
    agents, collided = collided_vehicles(rollout)
    _, offroad = offroad_vehicles(rollout)
    return agents, collided | offroad


@register_metric("offroad_rate")
def offroad_rate(rollout: Rollout) -> MetricValue:
    """Fraction of the controlled vehicles that go off-road at any future step."""
    agents, offroad = offroad_vehicles(rollout)
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
