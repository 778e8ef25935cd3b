"""The training tracks' smoothing (ctgpp.data.smoothing): exact on constant-velocity motion to the ends
of a run, hand-computed on constant acceleration, runs never mixed, standing vehicles keep their
heading; on the real logs it removes nuScenes' keyframe kinks and NGSIM's noise while staying within
centimetres of the log; a resumed training run keeps the smoothing it started with."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ctgpp.data.smoothing import local_linear_fit, smooth_scene, smooth_tracks
from ctgpp.dynamics import inverse
from ctgpp.scene.types import AgentTracks, AgentType, Scene

DT = 0.1


def _tracks(
    xy: np.ndarray, valid: np.ndarray, types: list[int] | None = None, yaw: np.ndarray | None = None
) -> AgentTracks:
    n, t = valid.shape
    return AgentTracks(
        ids=np.arange(n),
        types=np.array(types or [AgentType.VEHICLE] * n, dtype=np.int8),
        xy=xy,
        yaw=np.zeros((n, t)) if yaw is None else yaw,
        speed=np.zeros((n, t)),
        extent=np.tile([4.5, 1.9], (n, 1)),
        valid=valid,
    )


@pytest.mark.parametrize("heading", [0.0, 0.7, -2.9])
def test_constant_velocity_is_kept_exactly_to_the_ends_of_the_track(heading: float) -> None:
    t = np.arange(40) * DT
    direction = np.array([math.cos(heading), math.sin(heading)])
    xy = (np.array([3.0, -2.0]) + 12.5 * t[:, None] * direction)[None]
    out = smooth_tracks(_tracks(xy, np.ones((1, 40), dtype=bool)), DT, sigma_s=0.3)
    np.testing.assert_allclose(out.xy, xy, atol=1e-9)
    np.testing.assert_allclose(out.speed, 12.5, atol=1e-9)
    np.testing.assert_allclose(out.yaw, heading, atol=1e-9)


def test_constant_acceleration_is_fitted_as_computed_by_hand() -> None:
    """x(t) = t² (2 m/s² from rest): in the interior the local linear fit of a symmetric kernel is x(t)
    plus the kernel's second moment m2 = Σ w d² / Σ w (its slope is exact: 2t)."""
    sigma, reach = 0.3, 9
    d = np.arange(-reach, reach + 1) * DT
    w = np.exp(-0.5 * (d / sigma) ** 2)
    m2 = float((w * d * d).sum() / w.sum())
    t = np.arange(60) * DT
    values = np.stack([t**2, np.zeros_like(t)], axis=-1)[None]
    fitted, slope = local_linear_fit(values, np.ones((1, 60), dtype=bool), DT, sigma)
    inner = slice(reach, 60 - reach)
    np.testing.assert_allclose(fitted[0, inner, 0], t[inner] ** 2 + m2, atol=1e-9)
    np.testing.assert_allclose(slope[0, inner, 0], 2 * t[inner], atol=1e-9)
    assert m2 == pytest.approx(0.09, rel=0.02)  # σ² = 0.09 s² less the cut tails: 9 cm at 2 m/s²


def test_runs_separated_by_a_gap_are_smoothed_apart() -> None:
    """Two constant-velocity runs with different velocities, separated by two invalid steps: each is
    kept exactly (nothing of one leaks into the other); invalid steps stay zeros."""
    t = np.arange(30) * DT
    xy = np.zeros((1, 30, 2))
    xy[0, :12, 0] = 10.0 * t[:12]
    xy[0, 14:, 1] = 50.0 + 4.0 * t[14:]
    valid = np.ones((1, 30), dtype=bool)
    valid[0, 12:14] = False
    out = smooth_tracks(_tracks(xy, valid), DT, sigma_s=0.3)
    np.testing.assert_allclose(out.xy, xy, atol=1e-9)
    np.testing.assert_allclose(out.speed[0, :12], 10.0, atol=1e-9)
    np.testing.assert_allclose(out.speed[0, 14:], 4.0, atol=1e-9)
    np.testing.assert_allclose(out.yaw[0, 14:], math.pi / 2, atol=1e-9)
    assert not out.xy[0, 12:14].any() and (out.valid == valid).all()


def test_a_single_step_and_a_standing_vehicle_keep_their_logged_heading() -> None:
    xy = np.zeros((2, 20, 2))
    xy[1] = [5.0, 5.0]
    xy[1, :, 0] += np.random.default_rng(0).normal(0.0, 0.02, 20)  # jitter of a parked car's box
    valid = np.zeros((2, 20), dtype=bool)
    valid[0, 7] = True
    valid[1] = True
    yaw = np.full((2, 20), 1.2)
    out = smooth_tracks(_tracks(xy, valid, yaw=yaw), DT, sigma_s=0.3)
    assert out.speed[0, 7] == 0.0 and out.yaw[0, 7] == 1.2 and (out.xy[0, 7] == xy[0, 7]).all()
    assert (out.speed[1] < 0.5).all() and (out.yaw[1] == 1.2).all()


def test_only_vehicles_are_smoothed_and_zero_keeps_the_scene(scene_0103: Scene) -> None:
    assert smooth_scene(scene_0103, 0.0) is scene_0103
    with pytest.raises(ValueError, match="bandwidth"):
        smooth_scene(scene_0103, -0.1)
    out = smooth_scene(scene_0103).agents
    a = scene_0103.agents
    others = ~a.is_vehicle
    assert others.any()
    assert (out.xy[others] == a.xy[others]).all() and (out.yaw[others] == a.yaw[others]).all()
    assert (out.valid == a.valid).all() and (out.extent == a.extent).all()


def _moving_actions(scene: Scene) -> np.ndarray:
    """Inverse-dynamics actions (N, 2) of every vehicle logged without a gap for 2 s or more and
    moving faster than 2 m/s on average."""
    actions = []
    a = scene.agents
    for i in np.flatnonzero(a.is_vehicle):
        steps = np.flatnonzero(a.valid[i])
        if steps.size < 20 or steps[-1] - steps[0] + 1 != steps.size or a.speed[i, steps].mean() < 2.0:
            continue
        states = np.concatenate([a.xy[i, steps], a.speed[i, steps, None], a.yaw[i, steps, None]], axis=-1)
        actions.append(inverse(torch.from_numpy(states), scene.dt_s).numpy())
    return np.concatenate(actions)


def test_on_real_logs_the_kinks_and_noise_go_and_the_paths_stay(shared_data: Path) -> None:
    """nuScenes scene-0553 (keyframes joined by straight lines) and an NGSIM US-101 recording: the
    actions that reproduce the smoothed tracks are those of a car (accelerations within the bounds a
    car brakes and accelerates by, few yaw-rate sign changes), where the raw tracks' are spikes; the
    smoothed positions stay within 0.3 m of the log at the 99th percentile."""
    from ctgpp.data.commonroad import load_commonroad
    from ctgpp.data.scenarionet import load_scenarionet

    nuscenes = shared_data / "nuscenes-mini"
    scenes = [
        load_scenarionet(
            nuscenes / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0553.pkl", nuscenes / "drivable"
        ),
        load_commonroad(sorted((shared_data / "commonroad-ngsim" / "US101").glob("*.xml"))[0]),
    ]
    for raw in scenes:
        smooth = smooth_scene(raw)
        raw_acts, smooth_acts = _moving_actions(raw), _moving_actions(smooth)
        raw_acc, smooth_acc = (np.percentile(np.abs(acts[:, 0]), 99) for acts in (raw_acts, smooth_acts))
        assert smooth_acc < 6.0 and smooth_acc < 0.7 * raw_acc, (raw.id, raw_acc, smooth_acc)
        flips = [_sign_changes(acts[:, 1]) for acts in (raw_acts, smooth_acts)]
        assert flips[1] < 0.6 * flips[0], (raw.id, flips)
        moved = np.linalg.norm(smooth.agents.xy - raw.agents.xy, axis=-1)
        vehicles = raw.agents.valid & raw.agents.is_vehicle[:, None]
        assert np.percentile(moved[vehicles], 99) < 0.3, raw.id


def _sign_changes(rate: np.ndarray) -> float:
    signs = np.sign(np.where(np.abs(rate) > 1e-3, rate, 0.0))
    signs = signs[signs != 0]
    return float((np.diff(signs) != 0).sum() / max(rate.size, 1))


def test_a_run_resumed_with_another_smoothing_is_refused_before_training(tmp_path: Path) -> None:
    """A training state remembers the smoothing it was trained with: resuming with another is one
    clear line and a non-zero exit, and the state is left as it was."""
    from ctgpp.model.config import ModelConfig
    from ctgpp.train.loop import TrainConfig, train

    tiny = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=16, lane_hidden=32)
    scene = _short_scene()
    cfg = TrainConfig(1, batch_scenes=1, stride=40, val_every=1, val_windows=1, max_agents=4, smooth_s=0.3)
    train([scene], [scene], tiny, cfg, tmp_path / "run", progress=False)
    before = (tmp_path / "run" / "train_state.safetensors").read_bytes()
    with pytest.raises(ValueError, match="--smooth 0.3"):
        train(
            [scene],
            [scene],
            tiny,
            dataclasses.replace(cfg, steps=2, smooth_s=0.0),
            tmp_path / "run",
            progress=False,
        )
    assert (tmp_path / "run" / "train_state.safetensors").read_bytes() == before
    argv = ["train", "--out", str(tmp_path / "run"), "--smooth", "-1"]
    done = subprocess.run(
        [sys.executable, "-m", "ctgpp.cli.main", *argv], capture_output=True, text=True, timeout=120
    )
    assert done.returncode != 0 and "--smooth -1" in done.stderr and "Traceback" not in done.stderr


def _short_scene() -> Scene:
    from ctgpp.data.catalog import Catalog

    return Catalog.open(None).load("scene-0103")
