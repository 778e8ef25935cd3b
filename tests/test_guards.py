"""Realism guards: which vehicles a loss addresses (scopes), the guard loss's contract on real
scene-0103, the collision partner left free, guarded sampling against unguided from the same seed,
and the command line's --guards."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from ctgpp.guidance import GuidanceBatch, GuidanceLoss, build_guidance_batch, make_loss
from ctgpp.guidance.base import registered_losses
from ctgpp.guidance.constraints import collide_pairs
from ctgpp.guidance.guards import (
    GUARDS_FIRST,
    GuardConfig,
    GuardedLoss,
    RealismGuards,
    guard_report,
    with_guards,
)
from ctgpp.guidance.helpers import transform_coord_agents_to_world, transform_coord_world_to_agent_i
from ctgpp.guidance.rules.relative import ForVehicles
from ctgpp.guidance.scope import LossScope
from ctgpp.language.compiler import compile_query
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.policies.diffusion import DiffusionPolicy, SamplingConfig
from ctgpp.policies.factory import default_checkpoint
from ctgpp.sim.closed_loop import held_numbers
from tests.support.observations import logged_x, real_observation
from tests.support.rule_activation import active_params

COLLIDE = make_loss("collision", vehicle_a=1, vehicle_b=2)


@pytest.fixture(scope="module")
def batch() -> GuidanceBatch:
    return build_guidance_batch(real_observation())


@pytest.fixture(scope="module")
def logged() -> torch.Tensor:
    """x (B, 2, T, 6): the logged future of every vehicle of scene-0103 at 3 s, twice, no noise."""
    return logged_x(real_observation(), num_samples=2, noise=0.0)[0]


class Opaque(GuidanceLoss):
    """A loss that does not say which vehicles it addresses (as a language model's program)."""

    def forward(self, x: torch.Tensor, data_batch: object, agt_mask: torch.Tensor | None = None) -> torch.Tensor:  # noqa: E501
        return x[..., 2].mean(-1)


# --- scopes -------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(registered_losses()))
def test_every_rule_says_which_vehicles_it_addresses(name: str, batch: GuidanceBatch) -> None:
    scope = make_loss(name, **active_params(batch)[name]).scope()
    assert not scope.opaque
    assert scope.leave_lane is not None and scope.collide is not None
    if scope.vehicles is not None:  # a rule on some vehicles leaves only those out of their lanes
        assert scope.leave_lane <= scope.vehicles


@pytest.mark.parametrize(
    ("query", "vehicles", "leave_lane", "collide"),
    [
        ("vehicle 1 should collide with vehicle 2", {1, 2}, {1, 2}, {(1, 2)}),
        ("vehicle 3 should rear-end vehicle 1", {1, 3}, {3}, {(1, 3)}),
        ("vehicle 3 should change to the left lane", {3}, {3}, set()),
        ("vehicle 3 should turn right at the next intersection", {3}, {3}, set()),
        ("vehicle 3 should cut in ahead of vehicle 5", {3, 5}, {3}, set()),
        ("vehicle 2 stays within 25 m of vehicle 0", {2}, set(), set()),  # steers only vehicle 2
        ("vehicle 4 should follow its lane", {4}, set(), set()),
        ("vehicle 2 should not exceed 5 m/s", {2}, set(), set()),
    ],
)
def test_compiled_queries_expose_their_vehicles(
    query: str, vehicles: set[int], leave_lane: set[int], collide: set[tuple[int, int]]
) -> None:
    scope = compile_query(query, 12).loss.scope()
    assert (scope.vehicles, scope.leave_lane, scope.collide) == (vehicles, leave_lane, collide)


@pytest.mark.parametrize(
    "query,moves",
    [
        ("vehicle 5 should drive in the same direction as vehicle 0", {5}),
        ("vehicle 3 should change to the left lane", {3}),
        ("vehicle 2 should not exceed 5 m/s", {2}),
        ("vehicle 1 should collide with vehicle 2", {1, 2}),
        ("keep vehicle 4 at least 12 m away from vehicle 0", set()),  # vehicle 0 keeps it when 4 is held
        ("vehicle 2 stays within 25 m of vehicle 0", set()),
        ("keep vehicle 4 at least 12 m away from vehicle 0 and vehicle 4 should drive at 5 m/s", {4}),
        ("all vehicles stay below 10 m/s and no collisions", set()),
    ],
)
def test_the_vehicles_a_query_steers_are_driven_even_when_parked(query: str, moves: set[int]) -> None:
    assert compile_query(query, 12).loss.scope().moves == moves


def test_an_opaque_loss_drives_no_parked_vehicle() -> None:
    assert Opaque().scope().moves == set() and LossScope.everyone().moves == set()
    assert LossScope.everyone().restricted([3]).moves == {3}  # "vehicle 3 obeys the limit" steers it


def test_global_rules_address_everyone_and_keep_them_in_lane() -> None:
    scope = compile_query("all vehicles stay below 10 m/s and no collisions", 12).loss.scope()
    assert scope.vehicles is None and scope.keeps_lane(3) and not scope.may_collide(1, 2)


def test_an_opaque_loss_lifts_the_lane_guard_and_the_vehicle_pairs() -> None:
    scope = Opaque().scope()
    assert scope.opaque and not scope.keeps_lane(0) and scope.may_collide(0, 5)
    assert len(collide_pairs(scope, 4)) == 6
    report = guard_report(GuardConfig(), scope, 4)
    assert report["addressed"] == "unknown" and report["lane"]["vehicles"] == []
    assert report["follow"]["vehicles"] == []  # an opaque loss may set any vehicle's pace


def test_scopes_join_and_restrict() -> None:
    joined = COLLIDE.scope().union(make_loss("lane_change", vehicle=5).scope())
    assert joined.vehicles == {1, 2, 5} and joined.leave_lane == {1, 2, 5}
    opaque = LossScope.unknown().restricted([2, 3])
    assert (opaque.vehicles, opaque.leave_lane, opaque.collide) == ({2, 3}, {2, 3}, {(2, 3)})
    assert opaque.opaque
    steered = make_loss("keep_distance", follower=2, leader=0).scope().restricted([2])
    assert steered == LossScope.of([2])


# --- the guard loss ------------------------------------------------------------------------------


@pytest.mark.parametrize("guards", [("offroad", "collision", "lane"), ("offroad", "lane"), ("collision",)])
def test_contract_shape_and_gradients_where_the_guards_act(
    guards: tuple[str, ...], batch: GuidanceBatch, logged: torch.Tensor
) -> None:
    """Vehicle 3 drives onto vehicle 4's place (out of its lane, into a parked car): finite costs of
    the contract's shape and finite, non-zero gradients on its row."""
    loss = RealismGuards(GuardConfig(guards=guards))
    x = _moved_onto(logged, batch, 3, 4).requires_grad_(True)
    cost = loss(x, batch)
    assert cost.shape == ((2,) if "collision" in guards else (x.shape[0], 2))
    assert torch.isfinite(cost).all() and float(cost.detach().sum()) > 0
    cost.sum().backward()
    assert torch.isfinite(x.grad).all() and float(x.grad[3].abs().sum()) > 0


def test_zero_for_a_vehicle_in_its_lane_on_the_road_far_from_everyone(
    batch: GuidanceBatch, logged: torch.Tensor
) -> None:
    """Vehicle 5 (9 m/s) on its logged future: no cost and no gradient from any guard."""
    x = logged.clone().requires_grad_(True)
    per_vehicle = RealismGuards(GuardConfig(guards=("offroad", "lane")))(x, batch)
    assert float(per_vehicle[5].detach().abs().sum()) == 0.0
    RealismGuards(GuardConfig())(x, batch).sum().backward()
    assert float(x.grad[5].abs().sum()) == 0.0


def test_a_vehicle_asked_to_collide_is_not_pushed_away_from_its_partner(
    batch: GuidanceBatch, logged: torch.Tensor
) -> None:
    """Vehicle 5 drives onto vehicle 0's path (both clear of everyone else in the log): the collision
    guard pushes them apart, except under a rule that asks them to collide; a third vehicle on that
    path is still kept away from both."""
    x = _moved_onto(logged, batch, 5, 0)
    crash = make_loss("collision", vehicle_a=5, vehicle_b=0)
    guard = RealismGuards(GuardConfig(guards=("collision",)), crash.scope())
    plain = RealismGuards(GuardConfig(guards=("collision",)))
    for loss, pushed in ((plain, True), (guard, False)):
        xg = x.clone().requires_grad_(True)
        loss(xg, batch).sum().backward()
        assert (float(xg.grad[[0, 5]].abs().sum()) > 0) == pushed
    x3 = _moved_onto(x, batch, 10, 0).requires_grad_(True)
    guard(x3, batch).sum().backward()
    assert float(x3.grad[10].abs().sum()) > 0 and float(x3.grad[0].abs().sum()) > 0


def test_with_guards_composes_the_rule_and_the_guards(batch: GuidanceBatch, logged: torch.Tensor) -> None:
    assert with_guards(COLLIDE, GuardConfig.off()) is COLLIDE
    assert isinstance(with_guards(None, GuardConfig()), RealismGuards)
    both = with_guards(make_loss("speed_limit", limit_mps=3.0), GuardConfig(rule_weight=2.0))
    assert both is not None and both.couples_agents and both(logged, batch).shape == (2,)
    # the two apart (the guidance step lets the guards win where they conflict) sum to the whole
    assert isinstance(both, GuardedLoss)
    rule, guards = both.parts(logged, batch)
    torch.testing.assert_close(rule.sum(0) + guards, both(logged, batch))
    torch.testing.assert_close(rule, 2.0 * make_loss("speed_limit", limit_mps=3.0)(logged, batch))
    # filtration ranks the guards first: their cost GUARDS_FIRST times, then the rule's
    torch.testing.assert_close(both.ranking(logged, batch), rule.sum(0) + GUARDS_FIRST * guards)


@pytest.mark.model
def test_the_guarded_plan_costs_the_guards_less() -> None:
    """The shipped model on scene-0103 at 3 s, one re-plan of the default sampler from the same seed,
    three seeds: the plan the guarded policy executes (a sample per vehicle, chosen by the guards)
    costs the guards less than the unguided one. (Single samples may cost more: at the last steps'
    clip radius a guidance step moves every action it touches by up to 0.3; the choice among the N
    samples keeps the ones it helped.) The vehicles parked at the start are held, as the simulator
    holds them."""
    obs = real_observation()
    held = held_numbers(obs.scene, obs.tracks, obs.step, obs.controlled, True)
    obs = replace(obs, held=obs.controlled[held])
    guards = RealismGuards(GuardConfig())
    model = load_checkpoint(default_checkpoint())[0]
    data_batch = build_guidance_batch(obs, 52)
    for seed in range(3):
        costs = []
        for loss in (None, guards):
            samples = DiffusionPolicy(model, SamplingConfig(), loss).sample_plans(
                replace(obs, rng=np.random.default_rng(seed))
            )
            v = samples.chosen.shape[0]
            plan = samples.trajectories[torch.arange(v), samples.chosen][:, None]  # (V, 1, F, 6)
            costs.append(float(guards(plan, data_batch).sum()))
        assert costs[1] < costs[0], (seed, costs)


# --- command line --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["simulate"], GuardConfig()),
        (["simulate", "--guards", "off"], GuardConfig.off()),
        (["simulate", "--no-guards"], GuardConfig.off()),
        (["simulate", "--guards", "lane,offroad"], GuardConfig(guards=("offroad", "lane"))),
        (["evaluate"], GuardConfig.off()),
        (["evaluate", "--guards", "on"], GuardConfig()),
    ],
)
def test_guards_flag_reaches_the_config(argv: list[str], expected: GuardConfig) -> None:
    from ctgpp.cli.common import guard_config
    from ctgpp.cli.main import build_parser

    assert guard_config(build_parser(argv[0]).parse_args(argv)) == expected


def test_an_unknown_guard_is_refused() -> None:
    from ctgpp.cli.main import main

    assert main(["simulate", "--guards", "offroad,speed"]) != 0


@pytest.mark.model
@pytest.mark.parametrize("guards", ["on", "off"])
def test_metrics_record_the_guards(guards: str, tmp_path: Path) -> None:
    from ctgpp.cli.main import main

    out = tmp_path / "run"
    argv = ["simulate", "vehicle 1 should collide with vehicle 2", "--scene", "0103", "--steps", "2",
            "--samples", "1", "--animation", "none", "--guards", guards, "--out", str(out)]
    assert main(argv) == 0
    record = json.loads((out / "metrics.json").read_text())["guards"]
    if guards == "off":
        assert record["ran"] == []
        return
    assert record["ran"] == ["offroad", "collision", "lane", "follow"] and record["addressed"] == [1, 2]
    assert record["collision"]["exempt_pairs"] == [[1, 2]]
    moving = record["offroad"]["vehicles"]
    assert 1 in moving and 2 in moving and not set(record["held"]) & set(moving)
    assert set(record["lane"]["vehicles"]) == set(moving) - {1, 2}
    assert set(record["follow"]["vehicles"]) == set(moving) - {1, 2}  # the pair sets its own pace


def test_policies_without_diffusion_take_no_guards(tmp_path: Path) -> None:
    from ctgpp.cli.main import main

    out = tmp_path / "run"
    argv = ["simulate", "--scene", "0103", "--policy", "constvel", "--animation", "none", "--out", str(out)]
    assert main(argv) == 0
    record = json.loads((out / "metrics.json").read_text())["guards"]
    assert record["ran"] == [] and "takes no guards" in record["note"]


def _moved_onto(x: torch.Tensor, batch: GuidanceBatch, mover: int, target: int) -> torch.Tensor:
    """x with vehicle ``mover`` 1 m beside vehicle ``target`` (world frame), so that they overlap at
    every step (not exactly on top of it: there the overlap's gradient vanishes by symmetry)."""
    pos_w, yaw_w = transform_coord_agents_to_world(x[..., :2], x[..., 3:4], batch)
    beside = pos_w[target] + torch.tensor([0.6, 0.8])
    pos_i, yaw_i = transform_coord_world_to_agent_i(beside, yaw_w[target], batch, mover)
    out = x.clone()
    out[mover, ..., :2], out[mover, ..., 3:4] = pos_i, yaw_i
    return out



def test_the_vehicles_involved_are_those_in_a_term_that_costs(
    batch: GuidanceBatch, logged: torch.Tensor
) -> None:
    """Vehicle 3 drives onto vehicle 4's place: both are involved (their overlap costs), with every
    vehicle whose own off-road, lane or follow term costs anything; vehicle 5 on its logged future (no
    cost and no gradient, test above) is not. With a rule, the vehicles the rule reads join them: all
    for a global limit, the named one for a limit on one vehicle; a rule that cannot tell (no collision
    for one vehicle, which reads every pair with it) leaves every vehicle to try."""
    guards = RealismGuards(GuardConfig())
    scene = _moved_onto(logged, batch, 3, 4)[:, :1]
    involved = guards.involved(scene, batch)
    assert involved is not None and involved.shape == (scene.shape[0],) and involved.dtype == torch.bool
    assert bool(involved[3]) and bool(involved[4]) and not bool(involved[5])
    costs = RealismGuards(GuardConfig(guards=("offroad", "lane", "follow")))(scene, batch)[:, 0]  # (B,)
    assert bool(involved[costs > 0].all())
    apart = RealismGuards(GuardConfig(guards=("collision",))).involved(logged[:, :1], batch)
    assert apart is not None and not bool(apart[4]) and not bool(apart[5])  # on the log: clear
    everyone = GuardedLoss(make_loss("speed_limit", limit_mps=3.0), guards).involved(scene, batch)
    assert everyone is not None and bool(everyone.all())
    limit_5 = ForVehicles(make_loss("speed_limit", limit_mps=3.0), [5])
    one = GuardedLoss(limit_5, guards).involved(scene, batch)
    assert one is not None and one.tolist() == (involved | (torch.arange(len(involved)) == 5)).tolist()
    near = GuardedLoss(ForVehicles(make_loss("no_collision"), [3]), guards)
    assert near.involved(scene, batch) is None


def test_which_vehicles_a_rule_reads() -> None:
    """A separable rule restricted to some vehicles reads theirs; a pair rule its pair; a sum, every
    part's; a sequence, every part's and those it keeps to their pace; a rule that cannot tell, None."""
    from ctgpp.guidance import CompositeLoss, InOrder

    limit = make_loss("speed_limit", limit_mps=3.0)
    assert limit.reads(4) == frozenset({0, 1, 2, 3})
    assert ForVehicles(limit, [2]).reads(4) == frozenset({2})
    assert make_loss("keep_distance", follower=1, leader=3).reads(4) == frozenset({1, 3})
    assert make_loss("stay_away", vehicle=0, other=2).reads(4) == frozenset({0, 2})
    assert make_loss("keep_lane", vehicle=1).reads(4) == frozenset({1})
    assert ForVehicles(make_loss("no_collision"), [2]).reads(4) is None  # one vehicle against all
    both = CompositeLoss([(ForVehicles(limit, [2]), 1.0), (make_loss("keep_lane", vehicle=0), 1.0)])
    assert both.reads(4) == frozenset({0, 2})
    assert make_loss("cut_in", vehicle=1, ahead_of=2).reads(4) == frozenset({1, 2})
    assert make_loss("turn_at_next_intersection", vehicle=3, direction="left").reads(4) == frozenset({3})
    assert CompositeLoss([(limit, 1.0), (ForVehicles(make_loss("no_collision"), [2]), 1.0)]).reads(4) is None
    speed, stop = make_loss("target_speed", speed_mps=5.0), make_loss("stop")
    then = InOrder([ForVehicles(speed, [1]), ForVehicles(stop, [1])], [(), (0,)])
    assert then.reads(4) == frozenset({1})
