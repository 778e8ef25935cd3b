"""INTERACTION dataset recordings (drone tracks + Lanelet2 maps) -> :class:`Scene` s (DESIGN.md, Data).

A recording ``<root>/recorded_trackfiles/<location>/vehicle_tracks_NNN.csv.gz`` is minutes long: it is
cut into consecutive, non-overlapping scenes of :data:`SCENE_STEPS` steps at 10 Hz; a last piece
shorter than :data:`MIN_SCENE_STEPS` is dropped. Vehicles are valid only at their own frames. The map
``<root>/maps/<location>.osm`` is read with the optional dependency ``lanelet2`` (``pip install
ctgpp[interaction]``) in the tracks' frame (UTM projection with origin latitude 0, longitude 0);
lanes are the lanelets' centerlines with successors and left/right neighbours of the routing graph
for German vehicle traffic rules (plus the joins it misses where lanelets meet at a point); the
drivable area is the union of the lanelet polygons, rasterized.
The data's licence forbids redistribution: read it in place, never copy it into the package.
"""

from __future__ import annotations

import csv
import gzip
import io
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from ctgpp.data.lane_topology import detect_intersections, successor_edges
from ctgpp.data.nuscenes_drivable import rasterize_polygons
from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene

DT_S = 0.1
SCENE_STEPS = 200  # 20 s scenes, like nuScenes
MIN_SCENE_STEPS = 130  # the episode needs 3 s of history + 10 s to simulate
DRIVABLE_RESOLUTION_M = 0.2
DRIVABLE_MARGIN_M = 10.0

COLUMNS = ("track_id", "frame_id", "timestamp_ms", "agent_type", "x", "y", "vx", "vy", "psi_rad",
           "length", "width")
_TYPES = {"car": AgentType.VEHICLE, "truck": AgentType.VEHICLE, "pedestrian/bicycle": AgentType.CYCLIST}


def is_interaction_track_file(path: Path) -> bool:
    """Whether ``path`` is named like an INTERACTION track file (``vehicle_tracks_NNN.csv.gz``)."""
    return path.name.startswith("vehicle_tracks_") and path.name.endswith(".csv.gz")


def scene_windows(n_steps: int, scene_steps: int = SCENE_STEPS, min_steps: int = MIN_SCENE_STEPS) -> list[
    tuple[int, int]
]:
    """Consecutive, non-overlapping [start, stop) step ranges of ``scene_steps`` covering ``n_steps``;
    a last piece shorter than ``min_steps`` is dropped."""
    windows = [(s, min(s + scene_steps, n_steps)) for s in range(0, n_steps, scene_steps)]
    return [(a, b) for a, b in windows if b - a >= min_steps]


def map_path(track_file: Path) -> Path:
    """The map of ``<root>/recorded_trackfiles/<location>/...``: ``<root>/maps/<location>.osm``."""
    track_file = Path(track_file)
    return track_file.parents[2] / "maps" / f"{track_file.parent.name}.osm"


def load_interaction(path: Path, max_scenes: int | None = None) -> list[Scene]:
    """Read one INTERACTION recording into its scenes (dataset ``"interaction"``, map = location).

    Scene ids are ``interaction-<location>-<NNN>-<k>`` with k the window's index in the recording.
    ``max_scenes`` keeps only the first scenes. Raises ValueError naming the file when the CSV or the
    map cannot be read or ``lanelet2`` is not installed.
    """
    path = Path(path)
    location = path.parent.name
    number = path.name.removeprefix("vehicle_tracks_").removesuffix(".csv.gz")
    rows, types = _read_tracks(path)
    lanes, polygons = lanelet_map(map_path(path))
    tracks = _tracks(rows, types)
    extra_points = tracks.xy[tracks.valid]  # (V, 2) every valid position of the recording
    drivable = _drivable(polygons, extra_points)
    windows = scene_windows(tracks.xy.shape[1])
    scenes = []
    for k, (start, stop) in enumerate(windows[:max_scenes]):
        window = _window(tracks, start, stop)
        if not window.valid.any():
            continue
        scenes.append(
            Scene(
                id=f"interaction-{location}-{number}-{k}",
                map_name=location,
                dataset="interaction",
                dt_s=DT_S,
                agents=window,
                lanes=lanes,
                drivable=drivable,
                ego=-1,
            )
        )
    return scenes


def _read_tracks(path: Path) -> tuple[np.ndarray, list[str]]:
    """(N, 10) float rows of the numeric columns (all but agent_type) and the N agent types."""
    if not path.is_file():
        raise FileNotFoundError(f"INTERACTION track file {path} does not exist")
    try:
        with gzip.open(path, "rt", newline="") as handle:
            text = handle.read()
        reader = csv.reader(io.StringIO(text))
        header = tuple(next(reader))
        if header != COLUMNS:
            raise ValueError(f"unexpected columns {','.join(header)}")
        records = [r for r in reader if r]
        types = [r[3] for r in records]
        rows = np.array([r[:3] + r[4:] for r in records], dtype=np.float64).reshape(-1, len(COLUMNS) - 1)
    except (OSError, EOFError, ValueError, IndexError, StopIteration, UnicodeDecodeError) as err:
        reason = f"{type(err).__name__}: {err}".replace("\n", " ")
        raise ValueError(f"{path.name}: not a readable INTERACTION track file ({reason})") from err
    if len(rows) == 0:
        raise ValueError(f"{path.name}: INTERACTION track file holds no rows")
    if not np.isfinite(rows).all():
        raise ValueError(f"{path.name}: INTERACTION track file holds non-finite values")
    return rows, types


def _tracks(rows: np.ndarray, types: list[str]) -> AgentTracks:
    """All tracks of a recording on one time axis, step 0 = the first frame."""
    track_id, frame = rows[:, 0].astype(np.int64), rows[:, 1].astype(np.int64)
    ids, agent = np.unique(track_id, return_inverse=True)
    step = frame - frame.min()
    n_agents, n_steps = len(ids), int(step.max()) + 1
    xy = np.zeros((n_agents, n_steps, 2))
    yaw = np.zeros((n_agents, n_steps))
    speed = np.zeros((n_agents, n_steps))
    valid = np.zeros((n_agents, n_steps), dtype=bool)
    xy[agent, step] = rows[:, 3:5]
    speed[agent, step] = np.hypot(rows[:, 5], rows[:, 6])
    yaw[agent, step] = wrap_angle(rows[:, 7])
    valid[agent, step] = True
    extent = np.zeros((n_agents, 2))
    extent[agent] = rows[:, 8:10]  # (length m, width m), constant per track
    kinds = np.full(n_agents, AgentType.OTHER, dtype=np.int8)
    kinds[agent] = [_TYPES.get(t, AgentType.OTHER) for t in types]
    return AgentTracks(ids=ids, types=kinds, xy=xy, yaw=yaw, speed=speed, extent=extent, valid=valid)


def _window(tracks: AgentTracks, start: int, stop: int) -> AgentTracks:
    """The agents valid somewhere in steps [start, stop), cut to those steps."""
    keep = tracks.valid[:, start:stop].any(axis=1)  # (A,)
    return AgentTracks(
        ids=tracks.ids[keep],
        types=tracks.types[keep],
        xy=tracks.xy[keep, start:stop],
        yaw=tracks.yaw[keep, start:stop],
        speed=tracks.speed[keep, start:stop],
        extent=tracks.extent[keep],
        valid=tracks.valid[keep, start:stop],
    )


def _drivable(polygons: list[np.ndarray], extra_points: np.ndarray) -> DrivableArea:
    return rasterize_polygons(polygons, DRIVABLE_RESOLUTION_M, DRIVABLE_MARGIN_M, extra_points)


@lru_cache(maxsize=16)
def lanelet_map(path: Path) -> tuple[LaneGraph, list[np.ndarray]]:
    """The Lanelet2 map at ``path`` as a :class:`LaneGraph` and its lanelet polygons ((n_i, 2) rings, m).

    Cached: every recording of a location shares its map.
    """
    lanelet2 = _lanelet2()
    if not Path(path).is_file():
        raise ValueError(f"{Path(path).name}: INTERACTION map does not exist (expected at {path})")
    projector = lanelet2.projection.UtmProjector(lanelet2.io.Origin(0, 0))
    try:
        lanelet_map_ = lanelet2.io.load(str(path), projector)
    except Exception as err:  # lanelet2 raises its own (C++) error kinds
        reason = f"{type(err).__name__}: {err}".replace("\n", " ")
        raise ValueError(f"{Path(path).name}: not a readable Lanelet2 map ({reason})") from err
    if len(lanelet_map_.laneletLayer) == 0:
        raise ValueError(f"{Path(path).name}: Lanelet2 map holds no lanelets")
    rules = lanelet2.traffic_rules.create(
        lanelet2.traffic_rules.Locations.Germany, lanelet2.traffic_rules.Participants.Vehicle
    )
    graph = lanelet2.routing.RoutingGraph(lanelet_map_, rules)
    return _lane_graph(lanelet_map_, graph)


def require_lanelet2() -> None:
    """Raise ValueError (one line, naming the extra) where ``lanelet2`` is not installed."""
    _lanelet2()


def _lanelet2() -> Any:
    try:
        import lanelet2
    except ImportError as err:
        raise ValueError(
            "reading INTERACTION maps needs the optional dependency lanelet2: "
            "pip install 'ctgpp[interaction]'"
        ) from err
    return lanelet2


def _xy(linestring: Any) -> np.ndarray:
    return np.array([(p.x, p.y) for p in linestring], dtype=np.float64).reshape(-1, 2)


def _lane_graph(lanelet_map_: Any, graph: Any) -> tuple[LaneGraph, list[np.ndarray]]:
    """Lanelets (sorted by id) as lanes; successors, predecessors and neighbours of the routing graph."""
    lanelets = sorted(lanelet_map_.laneletLayer, key=lambda ll: ll.id)
    index = {ll.id: i for i, ll in enumerate(lanelets)}
    centerlines = [_xy(ll.centerline) for ll in lanelets]
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in centerlines])]).astype(np.int64)
    routed = {(i, index[n.id]) for i, ll in enumerate(lanelets) for n in graph.following(ll)}
    # some maps join lanelets at a shared point without a shared bound, so the routing graph misses the
    # link (DR_USA_Intersection_GL: 11 of 111 joins); the successor rule of the maps without links adds
    # them (lane_topology: start within 0.5 m of an end, headings within 60°)
    geometric = {(int(a), int(b)) for a, b in successor_edges(centerlines)}
    successors = sorted(routed | geometric)
    predecessors = [(j, i) for i, j in successors]

    def neighbour(lanelet: Any, side: str) -> int:
        # a lane-change neighbour, else a same-direction lanelet beside it where changing is not allowed
        other = getattr(graph, side)(lanelet) or getattr(graph, f"adjacent{side.capitalize()}")(lanelet)
        return index.get(other.id, -1) if other is not None else -1

    polygons = [np.concatenate([_xy(ll.leftBound), _xy(ll.rightBound)[::-1]], axis=0) for ll in lanelets]
    lanes = LaneGraph(
        ids=np.array([ll.id for ll in lanelets], dtype=np.int64),
        points=np.concatenate(centerlines, axis=0) if centerlines else np.zeros((0, 2)),
        offsets=offsets,
        successors=np.array(successors, dtype=np.int64).reshape(-1, 2),
        predecessors=np.array(predecessors, dtype=np.int64).reshape(-1, 2),
        left=np.array([neighbour(ll, "left") for ll in lanelets], dtype=np.int64),
        right=np.array([neighbour(ll, "right") for ll in lanelets], dtype=np.int64),
        intersection=detect_intersections(centerlines),  # connectors, by the rule of the other maps
    )
    return lanes, polygons
