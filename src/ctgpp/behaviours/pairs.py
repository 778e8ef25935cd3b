"""Measures and checks of the behaviours between vehicles: collisions, distances, sides, directions.

Distance bands are the sentence's numbers, with no tolerance added. A pair that starts outside its
band cannot be inside it at once: it is judged from the step it first gets inside (said in the
verdict), and must stay inside from there to the end.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Vehicles, Verdict
from ctgpp.behaviours.tracks import Track, both_valid, track, tracks, wrapped_deg
from ctgpp.geometry import boxes_overlap
from ctgpp.interfaces import Rollout
from ctgpp.metrics import rules as paper
from ctgpp.metrics.collision import collision_steps

SAME_DIRECTION_DEG = 30.0
TURN_ROUND_DEG = 150.0  # two vehicles this far apart in heading at t = 0 face opposite ways
REAR_END_MAX_DEG = 60.0
EVERY_STEP = "every simulated step, t = 0.1 s to the end"

Params = Mapping[str, Any]


def _pair(rollout: Rollout, p: Params, keys: tuple[str, str]) -> tuple[Track, Track]:
    return track(rollout, p[keys[0]]), track(rollout, p[keys[1]])


def _overlaps(a: Track, b: Track) -> np.ndarray:
    return boxes_overlap(a.xy, a.yaw, a.extent, b.xy, b.yaw, b.extent) & both_valid(a, b)


def _closest_text(a: Track, b: Track) -> str:
    d = np.linalg.norm(a.xy - b.xy, axis=-1)[both_valid(a, b)]
    return f"no overlap; closest centre distance {d.min() if d.size else math.nan:.1f} m"


# --- collisions --------------------------------------------------------------------------------------


def collision_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """1 when the pair never collides (the rule is violated), 0 when it does (paper appendix E)."""
    track(rollout, p["vehicle_a"]), track(rollout, p["vehicle_b"])  # MissingVehicle when absent
    return paper.collision(rollout, p["vehicle_a"], p["vehicle_b"])


def collision_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The pair's oriented boxes overlap at some step."""
    a, b = _pair(rollout, p, ("vehicle_a", "vehicle_b"))
    hit = _overlaps(a, b)
    if hit.any():
        return Verdict(True, f"boxes overlap from t = {a.time(int(np.argmax(hit))):.1f} s", EVERY_STEP)
    return Verdict(False, _closest_text(a, b), EVERY_STEP)


def _rear_end(a: Track, b: Track) -> tuple[bool, str]:
    hit = _overlaps(a, b)
    if not hit.any():
        return False, _closest_text(a, b)
    k = int(np.argmax(hit))
    rel = a.xy[k] - b.xy[k]
    lon = rel[0] * math.cos(b.yaw[k]) + rel[1] * math.sin(b.yaw[k])
    dyaw = abs(wrapped_deg(float(a.yaw[k] - b.yaw[k])))
    ok = lon < 0 and dyaw < REAR_END_MAX_DEG
    return ok, f"overlap at t = {a.time(k):.1f} s, {lon:.1f} m along the target, headings {dyaw:.0f}° apart"


def rear_end_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """1 when the vehicle never hits the target from behind, 0 when it does."""
    return 0.0 if _rear_end(*_pair(rollout, p, ("vehicle", "target")))[0] else 1.0


def rear_end_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The boxes overlap, and at the first overlap the vehicle's centre is behind the target's (in the
    target's frame) and their headings differ by less than 60°."""
    ok, said = _rear_end(*_pair(rollout, p, ("vehicle", "target")))
    return Verdict(ok, said, EVERY_STEP)


def _colliding(rollout: Rollout, vehicles: Vehicles) -> tuple[list[Track], list[int]]:
    ts = tracks(rollout, vehicles)
    hits = collision_steps(rollout.sim, np.array([t.agent for t in ts]), rollout.future)  # (C, T)
    return ts, [t.number for t, h in zip(ts, hits, strict=True) if h.any()]


def no_collision_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Fraction of the vehicles that collide with any agent (replayed ones included)."""
    ts, bad = _colliding(rollout, vehicles)
    return len(bad) / len(ts) if ts else math.nan


def no_collision_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """No vehicle in scope overlaps any valid agent."""
    ts, bad = _colliding(rollout, vehicles)
    said = f"{len(bad)} of {len(ts)} vehicles collide" + (f": {bad}" if bad else "")
    return Verdict(not bad, said, EVERY_STEP)


# --- distances ---------------------------------------------------------------------------------------


def _band_verdict(a: Track, b: Track, ok: np.ndarray, d: np.ndarray, asked: str) -> Verdict:
    """Inside the band at every step both are present from the first one it could be: the first step
    when it starts inside, else the first step it gets inside; then to the end."""
    steps = np.flatnonzero(both_valid(a, b))
    if not steps.size:
        return Verdict(False, "the two vehicles are never present together", BAND_WINDOW)
    ok, d = ok[steps], d[steps]
    span = f"distance {d.min():.1f}-{d.max():.1f} m (asked {asked})"
    if not ok.any():
        return Verdict(False, f"{span}; never inside", BAND_WINDOW)
    start = 0 if a.hold else int(np.argmax(ok))  # a deadline: inside from the window's first step
    late = f"; inside from t = {a.time(int(steps[start])):.1f} s" if start else ""
    if ok[start:].all():
        return Verdict(True, span + late, BAND_WINDOW)
    k = start + int(np.flatnonzero(~ok[start:])[0])
    return Verdict(False, f"{span}{late}; outside at t = {a.time(int(steps[k])):.1f} s ({d[k]:.1f} m)",
                   BAND_WINDOW)


BAND_WINDOW = "every step from the first one inside the band (t = 0.1 s when it starts inside) to the end"


def keep_distance_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the steps of how far (m) the centre distance lies outside [min_m, max_m]."""
    track(rollout, p["follower"]), track(rollout, p["leader"])
    return paper.keep_distance(rollout, p["follower"], p["leader"], p["min_m"], p["max_m"])


def keep_distance_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The centre distance lies in [min_m, max_m] (:func:`_band_verdict`); a miss says when the two
    start facing opposite ways (:func:`turn_round_note`)."""
    a, b = _pair(rollout, p, ("follower", "leader"))
    d = np.linalg.norm(a.xy - b.xy, axis=-1)
    lo, hi = float(p["min_m"]), float(p["max_m"])
    verdict = _band_verdict(a, b, (d >= lo) & (d <= hi), d, f"{lo:g}-{hi:g} m")
    if verdict.satisfied:
        return verdict
    return replace(verdict, measured=verdict.measured + turn_round_note(a, b))


def turn_round_note(a: Track, b: Track) -> str:
    """Words for a verdict's miss when vehicles a and b head at least ``TURN_ROUND_DEG`` apart at
    t = 0: keeping close to, or heading the way of, the other then asks one of them to turn round
    (a U-turn, or from rest); "" otherwise."""
    gap = abs(wrapped_deg(a.yaw0 - b.yaw0))
    if gap < TURN_ROUND_DEG:
        return ""
    return (f"; at t = 0 vehicles {a.number} and {b.number} head {gap:.0f}° apart ({a.speed0:.1f} and "
            f"{b.speed0:.1f} m/s): one of them would have to turn round")


def stay_away_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean shortfall (m) of the centre distance below ``min_m`` over the steps both are present."""
    a, b = _pair(rollout, p, ("vehicle", "other"))
    d = np.linalg.norm(a.xy - b.xy, axis=-1)[both_valid(a, b)]
    return float(np.maximum(float(p["min_m"]) - d, 0.0).mean()) if d.size else math.nan


def stay_away_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The centre distance is at least ``min_m`` (:func:`_band_verdict`)."""
    a, b = _pair(rollout, p, ("vehicle", "other"))
    d = np.linalg.norm(a.xy - b.xy, axis=-1)
    return _band_verdict(a, b, d >= float(p["min_m"]), d, f"at least {float(p['min_m']):g} m")


# --- directions and sides ----------------------------------------------------------------------------


def _heading_gap(a: Track, b: Track) -> float:
    both = np.flatnonzero(both_valid(a, b))
    return abs(wrapped_deg(float(a.yaw[both[-1]] - b.yaw[both[-1]]))) if both.size else math.nan


def same_direction_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """The heading difference (°) at the last step both are present."""
    return _heading_gap(*_pair(rollout, p, ("vehicle", "other")))


def same_direction_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The headings differ by less than 30° at the end; a miss says when the two start facing
    opposite ways (:func:`turn_round_note`)."""
    a, b = _pair(rollout, p, ("vehicle", "other"))
    diff = _heading_gap(a, b)
    ok = diff < SAME_DIRECTION_DEG
    note = "" if ok else turn_round_note(a, b)
    return Verdict(ok, f"heading difference at the end {diff:.0f}° (needs < 30){note}",
                   "the last step both vehicles are present")


def _side_offsets(a: Track, b: Track, side: str) -> np.ndarray:
    """(T,) lateral offset (m) of a in b's frame, positive on ``side``; NaN where either is absent."""
    rel = a.xy - b.xy
    lat = -rel[:, 0] * np.sin(b.yaw) + rel[:, 1] * np.cos(b.yaw)
    signed = lat if side == "left" else -lat
    return np.where(both_valid(a, b), signed, np.nan)


def side_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean (m) of how far the vehicle is on the wrong side of the other, over the steps."""
    s = _side_offsets(*_pair(rollout, p, ("vehicle", "other")), p["side"])
    return float(np.nanmean(np.maximum(-s, 0.0))) if np.isfinite(s).any() else math.nan


def side_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The vehicle is on ``side`` of the other (lateral coordinate in its frame) from the first step
    it is there (the first step when it starts there) to the end."""
    a, b = _pair(rollout, p, ("vehicle", "other"))
    s = _side_offsets(a, b, p["side"])
    both = both_valid(a, b)
    if not both.any():
        return Verdict(False, "the two vehicles are never present together", BAND_WINDOW)
    steps = np.flatnonzero(both)
    ok, s = s[steps] > 0, s[steps]
    if not ok.any():
        return Verdict(False, f"never on the {p['side']}; lateral offset {float(s.min()):.1f} m at worst",
                       SIDE_WINDOW)
    first = int(np.argmax(ok))
    if not ok[first:].all():
        k = first + int(np.flatnonzero(~ok[first:])[0])
        return Verdict(False, f"on the {p['side']} from t = {a.time(int(steps[first])):.1f} s, then on the "
                       f"other side at t = {a.time(int(steps[k])):.1f} s", SIDE_WINDOW)
    late = f" from t = {a.time(int(steps[first])):.1f} s" if first else ""
    return Verdict(True, f"on the {p['side']}{late}; lateral offset {float(s[first:].min()):.1f} m at least",
                   SIDE_WINDOW)


SIDE_WINDOW = "every step from the first one on that side (t = 0.1 s when it starts there) to the end"


# --- comparisons -------------------------------------------------------------------------------------


def _speeds_together(rollout: Rollout, p: Params) -> tuple[Track, Track, np.ndarray, np.ndarray]:
    a, b = _pair(rollout, p, ("vehicle", "other"))
    both = both_valid(a, b)
    return a, b, a.speed[both], b.speed[both]


def faster_than_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the steps both are present of how much slower (m/s) the vehicle is than the other."""
    _, _, va, vb = _speeds_together(rollout, p)
    return float(np.maximum(vb - va, 0.0).mean()) if va.size else math.nan


def faster_than_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The vehicle's mean speed over the steps both are present is higher than the other's."""
    a, b, va, vb = _speeds_together(rollout, p)
    if not va.size:
        return Verdict(False, "the two vehicles are never present together", COMPARE_WINDOW)
    said = (f"vehicle {a.number} {va.mean():.1f} m/s on average, vehicle {b.number} {vb.mean():.1f} m/s "
            f"(faster at {int((va > vb).sum())} of {va.size} steps)")
    return Verdict(bool(va.mean() > vb.mean()), said, COMPARE_WINDOW)


COMPARE_WINDOW = "the mean over every simulated step both vehicles are present"
