"""Scene pictures and rollout animations on a real nuScenes scene (scene-0103, boston-seaport)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_rgba
from matplotlib.lines import Line2D
from PIL import Image

from ctgpp.data.scenarionet import load_scenarionet
from ctgpp.interfaces import Rollout
from ctgpp.metrics import vehicle_events
from ctgpp.scene.types import AgentTracks, AgentType, Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.viz import (
    Event,
    QueryCaption,
    animate_rollout,
    draw_scene,
    event_lines,
    plot_scene,
    rollout_events,
)
from ctgpp.viz import animation as animation_module
from ctgpp.viz.animation import Clip, frame_indices
from ctgpp.viz.colors import REPLAYED_COLORS, VEHICLE_PALETTE, vehicle_color
from ctgpp.viz.painter import EVENT_FRESH_S, MARKER_FACE_ALPHA

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


# ------------------------------------------------------------- pictures that explain (issue 18)


def crashed_replay(scene: Scene) -> Rollout:
    """The log replay with vehicle 1 driven into vehicle 2 over the first 4 s, and vehicle 4 put on a
    spot off the road (on the map) from t = 3 s on."""
    r = log_replay(scene)
    xy = r.sim.xy.copy()
    v1, v2, v4 = (int(np.flatnonzero(r.number == k)[0]) for k in (1, 2, 4))
    for k in range(r.current, r.sim.num_steps):
        f = min(1.0, (k - r.current) / 40)
        xy[v1, k] = (1 - f) * xy[v1, r.current] + f * xy[v2, k]
    area = scene.drivable
    offsets = np.stack(np.meshgrid(np.arange(-30, 31), np.arange(-30, 31)), -1).reshape(-1, 2)  # (G, 2) m
    grid = xy[v4, r.current] + offsets
    disks = grid[:, None] + 4.0 * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])[None]  # (G, 5, 2)
    off = ~area.is_drivable(disks).any(axis=1) & area.covers(disks).all(axis=1)
    xy[v4, r.current + 30 :] = grid[np.flatnonzero(off)[0]]
    sim = AgentTracks(ids=r.sim.ids, types=r.sim.types, xy=xy, yaw=r.sim.yaw, speed=r.sim.speed,
                      extent=r.sim.extent, valid=r.sim.valid)
    return Rollout(scene=scene, first_step=r.first_step, current=r.current, sim=sim, controlled=r.controlled,
                   number=r.number, policy="edited replay")


def by_gid(fig, gid: str) -> list:
    return [a for a in fig.axes[0].get_children() if a.get_gid() == gid]


def test_every_numbered_vehicle_has_its_own_colour() -> None:
    colors = np.array([vehicle_color(n) for n in range(60)])[:, :3]  # (60, 3)
    distance = np.linalg.norm(colors[:, None] - colors[None], axis=-1)  # (60, 60)
    np.fill_diagonal(distance, np.inf)
    assert distance.min() > 0.0  # sixty vehicles (a US101 scene has 50), sixty colours
    first = len(VEHICLE_PALETTE)
    assert distance[:first, :first].min() > 0.25  # the palette's colours are far apart
    saturation = colors.max(axis=1) - colors.min(axis=1)
    assert saturation.min() > 0.15  # none is grey, the colour of replayed agents
    for grey in REPLAYED_COLORS.values():
        rgb = np.array(to_rgba(grey)[:3])
        assert (rgb.max() - rgb.min()) < 0.1


def test_boxes_and_tags_wear_the_vehicle_colour(scene: Scene) -> None:
    rollout = log_replay(scene)
    fig = draw_scene(scene, START, rollout=rollout)
    (boxes,) = by_gid(fig, "agent-boxes")
    shown = np.flatnonzero(rollout.sim.valid[:, rollout.current])
    faces = boxes.get_facecolor()  # (shown, 4), in agent order
    assert len(faces) == len(shown)
    numbered = [(a, int(rollout.number[a])) for a in shown if rollout.number[a] >= 0]
    for i, a in enumerate(shown):
        if rollout.number[a] >= 0:
            np.testing.assert_allclose(faces[i], vehicle_color(int(rollout.number[a])))
        else:
            assert faces[i][:3].max() - faces[i][:3].min() < 0.1  # replayed agents are grey
    assert len({tuple(faces[i]) for i, a in enumerate(shown) if rollout.number[a] >= 0}) == len(numbered)
    tags = {int(t.get_text().split()[0]): t.get_bbox_patch().get_facecolor() for t in labels(fig)}
    assert sorted(tags) == sorted(n for _, n in numbered)
    for n, face in tags.items():
        np.testing.assert_allclose(face, vehicle_color(n))


def test_event_list_and_marks_match_the_metrics_events(scene: Scene) -> None:
    rollout = crashed_replay(scene)
    records = vehicle_events(rollout)  # the events of metrics.json
    collided = {(r["vehicle"], r["collision"]["vehicle"], r["collision"]["time_s"]) for r in records
                if r["collision"] is not None}
    offroad = {(r["vehicle"], r["offroad"]["time_s"]) for r in records if r["offroad"] is not None}
    assert {(v, p) for v, p, _ in collided} >= {(1, 2), (2, 1)} and offroad == {(4, 3.0)}

    events = rollout_events(rollout)
    fig = draw_scene(scene, START, rollout=rollout, events=events)
    (listing,) = by_gid(fig, "event-list")
    lines = listing.get_text().splitlines()[1:]
    pairs = {frozenset((v, p)) for v, p, _ in collided}
    assert len(lines) == len(pairs) + len(offroad)  # a crash of two numbered vehicles is listed once
    for v, p, t in collided:
        assert (f"{t:4.1f} s  collision  vehicle {v} × vehicle {p}" in lines
                or f"{t:4.1f} s  collision  vehicle {p} × vehicle {v}" in lines)
    for v, t in offroad:
        assert f"{t:4.1f} s  off-road   vehicle {v}" in lines
    # marked where they happen: the crash midway between the two cars, the off-road car where it went
    (stars,) = by_gid(fig, "event-collision")
    (triangles,) = by_gid(fig, "event-offroad")
    assert len(stars.get_xydata()) == len(pairs)
    v1, v2, v4 = (int(np.flatnonzero(rollout.number == k)[0]) for k in (1, 2, 4))
    t12 = rollout.current + round(min(t for v, _, t in collided if v == 1) / rollout.dt_s)
    np.testing.assert_allclose(stars.get_xydata()[0], (rollout.sim.xy[v1, t12] + rollout.sim.xy[v2, t12]) / 2)
    np.testing.assert_allclose(triangles.get_xydata(), rollout.sim.xy[v4, rollout.current + 30][None])


def test_no_event_list_on_a_picture_without_events(scene: Scene) -> None:
    fig = draw_scene(scene, START)
    (listing,) = by_gid(fig, "event-list")
    assert listing.get_text() == ""
    lines = event_lines([])
    assert lines == ["none"]


def test_query_and_verdict_in_the_title_and_its_vehicles_highlighted(scene: Scene) -> None:
    rollout = log_replay(scene)
    for satisfied, word, colour in ((True, "met", "#1a7f37"), (False, "not met", "#c62828"),
                                    (None, "not checked", "#555555")):
        query = QueryCaption("vehicle 1 should collide with vehicle 2", satisfied, frozenset({1, 2}))
        fig = draw_scene(scene, START, rollout=rollout, query=query)
        (verdict,) = by_gid(fig, "query-verdict")
        assert verdict.get_text().startswith('query "vehicle 1 should collide with vehicle 2": ' + word)
        assert to_rgba(verdict.get_color()) == to_rgba(colour)
    (boxes,) = by_gid(fig, "agent-boxes")
    shown = np.flatnonzero(rollout.sim.valid[:, rollout.current])
    widths = dict(zip(rollout.number[shown].tolist(), boxes.get_linewidth(), strict=True))
    assert min(widths[1], widths[2]) > 2 * max(w for n, w in widths.items() if n not in (1, 2))
    edges = {int(t.get_text().split()[0]): t.get_bbox_patch().get_linewidth() for t in labels(fig)}
    assert min(edges[1], edges[2]) > 2 * max(w for n, w in edges.items() if n not in (1, 2))
    report = {"text": "vehicle 3 should stop", "satisfied": "unknown (no independent check)", "vehicles": [3]}
    assert QueryCaption.from_report(report) == QueryCaption("vehicle 3 should stop", None, frozenset({3}))


def test_parked_cars_are_in_the_first_frame(scene: Scene) -> None:
    rollout = log_replay(scene)
    clip = Clip(rollout)
    (ghosts,) = by_gid(clip.figure, "parked-ghosts")
    (boxes,) = by_gid(clip.figure, "agent-boxes")
    sim, first, last = rollout.sim, int(clip.indices[0]), int(clip.indices[-1])
    later = np.flatnonzero((rollout.number < 0) & ~sim.valid[:, first] & sim.valid[:, first:].any(axis=1)
                           & (sim.types == AgentType.VEHICLE))
    parked = [a for a in later if np.ptp(sim.xy[a][sim.valid[a]], axis=0).max() < 0.7]
    assert len(parked) > 10  # scene-0103's parked cars enter the log only as the ego comes near

    def centres(collection) -> np.ndarray:
        return np.array([p.vertices[:4].mean(axis=0) for p in collection.get_paths()]).reshape(-1, 2)

    clip.frame(first)
    assert len(boxes.get_paths()) == sim.valid[:, first].sum()
    assert len(centres(ghosts)) >= len(parked)
    for a in parked:  # each is drawn in frame 0, where the log will show it
        seen = sim.xy[a, np.argmax(sim.valid[a])]
        assert np.linalg.norm(centres(ghosts) - seen, axis=-1).min() < 1.0
    walkers = np.flatnonzero((sim.types == AgentType.PEDESTRIAN) & ~sim.valid[:, first])
    assert len(walkers) and not np.isin(walkers, clip.painter.parked.agents).any()  # people are not parked

    clip.frame(last)  # those the log holds now are drawn solid, not also as a ghost
    solid = centres(boxes)
    assert len(centres(ghosts)) < len(parked)
    for ghost in centres(ghosts):
        assert np.linalg.norm(solid - ghost, axis=-1).min() > 0.3


def test_collision_marks_appear_when_it_happens_and_never_cover_a_number(scene: Scene) -> None:
    rollout = crashed_replay(scene)
    events = rollout_events(rollout)
    t_crash = min(e.time_s for e in events if e.kind == "collision")
    clip = Clip(rollout, events=events)
    (recent,) = by_gid(clip.figure, "event-collision")
    (past,) = by_gid(clip.figure, "event-collision-past")
    step = rollout.current + round(t_crash / rollout.dt_s)
    clip.frame(step - 1)
    assert len(recent.get_xydata()) == len(past.get_xydata()) == 0
    assert "none" in by_gid(clip.figure, "event-list")[0].get_text()
    clip.frame(step)
    assert len(recent.get_xydata()) == 1 and len(past.get_xydata()) == 0
    clip.frame(step + round(EVENT_FRESH_S / rollout.dt_s) + 1)
    assert len(recent.get_xydata()) == 0 and len(past.get_xydata()) == 1

    # A star put on every vehicle's tag at t = 0: in the frame the tags show their colour, no gold.
    renderer = clip.figure.canvas.get_renderer()
    tags = {a: t for a, t in clip.painter._labels.items() if rollout.sim.valid[a, rollout.current]}
    clip.frame(rollout.current)
    boxes = {a: tag.get_bbox_patch().get_window_extent(renderer) for a, tag in tags.items()}
    to_data = clip.painter.ax.transData.inverted()
    clip.events = [Event("collision", to_data.transform(((b.x0 + b.x1) / 2, (b.y0 + b.y1) / 2)),
                         int(rollout.number[a]), 0.0) for a, b in boxes.items()]
    frame = clip.frame(rollout.current).astype(float) / 255.0
    gold = np.array(to_rgba("#ffd700")[:3])
    height = frame.shape[0]
    for a, b in boxes.items():
        rows = slice(height - int(b.y1) + 2, height - int(b.y0) - 2)
        region = frame[rows, int(b.x0) + 2 : int(b.x1) - 2].reshape(-1, 3)
        own = np.abs(region - np.array(vehicle_color(int(rollout.number[a]))[:3])).max(axis=1) < 0.08
        assert own.mean() > 0.25, a
        assert (np.abs(region - gold).max(axis=1) < 0.1).sum() == 0, a


def test_the_gif_keeps_every_vehicle_colour_and_the_collision_marker(scene: Scene, tmp_path: Path) -> None:
    rollout = crashed_replay(scene)
    events = rollout_events(rollout)
    out = animate_rollout(rollout, tmp_path / "clip.gif", events=events, stride=5)
    crash = rollout.current + round(min(e.time_s for e in events if e.kind == "collision") / rollout.dt_s)
    indices = frame_indices(rollout, 5)
    with Image.open(out) as im:
        im.seek(0)
        first = {tuple(c) for c in np.asarray(im.convert("RGB")).reshape(-1, 3)}
        im.seek(int(np.searchsorted(indices, crash)))
        marked = {tuple(c) for c in np.asarray(im.convert("RGB")).reshape(-1, 3)}
    for a in np.flatnonzero(rollout.number >= 0):
        if rollout.sim.valid[a, rollout.current]:
            assert tuple(round(c * 255) for c in vehicle_color(int(rollout.number[a]))[:3]) in first
    alpha = MARKER_FACE_ALPHA[0]  # the star's see-through face over the road
    star = alpha * np.array(to_rgba("#ffd700")[:3]) + (1 - alpha) * np.array(to_rgba("#dcdcdc")[:3])
    assert not any(np.abs(np.array(c) / 255 - star).max() < 3 / 255 for c in first)  # no crash yet
    assert any(np.abs(np.array(c) / 255 - star).max() < 3 / 255 for c in marked)


def busy_scene(scene: Scene, n: int = 64) -> Scene:
    """scene-0103's map with ``n`` vehicles in a tight 8-wide grid around the ego's start, 3.4 m along and
    2 m across (numbers 10 to 63 make tags wider than a car's gap), one step long."""
    from dataclasses import replace

    centre = scene.agents.xy[scene.ego, START]
    k = np.arange(n)
    xy = centre + np.stack([(k % 8) * 3.4, (k // 8) * 2.0], axis=-1)  # (n, 2): lanes 2 m apart
    steps = START + 1
    tracks = AgentTracks(
        ids=np.array([f"v{i}" for i in k]), types=np.full(n, AgentType.VEHICLE, dtype=np.int8),
        xy=np.repeat(xy[:, None], steps, axis=1), yaw=np.zeros((n, steps)), speed=np.ones((n, steps)),
        extent=np.tile([3.0, 1.6], (n, 1)), valid=np.ones((n, steps), dtype=bool))
    return replace(scene, agents=tracks, ego=0)


def test_labels_never_cover_one_another_on_a_busy_scene(scene: Scene) -> None:
    busy = busy_scene(scene)
    fig = draw_scene(busy, START)
    renderer = fig.canvas.get_renderer()
    fig.canvas.draw()
    tags = labels(fig)
    assert len(tags) == 64
    boxes = np.array([t.get_bbox_patch().get_window_extent(renderer).extents for t in tags])  # (64, 4)
    w = np.minimum(boxes[:, None, 2], boxes[None, :, 2]) - np.maximum(boxes[:, None, 0], boxes[None, :, 0])
    h = np.minimum(boxes[:, None, 3], boxes[None, :, 3]) - np.maximum(boxes[:, None, 1], boxes[None, :, 1])
    overlap = (np.clip(w, 0, None) * np.clip(h, 0, None))[~np.eye(len(tags), dtype=bool)]
    assert overlap.max() < 1.0, f"{(overlap >= 1.0).sum() // 2} pairs of tags overlap"
    anchors = fig.axes[0].transData.transform(np.array([t.xy for t in tags]))  # each tag stays near its car
    gap = np.maximum(np.maximum(boxes[:, 0] - anchors[:, 0], anchors[:, 0] - boxes[:, 2]),
                     np.maximum(boxes[:, 1] - anchors[:, 1], anchors[:, 1] - boxes[:, 3]))
    assert gap.max() < 8 * (boxes[:, 3] - boxes[:, 1]).max()
    tag0 = next(t for t in tags if t.get_text() == "0 (ego)")  # the first placed keeps the first place
    box0 = tag0.get_bbox_patch().get_window_extent(renderer)
    anchor0 = fig.axes[0].transData.transform(tag0.xy)
    gap_px = 4.0 * fig.dpi / 72  # up and to the right, 4 pt from its car, as on a quiet scene
    corner = np.array([box0.x0 - anchor0[0], box0.y0 - anchor0[1]])  # the outline's width lies beyond
    assert (corner >= gap_px).all() and (corner <= gap_px + 1.5).all()


def test_the_label_layout_by_hand() -> None:
    from ctgpp.viz.label_layout import overlap_area, place_labels

    boxes = place_labels(np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([[10.0, 5.0], [10.0, 5.0]]), gap=2.0)
    assert boxes[0].tolist() == [2.0, 2.0, 12.0, 7.0]  # up and to the right
    assert boxes[1].tolist() == [3.0, -7.0, 13.0, -2.0]  # its up-right place is taken: down and right
    assert overlap_area(boxes[:1], boxes[1:]).tolist() == [0.0]
    assert overlap_area(np.array([[0.0, 0.0, 2.0, 2.0]]), np.array([[1.0, 1.0, 3.0, 3.0]])).tolist() == [1.0]
