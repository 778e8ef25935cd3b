"""Waymo Open Motion scenes in the GPUDrive / Nocturne JSON format (``<scenario_id>.json.gz``) -> Scene.

A file is a gzip of one JSON object (``shared/data/README.md``, waymo-gpudrive): ``objects`` with 91
steps at 0.1 s of ``position`` {x, y, z}, ``heading``, ``velocity`` {x, y}, ``valid``, and ``roads``
polylines typed lane / road_edge / road_line / crosswalk / ...; global metres.

- Agents: vehicle / pedestrian / cyclist keep their type (anything else is OTHER); speed is the norm
  of the velocity. A step is valid only where ``valid`` is true and the position is finite: invalid
  steps carry placeholders (-10000, -10000) or (1e-4, 1e-4) that must never be read as positions.
- Heading unit: GPUDrive files store radians, Nocturne-style files (no ``metadata``) degrees, and a
  few break that rule, so the unit is chosen per file: the one whose headings agree better with the
  velocity direction of moving agents (without moving agents: degrees when some |heading| > 2π).
- Ego: ``metadata.sdc_track_index`` (GPUDrive files) names the recording car; it is put first and
  ``ego = 0``, as the ScenarioNet reader does with ``sdc_id``. Files without it (Nocturne-style) do not
  mark the SDC (``mark_as_expert`` flags other agents, and the SDC rarely) and get ``ego = -1``, as NGSIM.
- Lanes: the ``lane`` polylines (driving direction) with connectivity rebuilt geometrically
  (:mod:`ctgpp.data.lane_topology`), as for nuScenes: the files hold no lane links.
- Drivable area: road edges are open polylines that enclose nothing by themselves (gaps at
  driveways, the map's border), so no polygon can be filled from them. Instead: the lanes widened by
  ``LANE_HALF_WIDTH_M`` (as for nuScenes), plus the area reachable from the lane centrelines within
  ``EDGE_REACH_M`` without crossing a road edge (the edges are the boundary: shoulders and parking
  strips up to the kerb count, the far side of a kerb does not; gaps leak at most ``EDGE_REACH_M``),
  plus the ``driveway`` polygons. Parking lots are not mapped: vehicles driving in them are off the
  area (over all 245 scenes 98.8 % of moving vehicle positions are on it, 25 scenes under 95 %).
- Crosswalks, road lines, stop signs and speed bumps are not kept: :class:`Scene` has no place for
  them (crosswalks lie on the road, so they are inside the drivable area). Traffic-light states are
  dropped too.
"""

from __future__ import annotations

import gzip
import json
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from ctgpp.data.lane_topology import detect_intersections, reconstruct_connectivity
from ctgpp.data.nuscenes_drivable import rasterize_polygons
from ctgpp.data.stitching import stitch_fragments
from ctgpp.data.timebase import SIM_DT_S, finite_tracks
from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene

SUFFIX = ".json.gz"
DATASET = "waymo"
DRIVABLE_MARGIN_M = 30.0
RESOLUTION_M = 0.2
LANE_HALF_WIDTH_M = 1.8
EDGE_REACH_M = 8.0
EDGE_HALF_WIDTH_M = 0.2  # road edges drawn as barriers this thick on each side
HEADING_PROBE_MPS = 1.0  # agents this fast decide the heading unit (their velocity has a direction)
_TYPES = {"vehicle": AgentType.VEHICLE, "pedestrian": AgentType.PEDESTRIAN, "cyclist": AgentType.CYCLIST}


def is_waymo_json(path: Path) -> bool:
    """True for a ``*.json.gz`` file name (the GPUDrive / Nocturne scene files)."""
    return Path(path).name.endswith(SUFFIX)


def scenario_id(raw: dict, path: Path) -> str:
    """``scenario_id`` of the file, else its ``name`` without ``.json`` (older files), else the stem."""
    name = str(raw.get("scenario_id") or raw.get("name") or Path(path).name[: -len(SUFFIX)])
    return name.removesuffix(".json")


def _points(items: list, keys: tuple[str, ...] = ("x", "y")) -> np.ndarray:
    """(n, len(keys)) float array of a list of {x, y, ...} dicts."""
    return np.array([[float(p[k]) for k in keys] for p in items], dtype=np.float64).reshape(-1, len(keys))


def _heading_in_degrees(objects: list[dict]) -> bool:
    """Whether the file's headings are degrees (see the module docstring)."""
    err_rad, err_deg, largest = [], [], 0.0
    for obj in objects:
        ok = np.asarray(obj["valid"], dtype=bool)
        heading = np.asarray(obj["heading"], dtype=np.float64)
        if not ok.any():
            continue
        largest = max(largest, float(np.nanmax(np.abs(heading[ok]), initial=0.0)))
        velocity = _points(obj["velocity"])
        moving = ok & (np.linalg.norm(velocity, axis=1) > HEADING_PROBE_MPS)
        direction = np.arctan2(velocity[moving, 1], velocity[moving, 0])
        err_rad.append(np.abs(wrap_angle(heading[moving] - direction)))
        err_deg.append(np.abs(wrap_angle(np.deg2rad(heading[moving]) - direction)))
    if err_rad and sum(len(e) for e in err_rad):
        return bool(np.nanmedian(np.concatenate(err_deg)) < np.nanmedian(np.concatenate(err_rad)))
    return largest > 2 * np.pi + 1e-3


def _tracks(raw: dict) -> tuple[AgentTracks, int]:
    """Agent tracks, the SDC first when the file names it; returns (tracks, ego index or -1)."""
    objects: list[dict] = raw["objects"]
    if not isinstance(objects, list) or not objects:
        raise ValueError("the scene holds no objects")
    sdc = (raw.get("metadata") or {}).get("sdc_track_index")
    sdc = int(sdc) if isinstance(sdc, int) and 0 <= sdc < len(objects) else -1
    order = sorted(range(len(objects)), key=lambda i: i != sdc)  # stable: SDC first, rest in file order
    n, n_steps = len(order), len(objects[0]["valid"])
    degrees = _heading_in_degrees(objects)
    xy = np.zeros((n, n_steps, 2))
    yaw = np.zeros((n, n_steps))
    speed = np.zeros((n, n_steps))
    extent = np.zeros((n, 2))
    valid = np.zeros((n, n_steps), dtype=bool)
    types = np.zeros(n, dtype=np.int8)
    for a, i in enumerate(order):
        obj = objects[i]
        position = _points(obj["position"])
        heading = np.asarray(obj["heading"], dtype=np.float64)
        if not len(position) == len(heading) == len(obj["valid"]) == n_steps:
            raise ValueError(f"object {i} does not have {n_steps} steps of position, heading and valid")
        ok = np.asarray(obj["valid"], dtype=bool) & np.isfinite(position).all(axis=1)
        valid[a] = ok
        xy[a] = np.where(ok[:, None], position, 0.0)
        yaw[a] = np.where(ok, wrap_angle(np.deg2rad(heading) if degrees else heading), 0.0)
        speed[a] = np.where(ok, np.linalg.norm(_points(obj["velocity"]), axis=1), 0.0)
        types[a] = _TYPES.get(str(obj.get("type", "")), AgentType.OTHER)
        extent[a] = (float(obj["length"]), float(obj["width"]))
    given = [str(objects[i].get("id", "")) for i in order]
    ids = given if "" not in given and len(set(given)) == n else [str(i) for i in order]
    agents = AgentTracks(
        ids=np.asarray(ids, dtype=np.str_),
        types=types,
        xy=xy,
        yaw=yaw,
        speed=speed,
        extent=extent,
        valid=valid,
    )
    ego = 0 if sdc >= 0 and valid[0].any() else -1
    return finite_tracks(agents), ego


def _polylines(roads: list[dict], kind: str) -> tuple[list[str], list[np.ndarray]]:
    """Ids and (n, 2) polylines (repeated points removed, at least 2 left) of the roads of one type."""
    ids, lines = [], []
    for k, road in enumerate(roads):
        if road.get("type") != kind:
            continue
        line = _points(road.get("geometry") or [])
        if len(line) == 0:
            continue
        line = line[np.concatenate([[True], np.linalg.norm(np.diff(line, axis=0), axis=1) > 1e-6])]
        if len(line) >= 2 and np.isfinite(line).all():
            ids.append(str(road.get("id", k)))
            lines.append(line)
    return ids, lines


def _lanes(roads: list[dict]) -> LaneGraph:
    """The ``lane`` polylines with geometrically rebuilt connectivity."""
    ids, lines = _polylines(roads, "lane")
    successors, predecessors, left, right = reconstruct_connectivity(lines)
    lengths = np.array([len(line) for line in lines], dtype=np.int64)
    return LaneGraph(
        ids=np.asarray(ids, dtype=np.str_),
        points=np.concatenate(lines) if lines else np.zeros((0, 2)),
        offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        successors=successors,
        predecessors=predecessors,
        left=left,
        right=right,
        intersection=detect_intersections(lines),
    )


def _drivable(
    agents: AgentTracks, lanes: LaneGraph, edges: list[np.ndarray], driveways: list[np.ndarray]
) -> DrivableArea:
    """Widened lanes and driveway polygons, plus what the lanes reach up to the road edges (module
    docstring). edges: (n, 2) polylines; driveways: (n, 2) rings."""
    points = agents.xy[agents.valid]
    if len(points) == 0:
        points = lanes.points
    extent = np.stack([points.min(axis=0), points.max(axis=0)])  # (2, 2) min, max corner
    lo, hi = extent[0] - DRIVABLE_MARGIN_M - EDGE_REACH_M, extent[1] + DRIVABLE_MARGIN_M + EDGE_REACH_M

    def near(line: np.ndarray) -> bool:
        return bool(np.all(line.max(axis=0) >= lo) and np.all(line.min(axis=0) <= hi))

    lines = [lanes.lane(i) for i in range(lanes.num_lanes) if near(lanes.lane(i))]
    edges = [e for e in edges if near(e)]
    driveways = [d for d in driveways if near(d) and len(d) >= 3]

    def raster(
        polylines: list[np.ndarray], half_width_m: float, rings: tuple[np.ndarray, ...] = ()
    ) -> DrivableArea:
        return rasterize_polygons(
            rings, RESOLUTION_M, DRIVABLE_MARGIN_M, points,
            buffered_lines=polylines, buffer_m=half_width_m, extent_xy=extent,
        )  # fmt: skip

    lane_area = raster(lines, LANE_HALF_WIDTH_M, tuple(driveways))
    reach = raster(lines, EDGE_REACH_M).mask & ~raster(edges, EDGE_HALF_WIDTH_M).mask
    seeds = raster(lines, RESOLUTION_M).mask & reach  # the centrelines themselves
    labels, _ = ndimage.label(reach)
    kept = np.isin(labels, np.unique(labels[seeds])) & (labels > 0)
    return DrivableArea(mask=lane_area.mask | kept, origin_xy=lane_area.origin_xy, resolution_m=RESOLUTION_M)


def _read(path: Path) -> dict[str, Any]:
    try:
        with gzip.open(path, "rt", encoding="utf-8") as file:
            raw = json.load(file)
    except (EOFError, zlib.error, gzip.BadGzipFile, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable gzip of JSON ({type(err).__name__}: {err})") from None
    if not isinstance(raw, dict) or not {"objects", "roads"} <= raw.keys():
        raise ValueError(
            f"{path} is not a GPUDrive / Nocturne scene (expected a JSON object with objects, roads)"
        )
    return raw


def load_waymo_json(path: Path, stitch: bool = True) -> Scene:
    """Read one GPUDrive / Nocturne ``.json.gz`` scene as a :class:`Scene` (see the module docstring).

    ``stitch``: join the fragments of one vehicle's track (:mod:`ctgpp.data.stitching`); False reads
    the tracks as the file holds them.

    Scene id ``waymo-<scenario_id>``, dataset ``"waymo"``, dt 0.1 s. The drivable raster covers the
    valid agent positions plus ``DRIVABLE_MARGIN_M``. Raises ``FileNotFoundError`` for a missing file
    and a one-line ``ValueError`` naming the file for one that is not a readable scene.
    """
    path = Path(path)
    raw = _read(path)
    try:
        agents, ego = _tracks(raw)
        if stitch:
            agents, _ = stitch_fragments(agents, SIM_DT_S, keep=ego)
        if not agents.valid.any():
            raise ValueError("no agent has a valid, finite position")
        lanes = _lanes(raw["roads"])
        roads = raw["roads"]
        drivable = _drivable(
            agents, lanes, _polylines(roads, "road_edge")[1], _polylines(roads, "driveway")[1]
        )
    except (KeyError, TypeError, IndexError, AttributeError, ValueError) as err:
        raise ValueError(
            f"{path}: malformed GPUDrive / Nocturne scene ({type(err).__name__}: {err})"
        ) from None
    return Scene(
        id=f"{DATASET}-{scenario_id(raw, path)}",
        map_name="",
        dataset=DATASET,
        dt_s=SIM_DT_S,
        agents=agents,
        lanes=lanes,
        drivable=drivable,
        ego=ego,
    )
