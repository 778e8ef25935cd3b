"""Lane topology reconstruction and lane projections, on hand-built roads and real nuScenes lanes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ctgpp.data.lane_topology import detect_intersections, reconstruct_connectivity
from ctgpp.scene.lanes import (
    follow_lane,
    lane_length,
    lane_points_ahead,
    lanes_ahead,
    left_lane,
    nearest_lane,
    project_to_lane,
    right_lane,
)
from ctgpp.scene.types import LaneGraph


def _straight(x0: float, x1: float, y: float, n: int = 21) -> np.ndarray:
    return np.stack([np.linspace(x0, x1, n), np.full(n, y)], axis=1)


def _graph(lines: list[np.ndarray]) -> LaneGraph:
    succ, pred, left, right = reconstruct_connectivity(lines)
    lengths = [len(line) for line in lines]
    return LaneGraph(
        ids=np.array([str(i) for i in range(len(lines))]),
        points=np.concatenate(lines),
        offsets=np.concatenate([[0], np.cumsum(lengths)]),
        successors=succ,
        predecessors=pred,
        left=left,
        right=right,
        intersection=detect_intersections(lines),
    )


@pytest.fixture(scope="module")
def road() -> LaneGraph:
    """Two eastbound lanes (y = 0 and 3.5), their continuations, a westbound lane, a right turn."""
    theta = np.linspace(np.pi / 2, 0.0, 20)  # quarter circle from (50, 0) turning right to (60, -10)
    turn = np.stack([50 + 10 * np.cos(theta), -10 + 10 * np.sin(theta)], axis=1)
    lines = [
        _straight(0, 50, 0.0),  # 0
        _straight(0, 50, 3.5),  # 1: left of 0
        _straight(50.2, 100, 0.0),  # 2: successor of 0 (0.2 m gap)
        _straight(50, 100, 3.5),  # 3: successor of 1
        _straight(100, 0, -3.5),  # 4: westbound, never a neighbour of 0
        turn,  # 5: right turn leaving the end of 0
        _straight(50, 100, 9.5),  # 6: eastbound but 6 m beside 3: no neighbour
    ]
    return _graph(lines)


def test_reconstructed_successors_and_neighbours(road: LaneGraph) -> None:
    assert road.successors.tolist() == [[0, 2], [0, 5], [1, 3]]
    assert road.predecessors.tolist() == [[2, 0], [3, 1], [5, 0]]
    assert road.left.tolist() == [1, -1, 3, -1, -1, -1, -1]
    assert road.right.tolist() == [-1, 0, -1, 2, -1, -1, -1]
    # 2 and 5 leave the same point in different directions: connectors of an intersection
    assert road.intersection.tolist() == [False, False, True, False, False, True, False]


def test_projection_on_a_straight_lane(road: LaneGraph) -> None:
    p = project_to_lane(road, 0, np.array([12.3, 1.2]))
    assert (p.lane, p.s_m, p.d_m, p.heading) == (
        0,
        pytest.approx(12.3),
        pytest.approx(1.2),
        pytest.approx(0.0),
    )
    np.testing.assert_allclose(p.xy, [12.3, 0.0], atol=1e-12)
    assert project_to_lane(road, 4, np.array([30.0, -2.0])).d_m == pytest.approx(
        -1.5
    )  # westbound: left is south
    end = project_to_lane(road, 0, np.array([55.0, 1.0]))  # past the end: clamped
    assert end.s_m == pytest.approx(50.0) and end.d_m == pytest.approx(1.0)


def test_nearest_lane_prefers_aligned_lane(road: LaneGraph) -> None:
    assert nearest_lane(road, np.array([20.0, -1.9]), 0.0).lane == 0  # closer to 4 but heading east
    assert nearest_lane(road, np.array([20.0, -1.9]), math.pi).lane == 4
    assert nearest_lane(road, np.array([20.0, 20.0]), 0.0) is None


def test_left_and_right_projection(road: LaneGraph) -> None:
    p = project_to_lane(road, 0, np.array([20.0, 0.3]))
    left = left_lane(road, p)
    assert left.lane == 1 and left.d_m == pytest.approx(-3.5) and left.s_m == pytest.approx(20.0)
    assert right_lane(road, p) is None
    assert right_lane(road, left).lane == 0


def test_lanes_ahead_and_points_ahead(road: LaneGraph) -> None:
    p = project_to_lane(road, 0, np.array([40.0, 0.0]))
    assert lanes_ahead(road, p, 5.0) == [[0]]
    assert lanes_ahead(road, p, 30.0) == [[0, 2], [0, 5]]  # straight first
    pts = lane_points_ahead(road, p, 30.0, 2.0)
    assert pts.shape == (16, 2)
    np.testing.assert_allclose(pts[0], [40.0, 0.0])
    np.testing.assert_allclose(pts[:, 1], 0.0, atol=1e-9)
    np.testing.assert_allclose(np.diff(pts[:, 0]), 2.0)  # arc length runs on across the 0.2 m gap
    short = lane_points_ahead(road, project_to_lane(road, 3, np.array([95.0, 3.5])), 30.0, 1.0)
    assert len(short) == 6  # the chain ends after 5 m


# ---- real nuScenes lanes ------------------------------------------------------------------


# scene_0103: the session fixture of conftest.py (nuScenes scene-0103 from its ScenarioNet pickle)


def test_real_successor_coverage(scene_0103) -> None:
    lanes = scene_0103.lanes
    has_successor = np.isin(np.arange(lanes.num_lanes), lanes.successors[:, 0])
    assert lanes.num_lanes == 358 and has_successor.mean() > 0.85  # README: about 90%
    ends = lanes.points[lanes.offsets[1:] - 1]
    starts = lanes.points[lanes.offsets[:-1]]
    gap = np.linalg.norm(ends[lanes.successors[:, 0]] - starts[lanes.successors[:, 1]], axis=1)
    assert gap.max() <= 0.5


def test_real_neighbours_are_on_the_correct_side(scene_0103) -> None:
    lanes = scene_0103.lanes
    for table, sign in ((lanes.left, 1.0), (lanes.right, -1.0)):
        assert (table >= 0).sum() > 50
        for i in np.flatnonzero(table >= 0):
            # the neighbour's points beside lane i, as lateral offsets seen from lane i (left +)
            beside = [project_to_lane(lanes, i, q) for q in lanes.lane(int(table[i]))]
            d = np.array(
                [sign * p.d_m for p in beside if 0 < p.s_m < lane_length(lanes, i) and abs(p.d_m) < 5.5]
            )
            correct, wrong = (d >= 1.5).sum(), (d <= -1.5).sum()
            assert correct >= 2 and correct > wrong
    left, right = lanes.left, lanes.right
    assert np.mean([right[j] == i for i, j in enumerate(left) if j >= 0]) > 0.8  # mostly mutual


def test_projection_lies_on_the_polyline(scene_0103) -> None:
    lanes = scene_0103.lanes
    rng = np.random.default_rng(1)
    for lane in rng.choice(lanes.num_lanes, 25, replace=False):
        line = lanes.lane(int(lane))
        for xy in line[rng.integers(len(line), size=4)] + rng.normal(0, 2.0, (4, 2)):
            p = project_to_lane(lanes, int(lane), xy)
            a, b = line[:-1], line[1:]
            t = np.clip(np.einsum("kd,kd->k", p.xy - a, b - a) / np.einsum("kd,kd->k", b - a, b - a), 0, 1)
            assert np.min(np.linalg.norm(a + t[:, None] * (b - a) - p.xy, axis=1)) < 1e-6
            assert 0.0 <= p.s_m <= lane_length(lanes, int(lane)) + 1e-9
            # no point of the lane is closer than the projection
            assert np.linalg.norm(xy - p.xy) <= np.min(np.linalg.norm(line - xy, axis=1)) + 1e-9
            assert abs(p.d_m) <= np.linalg.norm(xy - p.xy) + 1e-9


def _transitions(scene, follow: bool) -> tuple[int, int, int]:
    """(transitions, via successors <= 2 hops or left/right, also counting fork/merge siblings)."""
    agents, lanes = scene.agents, scene.lanes
    succ = [set(lanes.successors_of(i)) for i in range(lanes.num_lanes)]
    pred = [set(lanes.predecessors_of(i)) for i in range(lanes.num_lanes)]
    movers = [i for i in np.flatnonzero(agents.is_vehicle) if (agents.speed[i] > 1.0).sum() > 10]
    n = strict = loose = 0
    for i in movers:
        prev = None
        for t in range(agents.num_steps):
            xy, yaw = agents.xy[i, t], agents.yaw[i, t]
            proj = None
            if agents.valid[i, t] and agents.speed[i, t] > 1.0:
                proj = (
                    follow_lane(lanes, prev[0] if prev else None, xy, yaw)
                    if follow
                    else nearest_lane(lanes, xy, yaw)
                )
            if proj is not None and prev is not None and proj.lane != prev[0].lane:
                step = xy - prev[1]
                heading = agents.yaw[i, t - 1]
                lon = math.cos(heading) * step[0] + math.sin(heading) * step[1]
                lat = -math.sin(heading) * step[0] + math.cos(heading) * step[1]
                if lon > 0 and abs(lat) < 0.5:  # moving forward, no lateral jump
                    a, b = prev[0].lane, proj.lane
                    ok = (
                        b in succ[a]
                        or any(b in succ[j] for j in succ[a])
                        or b in (lanes.left[a], lanes.right[a])
                    )
                    n += 1
                    strict += ok
                    loose += ok or bool(pred[a] & pred[b]) or bool(succ[a] & succ[b])
            prev = (proj, xy) if proj is not None else None
    return n, strict, loose


def test_vehicles_move_along_reconstructed_connectivity(scene_0103) -> None:
    n, strict, loose = _transitions(scene_0103, follow=True)
    assert n >= 15
    assert strict / n >= 0.9  # measured 20 / 22
    assert loose / n >= 0.95  # the rest are fork / merge siblings: measured 22 / 22
