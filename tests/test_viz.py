"""Scene pictures and rollout animations on a real nuScenes scene (scene-0103, boston-seaport)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from matplotlib.lines import Line2D
from PIL import Image

from ctgpp.data.scenarionet import load_scenarionet
from ctgpp.scene.types import AgentTracks, Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.rollout import Rollout
from ctgpp.viz import Event, animate_rollout, draw_scene, plot_scene
from ctgpp.viz import animation as animation_module
from ctgpp.viz.animation import frame_indices

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "nuscenes-mini"
START = 30


@pytest.fixture(scope="module")
def scene() -> Scene:
    return load_scenarionet(DATA / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0103.pkl", DATA / "drivable")


def log_replay(scene: Scene, start: int = START, n_future: int = 100) -> Rollout:
    """Replay of the log over [start - 30, start + n_future]; the vehicles present at start are controlled."""
    a = scene.agents
    window = slice(start - 30, start + n_future + 1)
    sim = AgentTracks(ids=a.ids, types=a.types, xy=a.xy[:, window], yaw=a.yaw[:, window],
                      speed=a.speed[:, window], extent=a.extent, valid=a.valid[:, window])
    ctrl = controlled_vehicles(scene, start)
    controlled = np.zeros(a.num_agents, dtype=bool)
    controlled[ctrl] = True
    number = np.full(a.num_agents, -1)
    number[ctrl] = np.arange(len(ctrl))
    return Rollout(scene=scene, first_step=start - 30, current=30, sim=sim, controlled=controlled,
                   number=number, policy="log replay")


def labels(fig) -> list:
    return [t for t in fig.axes[0].texts if t.get_gid() == "vehicle-label" and t.get_visible()]


def test_plot_scene_writes_png_of_expected_size(scene: Scene, tmp_path: Path) -> None:
    out = plot_scene(scene, START, tmp_path / "pics" / "scene.png")
    assert out == tmp_path / "pics" / "scene.png"
    with Image.open(out) as im:
        assert im.format == "PNG"
        assert im.size == (1600, 1600)
        pixels = np.asarray(im.convert("RGB"))
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 20  # a drawing, not a blank canvas
    assert [p.name for p in out.parent.iterdir()] == ["scene.png"]  # no temporary file left behind


def test_labels_follow_displayed_numbering(scene: Scene) -> None:
    ctrl = controlled_vehicles(scene, START)
    drawn = labels(draw_scene(scene, START))
    assert len(drawn) == len(ctrl) > 5
    by_text = {t.get_text(): np.asarray(t.xy) for t in drawn}
    assert scene.ego == ctrl[0] and "0 (ego)" in by_text
    for k, agent in enumerate(ctrl):
        text = "0 (ego)" if k == 0 else str(k)
        np.testing.assert_allclose(by_text[text], scene.agents.xy[agent, START])


def test_events_are_drawn_as_star_and_triangle(scene: Scene) -> None:
    ctrl = controlled_vehicles(scene, START)
    hit = scene.agents.xy[ctrl[3], START]
    off = np.array([[640.0, 1600.0], [650.5, 1610.25]])
    events = [Event("collision", hit, 3, 0.0), Event("offroad", off[0], 1, 1.0),
              Event("offroad", off[1], 2, 2.5)]
    fig = draw_scene(scene, START, events=events)
    markers = {ln.get_gid(): ln for ln in fig.axes[0].lines if isinstance(ln, Line2D)}
    assert markers["event-collision"].get_marker() == "*"
    assert markers["event-offroad"].get_marker() == "^"
    np.testing.assert_allclose(markers["event-collision"].get_xydata(), hit[None])
    np.testing.assert_allclose(markers["event-offroad"].get_xydata(), off)
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "collision" in legend and "off-road" in legend
    with pytest.raises(ValueError):
        Event("spin-out", hit, 0, 0.0)  # type: ignore[arg-type]


def test_rollout_picture_uses_rollout_numbers_and_window(scene: Scene, tmp_path: Path) -> None:
    rollout = log_replay(scene)
    fig = draw_scene(scene, START, rollout=rollout, radius_m=40.0)
    for label in labels(fig):
        agent = int(np.flatnonzero(rollout.number == int(label.get_text().split()[0]))[0])
        np.testing.assert_allclose(label.xy, scene.agents.xy[agent, START])
    x0, x1 = fig.axes[0].get_xlim()
    assert x1 - x0 == pytest.approx(80.0)
    np.testing.assert_allclose(np.mean(fig.axes[0].get_xlim()), scene.agents.xy[scene.ego, START, 0])
    with pytest.raises(ValueError):
        draw_scene(scene, START + 200, rollout=rollout)
    assert plot_scene(scene, START + 50, tmp_path / "later.png", rollout=rollout).is_file()


def test_animation_gif_has_one_frame_per_drawn_step(scene: Scene, tmp_path: Path) -> None:
    rollout = log_replay(scene)
    assert len(frame_indices(rollout)) == 101
    events = [Event("collision", scene.agents.xy[scene.ego, START + 40], 0, 4.0)]
    out = animate_rollout(rollout, tmp_path / "clip.gif", events=events, stride=2)
    with Image.open(out) as im:
        assert im.format == "GIF"
        assert im.n_frames == len(range(rollout.current, rollout.sim.num_steps, 2)) == 51
        assert im.size == (800, 800)
        assert im.info["duration"] == 100


def test_mp4_without_ffmpeg_falls_back_to_gif(scene: Scene, tmp_path: Path, monkeypatch, caplog) -> None:
    monkeypatch.setattr(animation_module.shutil, "which", lambda name: None)
    rollout = log_replay(scene, n_future=9)
    with caplog.at_level(logging.WARNING, logger="ctgpp.viz.animation"):
        out = animate_rollout(rollout, tmp_path / "clip.mp4", fps=5)
    assert out == tmp_path / "clip.gif" and not (tmp_path / "clip.mp4").exists()
    assert "ffmpeg" in caplog.text
    with Image.open(out) as im:
        assert im.n_frames == 10
        assert im.info["duration"] == 200
