"""ScenarioNet scenario pickles (nuScenes, Waymo, nuPlan, Lyft, Argoverse 2 conversions) -> Scene.

A scenario is a plain dict ``id, version, length, metadata, tracks, dynamic_map_states,
map_features`` (``shared/data/README.md``), read with the restricted unpickler of
:mod:`ctgpp.data.safe_pickle`. Lanes are the map features whose type starts with ``LANE``; their
connectivity comes from Waymo-style ``entry_lanes / exit_lanes / left_neighbor / right_neighbor``
when present, otherwise it is rebuilt geometrically (:mod:`ctgpp.data.lane_topology`). The drivable
area is a crop of the nuScenes map mask when ``drivable_dir/<map>.png`` exists, else the union of
the lane polygons (centerlines buffered by 1.8 m where a lane has no polygon). A vehicle whose
stored width exceeds its length has the two swapped (the ego box of the nuScenes conversions).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ctgpp.data.lane_topology import detect_intersections, reconstruct_connectivity
from ctgpp.data.nuscenes_drivable import nuscenes_drivable, rasterize_polygons
from ctgpp.data.safe_pickle import safe_load
from ctgpp.data.stitching import stitch_fragments
from ctgpp.data.timebase import SIM_DT_S, check_dt, finite_tracks
from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene

DRIVABLE_MARGIN_M = 30.0
LANE_HALF_WIDTH_M = 1.8
POLYGON_RESOLUTION_M = 0.2
_SKIP = {"dataset_summary.pkl", "dataset_mapping.pkl"}
_TYPES = {
    "VEHICLE": AgentType.VEHICLE,
    "PEDESTRIAN": AgentType.PEDESTRIAN,
    "CYCLIST": AgentType.CYCLIST,
    "TRAFFIC_CONE": AgentType.STATIC,
    "TRAFFIC_BARRIER": AgentType.STATIC,
}


def iter_scenarionet(src: Path) -> Iterator[Path]:
    """Scenario pickles in a ScenarioNet dataset folder (recursively, sorted), skipping its summaries."""
    for path in sorted(Path(src).rglob("*.pkl")):
        if path.name not in _SKIP:
            yield path


def _tracks(raw: dict, path: Path) -> tuple[AgentTracks, int]:
    """Agent tracks, ego first, then the file's order; returns (tracks, ego index or -1)."""
    tracks: dict = raw["tracks"]
    if not isinstance(tracks, dict) or not tracks:
        raise ValueError(f"{path}: the scenario holds no tracks")
    sdc = str(raw.get("metadata", {}).get("sdc_id", ""))
    order = sorted(tracks, key=lambda k: str(k) != sdc)  # stable: ego first, rest in dict order
    n_steps = int(raw.get("length") or len(next(iter(tracks.values()))["state"]["valid"]))
    n = len(order)
    xy = np.zeros((n, n_steps, 2))
    yaw = np.zeros((n, n_steps))
    speed = np.zeros((n, n_steps))
    extent = np.zeros((n, 2))
    valid = np.zeros((n, n_steps), dtype=bool)
    types = np.zeros(n, dtype=np.int8)
    for a, key in enumerate(order):
        track = tracks[key]
        state = track["state"]
        ok = np.asarray(state["valid"]).reshape(-1).astype(bool)
        if len(ok) != n_steps:
            raise ValueError(f"{path}: track {key} has {len(ok)} steps, the scenario {n_steps}")
        valid[a] = ok
        xy[a] = np.where(ok[:, None], np.asarray(state["position"], dtype=np.float64)[:, :2], 0.0)
        yaw[a] = np.where(ok, np.asarray(state["heading"], dtype=np.float64).reshape(-1), 0.0)
        vel = np.asarray(state["velocity"], dtype=np.float64)[:, :2]
        speed[a] = np.where(ok, np.linalg.norm(vel, axis=1), 0.0)
        types[a] = _TYPES.get(str(track.get("type", "")), AgentType.OTHER)
        if ok.any():
            length = np.asarray(state["length"], dtype=np.float64).reshape(-1)[ok]
            width = np.asarray(state["width"], dtype=np.float64).reshape(-1)[ok]
            extent[a] = _box(float(np.median(length)), float(np.median(width)), types[a])
    ids = np.asarray([str(k) for k in order], dtype=np.str_)
    agents = AgentTracks(ids=ids, types=types, xy=xy, yaw=yaw, speed=speed, extent=extent, valid=valid)
    return finite_tracks(agents), (0 if order and str(order[0]) == sdc else -1)


def _box(length_m: float, width_m: float, kind: int) -> tuple[float, float]:
    """(length, width) m of an agent's box: a vehicle's longer side is its length. Converted files
    can store them the other way round (the ego of the nuScenes ScenarioNet files: 1.73 m long,
    4.08 m wide); its heading is kept, so the box is turned to lie along it."""
    if kind == AgentType.VEHICLE and width_m > length_m:
        return width_m, length_m
    return length_m, width_m


def _clean_line(points: list | np.ndarray) -> np.ndarray:
    """(n, 2) polyline without repeated consecutive points."""
    line = np.asarray(points, dtype=np.float64)[:, :2]
    keep = np.concatenate([[True], np.linalg.norm(np.diff(line, axis=0), axis=1) > 1e-6])
    return line[keep]


def _feature_ids(value: object) -> list[str]:
    """Lane references as strings: a list of ids, or of dicts with ``feature_id`` (Waymo neighbours)."""
    if value is None:
        return []
    items = value if isinstance(value, list | tuple | np.ndarray) else [value]
    return [str(v["feature_id"]) if isinstance(v, dict) else str(v) for v in items]


def _lanes(features: dict) -> tuple[LaneGraph, list[np.ndarray | None]]:
    """The lane graph and each lane's polygon (or None)."""
    ids, lines, polygons, records = [], [], [], []
    for key, feat in features.items():
        if not str(feat.get("type", "")).startswith("LANE") or "polyline" not in feat:
            continue
        line = _clean_line(feat["polyline"])
        if len(line) < 2:
            continue
        ids.append(str(key))
        lines.append(line)
        poly = feat.get("polygon")
        polygons.append(
            np.asarray(poly, dtype=np.float64)[:, :2] if poly is not None and len(poly) >= 3 else None
        )
        records.append(feat)
    keys = ("entry_lanes", "exit_lanes", "left_neighbor", "right_neighbor")
    if any(k in feat for feat in records for k in keys):
        successors, predecessors, left, right = _given_connectivity(ids, records)
    else:
        successors, predecessors, left, right = reconstruct_connectivity(lines)
    lengths = np.array([len(line) for line in lines], dtype=np.int64)
    graph = LaneGraph(
        ids=np.asarray(ids, dtype=np.str_),
        points=np.concatenate(lines) if lines else np.zeros((0, 2)),
        offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        successors=successors,
        predecessors=predecessors,
        left=left,
        right=right,
        intersection=detect_intersections(lines),
    )
    return graph, polygons


def _given_connectivity(ids: list[str], records: list[dict]) -> tuple[np.ndarray, ...]:
    """Connectivity from Waymo-style lane references (unknown ids are ignored)."""
    index = {lane_id: i for i, lane_id in enumerate(ids)}
    edges: set[tuple[int, int]] = set()
    left = np.full(len(ids), -1, dtype=np.int64)
    right = np.full(len(ids), -1, dtype=np.int64)
    for i, feat in enumerate(records):
        edges.update((i, index[j]) for j in _feature_ids(feat.get("exit_lanes")) if j in index)
        edges.update((index[j], i) for j in _feature_ids(feat.get("entry_lanes")) if j in index)
        for key, table in (("left_neighbor", left), ("right_neighbor", right)):
            found = [index[j] for j in _feature_ids(feat.get(key)) if j in index]
            table[i] = found[0] if found else -1
    successors = np.array(sorted(edges), dtype=np.int64).reshape(-1, 2)
    predecessors = np.array(sorted((b, a) for a, b in edges), dtype=np.int64).reshape(-1, 2)
    return successors, predecessors, left, right


def _drivable(
    agents: AgentTracks,
    lanes: LaneGraph,
    polygons: list[np.ndarray | None],
    map_name: str,
    drivable_dir: Path | None,
) -> DrivableArea:
    """nuScenes mask crop when available, else rasterised lane polygons; covers the agents + margin."""
    points = agents.xy[agents.valid]
    if len(points) == 0:
        points = lanes.points
    extent = np.stack([points.min(axis=0), points.max(axis=0)])
    png = Path(drivable_dir) / f"{map_name}.png" if drivable_dir is not None and map_name else None
    if png is not None and png.is_file():
        return nuscenes_drivable(png, extent[0] - DRIVABLE_MARGIN_M, extent[1] + DRIVABLE_MARGIN_M)
    lo, hi = extent[0] - DRIVABLE_MARGIN_M - 10.0, extent[1] + DRIVABLE_MARGIN_M + 10.0
    rings: list[np.ndarray] = []
    lines: list[np.ndarray] = []
    for i, poly in enumerate(polygons):
        src = poly if poly is not None else lanes.lane(i)
        if np.any(src.max(axis=0) < lo) or np.any(src.min(axis=0) > hi):
            continue  # wholly outside the raster
        (rings if poly is not None else lines).append(src)
    return rasterize_polygons(
        rings,
        POLYGON_RESOLUTION_M,
        DRIVABLE_MARGIN_M,
        points,
        buffered_lines=lines,
        buffer_m=LANE_HALF_WIDTH_M,
        extent_xy=extent,
    )


def load_scenarionet(path: Path, drivable_dir: Path | None = None) -> Scene:
    """Read one ScenarioNet scenario pickle as a :class:`Scene` (see the module docstring).

    The drivable raster covers the valid agent positions plus ``DRIVABLE_MARGIN_M``; a state with a
    NaN or infinite value is invalid at its step. The scene keeps the file's time step (``sample_rate``,
    else the spacing of ``ts``; :func:`ctgpp.data.timebase.conform_scene` resamples it).
    Raises :class:`ctgpp.data.safe_pickle.UnsafePickleError` for pickles that could run code and
    ``ValueError`` naming the file for files that are not readable ScenarioNet scenarios.
    """
    path = Path(path)
    raw = safe_load(path)
    if not isinstance(raw, dict) or not {"tracks", "map_features", "metadata"} <= raw.keys():
        raise ValueError(f"{path} is not a ScenarioNet scenario (expected a dict with tracks, map_features)")
    try:
        meta = raw["metadata"]
        agents, ego = _tracks(raw, path)
        if not agents.valid.any():
            raise ValueError(f"{path}: no agent of the scenario has a valid, finite position")
        dt_s = _dt_s(meta)
        if str(meta.get("dataset", "")).lower() == "waymo":  # its tracker's lost-and-found ids
            agents, _ = stitch_fragments(agents, dt_s, keep=ego)
        lanes, polygons = _lanes(raw["map_features"])
        map_name = str(meta.get("map", ""))
        drivable = _drivable(agents, lanes, polygons, map_name, drivable_dir)
    except (KeyError, TypeError, IndexError, AttributeError) as err:
        raise ValueError(f"{path}: malformed ScenarioNet scenario ({type(err).__name__}: {err})") from None
    check_dt(dt_s, str(path))
    return Scene(
        id=str(raw.get("id") or meta.get("scenario_id") or path.stem),
        map_name=map_name,
        dataset=str(meta.get("dataset", "scenarionet")),
        dt_s=dt_s,
        agents=agents,
        lanes=lanes,
        drivable=drivable,
        ego=ego,
    )


def _dt_s(meta: dict) -> float:
    """The scenario's time step in s: ``sample_rate``, else the median spacing of ``ts``, else 0.1."""
    if meta.get("sample_rate") is not None:
        return float(meta["sample_rate"])
    ts = np.asarray(meta.get("ts", []), dtype=np.float64).reshape(-1)
    return float(np.median(np.diff(ts))) if len(ts) > 1 else SIM_DT_S
