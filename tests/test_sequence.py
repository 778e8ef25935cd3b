"""Sequences guide in their order (issue 36, item 6): "one by one" and "then" hold a part back until
the parts it waits for are reached, judged on the simulated past (real scene, the paper's failure
case on scene-0553)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from ctgpp.guidance import CompositeLoss, GuidanceBatch, InOrder, build_guidance_batch, make_loss
from ctgpp.guidance.composite import join_costs
from ctgpp.guidance.rules.lane_change import REACHED_M
from ctgpp.guidance.sequence import KeepPace
from ctgpp.interfaces import Observation
from ctgpp.language.compiler import compile_query
from ctgpp.language.compiler.compiled import prerequisites
from ctgpp.scene.lanes import nearest_lane
from tests.support.observations import logged_x, real_observation

FAILURE_CASE = ("vehicle 20 and 21 move to the rightmost lane one by one and then both turn right at the "
                "next intersection")
START = 40  # scene-0553 at 4 s, where the paper's failure case starts


@pytest.fixture(scope="module")
def start_obs() -> Observation:
    return real_observation("scene-0553", START)


def later(obs: Observation, steps: int, place: dict[int, np.ndarray] | None = None) -> Observation:
    """``obs`` ``steps`` later in the same episode (the log as the simulated past), with the vehicles
    of ``place`` (displayed number -> world x, y, yaw) put there at that step."""
    tracks = replace(obs.tracks, xy=obs.tracks.xy.copy(), yaw=obs.tracks.yaw.copy(),
                     valid=obs.tracks.valid.copy())
    step = obs.step + steps
    tracks.valid[obs.controlled, obs.step + 1 : step + 1] = obs.scene.agents.valid[
        obs.controlled, obs.step + 1 : step + 1]
    for v, pose in (place or {}).items():
        agent = obs.controlled[v]
        tracks.xy[agent, step], tracks.yaw[agent, step] = pose[:2], pose[2]
    return replace(obs, tracks=tracks, step=step)


def on_line(batch: GuidanceBatch, world_line: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The pose (x, y, yaw) on the polyline (M, 2) nearest ``near`` (2,), heading along it."""
    k = int(np.argmin(np.linalg.norm(world_line[:-1] - near, axis=1)))
    d = world_line[k + 1] - world_line[k]
    return np.array([*world_line[k], math.atan2(d[1], d[0])])


def test_the_failure_case_waits_one_by_one_and_each_turn_for_its_own_lane() -> None:
    compiled = compile_query(FAILURE_CASE, 30)
    assert [p.rule for p in compiled.parts] == ["move_to_rightmost_lane", "move_to_rightmost_lane",
                                                "turn_at_next_intersection", "turn_at_next_intersection"]
    assert prerequisites(compiled.parts) == [(), (0,), (0,), (1,)]
    assert isinstance(compiled.loss, InOrder) and compiled.loss.waits == [(), (0,), (0,), (1,)]
    namespace: dict = {}
    exec(compiled.code, namespace)  # the code shown builds the same sequence
    assert namespace["loss"].waits == compiled.loss.waits


def test_disjoint_vehicles_wait_for_the_stage_before() -> None:
    compiled = compile_query("vehicle 1 stops; after that vehicle 2 stops", 5)
    assert prerequisites(compiled.parts) == [(), (0,)]
    plain = compile_query("vehicle 1 stops and vehicle 2 stops", 5)
    assert isinstance(plain.loss, CompositeLoss)  # no sequence: nothing waits


def test_at_the_start_only_the_first_lane_change_guides(start_obs: Observation) -> None:
    batch = build_guidance_batch(start_obs)
    loss = compile_query(FAILURE_CASE, batch.num_vehicles).loss
    assert isinstance(loss, InOrder)
    assert loss.on(batch) == [True, False, False, False]
    x, _ = logged_x(start_obs)
    alone = CompositeLoss([(make_loss("move_to_rightmost_lane", vehicle=20), 1.0), (KeepPace(20), 1.0),
                           (KeepPace(21), 1.0), (make_loss("keep_lane", vehicle=21), 1.0)])
    assert torch.equal(loss(x, batch), alone(x, build_guidance_batch(start_obs)))
    assert loss.constraints(batch).routes == {}  # no turn is driven before its lane change


def test_a_reached_lane_releases_what_waits_for_it_and_stays_reached(start_obs: Observation) -> None:
    first = build_guidance_batch(start_obs)
    rightmost = make_loss("move_to_rightmost_lane", vehicle=20)
    line = rightmost.committed_line(first, 20)
    assert line is not None
    agent = start_obs.controlled[20]
    pose = on_line(first, line, start_obs.scene.agents.xy[agent, START + 10])
    there = build_guidance_batch(later(start_obs, 10, {20: pose}))
    assert rightmost.reached(there) is True
    loss = compile_query(FAILURE_CASE, there.num_vehicles).loss
    assert loss.on(there) == [True, True, True, False]  # vehicle 21 changes now, vehicle 20 may turn
    # vehicle 20's turn has taken over from its lane change: that part no longer guides
    assert loss.guiding(there) == [False, True, True, False]
    assert 20 in loss.constraints(there).routes and 21 not in loss.constraints(there).routes
    # 1 s on, vehicle 20 back where the log has it: reached once, so still reached
    back = build_guidance_batch(later(later(start_obs, 10, {20: pose}), 10))
    assert rightmost.reached(back) is True
    # never on the lane: not reached
    assert rightmost.reached(build_guidance_batch(later(start_obs, 10))) is False


def test_reached_needs_the_lane_not_just_its_neighbourhood(start_obs: Observation) -> None:
    first = build_guidance_batch(start_obs)
    rightmost = make_loss("move_to_rightmost_lane", vehicle=20)
    line = rightmost.committed_line(first, 20)
    assert line is not None
    pose = on_line(first, line, start_obs.scene.agents.xy[start_obs.controlled[20], START + 10])
    beside = pose.copy()
    beside[:2] += (REACHED_M + 0.3) * np.array([-math.sin(pose[2]), math.cos(pose[2])])  # left of the lane
    assert rightmost.reached(build_guidance_batch(later(start_obs, 10, {20: beside}))) is False
    turned = pose.copy()
    turned[2] += math.radians(45.0)
    assert rightmost.reached(build_guidance_batch(later(start_obs, 10, {20: turned}))) is False


def test_the_connector_from_the_lane_beside_is_not_the_rightmost_lane(start_obs: Observation) -> None:
    """Vehicle 21's committed rightmost lane (the right-turn pocket, lane 89) is continued straight on
    into the intersection's connector from the lane beside it (lane 50): a vehicle there, having come
    from its own lane, has not moved over (it counted as reached before, which handed over to its
    turn inside the intersection, a lane over). On the pocket itself it has."""
    first = build_guidance_batch(start_obs)
    rightmost = make_loss("move_to_rightmost_lane", vehicle=21)
    line = rightmost.committed_line(first, 21)
    assert line is not None
    lanes = start_obs.scene.lanes

    def lane_at(k: int) -> int:
        d = line[k + 1] - line[k]
        proj = nearest_lane(lanes, line[k], math.atan2(d[1], d[0]))
        assert proj is not None
        return proj.lane

    inside = next(k for k in range(len(line) - 1) if lanes.intersection[lane_at(k)])
    assert lane_at(inside - 10) == 89 and lane_at(inside + 5) == 368  # the straight connector from 50
    connector = on_line(first, line, line[inside + 5])
    assert rightmost.reached(build_guidance_batch(later(start_obs, 10, {21: connector}))) is False
    pocket = on_line(first, line, line[inside - 10])
    assert rightmost.reached(build_guidance_batch(later(start_obs, 10, {21: pocket}))) is True


def test_keep_pace_by_hand(start_obs: Observation) -> None:
    batch = build_guidance_batch(start_obs)
    v = 20
    x = torch.zeros(batch.num_vehicles, 2, 52, 6)
    x[v, 1, :, 4] = -1.0  # sample 1 brakes at 1 m/s², sample 0 keeps its speed
    x.requires_grad_()
    cost = KeepPace(v)(x, batch)  # (B, N)
    assert cost.shape == (batch.num_vehicles, 2)
    c = cost.detach()
    assert float(c[v, 0]) == 0.0 and float(c[:v].abs().sum() + c[v + 1 :].abs().sum()) == 0.0
    t = torch.arange(1, 53, dtype=torch.float32) * 0.1  # s: the shortfall after t is 1 m/s² · t
    w = 0.95 ** torch.arange(52, dtype=torch.float32)
    assert float(c[v, 1]) == pytest.approx(float((t * w).sum() / w.sum()), rel=1e-5)
    cost.sum().backward()
    assert x.grad is not None and float(x.grad[v, 1, :, 4].max()) < 0  # more acceleration costs less


def test_in_order_checks_its_waits() -> None:
    stop = make_loss("stop")
    with pytest.raises(ValueError, match="earlier parts"):
        InOrder([stop, stop], [(1,), ()])
    with pytest.raises(ValueError, match="one waits entry per part"):
        InOrder([stop], [(), ()])


def test_a_held_speed_hands_over_to_the_stop_after_it(start_obs: Observation) -> None:
    """"Vehicle 20 slows down to 3 m/s and then stops": at the start only the speed guides (with no pull
    to keep its pace); once the simulated past holds it for a second, the stop alone guides (not a pull
    to both speeds)."""
    compiled = compile_query("vehicle 20 slows down to 3 m/s and then stops", 30)
    loss = compiled.loss
    assert isinstance(loss, InOrder)
    first = build_guidance_batch(start_obs)
    assert loss.guiding(first) == [True, False]
    x, _ = logged_x(start_obs)
    # the speed sets vehicle 20's pace while its stop waits: no pull to keep the speed it has
    assert torch.equal(loss(x, first), join_costs([loss.parts[0](x, first)]))
    agent = start_obs.controlled[20]
    held = later(start_obs, 12)
    speed = held.tracks.speed.copy()
    speed[agent, START + 1 : START + 13] = 3.0
    at_speed = build_guidance_batch(replace(held, tracks=replace(held.tracks, speed=speed)))
    assert loss.on(at_speed) == [True, True] and loss.guiding(at_speed) == [False, True]
    assert torch.equal(loss(x, at_speed), join_costs([loss.parts[1](x, at_speed)]))
    # 0.9 s in the band is not enough
    speed[agent, START + 1 : START + 13] = [9.0, 9.0, 9.0] + [3.0] * 9
    short = build_guidance_batch(replace(held, tracks=replace(held.tracks, speed=speed)))
    assert loss.guiding(short) == [True, False]
