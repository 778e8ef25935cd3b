"""What training draws (issue 35): mirrored windows are the windows of the mirrored scene, turning
windows are drawn with the chosen share, a time budget stops a run at a save it can resume from."""

from __future__ import annotations

import math
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from ctgpp.cli.train_cmd import weighted_spec
from ctgpp.data.batch import collate
from ctgpp.data.mirror import mirror_batch, mirror_scene
from ctgpp.data.sampling import is_turning, turn_weights, window_turns, window_weights
from ctgpp.data.windows import build_window
from ctgpp.model.config import ModelConfig
from ctgpp.scene.types import AgentTracks, Scene
from ctgpp.train.batches import BatchDraws
from ctgpp.train.loop import TrainConfig, train

TINY = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=16, lane_hidden=32)


@pytest.mark.parametrize("step", [30, 90, 150])
def test_the_mirrored_window_is_the_window_of_the_mirrored_scene(scene_0103: Scene, step: int) -> None:
    """Every array of the batch, lanes and drivable grid included, and the training draws (which
    vehicles are held) alike: mirroring the batch needs no rebuilt window."""
    config = ModelConfig().window_config(32)
    original = collate([build_window(scene_0103, step, config)])
    of_mirrored_scene = collate([build_window(mirror_scene(scene_0103), step, config)])
    mirrored = mirror_batch(original, torch.tensor([True]))
    assert original.num_agents > 4 and bool(original.lanes_valid.any()) and bool(original.ctx_mask.any())
    for field in fields(original):
        want, got = getattr(of_mirrored_scene, field.name), getattr(mirrored, field.name)
        assert want.shape == got.shape, field.name
        torch.testing.assert_close(got.double(), want.double(), atol=1e-4, rtol=0, msg=field.name)


def test_mirroring_only_the_flagged_windows_and_twice_is_the_original(scene_0103: Scene) -> None:
    config = ModelConfig().window_config(16)
    batch = collate([build_window(scene_0103, step, config) for step in (40, 120)])
    once = mirror_batch(batch, torch.tensor([True, False]))
    twice = mirror_batch(once, torch.tensor([True, False]))
    for field in fields(batch):
        assert torch.equal(getattr(twice, field.name), getattr(batch, field.name)), field.name
        assert torch.equal(getattr(once, field.name)[1], getattr(batch, field.name)[1]), field.name
    assert torch.equal(once.hist[0, ..., 1], -batch.hist[0, ..., 1])  # the lateral position
    assert torch.equal(once.drivable[0], batch.drivable[0].flip(-1))  # the grid's left is its right


def test_the_mirrored_scene_reflects_the_map(scene_0103: Scene) -> None:
    mirrored = mirror_scene(scene_0103)
    rng = np.random.default_rng(0)
    logged = scene_0103.agents.xy[scene_0103.agents.valid]
    points = rng.uniform(logged.min(0), logged.max(0), size=(2000, 2))
    reflected = points * np.array([1.0, -1.0])
    assert np.array_equal(mirrored.drivable.is_drivable(reflected), scene_0103.drivable.is_drivable(points))
    lanes = scene_0103.lanes
    has_left = np.flatnonzero(lanes.left >= 0)
    assert len(has_left) > 0
    assert np.array_equal(mirrored.lanes.right[has_left], lanes.left[has_left])  # its left is now its right


def _turning_agents() -> Scene:
    """Three vehicles over 9 steps at 0.1 s: one turns left by 90°, one drives straight, one stands."""
    steps = 9
    yaw = np.zeros((3, steps))
    yaw[0] = np.linspace(0.0, math.pi / 2, steps)
    speed = np.array([[8.0] * steps, [8.0] * steps, [0.0] * steps])
    xy = np.zeros((3, steps, 2))
    xy[:, :, 1] = np.arange(3)[:, None] * 10.0
    agents = AgentTracks(
        ids=np.array(["a", "b", "c"]),
        types=np.zeros(3, dtype=np.int8),
        xy=xy,
        yaw=yaw,
        speed=speed,
        extent=np.full((3, 2), [4.5, 1.9]),
        valid=np.ones((3, steps), dtype=bool),
    )
    agents.yaw[2] = -2.0  # at rest: its heading never counts
    return agents


def test_a_window_turns_by_its_largest_heading_change(scene_0103: Scene) -> None:
    scene = replace(scene_0103, agents=_turning_agents())
    assert window_turns(scene, 0, 8) == pytest.approx(math.pi / 2)
    assert window_turns(scene, 0, 4) == pytest.approx(math.pi / 4)
    assert window_turns(scene, 4, 100) == pytest.approx(math.pi / 4)  # to the last logged step
    assert list(is_turning(np.radians([44.9, 45.0, 120.0]))) == [False, True, True]


def test_turning_windows_are_drawn_with_the_chosen_share() -> None:
    turning = np.array([True, True] + [False] * 8)
    weights = turn_weights(turning, 0.5)
    assert weights.sum().item() == pytest.approx(1.0)
    assert weights[:2].tolist() == pytest.approx([0.25, 0.25])
    assert weights[2:].tolist() == pytest.approx([0.0625] * 8)
    uniform = torch.full((10,), 0.1, dtype=torch.float64)
    assert torch.equal(turn_weights(turning, 0.1), uniform)  # turns are 20 % already
    assert torch.equal(turn_weights(np.zeros(10, dtype=bool), 0.5), uniform)  # no turn to favour
    draws = torch.multinomial(weights, 20000, replacement=True, generator=torch.Generator().manual_seed(0))
    assert (draws < 2).float().mean().item() == pytest.approx(0.5, abs=0.02)
    with pytest.raises(ValueError, match="turn share"):
        turn_weights(turning, 1.0)


def test_weighted_data_sets_and_the_turn_share_compose_by_hand() -> None:
    """Windows 0-1 of a data set weighted 3, 2-5 of one weighted 1; windows 0 and 2 turn. Without a
    turn share the draws follow the weights (3, 3, 1, 1, 1, 1) / 10; with a share of 0.5 the turning
    windows (mass 4/10) get 0.5 in proportion 3:1, the others 0.5 in proportion 3:1:1:1."""
    base = np.array([3.0, 3.0, 1.0, 1.0, 1.0, 1.0])
    turning = np.array([True, False, True, False, False, False])
    assert turn_weights(turning, 0.0, base).tolist() == pytest.approx([0.3, 0.3, 0.1, 0.1, 0.1, 0.1])
    assert turn_weights(turning, 0.3, base).tolist() == pytest.approx([0.3, 0.3, 0.1, 0.1, 0.1, 0.1])
    weights = turn_weights(turning, 0.5, base).tolist()
    assert weights == pytest.approx([0.375, 0.25, 0.125, 1 / 12, 1 / 12, 1 / 12])
    with pytest.raises(ValueError, match="positive"):
        turn_weights(turning, 0.5, np.array([1.0, 0.0, 1.0, 1.0, 1.0, 1.0]))


def test_a_split_weighted_w_is_drawn_w_times_as_often(scene_0103: Scene) -> None:
    scenes = [scene_0103, scene_0103]
    items = [(0, 40), (0, 60), (1, 40), (1, 60)]
    weights, turning = window_weights(items, scenes, 0.0, scene_weights=[4.0, 1.0])
    assert turning is None and weights is not None
    assert weights.tolist() == pytest.approx([0.4, 0.4, 0.1, 0.1])
    assert window_weights(items, scenes, 0.0, scene_weights=[2.0, 2.0]) == (None, None)  # all alike
    with pytest.raises(ValueError, match="scene weights"):
        window_weights(items, scenes, 0.0, scene_weights=[1.0])


def test_the_weight_of_a_training_split_is_read_after_its_last_star() -> None:
    assert weighted_spec("mini_train") == ("mini_train", 1.0)
    assert weighted_spec("/data/waymo:train*5") == ("/data/waymo:train", 5.0)
    assert weighted_spec("/a*b/waymo:train*0.5") == ("/a*b/waymo:train", 0.5)
    for bad in ["mini_train*", "mini_train*0", "mini_train*-2", "mini_train*nan", "mini_train*x"]:
        with pytest.raises(ValueError, match="positive number"):
            weighted_spec(bad)


def test_a_time_budget_stops_at_a_save_and_the_run_resumes_to_the_same_end(
    scene_0103: Scene, tmp_path: Path
) -> None:
    """Mirrored, turn-balanced training stopped by its budget and resumed ends exactly where one
    uninterrupted run ends; a resume with other draws is refused."""
    base = TrainConfig(
        4,
        batch_scenes=2,
        lr=1e-3,
        stride=20,
        val_every=2,
        val_windows=2,
        max_agents=8,
        mirror=True,
        turn_share=0.5,
    )
    scenes = [scene_0103]
    first = train(scenes, scenes, TINY, replace(base, budget_s=1e-9), tmp_path / "cut", progress=False)
    assert first["steps"] == 2  # stopped at the first save once the budget was spent
    again = train(scenes, scenes, TINY, base, tmp_path / "cut", progress=False)
    whole = train(scenes, scenes, TINY, base, tmp_path / "whole", progress=False)
    assert again["steps"] == 4 and again["history"] == whole["history"]
    assert whole["turning_windows"] > 0
    with pytest.raises(ValueError, match="--mirror"):
        train(scenes, scenes, TINY, replace(base, mirror=False), tmp_path / "cut", progress=False)
    with pytest.raises(ValueError, match="--turn-share"):
        train(scenes, scenes, TINY, replace(base, turn_share=0.2), tmp_path / "cut", progress=False)


def test_batches_built_in_worker_processes_train_exactly_as_in_process(
    scene_0103: Scene, tmp_path: Path
) -> None:
    """The batch of a step is drawn from the step alone, so workers building them ahead change nothing."""
    base = TrainConfig(
        4, batch_scenes=2, lr=1e-3, stride=20, val_every=2, val_windows=2, max_agents=8, mirror=True
    )
    here = train([scene_0103], [scene_0103], TINY, base, tmp_path / "here", progress=False)
    ahead = train(
        [scene_0103], [scene_0103], TINY, replace(base, loader_workers=2), tmp_path / "ahead", progress=False
    )
    assert here["history"] == ahead["history"]
    want, got = (load_file(str(tmp_path / d / "model.safetensors")) for d in ("here", "ahead"))
    assert all(torch.equal(want[k], got[k]) for k in want)


def test_the_batch_of_a_step_depends_on_the_step_alone() -> None:
    draws = BatchDraws(n_items=50, size=8, seed=3, mirror=True)
    assert draws.at(7)[0] == draws.at(7)[0] and torch.equal(draws.at(7)[1], draws.at(7)[1])
    assert draws.at(7)[0] != draws.at(8)[0]
    assert BatchDraws(50, 8, seed=3, rank=1).at(7)[0] != BatchDraws(50, 8, seed=3).at(7)[0]
    streams = {
        tuple(BatchDraws(10**6, 4, seed=0, rank=r).at(s)[0]) for r in range(4) for s in range(0, 20000, 7)
    }
    assert len(streams) == 4 * len(range(0, 20000, 7))  # no process repeats another's batches later
    plain = BatchDraws(n_items=50, size=8, seed=3)
    assert plain.at(7)[0] == draws.at(7)[0] and not plain.at(7)[1].any()  # mirroring draws after the windows
