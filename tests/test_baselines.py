"""The CTG and BITS baselines: rasters, models, training, checkpoints, ranking and closed-loop policies,
on the embedded nuScenes scene-0103 (real data)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
import torch
from torch import Tensor

from ctgpp.baselines import (
    BITSConfig,
    BITSModel,
    CTGConfig,
    CTGDenoiser,
    checkpoint_kind,
    load_model,
    rank_candidates,
    rasterize,
)
from ctgpp.baselines.raster import CHANNELS, RasterWindow, collate_rasters
from ctgpp.cli.main import main
from ctgpp.data.catalog import Catalog
from ctgpp.data.windows import WindowConfig, build_window
from ctgpp.diffusion.guided import action_trajectories
from ctgpp.guidance import GuidanceLoss, build_guidance_batch, make_loss
from ctgpp.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from ctgpp.model.config import ModelConfig
from ctgpp.model.denoiser import Denoiser
from ctgpp.policies.bits import BITSPlanConfig, BITSPolicy
from ctgpp.policies.ctg import CTGPolicy
from ctgpp.policies.diffusion import SamplingConfig
from ctgpp.policies.factory import PolicyFactory
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import SimConfig, initial_observation, simulate
from ctgpp.train.loop import TrainConfig, train

TINY_CTG = CTGConfig(unet_width=8, cond_dim=16, map_channels=8, raster_pixels=32)
TINY_BITS = BITSConfig(hidden=32, map_channels=8, raster_pixels=32)
TRAIN = TrainConfig(30, batch_scenes=2, lr=2e-3, stride=10, val_every=15, val_windows=4, max_agents=12)
SAMPLING = SamplingConfig.evenly("ddim", 3, 2)


@pytest.fixture(scope="module", autouse=True)
def one_thread() -> Iterator[None]:
    """The machine's cores are shared: one thread avoids oversubscription stalls."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Catalog.open().load("scene-0103")


@pytest.fixture(scope="module")
def batch(scene: Scene):  # type: ignore[no-untyped-def]
    items = []
    for step in (40, 80):
        w = build_window(scene, step, WindowConfig(max_agents=10))
        items.append(RasterWindow(w, rasterize(scene, scene.agents, step, w.agent_index, TINY_CTG.raster())))
    return collate_rasters(items)


@pytest.fixture(scope="module")
def trained(scene: Scene, tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict]]:
    out = {}
    for name, config in (("ctg", TINY_CTG), ("bits", TINY_BITS)):
        path = tmp_path_factory.mktemp(name)
        torch.manual_seed(0)
        out[name] = (
            path,
            train([scene], [scene], config, TRAIN, path, data_note="scene-0103", progress=False),
        )
    return out


def _rot(yaw: np.ndarray) -> np.ndarray:
    """(A,) yaws -> (A, 2, 2) row-vector rotations: v @ R rotates v counter-clockwise by yaw."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)


def test_raster_shows_the_map_and_the_others_but_never_the_future(scene: Scene) -> None:
    step, idx = 40, build_window(scene, 40).agent_index
    raster = rasterize(scene, scene.agents, step, idx)
    assert raster.shape == (len(idx), len(CHANNELS), 64, 64) and raster.dtype == np.float32
    own = (32, 16)  # the pixel of the vehicle's own centre: row G/2, column behind_m / res
    on_road = scene.drivable.is_drivable(
        scene.agents.xy[idx, step] + [0.5, 0.0] @ _rot(scene.agents.yaw[idx, step])
    )
    np.testing.assert_array_equal(raster[:, 0, own[0], own[1]], on_road)  # the pixel 0.5 m ahead
    assert (raster[:, 1].sum((1, 2)) > 0).mean() > 0.8  # nearly every vehicle sees lanes
    norm = raster[:, 2] ** 2 + raster[:, 3] ** 2  # lane directions are unit vectors on lane pixels
    np.testing.assert_allclose(norm, raster[:, 1], atol=1e-5)
    assert raster[:, 4].sum() > 0 and raster[:, 5].sum() > 0
    a = scene.agents
    xy = a.xy.copy()
    xy[:, step + 1 :] += 30.0
    scrambled = replace(a, xy=xy)
    np.testing.assert_array_equal(raster, rasterize(scene, scrambled, step, idx))
    alone = replace(a, valid=np.zeros_like(a.valid))  # nobody else: no boxes, no trails
    lonely = rasterize(scene, alone, step, idx)
    assert lonely[:, 4:].sum() == 0 and np.array_equal(lonely[:, :4], raster[:, :4])


def test_ctg_denoises_every_vehicle_independently(batch) -> None:  # type: ignore[no-untyped-def]
    torch.manual_seed(0)
    ctg = CTGDenoiser(TINY_CTG).eval()
    # the baselines' windows: every vehicle sampled, nearest lanes (the first checkpoints' inputs)
    legacy = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=16, lane_hidden=32, context=None, map=None)
    ctgpp = Denoiser(legacy).eval()
    s, a, f = batch.num_scenes, batch.num_agents, TINY_CTG.future_steps
    x, k = torch.randn(s, a, f, 2), torch.tensor([5, 60])
    hist = batch.hist.clone()
    hist[:, 1, :, :2] += 3.0  # vehicle 1's past moves 3 m
    x2 = x.clone()
    x2[:, 1] += 1.0  # and so do its noisy actions
    changed = replace(batch, hist=hist)
    with torch.no_grad():
        out, out2 = ctg(x, k, batch), ctg(x2, k, changed)
        ref, ref2 = ctgpp(x, k, batch), ctgpp(x2, k, changed)
    assert out.shape == (s, a, f, 2)
    others = [i for i in range(a) if i != 1]
    assert torch.allclose(out[:, others], out2[:, others], atol=1e-6)
    assert not torch.allclose(out[:, 1], out2[:, 1])
    assert not torch.allclose(ref[:, others], ref2[:, others], atol=1e-4)  # CTG++ couples vehicles


def test_bits_goal_distribution_and_policy_shapes(batch) -> None:  # type: ignore[no-untyped-def]
    model = BITSModel(TINY_BITS)
    ctx = model.encode(batch)
    cells = TINY_BITS.goal_cells**2
    assert ctx.goal_logits.shape == (batch.num_scenes, batch.num_agents, cells)
    assert ctx.goal_xy.shape == (batch.num_scenes, batch.num_agents, cells, 2)
    centres = model.cell_xy  # every cell centre maps back to its own cell
    assert torch.equal(model.goal_cell(centres), torch.arange(cells))
    goals = torch.randn(batch.num_scenes, batch.num_agents, 3, 2) * 10
    assert model.policy(ctx, goals).shape == (batch.num_scenes, batch.num_agents, 3, 52, 2)


@pytest.mark.parametrize("name", ["ctg", "bits"])
def test_training_lowers_the_loss(trained: dict[str, tuple[Path, dict]], name: str) -> None:
    path, record = trained[name]
    history = record["history"]
    assert [h["step"] for h in history] == [15, 30]
    assert history[-1]["val_loss"] < history[0]["val_loss"]
    assert checkpoint_kind(path) == name
    header = json.loads((path / "config.json").read_text())
    assert header["kind"] == name and header["extra"]["steps"] == 30


def test_save_load_gives_identical_outputs(batch, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    torch.manual_seed(1)
    x, k = torch.randn(batch.num_scenes, batch.num_agents, 52, 2), torch.tensor([3, 40])
    ctg, bits = CTGDenoiser(TINY_CTG).eval(), BITSModel(TINY_BITS).eval()
    save_checkpoint(tmp_path / "ctg", ctg, TINY_CTG, {"note": "x"})
    save_checkpoint(tmp_path / "bits", bits, TINY_BITS, {})
    ctg2, config, extra, kind = load_model(tmp_path / "ctg")
    assert (config, extra, kind) == (TINY_CTG, {"note": "x"}, "ctg")
    bits2 = load_model(tmp_path / "bits")[0]
    with torch.no_grad():
        assert torch.equal(ctg(x, k, batch), ctg2(x, k, batch))
        goals = torch.ones(batch.num_scenes, batch.num_agents, 2, 2)
        assert torch.equal(bits.policy(bits.encode(batch), goals), bits2.policy(bits2.encode(batch), goals))
    with pytest.raises(CheckpointError, match="ctgpp.baselines.load_model"):
        load_checkpoint(tmp_path / "ctg")


def test_old_checkpoints_without_a_kind_load_as_ctgpp(tmp_path: Path) -> None:
    config = ModelConfig(d_model=16, heads=2, blocks=1, edge_dim=8, lane_hidden=16)
    save_checkpoint(tmp_path, Denoiser(config), config, {})
    header = json.loads((tmp_path / "config.json").read_text())
    del header["kind"]
    (tmp_path / "config.json").write_text(json.dumps(header))
    assert checkpoint_kind(tmp_path) == "ctgpp"
    assert load_checkpoint(tmp_path)[1] == config and load_model(tmp_path)[3] == "ctgpp"


class _CoupledSpeed(GuidanceLoss):
    """A coupled loss with a per-vehicle optimum: sum over vehicles of |mean speed − target_i|."""

    couples_agents: ClassVar[bool] = True

    def __init__(self, targets: list[float]) -> None:
        super().__init__()
        self.targets = torch.tensor(targets)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        return (x[..., 2].mean(-1) - self.targets[:, None]).abs().sum(0)  # (N,)


def _speed_candidates(speeds: list[list[float]]) -> Tensor:
    """Constant-speed candidate trajectories (V, M, T, 6) along each vehicle's x axis."""
    v = torch.tensor(speeds)[..., None].expand(-1, -1, 52)  # (V, M, T)
    x = torch.cumsum(v * 0.1, dim=-1)
    zeros = torch.zeros_like(v)
    return torch.stack([x, zeros, v, zeros, zeros, zeros], dim=-1)


def test_bits_ranking_picks_the_lowest_rule_loss(scene: Scene) -> None:
    data_batch = build_guidance_batch(initial_observation(scene, 3.0))
    traj = _speed_candidates([[8.0, 4.0, 12.0], [6.0, 15.0, 9.0]])
    none = torch.zeros(2, 3)
    limit = make_loss("speed_limit", limit_mps=5.0)
    assert rank_candidates(traj, none, limit, data_batch).tolist() == [1, 0]
    assert rank_candidates(
        traj, torch.tensor([[0.0, 9.0, 0.0], [0.0, 0.0, 0.0]]), limit, data_batch
    ).tolist() == [
        0,
        0,
    ]  # a large collision / off-road cost outweighs the rule
    # a coupled rule: the best candidates have different indices, which one joint index cannot reach
    assert rank_candidates(traj, none, _CoupledSpeed([12.0, 6.0]), data_batch).tolist() == [2, 0]
    assert rank_candidates(traj, none, None, data_batch).tolist() == [0, 0]


def test_bits_opt_lowers_the_rule_loss_of_its_choice(
    scene: Scene, trained: dict[str, tuple[Path, dict]]
) -> None:
    model = load_model(trained["bits"][0])[0]
    rule = make_loss("speed_limit", limit_mps=2.0)
    obs = initial_observation(scene, 3.0)
    data_batch = build_guidance_batch(obs)
    losses = []
    for steps in (0, 20):
        policy = BITSPolicy(model, BITSPlanConfig(num_goals=4, opt_steps=steps), rule)  # type: ignore[arg-type]
        c = policy.candidates(replace(obs, rng=np.random.default_rng(3)))
        traj = action_trajectories(c.planned[None], c.current, 0.1)  # (V, 1, F, 6)
        losses.append(float(rule(traj, data_batch).sum()))
    assert policy.name == "bits+opt"
    assert losses[1] < 0.9 * losses[0]


@pytest.mark.parametrize("name", ["ctg", "bits", "bits+opt"])
def test_policies_plan_and_run_closed_loop(
    scene: Scene, trained: dict[str, tuple[Path, dict]], name: str
) -> None:
    factory = PolicyFactory(
        sampling=SAMPLING,
        checkpoints={k: p for k, (p, _) in trained.items()},
        bits_opt=BITSPlanConfig(opt_steps=3),
    )
    policy = factory(name, make_loss("speed_limit", limit_mps=3.0))
    assert isinstance(policy, CTGPolicy if name == "ctg" else BITSPolicy) and policy.name == name
    obs = initial_observation(scene, 3.0)
    plan = policy.plan(obs)
    assert plan.states.shape == (len(obs.controlled), 52, 4) and np.isfinite(plan.states).all()
    rollout = simulate(scene, policy, 3.0, seed=1, config=SimConfig(duration_steps=10))
    assert rollout.policy == name and np.isfinite(rollout.sim.xy[rollout.controlled]).all()


def test_missing_baseline_checkpoint_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="ctgpp train --model ctg"):
        PolicyFactory(checkpoints={"ctg": tmp_path / "none"})("ctg")


@pytest.mark.parametrize("model", ["ctg", "bits"])
def test_train_command_trains_a_baseline(model: str, tmp_path: Path) -> None:
    argv = ["train", "--model", model, "--out", str(tmp_path), "--train", "mini_val", "--val", "mini_val"]
    argv += ["--steps", "2", "--batch", "1", "--val-every", "2", "--val-windows", "2", "--d-model", "16"]
    assert main(argv) == 0
    assert load_model(tmp_path)[3] == model
