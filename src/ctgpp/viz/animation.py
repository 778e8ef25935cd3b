"""Animations of a rollout: one frame per simulated step, drawn by the same painter as the pictures.

A single Agg figure is drawn once (map, lanes, legend) and only the agents, labels, events and title
are updated per frame. GIF is written with Pillow; MP4 goes through ffmpeg when it is installed.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from ctgpp.sim.rollout import Rollout
from ctgpp.viz.scene_plot import Event, ScenePainter, new_figure, pick_view, write_atomic

log = logging.getLogger(__name__)


def frame_indices(rollout: Rollout, stride: int = 1) -> np.ndarray:
    """Window indices drawn as frames: from the simulation start (t = 0) to the window's last step."""
    idx = np.arange(rollout.current, rollout.sim.num_steps, stride)
    if idx[-1] != rollout.sim.num_steps - 1:
        idx = np.append(idx, rollout.sim.num_steps - 1)
    return idx


def render_frames(
    rollout: Rollout,
    *,
    events: Sequence[Event] | None = None,
    stride: int = 1,
    size_px: int = 800,
    dpi: float = 100.0,
    radius_m: float | None = None,
) -> list[np.ndarray]:
    """Render the rollout's future as RGB frames, each (size_px, size_px, 3) uint8.

    The view is fixed for the whole clip: the controlled vehicles over the future plus a margin (or a
    square of half-size ``radius_m`` around the ego's start position). Events appear from their time on.
    """
    scene, sim, events = rollout.scene, rollout.sim, list(events or ())
    numbers = np.asarray(rollout.number)
    numbered = np.flatnonzero(numbers >= 0)
    future = slice(rollout.current, sim.num_steps)
    points = sim.xy[numbered, future][sim.valid[numbered, future]]  # (n_valid, 2)
    ego = scene.ego if scene.ego >= 0 and sim.valid[scene.ego, rollout.current] else None
    view = pick_view(scene, points, None if ego is None else sim.xy[ego, rollout.current], radius_m)

    fig, ax = new_figure(size_px, dpi)
    painter = ScenePainter(ax, scene, view, numbers, fontsize=7.0)
    painter.add_legend(sim.valid[:, future].any(axis=1), futures=False, events=events)
    title = ax.set_title("", fontsize=9)
    dynamic = [*painter.dynamic_artists, title]
    for artist in dynamic:
        artist.set_animated(True)
    fig.canvas.draw()  # the static layers once; frames blit the dynamic artists over them
    background = fig.canvas.copy_from_bbox(fig.bbox)
    frames = []
    for index in frame_indices(rollout, stride):
        t_s = (index - rollout.current) * scene.dt_s
        painter.show_agents(sim, int(index))
        painter.show_events(events, until_s=t_s)
        scene_s = rollout.start_s + t_s
        title.set_text(f"{scene.id}   [{rollout.policy}]   t = {t_s:4.1f} s  (scene {scene_s:.1f} s)")
        fig.canvas.restore_region(background)
        for artist in dynamic:
            fig.draw_artist(artist)
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())  # (H, W, 4) -> (H, W, 3)
    return frames


def _write_gif(frames: list[np.ndarray], path: Path, fps: float) -> None:
    # One palette for the clip, from the first and last frames (the last one shows every event marker).
    palette = Image.fromarray(np.concatenate([frames[0], frames[-1]], axis=0)).quantize(
        colors=255, method=Image.Quantize.MEDIANCUT)
    first, *rest = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    first.save(path, format="GIF", save_all=True, append_images=rest, duration=round(1000.0 / fps), loop=0,
               optimize=False, disposal=1)


def _write_mp4(frames: list[np.ndarray], path: Path, fps: float, ffmpeg: str) -> None:
    h, w, _ = frames[0].shape
    cmd = [ffmpeg, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
           "-r", str(fps), "-i", "-", "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p", "-f", "mp4",
           str(path)]
    subprocess.run(cmd, input=b"".join(f.tobytes() for f in frames), check=True, capture_output=True)


def animate_rollout(
    rollout: Rollout,
    out_path: Path,
    *,
    fps: float = 10.0,
    events: Sequence[Event] | None = None,
    stride: int = 1,
    size_px: int = 800,
) -> Path:
    """Write an animation of the rollout's simulated future and return the path written.

    ``out_path`` ending in .mp4 writes MP4 through ffmpeg when ``shutil.which("ffmpeg")`` finds it;
    otherwise (and for any other suffix) a GIF is written, at ``out_path`` with a .gif suffix when an
    MP4 was asked for. One frame per ``stride`` simulated steps (plus the last), ``fps`` frames per
    second; the write is atomic.
    """
    out_path = Path(out_path)
    frames = render_frames(rollout, events=events, stride=stride, size_px=size_px)
    if out_path.suffix.lower() == ".mp4":
        ffmpeg = shutil.which("ffmpeg")
        if ffmpeg is not None:
            return write_atomic(out_path, lambda tmp: _write_mp4(frames, tmp, fps, ffmpeg))
        out_path = out_path.with_suffix(".gif")
        log.warning("ffmpeg not found: writing a GIF to %s instead of an MP4", out_path)
    return write_atomic(out_path, lambda tmp: _write_gif(frames, tmp, fps))
