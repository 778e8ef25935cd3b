"""CommonRoad XML scenarios (2020a format, e.g. NGSIM) -> :class:`Scene` (DESIGN.md, Data).

Parsing uses the optional dependency ``commonroad-io`` (``pip install ctgpp[commonroad]``), imported
only when a file is loaded. Agents are the scenario's dynamic obstacles (states at their own time
steps) and static obstacles (valid at every step); lanes are the lanelets' centerlines with the
lanelet network's successor, predecessor and same-direction adjacency; the drivable area is the union
of the lanelet polygons, rasterized.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ctgpp.data.nuscenes_drivable import rasterize_polygons
from ctgpp.data.splits import NGSIM_HELDOUT_LOCATIONS
from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentTracks, AgentType, LaneGraph, Scene

DRIVABLE_RESOLUTION_M = 0.2
DRIVABLE_MARGIN_M = 10.0

# Benchmark id prefix -> NGSIM location (the map name of the scene).
NGSIM_LOCATIONS = {"USA_US101": "US101", "USA_Lanker": "Lankershim", "USA_Peach": "Peachtree"}

_VEHICLE_TYPES = frozenset({"car", "truck", "bus", "motorcycle", "priorityVehicle", "taxi"})
_TYPE_BY_NAME = {"pedestrian": AgentType.PEDESTRIAN, "bicycle": AgentType.CYCLIST}


def iter_commonroad(src: Path) -> list[Path]:
    """Every ``*.xml`` file at or under ``src`` (recursive), sorted."""
    src = Path(src)
    if src.is_file():
        return [src]
    if not src.is_dir():
        raise FileNotFoundError(f"{src} does not exist")
    return sorted(p for p in src.rglob("*.xml") if p.is_file())


def ngsim_location(scene_id: str) -> str | None:
    """US101 / Lankershim / Peachtree for an NGSIM benchmark id (``USA_US101-10_1_T-1``), else None."""
    for prefix, location in NGSIM_LOCATIONS.items():
        if scene_id.startswith(prefix):
            return location
    return None


def ngsim_split(scene_id: str) -> str:
    """``"train"`` for US101 and Lankershim, ``"heldout"`` for Peachtree (by location, never by file)."""
    location = ngsim_location(scene_id)
    if location is None:
        prefixes = ", ".join(NGSIM_LOCATIONS)
        raise ValueError(f"{scene_id!r} is not an NGSIM benchmark id (expected a prefix among {prefixes})")
    return "heldout" if location in NGSIM_HELDOUT_LOCATIONS else "train"


def load_commonroad(path: Path) -> Scene:
    """Read one CommonRoad XML scenario into a :class:`Scene` (dataset ``"ngsim"``, no ego).

    The time axis spans step 0 to the last step of any obstacle at the scenario's dt. Raises
    FileNotFoundError for a missing file, ValueError naming the file when it cannot be parsed, and
    ImportError when ``commonroad-io`` is not installed.
    """
    path = Path(path)
    scenario = _read_scenario(path)
    scene_id = str(scenario.scenario_id) or path.stem
    agents = _agent_tracks(scenario)
    lanes, polygons = _lane_graph(scenario.lanelet_network)
    extra_points = agents.xy[agents.valid]  # (V, 2) every valid agent position
    drivable = rasterize_polygons(polygons, DRIVABLE_RESOLUTION_M, DRIVABLE_MARGIN_M, extra_points)
    map_name = ngsim_location(scene_id) or scene_id.split("-")[0]
    return Scene(
        id=scene_id,
        map_name=map_name,
        dataset="ngsim",
        dt_s=float(scenario.dt),
        agents=agents,
        lanes=lanes,
        drivable=drivable,
        ego=-1,
    )


@contextlib.contextmanager
def _quiet_commonroad() -> Iterator[None]:
    """Silence commonroad-io's per-element warnings (e.g. 2020a intersection names) while parsing."""
    logger = logging.getLogger("commonroad")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def _read_scenario(path: Path) -> Any:
    try:
        from commonroad.common.file_reader import CommonRoadFileReader
    except ImportError as err:
        raise ImportError(
            "reading CommonRoad XML needs the optional dependency commonroad-io: install ctgpp[commonroad]"
        ) from err
    if not path.is_file():
        raise FileNotFoundError(f"CommonRoad scenario {path} does not exist")
    try:
        with _quiet_commonroad():
            scenario, _ = CommonRoadFileReader(str(path)).open()
    except Exception as err:  # commonroad-io raises many kinds (ParseError, KeyError, AttributeError...)
        reason = f"{type(err).__name__}: {err}"
        raise ValueError(f"{path.name}: not a readable CommonRoad scenario ({reason})") from err
    return scenario


def _agent_type(obstacle: Any, is_static: bool) -> AgentType:
    if is_static:
        return AgentType.STATIC
    name = str(getattr(obstacle.obstacle_type, "value", obstacle.obstacle_type))
    if name in _VEHICLE_TYPES:
        return AgentType.VEHICLE
    return _TYPE_BY_NAME.get(name, AgentType.OTHER)


def _extent_and_shift(shape: Any) -> tuple[float, float, float]:
    """(length m, width m, origin x-shift m) of an obstacle shape; the shift moves origin -> box centre."""
    shift = float(getattr(shape, "origin_x_shift", 0.0) or 0.0)
    length = getattr(shape, "total_length", None) or getattr(shape, "length", None)
    if length is not None and getattr(shape, "width", None) is not None:
        return float(length), float(shape.width), shift
    if getattr(shape, "radius", None) is not None:
        return 2.0 * float(shape.radius), 2.0 * float(shape.radius), 0.0
    if getattr(shape, "vertices", None) is not None:
        vertices = np.asarray(shape.vertices, dtype=np.float64)  # (n, 2) in the obstacle frame
        size = vertices.max(axis=0) - vertices.min(axis=0)
        return float(size[0]), float(size[1]), 0.0
    return 0.0, 0.0, 0.0


def _state_values(state: Any) -> tuple[int, float, float, float, float]:
    """(time step, x m, y m, yaw rad, speed m/s) of a commonroad state; missing yaw/speed are NaN."""
    position = state.position
    position = np.asarray(getattr(position, "center", position), dtype=np.float64)
    yaw = getattr(state, "orientation", None)
    speed = getattr(state, "velocity", None)
    step = state.time_step
    step = int(getattr(step, "start", step))
    yaw_value = float(getattr(yaw, "start", yaw)) if yaw is not None else np.nan
    speed_value = abs(float(getattr(speed, "start", speed))) if speed is not None else np.nan
    return step, float(position[0]), float(position[1]), yaw_value, speed_value


def _obstacle_states(obstacle: Any) -> np.ndarray:
    """(n, 5) rows (step, x, y, yaw, speed) of an obstacle: its initial state, then its trajectory."""
    states = [obstacle.initial_state]
    trajectory = getattr(getattr(obstacle, "prediction", None), "trajectory", None)
    if trajectory is not None:
        states += list(trajectory.state_list)
    return np.array([_state_values(s) for s in states], dtype=np.float64)


def _agent_tracks(scenario: Any) -> AgentTracks:
    """Dynamic obstacles at their own steps, static obstacles at every step, on one time axis."""
    obstacles = [(o, False) for o in scenario.dynamic_obstacles]
    obstacles += [(o, True) for o in scenario.static_obstacles]
    rows = [_obstacle_states(o) for o, _ in obstacles]
    dynamic_steps = [r[:, 0] for r, (_, static) in zip(rows, obstacles, strict=True) if not static]
    n_steps = int(max((s.max() for s in dynamic_steps), default=0)) + 1
    n_agents = len(obstacles)
    xy = np.zeros((n_agents, n_steps, 2))
    yaw = np.zeros((n_agents, n_steps))
    speed = np.zeros((n_agents, n_steps))
    valid = np.zeros((n_agents, n_steps), dtype=bool)
    extent = np.zeros((n_agents, 2))
    for i, ((obstacle, static), states) in enumerate(zip(obstacles, rows, strict=True)):
        length, width, shift = _extent_and_shift(obstacle.obstacle_shape)
        extent[i] = (length, width)
        if static:
            states = np.repeat(states[:1], n_steps, axis=0)
            states[:, 0] = np.arange(n_steps)
            states[:, 4] = 0.0
        states = states[(states[:, 0] >= 0) & (states[:, 0] < n_steps)]
        steps = states[:, 0].astype(np.int64)
        heading = np.nan_to_num(states[:, 3])
        centre = states[:, 1:3] - shift * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
        xy[i, steps] = centre
        yaw[i, steps] = wrap_angle(heading)
        speed[i, steps] = _fill_speed(states[:, 4], centre, steps, float(scenario.dt))
        valid[i, steps] = True
    types = np.array([_agent_type(o, s) for o, s in obstacles], dtype=np.int8)
    ids = np.array([int(o.obstacle_id) for o, _ in obstacles], dtype=np.int64)
    return AgentTracks(ids=ids, types=types, xy=xy, yaw=yaw, speed=speed, extent=extent, valid=valid)


def _fill_speed(speed: np.ndarray, xy: np.ndarray, steps: np.ndarray, dt_s: float) -> np.ndarray:
    """(n,) speeds, where missing (NaN) replaced by finite differences of the positions (n, 2)."""
    missing = np.isnan(speed)
    if not missing.any():
        return speed
    if len(steps) < 2:
        return np.nan_to_num(speed)
    times = steps * dt_s
    derived = np.hypot(np.gradient(xy[:, 0], times), np.gradient(xy[:, 1], times))
    return np.where(missing, derived, speed)


def _lane_graph(network: Any) -> tuple[LaneGraph, list[np.ndarray]]:
    """The lanelets as a :class:`LaneGraph` and their polygons (left bound + reversed right bound)."""
    lanelets = sorted(network.lanelets, key=lambda lanelet: lanelet.lanelet_id)
    index = {lanelet.lanelet_id: i for i, lanelet in enumerate(lanelets)}
    centerlines = [np.asarray(lanelet.center_vertices, dtype=np.float64) for lanelet in lanelets]
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in centerlines])]).astype(np.int64)
    successors = [(i, index[j]) for i, ll in enumerate(lanelets) for j in ll.successor if j in index]
    predecessors = [(i, index[j]) for i, ll in enumerate(lanelets) for j in ll.predecessor if j in index]

    def neighbour(lanelet: Any, side: str) -> int:
        other = getattr(lanelet, f"adj_{side}")
        same = getattr(lanelet, f"adj_{side}_same_direction")
        return index.get(other, -1) if other is not None and same is True else -1

    in_intersection = _intersection_lanelets(network)
    polygons = [
        np.concatenate([np.asarray(lanelet.left_vertices), np.asarray(lanelet.right_vertices)[::-1]], axis=0)
        for lanelet in lanelets
    ]
    lanes = LaneGraph(
        ids=np.array([lanelet.lanelet_id for lanelet in lanelets], dtype=np.int64),
        points=np.concatenate(centerlines, axis=0) if centerlines else np.zeros((0, 2)),
        offsets=offsets,
        successors=np.array(successors, dtype=np.int64).reshape(-1, 2),
        predecessors=np.array(predecessors, dtype=np.int64).reshape(-1, 2),
        left=np.array([neighbour(lanelet, "left") for lanelet in lanelets], dtype=np.int64),
        right=np.array([neighbour(lanelet, "right") for lanelet in lanelets], dtype=np.int64),
        intersection=np.array([lanelet.lanelet_id in in_intersection for lanelet in lanelets], dtype=bool),
    )
    return lanes, polygons


def _intersection_lanelets(network: Any) -> set[int]:
    """Ids of the lanelets that cross an intersection: its incomings' left/right/straight successors.

    commonroad-io >= 2024 names them ``outgoing_*`` (2020a ``successors*`` are mapped onto them).
    """
    members: set[int] = set()
    for intersection in getattr(network, "intersections", None) or []:
        for incoming in intersection.incomings:
            for direction in ("left", "right", "straight"):
                for name in (f"outgoing_{direction}", f"successors_{direction}"):
                    members.update(int(i) for i in (getattr(incoming, name, None) or ()))
    return members
