"""The scenes the page may pick from, and one scene at an episode's start as data the browser draws.

Scenes are named to the browser by a key, ``SET:ID`` (``embedded:scene-0103``, ``ngsim:USA_...``):
the set is the embedded nuScenes scenes or a ``--data`` directory, known only to the server; the
browser never sends a path.
"""

from __future__ import annotations

import base64
import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from ctgpp.data.catalog import Catalog, CatalogEntry
from ctgpp.scene.types import AgentType, Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS
from ctgpp.sim.closed_loop import (
    DURATION_S,
    MIN_HISTORY_S,
    episode_bounds,
    episode_config,
    initial_observation,
)
from ctgpp.viz.colors import REPLAYED_COLORS, vehicle_color

KEY_PATTERN = re.compile(r"^[A-Za-z0-9_.-]{1,40}:[A-Za-z0-9_.-]{1,120}$")
MAX_DURATION_S = 20.0  # the longest episode the page may ask for
VIEW_MARGIN_M = 12.0  # room around the vehicles in the first view
DRIVABLE_RGBA = (222, 222, 222, 255)  # the drivable area's colour in the page
TYPE_NAMES = {t: t.name.lower() for t in AgentType}


def hex_color(rgba: Sequence[float]) -> str:
    """An RGBA colour (0-1) as ``#rrggbb``."""
    return "#" + "".join(f"{round(float(c) * 255):02x}" for c in rgba[:3])


def agent_color(number: int, agent_type: int) -> str:
    """The colour of an agent in the page: its vehicle colour when numbered (as in ``scene.png``),
    else the grey of its kind."""
    if number >= 0:
        return hex_color(vehicle_color(number))
    kind = {AgentType.VEHICLE: "vehicle", AgentType.PEDESTRIAN: "pedestrian",
            AgentType.CYCLIST: "cyclist"}.get(AgentType(agent_type), "static")
    return REPLAYED_COLORS[kind]


def max_duration_s(entry: CatalogEntry) -> float:
    """The longest episode a scene hosts (1 s of history at least), at most ``MAX_DURATION_S``."""
    return min(MAX_DURATION_S, math.floor((entry.duration_s - MIN_HISTORY_S) * 10 + 1e-6) / 10)


@dataclass(frozen=True)
class SceneSet:
    """One data directory the server offers: ``name`` (its key prefix), ``catalog``, and ``data``, the
    directory to hand to :func:`ctgpp.load_scene` (None: the embedded scenes)."""

    name: str
    catalog: Catalog
    data: Path | None


class SceneSets:
    """The embedded scenes and the ``--data`` directories, looked up by key."""

    def __init__(self, data_dirs: Sequence[Path] = ()) -> None:
        self.sets = [SceneSet("embedded", Catalog.open(None), None)]
        for path in data_dirs:
            name = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(path).resolve().name)[:40] or "data"
            taken = {s.name for s in self.sets}
            unique, k = name, 2
            while unique in taken:
                unique, k = f"{name[:36]}-{k}", k + 1
            self.sets.append(SceneSet(unique, Catalog.open(Path(path)), Path(path)))
        self._entries = {
            f"{s.name}:{e.id}": (s, e) for s in self.sets for e in s.catalog.entries
        }

    def listing(self) -> list[dict[str, Any]]:
        """Every scene: key, set, id, map, duration, vehicles, split and the longest episode."""
        return [
            {"key": key, "set": s.name, "id": e.id, "map": e.map_name, "duration_s": e.duration_s,
             "vehicles": e.num_vehicles, "split": e.split, "max_duration_s": max_duration_s(e)}
            for key, (s, e) in self._entries.items() if max_duration_s(e) > 0
        ]

    def lookup(self, key: str) -> tuple[SceneSet, CatalogEntry]:
        """The set and entry of ``key``; KeyError (naming the key) for any other string."""
        if not KEY_PATTERN.match(key) or key not in self._entries:
            raise KeyError(f"unknown scene {key[:60]!r}")
        return self._entries[key]

    def view(self, key: str, duration_s: float = DURATION_S) -> dict[str, Any]:
        """The scene ``key`` at the start of a ``duration_s`` episode, as the page draws it."""
        self.lookup(key)
        return _view(self, key, round(float(duration_s), 1))


@lru_cache(maxsize=16)
def _view(sets: SceneSets, key: str, duration_s: float) -> dict[str, Any]:
    scene_set, entry = sets.lookup(key)
    return scene_view(scene_set.catalog.load(entry.id), duration_s)


def scene_view(scene: Scene, duration_s: float = DURATION_S) -> dict[str, Any]:
    """The first frame of an episode of ``scene``: lanes, the drivable area (a PNG), and every agent
    present at the start with its number (-1 for replayed agents), type, pose, box, speed, whether it
    moves and its colour; ``view`` the region around the vehicles (x0, y0, x1, y1 m).

    ValueError when the scene is too short for a ``duration_s`` episode."""
    config = episode_config(scene, duration_s)
    start_s = episode_bounds(scene, config)[0]
    obs = initial_observation(scene, start_s, config)  # parked cars held where the log has not seen them
    tracks, step = obs.tracks, obs.step
    numbers = np.full(tracks.num_agents, -1)
    numbers[obs.controlled] = np.arange(len(obs.controlled))
    agents = []
    for a in np.flatnonzero(tracks.valid[:, step]):
        speed = float(tracks.speed[a, step])
        agents.append({
            "number": int(numbers[a]), "type": TYPE_NAMES[AgentType(int(tracks.types[a]))],
            "x": round(float(tracks.xy[a, step, 0]), 2), "y": round(float(tracks.xy[a, step, 1]), 2),
            "yaw": round(float(tracks.yaw[a, step]), 3), "length": round(float(tracks.extent[a, 0]), 2),
            "width": round(float(tracks.extent[a, 1]), 2), "speed": round(speed, 2),
            "moving": bool(numbers[a] >= 0 and speed >= MOVING_SPEED_MPS),
            "color": agent_color(int(numbers[a]), int(tracks.types[a])),
        })
    present = obs.controlled if len(obs.controlled) else np.flatnonzero(tracks.valid[:, step])
    return {
        "id": scene.id, "map": scene.map_name, "start_s": start_s, "duration_s": duration_s,
        "history_s": round((config.history_steps - 1) * scene.dt_s, 6),
        "vehicles": len(obs.controlled), "agents": agents,
        "lanes": lane_polylines(scene), "drivable": drivable_image(scene),
        "view": _fit(tracks.xy[present, step]),
    }


def lane_polylines(scene: Scene) -> list[list[float]]:
    """Each lane's centerline as a flat list x0, y0, x1, y1, ... (m, 0.1 m)."""
    lanes = scene.lanes
    return [np.round(lanes.lane(i), 1).ravel().tolist() for i in range(lanes.num_lanes)]


def drivable_image(scene: Scene) -> dict[str, Any]:
    """The drivable area as a PNG data URL (row 0 the southern edge, as the raster), with the world
    position of its south-west corner and its metres per pixel."""
    from PIL import Image

    area = scene.drivable
    rgba = np.zeros((*area.mask.shape, 4), dtype=np.uint8)
    rgba[area.mask] = DRIVABLE_RGBA
    buffer = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buffer, "PNG")
    url = "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")
    return {"png": url, "x0": float(area.origin_xy[0]), "y0": float(area.origin_xy[1]),
            "resolution_m": float(area.resolution_m), "width": int(area.mask.shape[1]),
            "height": int(area.mask.shape[0])}


def _fit(xy: np.ndarray) -> list[float]:
    """A square region (x0, y0, x1, y1 m) around the points ``xy`` (N, 2) with a margin."""
    if len(xy) == 0:
        return [-50.0, -50.0, 50.0, 50.0]
    low, high = xy.min(axis=0), xy.max(axis=0)
    centre, half = (low + high) / 2, max(float((high - low).max()) / 2 + VIEW_MARGIN_M, 25.0)
    corners = (centre[0] - half, centre[1] - half, centre[0] + half, centre[1] + half)
    return [round(float(v), 1) for v in corners]
