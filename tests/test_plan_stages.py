"""The plan pipeline's contract, kept by every stage: the shapes and units of the plans, held vehicles
standing still, no speed lifted over a cap the loss asks for, the same output for the same input; the
pipeline's order and switches; what the stages report; a turn under a speed limit on real scene-0103."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

import ctgpp
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.guidance import CompositeLoss, build_guidance_batch, make_loss
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.constraints import PlanConstraints
from ctgpp.guidance.guards import GuardConfig, with_guards
from ctgpp.guidance.rules.relative import ForVehicles
from ctgpp.interfaces import Observation
from ctgpp.policies.stages import (
    PIPELINE,
    Brakes,
    Composition,
    GuidedSampling,
    PlanContext,
    PlanSet,
    Ranking,
    RouteSteering,
    SpeedCaps,
    StageConfig,
    plan_pipeline,
    run_stages,
)
from ctgpp.policies.stages.base import measure_change
from tests.support.observations import logged_x, real_observation

CAP_MPS = 3.0
TURNER = 3  # vehicle 3 of scene-0103 at 3 s: 10 m/s with a left turn 1 m ahead
STAGES = [RouteSteering(), SpeedCaps(), Ranking(), Composition(), Brakes()]


def _context(obs: Observation, loss: GuidanceLoss | None = None) -> PlanContext:
    batch = build_guidance_batch(obs, 52)
    moving = torch.from_numpy(~np.isin(obs.controlled, obs.held))
    constraints = PlanConstraints() if loss is None else loss.constraints(batch)
    return PlanContext(obs, batch, loss, constraints, moving, 0.1, StageConfig())


@pytest.fixture(scope="module")
def turn_and_cap() -> tuple[PlanSet, PlanContext]:
    """Real scene-0103 at 3 s: two samples of every vehicle's logged actions, noised; one standing vehicle
    held; the loss "vehicle 3 takes a left and drives no faster than 3 m/s" with the realism guards."""
    obs = real_observation("scene-0103", 30)
    speeds = obs.tracks.speed[obs.controlled, obs.step]
    held = obs.controlled[np.flatnonzero(speeds < 0.5)[:1]]
    assert len(held) == 1
    obs = replace(obs, held=held)
    x, window = logged_x(obs, num_samples=2, noise=0.3)
    actions = clip_actions(x[..., 4:6].transpose(0, 1).float())  # (N, V, F, 2)
    current = torch.zeros(len(obs.controlled), 4)
    current[:, 2] = torch.from_numpy(speeds.astype(np.float32))
    rows = np.flatnonzero(np.isin(obs.controlled, held))
    actions[:, rows] = 0.0
    current[rows] = 0.0
    rule = CompositeLoss([
        (make_loss("turn_at_next_intersection", vehicle=TURNER, direction="left"), 1.0),
        (ForVehicles(make_loss("speed_limit", limit_mps=CAP_MPS), vehicles=[TURNER]), 1.0),
    ])
    loss = with_guards(rule, GuardConfig())
    assert loss is not None
    return PlanSet(actions, current), _context(obs, loss)


def _speeds(plans: PlanSet) -> torch.Tensor:
    return rollout(plans.current[None], plans.actions, 0.1)[..., 2]  # (N, V, F)


@pytest.mark.parametrize("stage", STAGES, ids=lambda s: s.name)
def test_every_stage_keeps_the_contract(stage, turn_and_cap: tuple[PlanSet, PlanContext]) -> None:  # type: ignore[no-untyped-def]
    plans, ctx = turn_and_cap
    if stage.name in ("compose", "brake"):  # they act on ranked plans
        plans = Ranking().run(plans, ctx)
    before = plans.actions.clone()
    out = stage.run(plans, ctx)
    assert torch.equal(plans.actions, before)  # the input is not modified
    assert out.actions.shape == plans.actions.shape and out.actions.dtype == plans.actions.dtype
    assert out.current is plans.current or torch.equal(out.current, plans.current)
    assert torch.equal(out.actions, clip_actions(out.actions))  # within the action bounds
    held = ~ctx.moving
    assert bool((out.actions[:, held] == 0).all())  # held vehicles stand still
    cap = ctx.constraints.cap_tensor(plans.actions.shape[1])
    over_before = (_speeds(plans) - cap[None, :, None]).clamp_min(0.0)
    over_after = (_speeds(out) - cap[None, :, None]).clamp_min(0.0)
    assert bool((over_after <= over_before + 1e-4).all())  # no cap lifted
    again = stage.run(plans, ctx)
    assert torch.equal(again.actions, out.actions)  # deterministic
    assert (again.chosen is None) == (out.chosen is None)
    if out.chosen is not None:
        assert torch.equal(again.chosen, out.chosen)


def test_the_turn_is_steered_and_capped_together(turn_and_cap: tuple[PlanSet, PlanContext]) -> None:
    """The steering keeps the turner going on a clear way, but never above its cap: each step's speed is
    at most the cap, or less than the step before while it brakes down to it (10 m/s at the start)."""
    plans, ctx = turn_and_cap
    row = TURNER
    assert row in ctx.constraints.routes and ctx.constraints.speed_caps[row] == CAP_MPS
    steered = RouteSteering().run(plans, ctx)
    assert not torch.equal(steered.actions[:, row], plans.actions[:, row])
    speed = _speeds(steered)[:, row]  # (N, F)
    previous = torch.cat([plans.current[row, 2].expand(speed.shape[0], 1), speed[:, :-1]], dim=1)
    assert bool(((speed <= CAP_MPS + 1e-4) | (speed < previous)).all())
    capped = SpeedCaps().run(steered, ctx)
    assert bool((_speeds(capped)[:, row] <= speed + 1e-5).all())  # the caps only lower what steering left


def test_the_pipeline_order_and_its_switches() -> None:
    sampling = GuidedSampling(lambda obs: None, None, 2, None)  # type: ignore[arg-type]
    names = [s.name for s in plan_pipeline(sampling, StageConfig())]
    assert names == list(PIPELINE) == ["sample", "steer", "cap", "rank", "compose", "brake"]
    assert [s.name for s in plan_pipeline(sampling, StageConfig.off())] == ["sample", "rank", "compose"]
    assert [s.name for s in plan_pipeline(sampling, StageConfig.parse("brake,steer"))] == [
        "sample", "steer", "rank", "compose", "brake"]
    assert [s.name for s in plan_pipeline(sampling, StageConfig(), compose=False)] == [
        "sample", "steer", "cap", "rank", "brake"]  # --filtration scene: the paper's one sample per scene
    with pytest.raises(ValueError, match="unknown stage 'guards'"):
        StageConfig.parse("guards")


def test_a_stage_reports_the_vehicles_it_changed_and_by_how_much() -> None:
    """By hand: vehicle 1 of two, at 5 m/s, brakes at 2 m/s² for 1 s instead of driving on: 2 m/s slower
    and 1 m behind (0.1 s steps, semi-implicit Euler: 1.1 m) at the end."""
    current = torch.tensor([[0.0, 0.0, 5.0, 0.0], [0.0, 0.0, 5.0, 0.0]])
    before = PlanSet(torch.zeros(1, 2, 10, 2), current)
    braked = before.actions.clone()
    braked[0, 1, :, 0] = -2.0
    change = measure_change("brake", before, replace(before, actions=braked), 0.1)
    assert change is not None and change.vehicles == (1,)
    assert change.speed_mps == pytest.approx(2.0)
    assert change.shift_m == pytest.approx(1.1)
    assert measure_change("brake", before, before, 0.1) is None


def test_stages_run_without_a_loss_and_report_nothing_when_nothing_changes() -> None:
    obs = real_observation("scene-0103", 30)
    ctx = _context(obs)
    v = len(obs.controlled)
    plans = PlanSet(torch.zeros(2, v, 52, 2), torch.zeros(v, 4))  # everyone standing: nothing to do
    stages = [RouteSteering(), SpeedCaps(), Ranking(), Composition(), Brakes()]
    out, changes = run_stages([GuidedSampling(lambda o: None, None, 2, None), *stages],  # type: ignore[arg-type]
                              plans, replace(ctx, moving=torch.zeros(v, dtype=torch.bool)))
    assert changes == () and torch.equal(out.actions, plans.actions) and out.loss is None


@pytest.mark.model
@pytest.mark.parametrize("seed", [0, 1])
def test_a_capped_turn_never_goes_faster_than_its_limit(seed: int) -> None:
    """Closed loop on real scene-0103: "vehicle 3 should take a left at the next intersection and drive no
    faster than 3 m/s". Before the stages were declared, the steering's keep-going lifted the cap (5 m/s
    after 2 s); now vehicle 3, at 10 m/s at the start, brakes at the action bound and stays under the
    limit once it could be (0.8 s on), and metrics.json says which stages changed its plans."""
    query = "vehicle 3 should take a left at the next intersection and drive no faster than 3 m/s"
    result = ctgpp.simulate("scene-0103", query, seed=seed, start_s=3.0, duration_s=4.0)
    arrays = result.arrays()
    agent = int(np.flatnonzero(arrays["number"] == 3)[0])
    step = int(np.flatnonzero(arrays["time_s"] == 0.0)[0])
    speed = arrays["speed"][agent, step + 8 :]
    assert float(speed.max()) <= CAP_MPS + 1e-3
    stages = result.record()["stages"]
    assert stages["ran"] == list(PIPELINE)
    # the steering drives vehicle 3 along its turn under its cap: the cap stage then has nothing left
    assert 3 in stages["changed"]["steer"]["vehicles"]
    assert 3 not in stages["changed"].get("cap", {"vehicles": []})["vehicles"]


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["simulate"], StageConfig()),
        (["simulate", "--stages", "off"], StageConfig.off()),
        (["simulate", "--guards", "off"], StageConfig()),  # the guards do not switch the stages
        (["simulate", "--stages", "brake,steer"], StageConfig(stages=("steer", "brake"))),
        (["evaluate"], StageConfig.off()),  # the paper's protocol
        (["evaluate", "--stages", "on"], StageConfig()),
        (["evaluate-queries"], StageConfig()),
    ],
)
def test_stages_flag_reaches_the_config(argv: list[str], expected: StageConfig) -> None:
    from ctgpp.cli.common import stage_config
    from ctgpp.cli.main import build_parser

    assert stage_config(build_parser(argv[0]).parse_args(argv)) == expected


def test_an_unknown_stage_is_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from ctgpp.cli.main import main

    assert main(["simulate", "--stages", "steer,guards"]) != 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown stage 'guards'" in err and "steer, cap, brake" in err


@pytest.mark.model
def test_the_guards_do_not_choose_the_stages() -> None:
    """Before the pipeline was declared, ``--guards off`` silently dropped the caps, the steering and
    the brakes; now only ``--stages`` does, and the model alone runs none."""
    from ctgpp.guidance.guards import GuardConfig
    from ctgpp.policies.factory import PolicyFactory

    limit = make_loss("speed_limit", limit_mps=CAP_MPS)
    for guards in (GuardConfig(), GuardConfig.off()):
        policy = PolicyFactory.of("ctgpp", guards=guards)("ctgpp", limit)
        assert [s.name for s in policy.stages] == list(PIPELINE)  # type: ignore[attr-defined]
    paper = PolicyFactory.of("ctgpp", guards=GuardConfig.off(), stages=StageConfig.off())("ctgpp", limit)
    assert [s.name for s in paper.stages] == ["sample", "rank", "compose"]  # type: ignore[attr-defined]
    alone = PolicyFactory.of("ctgpp")("ctgpp-unguided", limit)
    assert [s.name for s in alone.stages] == ["sample", "rank", "compose"]  # type: ignore[attr-defined]
