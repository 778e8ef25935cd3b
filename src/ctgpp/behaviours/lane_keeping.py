"""Measures and checks of keeping to a lane: following the lane a vehicle starts on (under 1.5 m from
its centerline) and keeping to the lanes it may follow without changing lanes, turns included.

They read the simulated track (``rollout.sim``) and the scene's lane graph only — never a guidance
loss. The lane a vehicle starts on is taken at t = 0, the pose its guidance plans from, and followed
from lane end to lane end (:func:`~ctgpp.behaviours.lane_positions.chain_offsets`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Vehicles, Verdict
from ctgpp.behaviours.lane_positions import chain_distance, chain_offsets, reachable, with_start
from ctgpp.behaviours.tracks import Track, tracks
from ctgpp.interfaces import Rollout
from ctgpp.scene.lanes import nearest_lane
from ctgpp.scene.types import LaneGraph
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

FOLLOW_LANE_MAX_OFFSET_M = 1.5  # follow lane: largest lateral offset from the lane chain

Params = Mapping[str, Any]


def _follow_offsets(lanes: LaneGraph, t: Track) -> np.ndarray:
    """(T,) |lateral offset| m of the future from the lane chain the vehicle starts on (NaN off lanes)."""
    xy, yaw = with_start(t)
    offsets, _ = chain_offsets(lanes, xy, yaw)
    return np.abs(offsets[1:])


def _follow_scope(rollout: Rollout, p: Params, vehicles: Vehicles) -> list[Track]:
    chosen = (p["vehicle"],) if p.get("vehicle") is not None else vehicles
    return [t.valid_part() for t in tracks(rollout, chosen)]


def follow_lane_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the vehicles of the mean |lateral offset| (m) from the lane chain they start on."""
    out = [float(np.nanmean(o)) for t in _follow_scope(rollout, p, vehicles)
           if (o := _follow_offsets(rollout.scene.lanes, t)).size and np.isfinite(o).any()]
    return float(np.mean(out)) if out else math.nan


def follow_lane_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle (moving ones, when the rule is for every vehicle) stays under 1.5 m from the
    centerline of the lane chain it starts on."""
    bad, worst_all, named = [], 0.0, p.get("vehicle") is not None
    for t in _follow_scope(rollout, p, vehicles):
        if not named and t.speed.max(initial=0.0) < MOVING_SPEED_MPS:
            continue
        o = _follow_offsets(rollout.scene.lanes, t)
        if not o.size or np.isnan(o).all():
            bad.append(f"vehicle {t.number} starts on no lane")
            continue
        worst = float(np.nanmax(o))
        worst_all = max(worst_all, worst)
        if worst >= FOLLOW_LANE_MAX_OFFSET_M:
            bad.append(f"vehicle {t.number} {worst:.2f} m off")
    said = "; ".join(bad) if bad else f"largest lateral offset {worst_all:.2f} m"
    return Verdict(not bad, f"{said} (limit {FOLLOW_LANE_MAX_OFFSET_M:g} m)", EVERY_STEP)


EVERY_STEP = "every simulated step, t = 0.1 s to the end"


def _keep_excess(lanes: LaneGraph, t: Track, tolerance_m: float) -> np.ndarray | None:
    """(T,) distance (m) beyond the allowance from the lanes the vehicle may follow without changing
    lanes (its start lane and every lane it leads to); None when it starts on no lane."""
    start = nearest_lane(lanes, t.xy0, t.yaw0)
    if start is None:
        return None
    chain = reachable(lanes, start.lane)
    allowance = max(tolerance_m, abs(start.d_m))
    d = np.array([chain_distance(lanes, chain, p) for p in t.xy])
    return np.maximum(np.where(np.isfinite(d), d, 1e3) - allowance, 0.0)


def keep_lane_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the vehicles of the mean distance (m) beyond the allowance from their lanes."""
    out = [float(e.mean()) for t in _follow_scope(rollout, p, vehicles)
           if (e := _keep_excess(rollout.scene.lanes, t, float(p["tolerance_m"]))) is not None and e.size]
    return float(np.mean(out)) if out else math.nan


def keep_lane_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle stays within ``tolerance_m`` (or its distance at the start, when more) of the
    lanes it may follow without changing lanes, turns included; vehicles on no lane are left out."""
    bad = []
    for t in _follow_scope(rollout, p, vehicles):
        e = _keep_excess(rollout.scene.lanes, t, float(p["tolerance_m"]))
        if e is not None and e.size and e.max() > 0:
            bad.append(f"vehicle {t.number} {e.max():.1f} m beyond at t = {t.time(int(np.argmax(e))):.1f} s")
    return Verdict(not bad, "; ".join(bad) if bad else "every vehicle within its lanes", EVERY_STEP)
