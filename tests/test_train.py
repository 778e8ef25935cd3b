"""Training: the loop lowers the loss, resumes after a stop, runs under torchrun; checkpoints sample alike."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from ctgpp.data.terms import DATA_TERMS
from ctgpp.interfaces import Observation
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.model.config import ModelConfig
from ctgpp.policies.diffusion import DiffusionPolicy, SamplingConfig
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import simulate
from ctgpp.train.loop import TrainConfig, train

TINY = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=16, lane_hidden=32)


@pytest.fixture(scope="module")
def trained(scene_0103: Scene, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("ckpt")
    cfg = TrainConfig(40, batch_scenes=2, lr=1e-3, stride=10, val_every=20, val_windows=4, max_agents=16)
    record = train([scene_0103], [scene_0103], TINY, cfg, out, data_note="scene-0103", progress=False)
    return out, record


@pytest.mark.slow
def test_training_lowers_the_loss_and_writes_a_record(trained: tuple[Path, dict]) -> None:
    out, record = trained
    history = record["history"]
    assert [h["step"] for h in history] == [20, 40]
    assert history[-1]["val_loss"] < history[0]["val_loss"]
    for name in ("model.safetensors", "config.json", "train_state.safetensors", "curve.png"):
        assert (out / name).is_file()
    extra = json.loads((out / "config.json").read_text())["extra"]
    assert extra["steps"] == 40 and extra["final_val_loss"] == pytest.approx(history[-1]["val_loss"])
    assert extra["data_terms"] == [DATA_TERMS["nuscenes"]]  # what the model may be used under


@pytest.mark.slow
def test_training_resumes_where_it_stopped(
    scene_0103: Scene, trained: tuple[Path, dict], tmp_path: Path
) -> None:
    out, record = trained
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    for name in ("model.safetensors", "config.json", "train_state.safetensors", "train_state.json"):
        (resumed / name).write_bytes((out / name).read_bytes())
    cfg = TrainConfig(60, batch_scenes=2, lr=1e-3, stride=10, val_every=20, val_windows=4, max_agents=16)
    (resumed / ".model.x1y2.tmp.safetensors").write_bytes(b"")  # what a kill during a write leaves
    again = train([scene_0103], [scene_0103], TINY, cfg, resumed, progress=False)
    assert [h["step"] for h in again["history"]] == [20, 40, 60]
    assert again["history"][:2] == record["history"] and again["rank"] == 0
    assert not list(resumed.glob(".*.tmp*"))
    # exactly where an uninterrupted run goes: the same losses and the same weights
    whole = train([scene_0103], [scene_0103], TINY, cfg, tmp_path / "whole", progress=False)
    assert whole["history"] == again["history"]
    want, got = (load_file(str(d / "train_state.safetensors")) for d in (tmp_path / "whole", resumed))
    assert want.keys() == got.keys()
    for name, tensor in want.items():
        assert torch.equal(tensor, got[name]), name


def test_loaded_checkpoint_samples_the_same_plans(scene_0103: Scene, trained: tuple[Path, dict]) -> None:
    out, _ = trained
    sampling = SamplingConfig.evenly("ddim", 5, 3)
    a = simulate(scene_0103, DiffusionPolicy(load_checkpoint(out)[0], sampling), 3.0, seed=7)
    b = simulate(scene_0103, DiffusionPolicy.from_checkpoint(out, sampling), 3.0, seed=7)
    np.testing.assert_array_equal(a.sim.xy, b.sim.xy)
    c = simulate(scene_0103, DiffusionPolicy.from_checkpoint(out, sampling), 3.0, seed=8)
    assert not np.array_equal(a.sim.xy, c.sim.xy)


def test_policy_never_sees_the_logged_future(scene_0103: Scene, trained: tuple[Path, dict]) -> None:
    """Scrambling the log after the current step changes nothing in the plan, of the controlled
    vehicles or of the replayed agents: the simulator plays the replayed agents' log, the model sees
    only their predicted future (issue 34, ``ctgpp.guidance.prediction``)."""
    out, _ = trained
    policy = DiffusionPolicy.from_checkpoint(out, SamplingConfig.evenly("ddim", 3, 2))
    step = 40
    controlled = np.array([0, 1, 2, 3])
    a = scene_0103.agents

    def scrambled_log(agents: np.ndarray) -> Scene:
        xy = a.xy.copy()
        xy[agents, step + 1 :] += 50.0
        return replace(scene_0103, agents=replace(a, xy=xy))

    def obs(scene: Scene) -> Observation:
        tracks = replace(scene.agents, valid=scene.agents.valid.copy())
        tracks.valid[controlled, step + 1 :] = False
        return Observation(scene, tracks, step, controlled, 52, np.random.default_rng(0), start_step=step)

    plan = policy.plan(obs(scene_0103)).states
    np.testing.assert_array_equal(plan, policy.plan(obs(scrambled_log(controlled))).states)
    replayed = np.setdiff1d(np.flatnonzero(a.valid[:, step]), controlled)
    assert len(replayed) > 10
    np.testing.assert_array_equal(plan, policy.plan(obs(scrambled_log(replayed))).states)


@pytest.mark.slow
def test_torchrun_two_process_training(tmp_path: Path) -> None:
    """DistributedDataParallel over two CPU processes (gloo) through torchrun."""
    out = tmp_path / "ddp"
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_port=29517",
        "-m", "ctgpp.cli.main", "train", "--out", str(out), "--train", "mini_val", "--val", "mini_val",
        "--steps", "4", "--batch", "1", "--val-every", "2", "--val-windows", "2",
        "--d-model", "16", "--heads", "2", "--blocks", "1",
    ]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    record = json.loads((out / "config.json").read_text())["extra"]
    assert record["steps"] == 4 and [h["step"] for h in record["history"]] == [2, 4]


@pytest.mark.model
def test_the_shipped_checkpoint_loads_and_plans() -> None:
    """The default policy of `ctgpp simulate`: the checkpoint inside the package, one re-plan."""
    from ctgpp.data.catalog import Catalog
    from ctgpp.policies.factory import default_checkpoint, make_policy
    from ctgpp.sim.closed_loop import initial_observation

    model, config, record = load_checkpoint(default_checkpoint())
    assert record["steps"] >= 1000 and record["final_val_loss"] < 1.5
    obs = initial_observation(Catalog.open().load("scene-0103"), 3.0)
    plan = make_policy("ctgpp", sampling=SamplingConfig.evenly("ddim", 5, 2)).plan(obs)
    assert plan.states.shape == (len(obs.controlled), 52, 4) and np.isfinite(plan.states).all()
    # Moving vehicles keep moving forward: the model learned more than noise.
    moving = obs.tracks.speed[obs.controlled, obs.step] > 3.0
    travelled = np.linalg.norm(
        plan.states[moving, -1, :2] - obs.tracks.xy[obs.controlled[moving], obs.step], axis=-1
    )
    assert (travelled > 5.0).all()


def test_a_new_run_starts_from_the_weights_it_is_given(
    scene_0103: Scene, trained: tuple[Path, dict], tmp_path: Path
) -> None:
    """``init_from``: the new run's first state holds the given weights moved by its own steps only
    (a learning rate of 1e-9 leaves them there); a run from scratch starts elsewhere."""
    out, _ = trained
    cfg = TrainConfig(1, batch_scenes=1, lr=1e-9, stride=40, val_every=1, val_windows=1, max_agents=4)
    given = load_file(str(out / "model.safetensors"))
    warm_cfg = replace(cfg, init_from=str(out))
    train([scene_0103], [scene_0103], TINY, warm_cfg, tmp_path / "warm", progress=False)
    scratch = train([scene_0103], [scene_0103], TINY, cfg, tmp_path / "cold", progress=False)
    warm = load_file(str(tmp_path / "warm" / "train_state.safetensors"))
    cold = load_file(str(tmp_path / "cold" / "train_state.safetensors"))
    for name, tensor in given.items():
        assert torch.allclose(warm[f"model.{name}"], tensor, atol=1e-6), name
    assert any(not torch.allclose(cold[f"model.{n}"], t, atol=1e-3) for n, t in given.items())
    assert scratch["steps"] == 1


def test_init_from_a_checkpoint_of_another_shape_is_refused_before_training(
    trained: tuple[Path, dict], tmp_path: Path
) -> None:
    out, _ = trained  # 1 block of d_model 32: not the default 2 of 64
    argv = ["train", "--out", str(tmp_path / "x"), "--init-from", str(out)]
    done = subprocess.run(
        [sys.executable, "-m", "ctgpp.cli.main", *argv], capture_output=True, text=True, timeout=120
    )
    assert done.returncode != 0 and "does not match the model" in done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x" / "train_state.safetensors").exists()
