"""Measures and checks of the per-vehicle behaviours: speeds, stops, accelerations, the road, points.

Thresholds are the sentence's own numbers: a speed limit holds when the speed is at or below the
limit, with no tolerance added, from the first step at which the vehicle could be under it at the
action bounds (braking 10 m/s²); "slow down to / speed up to / stop" mean reach and stay: the condition
holds from some step to the end, for at least the last second. "Drive at v" holds within
``TARGET_TOL_MPS`` of v (a speed is held within a band, never exactly).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Vehicles, Verdict, vehicle_list
from ctgpp.behaviours.tracks import Track, earliest_speed_step, track, tracks
from ctgpp.interfaces import Rollout
from ctgpp.metrics import rules as paper
from ctgpp.metrics.offroad import offroad_steps
from ctgpp.scene.holds import HOLD_S, first_held, held_from, hold_steps
from ctgpp.scene.lanes import point_ahead
from ctgpp.scene.vehicles import MOVING_SPEED_MPS  # stopped: slower than this, not moving

TARGET_TOL_MPS = 1.0  # "drive at v": within this of v
GOAL_REACH_M = 2.0  # evaluation rule 7's goal counts as reached this close (its loss aims at 0 m)

Params = Mapping[str, Any]


def _restricted(vehicles: Vehicles) -> list[int] | None:
    return None if vehicles is None else list(vehicles)


# --- speed limit -------------------------------------------------------------------------------------


def speed_limit_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean excess speed (m/s) over the limit over the valid future steps (paper appendix E)."""
    return paper.speed_limit(rollout, p["limit_mps"], _restricted(vehicles))


def speed_limit_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle's speed is at or below the limit from the first step it could be (braking at
    10 m/s² from its start speed) to the end; says when each complied."""
    limit, bad, notes = float(p["limit_mps"]), [], []
    for t in tracks(rollout, vehicles):
        first = 0 if t.hold else earliest_speed_step(t.speed0, limit, True, t.dt_s)
        ok = (t.speed <= limit) | ~t.valid
        if not ok[first:].all():
            k = first + int(np.flatnonzero(~ok[first:])[0])
            bad.append(f"vehicle {t.number} at {t.speed[k]:.1f} m/s at t = {t.time(k):.1f} s (could be under "
                       f"from {t.time(first):.1f} s)")
        elif t.speed0 > limit:
            since = held_from(ok)
            notes.append(f"vehicle {t.number} under from {t.time(since or 0):.1f} s")
    late = f" ({'; '.join(notes)})" if notes else ""
    words = "; ".join(bad) if bad else "every vehicle at or under it" + late
    return Verdict(not bad, f"limit {limit:g} m/s: {words}", SPEED_LIMIT_WINDOW)


SPEED_LIMIT_WINDOW = (
    "each vehicle from the first step it could be under the limit braking at 10 m/s², to the end"
)

# --- reach a speed and stay there --------------------------------------------------------------------


def _targets(rollout: Rollout, t: Track, p: Params) -> np.ndarray:
    """(T,) target speeds of track t over its future (a number, or a table of rule 5; NaN: none)."""
    speed = p["speed_mps"]
    n_t = t.speed.shape[0]
    if np.ndim(speed) == 0:
        return np.full(n_t, float(speed))
    table = np.asarray(speed, dtype=np.float64)
    first = rollout.first_step + rollout.current + 1 if p.get("absolute_steps") else 0
    cols = np.arange(first, first + n_t)
    out = np.full(n_t, np.nan)
    inside = cols < table.shape[1]
    if t.number < table.shape[0]:
        out[inside] = table[t.number, cols[inside]]
    return out


def _reach_and_stay(t: Track, ok: np.ndarray, what: str) -> tuple[bool, str, float | None]:
    """Whether ``ok`` (T,) holds from some valid step to the last valid one, for at least the last
    second of them (in a deadline's window, ``t.hold``: from its first valid step; as a sequence's
    earlier stage, ``t.once``: for a second in a row at some step), in words, and the episode time it
    was reached (0 when it held from the first step; None when not satisfied)."""
    steps = np.flatnonzero(t.valid)
    if t.once:
        since = first_held(ok[steps], hold_steps(t.dt_s))
        if since is None:
            return False, f"vehicle {t.number} never {what} for {HOLD_S:g} s", None
    else:
        since = held_from(ok[steps])
    if t.hold and steps.size and since != 0:  # a deadline: held from the window's first step
        late = "never to the end" if since is None else f"only from t = {t.time(int(steps[since])):.1f} s"
        return False, f"vehicle {t.number} not {what} from t = {t.time(int(steps[0])):.1f} s ({late})", None
    if since is None or (len(steps) - since < hold_steps(t.dt_s) and not t.hold):
        return False, f"vehicle {t.number} not {what} over its last {hold_steps(t.dt_s) * t.dt_s:g} s", None
    at = t.time(int(steps[since]))
    done = 0.0 if since == 0 and t.shift_steps == 0 else at
    held = f" for {HOLD_S:g} s" if t.once else ""
    return True, f"vehicle {t.number} {what} from t = {at:.1f} s{held}", done


def _reached(done: list[float | None]) -> float | None:
    """The time every vehicle had reached its state (s), None when one has not."""
    return None if not done or any(d is None for d in done) else max(d for d in done if d is not None)


def target_speed_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean |speed - target| (m/s) over the valid future steps with a target (paper appendix E)."""
    return paper.target_speed(rollout, p["speed_mps"], _restricted(vehicles), bool(p.get("absolute_steps")))


def target_speed_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle reaches its target speed (within 1 m/s) and stays there to the end (at least 1 s)."""
    words, ok_all, done = [], True, []
    for t in tracks(rollout, vehicles):
        target = _targets(rollout, t, p)
        ok = (np.abs(t.speed - target) <= TARGET_TOL_MPS) | np.isnan(target)
        ok_t, said, at = _reach_and_stay(t, ok, f"within {TARGET_TOL_MPS:g} m/s of its target")
        ok_all &= ok_t
        done.append(at)
        words.append(said + f" (end {t.speed[t.valid][-1]:.1f} m/s)" if t.valid.any() else said)
    return Verdict(ok_all, "; ".join(words), REACH_WINDOW, _reached(done))


REACH_WINDOW = "reach and stay: from some step to the end of the episode, at least its last 1 s"


def reach_speed_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean shortfall (m/s) of the speed beyond the bound over the last second, over the vehicles."""
    bound, below = float(p["speed_mps"]), p["bound"] == "below"
    out = []
    for t in tracks(rollout, vehicles):
        last = t.speed[-hold_steps(t.dt_s):][t.valid[-hold_steps(t.dt_s):]]
        if last.size:
            out.append(float(np.maximum(last - bound if below else bound - last, 0.0).mean()))
    return float(np.mean(out)) if out else math.nan


def reach_speed_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle gets to at most (``bound`` "below") / at least ("above") the speed and stays
    there to the end (at least 1 s); says when, and when it could have at the action bounds."""
    bound, below = float(p["speed_mps"]), p["bound"] == "below"
    words, ok_all, done = [], True, []
    for t in tracks(rollout, vehicles):
        ok = t.speed <= bound if below else t.speed >= bound
        side = "at or under" if below else "at or over"
        ok_t, said, at = _reach_and_stay(t, ok, f"{side} {bound:g} m/s")
        could = t.time(earliest_speed_step(t.speed0, bound, below, t.dt_s))
        ok_all &= ok_t
        done.append(at)
        words.append(f"{said} (possible from {could:.1f} s)")
    return Verdict(ok_all, "; ".join(words), REACH_WINDOW, _reached(done))


def stop_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the vehicles of the highest speed (m/s) over the last second."""
    out = [float(t.speed[-hold_steps(t.dt_s):].max()) for t in tracks(rollout, vehicles) if t.valid.any()]
    return float(np.mean(out)) if out else math.nan


def stop_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle comes to a stop (under 0.5 m/s) and stays stopped to the end (at least 1 s)."""
    words, ok_all, done = [], True, []
    for t in tracks(rollout, vehicles):
        stopped = t.speed < MOVING_SPEED_MPS
        ok_t, said, at = _reach_and_stay(t, stopped, f"stopped (< {MOVING_SPEED_MPS:g} m/s)")
        ok_all &= ok_t
        done.append(at)
        words.append(said)
    return Verdict(ok_all, "; ".join(words), REACH_WINDOW, _reached(done))


# --- acceleration, road ------------------------------------------------------------------------------


def acceleration_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean excess (m/s²) of the acceleration magnitude over the limit (longitudinal and lateral)."""
    return paper.acceleration_limit(rollout, p["max_mps2"], _restricted(vehicles))


def acceleration_magnitudes(t: Track) -> np.ndarray:
    """(K,) m/s²: the acceleration magnitude of each step valid at both ends, from t = 0 (speed
    differences, and speed × yaw rate from heading differences)."""
    speed = np.concatenate([[t.speed0], t.speed])
    yaw = np.concatenate([[t.yaw0], t.yaw])
    valid = np.concatenate([[True], t.valid])
    lon = np.diff(speed) / t.dt_s
    lat = speed[1:] * ((np.diff(yaw) + np.pi) % (2 * np.pi) - np.pi) / t.dt_s
    return np.hypot(lon, lat)[valid[1:] & valid[:-1]]


def acceleration_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """No step's acceleration magnitude (speed differences, speed × yaw rate) exceeds the limit."""
    top = 0.0
    for t in tracks(rollout, vehicles):
        top = max(top, float(acceleration_magnitudes(t).max(initial=0.0)))
    limit = float(p["max_mps2"])
    return Verdict(top <= limit, f"largest acceleration {top:.2f} m/s² (limit {limit:g})", EVERY_STEP)


EVERY_STEP = "every simulated step, t = 0.1 s to the end"


def offroad_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Fraction of the vehicles whose centre leaves the drivable area (those starting off it excluded)."""
    if vehicles is None:
        return paper.no_offroad(rollout)
    off = offroad_steps(rollout, np.array([t.agent for t in tracks(rollout, vehicles)]))
    return float(off.any(axis=1).mean()) if len(off) else math.nan


def offroad_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """No vehicle's centre leaves the drivable area (vehicles that start off it excluded)."""
    ts = tracks(rollout, vehicles)
    off = offroad_steps(rollout, np.array([t.agent for t in ts]))  # (C, T)
    bad = [t.number for t, o in zip(ts, off, strict=True) if o.any()]
    return Verdict(not bad, f"{len(bad)} of {len(ts)} vehicles leave the road" + (f": {bad}" if bad else ""),
                   EVERY_STEP)


# --- points ------------------------------------------------------------------------------------------


def _goals(p: Params) -> list[tuple[int, np.ndarray]]:
    vs = vehicle_list(p["vehicle"])
    xs, ys = np.atleast_1d(p["x"]), np.atleast_1d(p["y"])
    return [(v, np.array([float(x), float(y)])) for v, x, y in zip(vs, xs, ys, strict=True)]


def _closest(rollout: Rollout, v: int, goal: np.ndarray) -> float:
    t = track(rollout, v)
    d = np.linalg.norm(t.xy - goal, axis=-1)[t.valid]
    return float(d.min()) if d.size else math.inf


def goal_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the vehicles of the closest approach (m) to their goal (paper appendix E)."""
    return paper.goal_waypoint(rollout, p["vehicle"], p["x"], p["y"])


def _reach_verdict(rollout: Rollout, p: Params, within_m: float) -> Verdict:
    words, ok_all = [], True
    for v, goal in _goals(p):
        d = _closest(rollout, v, goal)
        ok_all &= d <= within_m
        words.append(f"vehicle {v} passes {d:.1f} m from ({goal[0]:.1f}, {goal[1]:.1f})")
    return Verdict(ok_all, "; ".join(words) + f" (needs {within_m:g})", "closest approach over the episode")


def goal_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle passes within 2 m of its goal."""
    return _reach_verdict(rollout, p, GOAL_REACH_M)


def reach_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the vehicles of the closest approach (m) to their point beyond ``reach_m``."""
    return float(np.mean([max(_closest(rollout, v, g) - float(p["reach_m"]), 0.0) for v, g in _goals(p)]))


def reach_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle passes within ``reach_m`` of its point (the number its loss holds)."""
    return _reach_verdict(rollout, p, float(p["reach_m"]))


def stop_region_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean lowest speed (m/s) inside the region; the start speed for a vehicle never inside."""
    return paper.stop_region(rollout, p["vehicle"], p["x"], p["y"], p["radius_m"])


def stop_region_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle is stopped (under 0.5 m/s) at some step while inside its region."""
    words, ok_all = [], True
    for v, centre in _goals(p):
        t = track(rollout, v)
        d = np.linalg.norm(t.xy - centre, axis=-1)
        inside = (d <= float(p["radius_m"])) & t.valid
        if not inside.any():
            ok_all = False
            closest = d[t.valid].min(initial=math.inf)
            words.append(f"vehicle {v} never inside; closest {closest:.1f} m from the centre")
            continue
        low = float(t.speed[inside].min())
        ok_all &= low < MOVING_SPEED_MPS
        words.append(f"vehicle {v}: lowest speed inside {low:.2f} m/s")
    return Verdict(ok_all, "; ".join(words), "the steps inside the region")


def _ahead_goal(rollout: Rollout, p: Params) -> tuple[int, np.ndarray]:
    t = track(rollout, p["vehicle"])
    return t.number, point_ahead(rollout.scene.lanes, t.xy0, t.yaw0, float(p["distance_m"]))


def reach_ahead_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Closest approach (m) beyond ``reach_m`` to the point ``distance_m`` ahead of the start along the
    vehicle's lane (:func:`~ctgpp.scene.lanes.point_ahead`)."""
    v, goal = _ahead_goal(rollout, p)
    return max(_closest(rollout, v, goal) - float(p["reach_m"]), 0.0)


def reach_ahead_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The vehicle passes within ``reach_m`` of the point ``distance_m`` ahead of its start along its
    lane (along its heading off the lane graph)."""
    v, goal = _ahead_goal(rollout, p)
    d = _closest(rollout, v, goal)
    said = (f"vehicle {v} passes {d:.1f} m from the point {float(p['distance_m']):g} m ahead of its start, "
            f"({goal[0]:.1f}, {goal[1]:.1f}) (needs {float(p['reach_m']):g})")
    return Verdict(d <= float(p["reach_m"]), said, "closest approach over the episode")
