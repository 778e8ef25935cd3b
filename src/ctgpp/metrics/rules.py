"""Rule violations measured on a rollout (DESIGN.md, Metrics "rule"; paper appendix E).

These are measured on the simulated tracks, independently of the guidance losses that steer the
sampler: boxes, the drivable raster and logged speeds, over the future steps of the episode (t > 0).
Vehicles are named by their displayed numbers (``rollout.number``). Lower is better for every rule
except ``collision``, whose value is 1 when the pair never collides (the rule asked for a crash).

These are the measures of the paper's rules; :mod:`ctgpp.behaviours` joins each to its behaviour
(``ctgpp.behaviours.rule_violation`` evaluates a rule by name). ``stop_region``: a vehicle that never
enters its region counts as its speed at the simulation start — it never lost any of the speed it had
to lose there — so stopping short of the region does not satisfy the rule.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ctgpp.geometry import boxes_overlap
from ctgpp.interfaces import Rollout
from ctgpp.metrics.collision import collision_rate, controlled_vehicle_indices
from ctgpp.metrics.offroad import failed_vehicles, paper_offroad_rate


def vehicle_agents(rollout: Rollout, vehicles: int | Sequence[int] | None = None) -> np.ndarray:
    """Agent indices (C,) of displayed vehicle numbers (default: every controlled vehicle, in order)."""
    if vehicles is None:
        agents = controlled_vehicle_indices(rollout)
        return agents[np.argsort(rollout.number[agents], kind="stable")]
    wanted = [int(v) for v in np.atleast_1d(vehicles)]
    out = []
    for v in wanted:
        hit = np.flatnonzero(rollout.number == v)
        if hit.size == 0:
            raise ValueError(f"vehicle {v} is not controlled in this episode")
        out.append(int(hit[0]))
    return np.array(out, dtype=np.int64)


def _future(rollout: Rollout, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xy (C, T, 2) m, speed (C, T) m/s, valid (C, T) of ``agents`` over the future steps."""
    sim, f = rollout.sim, rollout.future
    return sim.xy[agents, f], sim.speed[agents, f], sim.valid[agents, f]


def _mean(values: np.ndarray, mask: np.ndarray) -> float:
    return float(values[mask].mean()) if mask.any() else float("nan")


def keep_distance(
    rollout: Rollout, follower: int, leader: int, min_m: float = 10.0, max_m: float = 30.0
) -> float:
    """Mean over future steps (both valid) of how far (m) the centre distance lies outside [min, max]."""
    xy, _, valid = _future(rollout, vehicle_agents(rollout, [follower, leader]))
    d = np.linalg.norm(xy[0] - xy[1], axis=-1)  # (T,)
    deviation = np.maximum(min_m - d, 0.0) + np.maximum(d - max_m, 0.0)
    return _mean(deviation, valid[0] & valid[1])


def pair_collides(rollout: Rollout, vehicle_a: int, vehicle_b: int) -> bool:
    """Whether the boxes of the two vehicles overlap at any future step."""
    a, b = vehicle_agents(rollout, [vehicle_a, vehicle_b])
    sim, f = rollout.sim, rollout.future
    both = sim.valid[a, f] & sim.valid[b, f]  # (T,)
    box_a = (sim.xy[a, f], sim.yaw[a, f], sim.extent[a])
    hit = boxes_overlap(*box_a, sim.xy[b, f], sim.yaw[b, f], sim.extent[b])
    return bool((hit & both).any())


def collision(rollout: Rollout, vehicle_a: int, vehicle_b: int) -> float:
    """1 when the pair never collides (the rule is violated), 0 when it does."""
    return 0.0 if pair_collides(rollout, vehicle_a, vehicle_b) else 1.0


def no_collision(rollout: Rollout) -> float:
    """Collision rate of the controlled vehicles (any agent, replayed ones included)."""
    return float(collision_rate(rollout).value)


def no_offroad(rollout: Rollout) -> float:
    """Off-road rate of the controlled vehicles (centre outside the drivable area), as the paper
    counts it: vehicles beyond the map included (:func:`~ctgpp.metrics.offroad.paper_offroad_rate`)."""
    return float(paper_offroad_rate(rollout).value)


def speed_limit(rollout: Rollout, limit_mps: float, vehicles: Sequence[int] | None = None) -> float:
    """Mean excess speed (m/s) over the limit, over the vehicles' valid future steps."""
    _, speed, valid = _future(rollout, vehicle_agents(rollout, vehicles))
    return _mean(np.maximum(speed - limit_mps, 0.0), valid)


def target_speed(
    rollout: Rollout,
    speed_mps: float | np.ndarray,
    vehicles: Sequence[int] | None = None,
    absolute_steps: bool = False,
) -> float:
    """Mean |speed − target| (m/s) over the vehicles' valid future steps that have a target.

    ``speed_mps``: one speed, or a table (B, S) whose row i is displayed vehicle i and whose column j
    is scene step j (``absolute_steps``) or future step j (t = 0.1 s is column 0); NaN = no target.
    """
    agents = vehicle_agents(rollout, vehicles)
    _, speed, valid = _future(rollout, agents)
    if np.ndim(speed_mps) == 0:
        target = np.full(speed.shape, float(speed_mps))
    else:
        table = np.asarray(speed_mps, dtype=np.float64)
        n_t = speed.shape[1]
        first = rollout.first_step + rollout.current + 1 if absolute_steps else 0
        cols = np.arange(first, first + n_t)
        target = np.full(speed.shape, np.nan)
        inside = cols < table.shape[1]
        target[:, inside] = table[rollout.number[agents]][:, cols[inside]]
    has = valid & ~np.isnan(target)
    return _mean(np.abs(speed - np.nan_to_num(target)), has)


def acceleration_limit(rollout: Rollout, max_mps2: float, vehicles: Sequence[int] | None = None) -> float:
    """Mean excess (m/s²) of the acceleration magnitude over the limit; longitudinal from speed
    differences, lateral = speed × yaw rate from heading differences, over steps valid at both ends."""
    agents = vehicle_agents(rollout, vehicles)
    sim, dt = rollout.sim, rollout.dt_s
    f = slice(rollout.current, sim.num_steps)  # the start and the future: differences end in the future
    speed, yaw, valid = sim.speed[agents, f], sim.yaw[agents, f], sim.valid[agents, f]
    lon = np.diff(speed, axis=1) / dt  # (C, T)
    yaw_rate = (np.diff(yaw, axis=1) + np.pi) % (2 * np.pi) - np.pi
    lat = speed[:, 1:] * yaw_rate / dt
    excess = np.maximum(np.hypot(lon, lat) - max_mps2, 0.0)
    return _mean(excess, valid[:, 1:] & valid[:, :-1])


def goal_waypoint(
    rollout: Rollout, vehicle: int | Sequence[int], x: float | Sequence[float], y: float | Sequence[float]
) -> float:
    """Mean over the vehicles of the minimum distance (m) to their goal (x, y world m) over the future."""
    xy, _, valid = _future(rollout, vehicle_agents(rollout, vehicle))
    goal = np.stack([np.atleast_1d(x), np.atleast_1d(y)], axis=-1).astype(np.float64)  # (C, 2)
    d = np.where(valid, np.linalg.norm(xy - goal[:, None], axis=-1), np.inf)  # (C, T)
    best = d.min(axis=1)
    return float(best[np.isfinite(best)].mean()) if np.isfinite(best).any() else float("nan")


def stop_region(
    rollout: Rollout,
    vehicle: int | Sequence[int],
    x: float | Sequence[float],
    y: float | Sequence[float],
    radius_m: float = 3.0,
) -> float:
    """Mean over the vehicles of the lowest speed (m/s) inside their region (a disc of ``radius_m``
    around (x, y) world m); a vehicle that never enters counts as its speed at the start."""
    agents = vehicle_agents(rollout, vehicle)
    xy, speed, valid = _future(rollout, agents)
    centre = np.stack([np.atleast_1d(x), np.atleast_1d(y)], axis=-1).astype(np.float64)  # (C, 2)
    inside = valid & (np.linalg.norm(xy - centre[:, None], axis=-1) <= radius_m)  # (C, T)
    lowest = np.where(inside, speed, np.inf).min(axis=1)
    start_speed = rollout.sim.speed[agents, rollout.current]
    return float(np.where(inside.any(axis=1), lowest, start_speed).mean())


def fail_excluding(rollout: Rollout, vehicles: Sequence[int] = ()) -> float:
    """The fail rate (collision or off-road) over the controlled vehicles other than ``vehicles``
    (displayed numbers): the pair a collision rule asks to crash is left out. NaN when none is left."""
    agents, failed = failed_vehicles(rollout)
    exempt = set(int(v) for v in vehicles)
    keep = np.array([int(rollout.number[a]) not in exempt for a in agents], dtype=bool)
    return float(failed[keep].mean()) if keep.any() else float("nan")
