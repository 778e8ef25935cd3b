"""Parked agents the log sees only part of the time are held at their place (scene.parked)."""

from __future__ import annotations

import numpy as np

from ctgpp.metrics.collision import collision_steps
from ctgpp.policies.factory import make_policy
from ctgpp.scene.parked import PARKED_OFF_LANE_M, fill_parked, parked_agents, parked_at_start
from ctgpp.scene.types import AgentTracks, AgentType, LaneGraph, Scene
from ctgpp.sim.closed_loop import initial_observation, simulate
from tests.support.rollouts import no_lanes

CAR = np.array([4.0, 2.0])


def _two_agents(n_steps: int = 20) -> AgentTracks:
    """Agent 0 parked at (0, 0) heading +x, logged at steps 8-11 only; agent 1 drives along +x at
    1 m per step from x = -10 at step 0, over the parked car's place at steps 7-13 (centres within
    the 4-m lengths)."""
    valid = np.zeros((2, n_steps), dtype=bool)
    valid[0, 8:12] = True
    valid[1] = True
    xy = np.zeros((2, n_steps, 2))
    xy[1, :, 0] = -10.0 + np.arange(n_steps)
    xy[0, ~valid[0]] = 0.0
    speed = np.zeros((2, n_steps))
    speed[1] = 10.0
    types = np.array([AgentType.VEHICLE, AgentType.VEHICLE], dtype=np.int8)
    return AgentTracks(
        np.array(["parked", "driver"]), types, xy, np.zeros((2, n_steps)), speed, np.stack([CAR, CAR]), valid
    )


def _copy(t: AgentTracks, n_steps: int) -> AgentTracks:
    pad = n_steps - t.num_steps

    def grow(x: np.ndarray) -> np.ndarray:
        return np.pad(x, [(0, 0), (0, pad)] + [(0, 0)] * (x.ndim - 2)).copy()

    return AgentTracks(t.ids, t.types, grow(t.xy), grow(t.yaw), grow(t.speed), t.extent.copy(), grow(t.valid))


def test_a_parked_car_is_held_where_the_log_leaves_its_place_free() -> None:
    log = _two_agents()
    # The driver's box overlaps the parked car's place while |x| < 4: steps 7..13.
    parked = parked_agents(log, np.array([-1, 0]))
    assert parked.agents.tolist() == [0]
    tracks = _copy(log, 25)
    filled = fill_parked(tracks, log, parked)
    # Back from step 8: step 7 is taken (the driver's box is there), so nothing before step 8 is
    # filled. Forward from step 11: steps 12 and 13 are taken, so nothing after.
    assert filled == 0
    assert tracks.valid[0].tolist() == log.valid[0].tolist() + [False] * 5


def test_a_parked_car_is_held_back_to_the_start_and_past_the_end_of_the_log() -> None:
    log = _two_agents()
    log.xy[0, log.valid[0]] = [0.0, 20.0]  # now 20 m to the side of the driver's path
    tracks = _copy(log, 25)
    filled = fill_parked(tracks, log, parked_agents(log, np.array([-1, 0])))
    assert tracks.valid[0].all()
    assert filled == 25 - 4
    assert np.allclose(tracks.xy[0], [0.0, 20.0]) and np.all(tracks.speed[0] == 0.0)
    assert tracks.valid[1].tolist() == [True] * 20 + [False] * 5  # the driver is not touched


def test_moving_agents_and_pedestrians_are_not_parked() -> None:
    log = _two_agents()
    log.types[0] = AgentType.PEDESTRIAN
    assert parked_agents(log, np.array([-1, -1])).agents.tolist() == []  # the driver moves 19 m


def test_scene_0103_parked_cars_stand_from_the_start_and_the_log_misses_them(scene_0103: Scene) -> None:
    """In scene-0103 the 31 vehicles that first appear in the 10 s after a 3 s start are parked
    (scene.parked's note): the simulator holds them from the start, and replaying the log collides no
    more than the log itself (its own annotation overlaps)."""
    obs = initial_observation(scene_0103, 3.0)
    step0 = obs.step
    late = np.flatnonzero(
        scene_0103.agents.is_vehicle
        & ~scene_0103.agents.valid[:, step0]
        & scene_0103.agents.valid[:, step0 + 1 : step0 + 101].any(axis=1)
    )
    parked = set(parked_agents(scene_0103.agents, np.full(scene_0103.agents.num_agents, -1)).agents.tolist())
    late_parked = [a for a in late if a in parked]
    assert len(late_parked) >= 25
    assert obs.tracks.valid[late_parked, step0].all()
    assert not obs.tracks.valid[obs.controlled, step0 + 1 :].any()  # the controlled future is the policy's

    replay = simulate(scene_0103, make_policy("replay"), 3.0)
    agents = np.flatnonzero(replay.controlled & replay.sim.is_vehicle)
    with_parked = collision_steps(replay.sim, agents, replay.future).sum()
    as_logged = collision_steps(replay.log, agents, replay.future).sum()
    assert with_parked == as_logged


# ---------------------------------------------------------------- parked at the start: past and map only


def _lane_along_x() -> LaneGraph:
    """One centerline along +x from x = -50 to 50 at y = 0."""
    edges = np.zeros((0, 2), dtype=np.int64)
    return LaneGraph(np.array(["0"]), np.array([[-50.0, 0.0], [50.0, 0.0]]), np.array([0, 2]), edges, edges,
                     np.full(1, -1), np.full(1, -1))


def _at_rest(cars: list[tuple[float, float, float]], n_steps: int = 40) -> AgentTracks:
    """Cars standing at (x, y, yaw) over ``n_steps``."""
    n = len(cars)
    xy = np.broadcast_to(np.array([[c[0], c[1]] for c in cars])[:, None], (n, n_steps, 2)).copy()
    yaw = np.broadcast_to(np.array([c[2] for c in cars])[:, None], (n, n_steps)).copy()
    return AgentTracks(np.array([f"c{i}" for i in range(n)]), np.zeros(n, dtype=np.int8), xy, yaw,
                       np.zeros((n, n_steps)), np.array([CAR] * n), np.ones((n, n_steps), dtype=bool))


def test_parked_at_start_is_off_the_travelled_path_and_at_rest_through_the_history() -> None:
    # 0 waits in the lane; 1 stands 3.5 m beside it (a kerbside car); 2 stands 2.5 m beside it (still
    # within PARKED_OFF_LANE_M: it may be waiting); 3 stands in the lane facing against it (no
    # centerline runs its way); 4 stands beside the lane but drove there within the history.
    t = _at_rest([(0.0, 0.0, 0.0), (10.0, 3.5, 0.0), (20.0, 2.5, 0.0), (30.0, 0.0, np.pi), (40.0, 3.5, 0.0)])
    t.speed[4, :25] = 5.0
    t.xy[4, :25, 0] -= 0.5 * (25 - np.arange(25))  # came from 12.5 m back
    parked = parked_at_start(t, _lane_along_x(), 30, np.arange(5), history_steps=31)
    assert parked.tolist() == [False, True, False, True, False]
    assert PARKED_OFF_LANE_M == 3.0


def test_parked_at_start_reads_no_log_after_the_start_and_no_map_parks_nobody() -> None:
    t = _at_rest([(10.0, 3.5, 0.0), (0.0, 0.0, 0.0)])
    before = parked_at_start(t, _lane_along_x(), 30, np.arange(2), history_steps=31)
    t.xy[:, 31:, 0] += np.arange(9) * 2.0  # the log drives both off after the start
    t.speed[:, 31:] = 20.0
    assert parked_at_start(t, _lane_along_x(), 30, np.arange(2), history_steps=31).tolist() == before.tolist()
    assert before.tolist() == [True, False]
    assert not parked_at_start(t, no_lanes(), 30, np.arange(2), history_steps=31).any()


def test_a_track_that_ends_while_it_moves_is_never_parked() -> None:
    """Issue 34: a car logged for two steps at 19 m/s lies within 1 m of its median, but it is driving."""
    log = _two_agents()
    log.valid[0] = False
    log.valid[0, 8:10] = True
    log.xy[0, 8:10] = [[0.0, 0.0], [1.9, 0.0]]
    log.speed[0, 8:10] = 19.0
    assert parked_agents(log, np.array([-1, 0])).agents.tolist() == []
    log.speed[0, 8:10] = 0.0  # the same two steps at rest: parked
    assert parked_agents(log, np.array([-1, 0])).agents.tolist() == [0]
