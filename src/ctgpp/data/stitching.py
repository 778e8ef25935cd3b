"""One vehicle's track fragments joined into one track.

A tracker that loses a vehicle (occluded, or far) and finds it again gives it a new id: the log then
holds one track that ends and another that begins where the first would be. In the Waymo Open Motion
scenes this is common, and it costs the simulation: a vehicle present at the start is simulated on
past its fragment's end, and the log then brings in "another" vehicle at the same place, at the step
it appears. Of the default's 17 collisions on each Waymo evaluation split, 12 were of that kind
(docs/benchmarks.md). INTERACTION's tracks (4 such pairs among 3,576 late vehicles of its val split)
and nuScenes' (none) are whole, and are not stitched.

A fragment ``b`` continues fragment ``a`` (both vehicles) when

- ``b`` starts at most ``MAX_GAP_S`` after ``a`` ends, and not before;
- ``b``'s first position is within ``MAX_MISS_M`` of ``a``'s last position carried on at ``a``'s last
  speed and heading over the gap;
- their headings there differ by at most ``MAX_TURN_RAD``.

Each fragment continues at most one and is continued by at most one, nearest first; chains join
transitively. The joined track keeps the first fragment's id, type and extent; the steps of the gap
stay invalid (unobserved, as any track's own gaps).

The constants were read off the Waymo ``train`` split alone (``scripts/fragments.py``): of 3,177
vehicle tracks that begin after a scene's first step with one ended in the 5 s before, the nearest
carried-on end lies within 1.5 m for 934, against a background of about 9 (the pairs at 4–6 m,
scaled by area). Within 1.5 m the pairs outnumber the background at least 7 to 1 in every 1-s band
of gap up to 5 s, at rest (68 to 1 and more) and moving (75 against 1.2 within 1 s, 7 against 0.9 at
2–3 s); beyond 1.5 m, for moving vehicles, they thin into it (11 at 1.5–2 m within 1 s, against 9 at
3–4 m). 77 of the 934 turn by more than 30° (mostly parked cars whose heading flips); they are left
apart, as a joined track would jump.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentTracks, AgentType

MAX_GAP_S = 5.0
MAX_MISS_M = 1.5
MAX_TURN_RAD = math.radians(30.0)


@dataclass(frozen=True)
class Join:
    """Fragment ``later`` (an id) continues fragment ``earlier`` after ``gap_steps`` unobserved steps;
    ``miss_m``: how far its start lies from ``earlier`` carried on."""

    earlier: str
    later: str
    gap_steps: int
    miss_m: float


@dataclass(frozen=True, eq=False)
class Candidates:
    """The vehicle tracks ended shortly before vehicle track ``begins`` begins, at step ``first``:
    ``ends`` (E,) their indices, ``gap_steps`` (E,) from each one's last step to ``first``, ``miss_m``
    (E,) the distance from ``begins``' first position to each one's last position carried on at its
    last speed and heading, ``turn_rad`` (E,) the headings' difference there."""

    begins: int
    first: int
    ends: np.ndarray
    gap_steps: np.ndarray
    miss_m: np.ndarray
    turn_rad: np.ndarray


def candidates(tracks: AgentTracks, dt_s: float, window_s: float, keep: int = -1) -> Iterator[Candidates]:
    """For each vehicle track with vehicle tracks ended up to ``window_s`` before it begins (never
    ``keep``, an index), those tracks carried on to its start (:class:`Candidates`)."""
    valid = tracks.valid
    has = valid.any(axis=1)
    first = np.where(has, valid.argmax(axis=1), -1)  # (A,)
    last = np.where(has, valid.shape[1] - 1 - valid[:, ::-1].argmax(axis=1), -1)  # (A,)
    vehicle = has & (tracks.types == AgentType.VEHICLE)
    if keep >= 0:
        vehicle[keep] = False
    window = int(round(window_s / dt_s))
    for begins in np.flatnonzero(vehicle).tolist():
        s = int(first[begins])
        ends = np.flatnonzero(vehicle & (last < s) & (last >= s - window))  # (E,) fragments ended before
        if not len(ends):
            continue
        e = last[ends]  # (E,)
        heading = tracks.yaw[ends, e]
        carried = tracks.xy[ends, e] + (tracks.speed[ends, e] * (s - e) * dt_s)[:, None] * np.stack(
            [np.cos(heading), np.sin(heading)], axis=-1
        )  # (E, 2)
        miss = np.linalg.norm(carried - tracks.xy[begins, s], axis=-1)  # (E,)
        turn = np.abs(wrap_angle(tracks.yaw[begins, s] - heading))  # (E,)
        yield Candidates(begins, s, ends, s - e, miss, turn)


def find_joins(tracks: AgentTracks, dt_s: float, keep: int = -1) -> list[tuple[int, int, Join]]:
    """The fragments that continue others: (earlier index, later index, join), each index at most once
    on each side, nearest first. ``keep`` (an index, e.g. the ego) is never joined."""
    pairs: list[tuple[float, int, int, int]] = []
    for c in candidates(tracks, dt_s, MAX_GAP_S, keep):
        for k in np.flatnonzero((c.miss_m <= MAX_MISS_M) & (c.turn_rad <= MAX_TURN_RAD)):
            pairs.append((float(c.miss_m[k]), int(c.ends[k]), c.begins, int(c.gap_steps[k])))
    joins: list[tuple[int, int, Join]] = []
    continued, continuing = set(), set()
    for miss_m, a, b, gap in sorted(pairs):  # nearest first
        if a in continued or b in continuing:
            continue
        continued.add(a)
        continuing.add(b)
        joins.append((a, b, Join(str(tracks.ids[a]), str(tracks.ids[b]), gap - 1, round(miss_m, 3))))
    return joins


def stitch_fragments(tracks: AgentTracks, dt_s: float, keep: int = -1) -> tuple[AgentTracks, list[Join]]:
    """``tracks`` with every fragment that continues another (:func:`find_joins`) joined into the
    first of its chain and removed; the agents keep their order, so an index before every removed
    one (``keep``, the ego at 0) keeps its place. Returns the tracks and the joins made."""
    joins = find_joins(tracks, dt_s, keep)
    if not joins:
        return tracks, []
    successor = {a: b for a, b, _ in joins}
    later = {b for _, b, _ in joins}
    xy, yaw, speed, valid = tracks.xy.copy(), tracks.yaw.copy(), tracks.speed.copy(), tracks.valid.copy()
    for root in sorted(successor.keys() - later):  # the first fragment of each chain
        b = successor[root]
        while True:
            steps = tracks.valid[b]  # (T,) its steps, after every step of the fragments before it
            xy[root, steps] = tracks.xy[b, steps]
            yaw[root, steps] = tracks.yaw[b, steps]
            speed[root, steps] = tracks.speed[b, steps]
            valid[root, steps] = True
            if b not in successor:
                break
            b = successor[b]
    kept = np.asarray([i for i in range(tracks.num_agents) if i not in later], dtype=np.int64)
    joined = AgentTracks(
        ids=tracks.ids[kept], types=tracks.types[kept], xy=xy[kept], yaw=yaw[kept], speed=speed[kept],
        extent=tracks.extent[kept], valid=valid[kept],
    )
    return joined, [join for _, _, join in joins]
