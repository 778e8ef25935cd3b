"""Was the query satisfied? An independent check of a rollout, one verdict per compiled part.

The checks read only the simulated tracks (``rollout.sim`` over the simulated future, t > 0), the
boxes, the drivable raster and the lane graph — never the guidance loss that steered the sampler.
Each returns whether the part holds and what was measured, in words. Tolerances:

- collision: the pair's oriented boxes overlap at some step; rear-end: they overlap and at the first
  overlap the vehicle's centre is behind the target's (in the target's frame) and their headings
  differ by less than 60°; no collisions: no vehicle in scope overlaps any valid agent.
- keep within d: the largest centre distance ≤ d + 1 m; keep between lo and hi: every distance in
  [lo - 1, hi + 1] m; stay away d: the smallest distance ≥ d - 0.5 m.
- speed limit: the highest speed ≤ limit + 0.5 m/s; target speed: the mean |speed - target| over the
  last 5 s ≤ 1 m/s; stop: the lowest speed < 0.5 m/s; stop in a region: the lowest speed while
  inside the region < 0.5 m/s; reach: the closest approach ≤ 2 m; stay on the road: no centre
  leaves the drivable area (vehicles that start off it excluded, as in the fail metric).
- lane rules (a turn: the heading change while moving): see :mod:`ctgpp.language.satisfaction_lanes`;
  same direction: headings within 30° at the end; stay on a side: the lateral coordinate in the
  other's frame has the right sign at every step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.language import satisfaction_lanes as lanes_check
from ctgpp.language.compiler import CompiledQuery, QueryPart
from ctgpp.metrics.boxes import boxes_overlap
from ctgpp.metrics.collision import collision_steps, controlled_vehicle_indices
from ctgpp.metrics.offroad import offroad_steps
from ctgpp.sim.rollout import Rollout

STOP_SPEED_MPS = 0.5
SPEED_TOL_MPS = 0.5
TARGET_TOL_MPS = 1.0
TARGET_WINDOW_S = 5.0
NEAR_TOL_M = 1.0
AWAY_TOL_M = 0.5
REACH_TOL_M = 2.0
SAME_DIRECTION_DEG = 30.0
REAR_END_MAX_DEG = 60.0


@dataclass(frozen=True)
class PartReport:
    """The verdict on one part of a query: its ``text``, whether it was ``satisfied`` and what was
    ``measured`` (numbers with units, in words)."""

    text: str
    satisfied: bool
    measured: str


class _Missing(Exception):
    """A vehicle of the part is not controlled in the rollout."""


@dataclass(frozen=True)
class _Track:
    """One agent over the future steps: xy (T, 2) m, yaw (T,) rad, speed (T,) m/s, valid (T,), extent (2,)."""

    agent: int
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    valid: np.ndarray
    extent: np.ndarray


def _track(rollout: Rollout, number: int) -> _Track:
    hit = np.flatnonzero(rollout.number == int(number))
    if hit.size == 0:
        raise _Missing(f"vehicle {number} is not controlled in this episode")
    a, sim, f = int(hit[0]), rollout.sim, rollout.future
    return _Track(a, sim.xy[a, f], sim.yaw[a, f], sim.speed[a, f], sim.valid[a, f], sim.extent[a])


def _scope(rollout: Rollout, part: QueryPart) -> list[_Track]:
    """Tracks of the vehicles a global part applies to (all controlled vehicles when unrestricted)."""
    if part.vehicles is not None:
        return [_track(rollout, v) for v in part.vehicles]
    agents = controlled_vehicle_indices(rollout)
    return [_track(rollout, int(rollout.number[a])) for a in agents[np.argsort(rollout.number[agents])]]


def _both(a: _Track, b: _Track) -> np.ndarray:
    return a.valid & b.valid


def _distances(rollout: Rollout, part: QueryPart, keys: tuple[str, str]) -> np.ndarray:
    a, b = (_track(rollout, part.params[k]) for k in keys)
    return np.linalg.norm(a.xy - b.xy, axis=-1)[_both(a, b)]


def _collision(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    a, b = _track(rollout, part.params["vehicle_a"]), _track(rollout, part.params["vehicle_b"])
    hit = boxes_overlap(a.xy, a.yaw, a.extent, b.xy, b.yaw, b.extent) & _both(a, b)
    if hit.any():
        return True, f"boxes overlap from t = {(np.argmax(hit) + 1) * rollout.dt_s:.1f} s"
    d = np.linalg.norm(a.xy - b.xy, axis=-1)[_both(a, b)]
    return False, f"no overlap; closest centre distance {d.min() if d.size else math.nan:.1f} m"


def _rear_end(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    a, b = _track(rollout, part.params["vehicle"]), _track(rollout, part.params["target"])
    hit = boxes_overlap(a.xy, a.yaw, a.extent, b.xy, b.yaw, b.extent) & _both(a, b)
    if not hit.any():
        d = np.linalg.norm(a.xy - b.xy, axis=-1)[_both(a, b)]
        return False, f"no overlap; closest centre distance {d.min() if d.size else math.nan:.1f} m"
    k = int(np.argmax(hit))
    rel = a.xy[k] - b.xy[k]
    lon = rel[0] * math.cos(b.yaw[k]) + rel[1] * math.sin(b.yaw[k])
    dyaw = abs(math.degrees(float(wrap_angle(np.float64(a.yaw[k] - b.yaw[k])))))
    ok = lon < 0 and dyaw < REAR_END_MAX_DEG
    when = (k + 1) * rollout.dt_s
    return ok, f"overlap at t = {when:.1f} s, {lon:.1f} m along the target, headings {dyaw:.0f}° apart"


def _no_collision(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    tracks = _scope(rollout, part)
    hits = collision_steps(rollout.sim, np.array([t.agent for t in tracks]), rollout.future)  # (C, T)
    bad = [int(rollout.number[t.agent]) for t, h in zip(tracks, hits, strict=True) if h.any()]
    return not bad, f"{len(bad)} of {len(tracks)} vehicles collide" + (f": {bad}" if bad else "")


def _keep_distance(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    d = _distances(rollout, part, ("follower", "leader"))
    lo, hi = part.params["min_m"], part.params["max_m"]
    if d.size == 0:
        return False, "the two vehicles are never present together"
    ok = d.min() >= lo - NEAR_TOL_M and d.max() <= hi + NEAR_TOL_M
    return ok, f"distance {d.min():.1f}-{d.max():.1f} m (asked {lo:g}-{hi:g} m, tolerance 1 m)"


def _stay_away(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    d = _distances(rollout, part, ("vehicle", "other"))
    if d.size == 0:
        return True, "the two vehicles are never present together"
    return d.min() >= part.params["min_m"] - AWAY_TOL_M, f"closest distance {d.min():.1f} m"


def _speeds(rollout: Rollout, part: QueryPart) -> list[tuple[int, np.ndarray]]:
    return [(int(rollout.number[t.agent]), t.speed[t.valid]) for t in _scope(rollout, part)]


def _speed_limit(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    top = max((float(v.max()) for _, v in _speeds(rollout, part) if v.size), default=0.0)
    limit = part.params["limit_mps"]
    return top <= limit + SPEED_TOL_MPS, f"highest speed {top:.1f} m/s (limit {limit:g} + 0.5)"


def _target_speed(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    target, last = part.params["speed_mps"], int(round(TARGET_WINDOW_S / rollout.dt_s))
    devs = [float(np.abs(t.speed[-last:][t.valid[-last:]] - target).mean())
            for t in _scope(rollout, part) if t.valid[-last:].any()]
    worst = max(devs, default=0.0)
    return worst <= TARGET_TOL_MPS, f"largest mean |speed - {target:g}| over the last 5 s: {worst:.2f} m/s"


def _stop(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    lows = {n: float(v.min()) for n, v in _speeds(rollout, part) if v.size}
    moving = [n for n, low in lows.items() if low >= STOP_SPEED_MPS]
    worst = max(lows.values(), default=math.nan)
    return not moving, f"lowest speed {worst:.2f} m/s" + (f"; never stopped: {moving}" if moving else "")


def _goal(part: QueryPart, t: _Track) -> np.ndarray:
    return np.linalg.norm(t.xy - np.array([part.params["x"], part.params["y"]]), axis=-1)


def _stop_region(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    t = _track(rollout, part.params["vehicle"])
    inside = (_goal(part, t) <= part.params["radius_m"]) & t.valid
    if not inside.any():
        closest = float(_goal(part, t)[t.valid].min())
        return False, f"never inside the region; closest {closest:.1f} m from its centre"
    low = float(t.speed[inside].min())
    return low < STOP_SPEED_MPS, f"lowest speed inside the region {low:.2f} m/s"


def _reach(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    t = _track(rollout, part.params["vehicle"])
    closest = float(_goal(part, t)[t.valid].min())
    return closest <= REACH_TOL_M, f"closest approach {closest:.1f} m (needs 2)"


def _offroad(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    tracks = _scope(rollout, part)
    off = offroad_steps(rollout, np.array([t.agent for t in tracks]))  # (C, T)
    bad = [int(rollout.number[t.agent]) for t, o in zip(tracks, off, strict=True) if o.any()]
    return not bad, f"{len(bad)} of {len(tracks)} vehicles leave the road" + (f": {bad}" if bad else "")


def _valid_track(rollout: Rollout, number: int) -> _Track:
    t = _track(rollout, number)
    keep = t.valid
    return _Track(t.agent, t.xy[keep], t.yaw[keep], t.speed[keep], t.valid[keep], t.extent)


Check = Callable[[Rollout, QueryPart], tuple[bool, str]]


def _lane_rule(fn: Callable[..., tuple[bool, str]], *keys: str) -> Check:
    """A check of a one-vehicle lane rule: ``fn(lanes, xy, yaw, *params[keys])`` on its valid track."""

    def check(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
        t = _valid_track(rollout, part.params["vehicle"])
        return fn(rollout.scene.lanes, t.xy, t.yaw, *(part.params[k] for k in keys))

    return check


def _follow_lane(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    if part.params.get("vehicle") is not None:
        return _lane_rule(lanes_check.follows_lane)(rollout, part)
    bad = []
    for t in _scope(rollout, part):
        ok, _ = lanes_check.follows_lane(rollout.scene.lanes, t.xy[t.valid], t.yaw[t.valid])
        if not ok and t.speed[t.valid].max(initial=0.0) >= STOP_SPEED_MPS:
            bad.append(int(rollout.number[t.agent]))
    return not bad, f"moving vehicles leaving their lane: {bad if bad else 'none'}"


def _turn(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    t = _valid_track(rollout, part.params["vehicle"])
    return lanes_check.turn(t.yaw, t.speed, part.params["direction"])


def _cut_in(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    a, b = _track(rollout, part.params["vehicle"]), _track(rollout, part.params["ahead_of"])
    both = _both(a, b)
    return lanes_check.cut_in(rollout.scene.lanes, a.xy[both], a.yaw[both], a.extent, b.xy[both],
                              b.yaw[both], b.extent, part.params["gap_m"])


def _same_direction(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    a, b = _track(rollout, part.params["vehicle"]), _track(rollout, part.params["other"])
    k = int(np.flatnonzero(_both(a, b))[-1])
    diff = abs(math.degrees(float(wrap_angle(np.float64(a.yaw[k] - b.yaw[k])))))
    return diff < SAME_DIRECTION_DEG, f"heading difference at the end {diff:.0f}° (needs < 30)"


def _side_of(rollout: Rollout, part: QueryPart) -> tuple[bool, str]:
    a, b = _track(rollout, part.params["vehicle"]), _track(rollout, part.params["other"])
    both = _both(a, b)
    rel = a.xy[both] - b.xy[both]
    lat = -rel[:, 0] * np.sin(b.yaw[both]) + rel[:, 1] * np.cos(b.yaw[both])
    signed = lat if part.params["side"] == "left" else -lat
    side = part.params["side"]
    return bool((signed > 0).all()), f"lateral offset on the {side}: {signed.min():.1f} m at worst"


CHECKS: dict[str, Check] = {
    "collision": _collision,
    "collide_from_behind": _rear_end,
    "no_collision": _no_collision,
    "keep_distance": _keep_distance,
    "keep_within": _keep_distance,
    "stay_away": _stay_away,
    "speed_limit": _speed_limit,
    "target_speed": _target_speed,
    "stop": _stop,
    "stop_region": _stop_region,
    "reach": _reach,
    "no_offroad": _offroad,
    "follow_lane": _follow_lane,
    "lane_change": _lane_rule(lanes_check.lane_change, "side"),
    "rightmost_lane": _lane_rule(lanes_check.rightmost),
    "turn": _turn,
    "cut_in": _cut_in,
    "same_direction": _same_direction,
    "stay_side_of": _side_of,
}


def check_satisfied(
    rollout: Rollout, compiled_or_parts: CompiledQuery | Sequence[QueryPart]
) -> list[PartReport]:
    """One :class:`PartReport` per part of a compiled query, measured on the rollout (module docstring)."""
    parts = compiled_or_parts.parts if isinstance(compiled_or_parts, CompiledQuery) else compiled_or_parts
    reports = []
    for part in parts:
        check = CHECKS.get(part.family)
        if check is None:
            reports.append(PartReport(part.text, False, f"no independent check for {part.family!r}"))
            continue
        try:
            ok, measured = check(rollout, part)
        except _Missing as err:
            ok, measured = False, str(err)
        reports.append(PartReport(part.text, bool(ok), measured))
    return reports
