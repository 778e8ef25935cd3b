"""Joining one vehicle's track fragments (ctgpp.data.stitching): hand-made tracks, and real Waymo
scenes read with and without it."""

from __future__ import annotations

import numpy as np
import pytest

from ctgpp.data.stitching import MAX_GAP_S, MAX_MISS_M, find_joins, stitch_fragments
from ctgpp.data.waymo_json import load_waymo_json
from ctgpp.scene.types import AgentTracks, AgentType
from tests.support.data import SHARED_DATA

DT = 0.1
STEPS = 100
WAYMO = SHARED_DATA / "waymo-gpudrive"


Segment = tuple[int, int, float, float, float, float]


def _tracks(segments: list[Segment], types: list[int] | None = None) -> AgentTracks:
    """One agent per (first step, last step, x at first step, y, heading rad, speed m/s): straight at
    constant speed."""
    n = len(segments)
    xy, yaw = np.zeros((n, STEPS, 2)), np.zeros((n, STEPS))
    speed, valid = np.zeros((n, STEPS)), np.zeros((n, STEPS), dtype=bool)
    for i, (first, last, x, y, heading, v) in enumerate(segments):
        t = np.arange(last - first + 1) * DT
        xy[i, first : last + 1] = np.stack([x + v * t * np.cos(heading), y + v * t * np.sin(heading)], -1)
        yaw[i, first : last + 1], speed[i, first : last + 1], valid[i, first : last + 1] = heading, v, True
    kinds = np.asarray(types if types is not None else [AgentType.VEHICLE] * n, dtype=np.int8)
    return AgentTracks(np.asarray([f"a{i}" for i in range(n)]), kinds, xy, yaw, speed,
                       np.tile([4.5, 1.9], (n, 1)), valid)


def test_a_vehicle_found_again_where_it_would_be_is_one_track() -> None:
    # a0 drives 10 m/s along x from step 0 to 20 (x = 20 m); 0.5 s unseen; carried on, it is at x = 26
    tracks = _tracks(
        [(0, 20, 0.0, 0.0, 0.0, 10.0), (26, 60, 26.3, 0.4, 0.05, 10.0), (0, 99, 0.0, 8.0, 0.0, 5.0)]
    )
    joined, joins = stitch_fragments(tracks, DT)
    assert [(j.earlier, j.later, j.gap_steps) for j in joins] == [("a0", "a1", 5)]
    assert joins[0].miss_m == pytest.approx(np.hypot(0.3, 0.4), abs=1e-3)
    assert joined.ids.tolist() == ["a0", "a2"]
    assert joined.valid[0].tolist() == [True] * 21 + [False] * 5 + [True] * 35 + [False] * 39
    np.testing.assert_array_equal(joined.xy[0, 26:61], tracks.xy[1, 26:61])
    np.testing.assert_array_equal(joined.yaw[0, :21], tracks.yaw[0, :21])
    for name in ("xy", "yaw", "speed", "valid"):  # the other agent is untouched
        np.testing.assert_array_equal(getattr(joined, name)[1], getattr(tracks, name)[2])


@pytest.mark.parametrize(
    ("later", "kind", "why"),
    [
        ((26, 60, 26.0, MAX_MISS_M + 0.1, 0.0, 10.0), AgentType.VEHICLE, "too far from where it would be"),
        ((26, 60, 26.0, 0.0, np.radians(35.0), 10.0), AgentType.VEHICLE, "turned by more than 30 degrees"),
        ((20, 60, 20.0, 0.0, 0.0, 10.0), AgentType.VEHICLE, "overlaps the first in time"),
        ((21 + round(MAX_GAP_S / DT), 80, 20 + 10 * (1 + MAX_GAP_S), 0.0, 0.0, 10.0), AgentType.VEHICLE,
         "unseen longer than the gap"),
        ((26, 60, 26.0, 0.0, 0.0, 10.0), AgentType.PEDESTRIAN, "not a vehicle"),
    ],
)
def test_tracks_that_do_not_continue_each_other_stay_apart(later: Segment, kind: int, why: str) -> None:
    tracks = _tracks([(0, 20, 0.0, 0.0, 0.0, 10.0), later], [AgentType.VEHICLE, kind])
    joined, joins = stitch_fragments(tracks, DT)
    assert joins == [], why
    assert joined is tracks


def test_the_longest_gap_still_joins() -> None:
    gap = round(MAX_GAP_S / DT)  # steps from the last seen to the first seen again
    tracks = _tracks([(0, 20, 0.0, 0.0, 0.0, 10.0), (20 + gap, 80, 20 + 10 * MAX_GAP_S, 0.0, 0.0, 10.0)])
    assert [j.gap_steps for _, _, j in find_joins(tracks, DT)] == [gap - 1]


def test_nearest_first_one_to_one_and_chains() -> None:
    tracks = _tracks([
        (0, 20, 0.0, 0.0, 0.0, 10.0),  # a0 ends at x = 20
        (23, 40, 23.0, 1.0, 0.0, 10.0),  # a1: 1.0 m from a0 carried on
        (23, 40, 23.0, 0.2, 0.0, 10.0),  # a2: 0.2 m: a0 continues as a2, not a1
        (45, 70, 45.0, 0.3, 0.0, 10.0),  # a3: continues a2 (x = 40 + 10 m/s x 0.5 s)
    ])
    joined, joins = stitch_fragments(tracks, DT)
    assert sorted((j.earlier, j.later) for j in joins) == [("a0", "a2"), ("a2", "a3")]
    assert joined.ids.tolist() == ["a0", "a1"]
    first = np.flatnonzero(joined.valid[0])
    assert (first.min(), first.max(), int(joined.valid[0].sum())) == (0, 70, 21 + 18 + 26)
    np.testing.assert_array_equal(joined.xy[0, 45:71], tracks.xy[3, 45:71])


def test_the_kept_agent_is_never_joined() -> None:
    tracks = _tracks([(0, 20, 0.0, 0.0, 0.0, 10.0), (26, 60, 26.0, 0.0, 0.0, 10.0)])
    assert find_joins(tracks, DT, keep=0) == [] and find_joins(tracks, DT, keep=1) == []
    assert len(find_joins(tracks, DT)) == 1


@pytest.mark.skipif(not WAYMO.is_dir(), reason=f"the Waymo GPUDrive scenes are not at {WAYMO}")
@pytest.mark.parametrize("name", ["10bc6ab41ff63646.json.gz", "72d042244ac3eeb5.json.gz"])
def test_real_waymo_scene_joins_its_fragments_and_keeps_everything_else(name: str) -> None:
    raw = load_waymo_json(WAYMO / name, stitch=False)
    scene = load_waymo_json(WAYMO / name)
    joins = find_joins(raw.agents, raw.dt_s, keep=raw.ego)
    later = {j.later for _, _, j in joins}
    assert scene.agents.num_agents == raw.agents.num_agents - len(joins)
    assert scene.agents.ids.tolist() == [i for i in raw.agents.ids.tolist() if i not in later]
    assert scene.ego == raw.ego
    index = {agent_id: k for k, agent_id in enumerate(raw.agents.ids.tolist())}
    earlier = {j.earlier for _, _, j in joins}
    for k, agent_id in enumerate(scene.agents.ids.tolist()):
        src = index[agent_id]
        mine = raw.agents.valid[src]
        np.testing.assert_array_equal(scene.agents.xy[k, mine], raw.agents.xy[src, mine])
        if agent_id not in earlier:  # untouched, step for step
            np.testing.assert_array_equal(scene.agents.valid[k], mine)
    # every valid state of the file is still there, once: no step of two fragments overlaps
    assert int(scene.agents.valid.sum()) == int(raw.agents.valid.sum())
    assert joins, f"{name} has fragments to join (chosen so)"
    # no vehicle track left that begins where an ended one would be
    assert find_joins(scene.agents, scene.dt_s, keep=scene.ego) == []
