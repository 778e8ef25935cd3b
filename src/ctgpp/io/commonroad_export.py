"""A rollout as a CommonRoad XML scenario (2020a format), written with ``commonroad-io``.

- Time step 0 of the scenario is the first step of the rollout's window (the logged history, then
  the simulated future; the simulation starts at step ``rollout.current``), at the scene's dt.
- Every moving agent is a dynamic obstacle: its first valid step is the initial state (position of
  the box centre, orientation, velocity = speed, acceleration and yaw rate by finite differences,
  slip angle 0), the following steps its trajectory prediction; the shape is a rectangle of the
  agent's length and width. Types: vehicle -> car, pedestrian -> pedestrian, cyclist -> bicycle,
  other -> unknown. CommonRoad has no obstacle that disappears and comes back: an agent with a gap
  in its validity becomes one obstacle per contiguous run (the first keeps the agent's id). A
  dynamic obstacle needs a trajectory after its initial state, so a run of a single step (an agent
  seen for 0.1 s of the window) is left out.
- A static object (cone, barrier) is a static obstacle of type constructionZone at its pose of its
  first valid step: CommonRoad's static obstacles have no time, they stand for the whole scenario
  (the few centimetres of annotation jitter such an object has in the log are not kept).
- No planning problem: a simulated scene poses none (vehicle 0 is an obstacle like the others).
  CommonRoad's 2020a XML schema asks for one, and fixes every initial state at step 0, which an
  agent that enters during the window (the replayed pedestrians of a nuScenes scene, say) does not
  have: it keeps its own first step. commonroad-io's object model, writer and reader carry both;
  the schema rejects the file for these two reasons only (nothing is shifted in time or invented).
- The scene's lanes are the lanelets: the centerline exactly, successors, predecessors and
  same-direction neighbours from the lane graph, intersection lanes typed ``intersection``. ctgpp
  scenes keep no lane edges, so the left and right bounds are rebuilt at each lane's measured width
  (:mod:`ctgpp.io.lane_bounds`): for a CommonRoad input the network has the original lanelet ids,
  centerlines and topology, with approximate bounds; for nuScenes the lanes become lanelets this way.
- Ids: CommonRoad wants one id space for lanelets and obstacles. Integer lane and agent ids that do
  not collide (CommonRoad input) are kept; otherwise lanelets are numbered 1..L in the scene's lane
  order and obstacles ``base + agent index``, base the first power of ten above the lanelet ids
  (:func:`commonroad_ids`).
- Floats are written with ``DECIMALS`` decimals (commonroad-io truncates), so positions read back
  within 1e-10 m.
"""

from __future__ import annotations

import inspect
import logging
import re
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from ctgpp import __version__
from ctgpp.geometry import wrap_angle
from ctgpp.io.atomic import atomic_path
from ctgpp.io.lane_bounds import lane_bounds
from ctgpp.scene.types import AgentType, LaneGraph

if TYPE_CHECKING:
    from pathlib import Path

    from ctgpp.interfaces import Rollout

DECIMALS = 10
_OBSTACLE_TYPES = {
    AgentType.VEHICLE: "CAR",
    AgentType.PEDESTRIAN: "PEDESTRIAN",
    AgentType.CYCLIST: "BICYCLE",
    AgentType.OTHER: "UNKNOWN",
}


def commonroad_ids(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """(L,) lanelet id of every lane and (A,) obstacle id of every agent, -1 for an agent that is not
    exported (no run of two valid steps); see the module docstring."""
    lane_ids, agent_ids = _ids(rollout)
    sim = rollout.sim
    static = (sim.types == AgentType.STATIC) & sim.valid.any(axis=1)
    exported = static | np.array([len(_runs(row)) > 0 for row in sim.valid], dtype=bool)
    return lane_ids, np.where(exported, agent_ids, -1)


def _ids(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """(L,) lanelet ids and (A,) obstacle ids of every lane and agent, exported or not."""
    lane_ids = _as_ints(rollout.scene.lanes.ids)
    if lane_ids is None or len(np.unique(lane_ids)) != len(lane_ids) or (lane_ids <= 0).any():
        lane_ids = np.arange(1, rollout.scene.lanes.num_lanes + 1, dtype=np.int64)
    agent_ids = _as_ints(rollout.sim.ids)
    if (
        agent_ids is None
        or len(np.unique(agent_ids)) != len(agent_ids)
        or (agent_ids <= 0).any()
        or np.isin(agent_ids, lane_ids).any()
    ):
        top = int(lane_ids.max()) if len(lane_ids) else 0
        base = 10 ** len(str(top)) if top > 0 else 1
        agent_ids = base + np.arange(rollout.sim.num_agents, dtype=np.int64)
    return lane_ids, agent_ids


def commonroad_scenario(rollout: Rollout) -> Any:
    """The rollout as a ``commonroad.scenario.scenario.Scenario`` (module docstring)."""
    from commonroad.scenario.scenario import Scenario

    scene = rollout.scene
    scenario = Scenario(float(rollout.dt_s), scenario_id=_scenario_id(scene.id, scene.map_name))
    lane_ids, agent_ids = _ids(rollout)
    scenario.add_objects(_lanelets(scene.lanes, lane_ids))
    next_id = int(max(lane_ids.max(initial=0), agent_ids.max(initial=0))) + 1
    for a in range(rollout.sim.num_agents):
        if rollout.sim.types[a] == AgentType.STATIC:
            if rollout.sim.valid[a].any():
                scenario.add_objects(_static_obstacle(rollout, a, int(agent_ids[a])))
            continue
        for k, (lo, hi) in enumerate(_runs(rollout.sim.valid[a])):
            obstacle_id = int(agent_ids[a]) if k == 0 else next_id
            next_id += k > 0
            scenario.add_objects(_obstacle(rollout, a, lo, hi, obstacle_id))
    return scenario


def write_commonroad(rollout: Rollout, path: Path) -> Path:
    """Write the rollout as CommonRoad XML to ``path`` atomically."""
    from commonroad.common.file_writer import CommonRoadFileWriter, OverwriteExistingFile
    from commonroad.planning.planning_problem import PlanningProblemSet

    scenario = commonroad_scenario(rollout)
    options: dict[str, Any] = {"decimal_precision": DECIMALS}
    if "file_format" in inspect.signature(CommonRoadFileWriter.__init__).parameters:  # >= 2024
        from commonroad.common.util import FileFormat

        options["file_format"] = FileFormat.XML
    source = f"ctgpp {__version__}: {rollout.scene.id} ({rollout.scene.dataset}), policy {rollout.policy}"
    writer = CommonRoadFileWriter(
        scenario, PlanningProblemSet(), author="ctgpp", affiliation="", source=source, tags=set(), **options
    )
    with atomic_path(path) as tmp:
        tmp.unlink()  # the writer asks before it replaces a file (it prints "Replace file")
        logger = logging.getLogger("commonroad")
        disabled = logger.disabled
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # per-element notes of commonroad-io
            logger.disabled = True
            try:
                writer.write_to_file(str(tmp), OverwriteExistingFile.ALWAYS)
            finally:
                logger.disabled = disabled
    return path


def _as_ints(ids: np.ndarray) -> np.ndarray | None:
    """``ids`` as int64 when every one is a decimal integer, else None."""
    text = [str(i) for i in ids]
    if not all(re.fullmatch(r"-?\d{1,15}", t) for t in text):
        return None
    return np.array([int(t) for t in text], dtype=np.int64)


def _scenario_id(scene_id: str, map_name: str) -> Any:
    """The scene's own benchmark id (CommonRoad input), else ``ZAM_<Map>-<scene number>_1_T-1``."""
    from commonroad.common.common_scenario import ScenarioID

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Not a valid scenario ID" for other ids
        parsed = ScenarioID.from_benchmark_id(scene_id, "2020a")
    if str(parsed) == scene_id:
        return parsed
    words = re.split(r"[^A-Za-z0-9]+", map_name)
    name = "".join(w[:1].upper() + w[1:] for w in words) or "Ctgpp"
    digits = re.findall(r"\d+", scene_id)
    number = int(digits[-1]) if digits and 0 < int(digits[-1]) < 10**9 else 1
    return ScenarioID(country_id="ZAM", map_name=name, map_id=number, configuration_id=1,
                      obstacle_behavior="T", prediction_id=1)


def _lanelets(lanes: LaneGraph, ids: np.ndarray) -> list[Any]:
    from commonroad.common.common_lanelet import LaneletType
    from commonroad.scenario.lanelet import Lanelet

    bounds = lane_bounds(lanes)
    lanelets = []
    for i, (left, right) in enumerate(bounds):
        j_left, j_right = int(lanes.left[i]), int(lanes.right[i])
        kind = LaneletType.INTERSECTION if lanes.intersection[i] else LaneletType.UNKNOWN
        lanelets.append(
            Lanelet(
                left_vertices=left,
                center_vertices=np.asarray(lanes.lane(i), dtype=np.float64),
                right_vertices=right,
                lanelet_id=int(ids[i]),
                predecessor=[int(ids[j]) for j in lanes.predecessors_of(i)],
                successor=[int(ids[j]) for j in lanes.successors_of(i)],
                adjacent_left=int(ids[j_left]) if j_left >= 0 else None,
                adjacent_left_same_direction=True if j_left >= 0 else None,
                adjacent_right=int(ids[j_right]) if j_right >= 0 else None,
                adjacent_right_same_direction=True if j_right >= 0 else None,
                lanelet_type={kind},
            )
        )
    return lanelets


def _runs(valid: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs ``[lo, hi)`` of True in ``valid`` (T,) that are two steps long or more."""
    edges = np.diff(np.concatenate([[0], valid.astype(np.int8), [0]]))
    runs = zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True)
    return [(lo, hi) for lo, hi in runs if hi - lo >= 2]


def _shape(length_m: float, width_m: float) -> Any:
    try:  # commonroad-io >= 2026
        from commonroad.geometry.obstacle_shapes.rect_obstacle_shape import RectObstacleShape

        return RectObstacleShape(width=width_m, length=length_m)
    except ImportError:
        from commonroad.geometry.shape import Rectangle

        return Rectangle(length=length_m, width=width_m)


def _obstacle(rollout: Rollout, a: int, lo: int, hi: int, obstacle_id: int) -> Any:
    """Agent ``a`` over window steps ``[lo, hi)`` (two or more) as a dynamic obstacle."""
    from commonroad.prediction.prediction import TrajectoryPrediction
    from commonroad.scenario.obstacle import DynamicObstacle, ObstacleType
    from commonroad.scenario.state import CustomState, InitialState
    from commonroad.scenario.trajectory import Trajectory

    sim, dt = rollout.sim, rollout.dt_s
    xy, yaw, speed = sim.xy[a, lo:hi], wrap_angle(sim.yaw[a, lo:hi]), sim.speed[a, lo:hi]
    initial = InitialState(
        time_step=lo,
        position=np.array(xy[0], dtype=np.float64),
        orientation=float(yaw[0]),
        velocity=float(speed[0]),
        acceleration=float((speed[1] - speed[0]) / dt),
        yaw_rate=float(wrap_angle(yaw[1] - yaw[0]) / dt),
        slip_angle=0.0,
    )
    shape = _shape(float(sim.extent[a, 0]), float(sim.extent[a, 1]))
    states = [
        CustomState(time_step=lo + k, position=np.array(xy[k], dtype=np.float64),
                    orientation=float(yaw[k]), velocity=float(speed[k]))
        for k in range(1, hi - lo)
    ]
    prediction = TrajectoryPrediction(Trajectory(lo + 1, states), shape)
    kind = getattr(ObstacleType, _OBSTACLE_TYPES[AgentType(int(sim.types[a]))])
    return DynamicObstacle(obstacle_id, kind, shape, initial, prediction)


def _static_obstacle(rollout: Rollout, a: int, obstacle_id: int) -> Any:
    """Static agent ``a`` as a static obstacle at its pose of its first valid step."""
    from commonroad.scenario.obstacle import ObstacleType, StaticObstacle
    from commonroad.scenario.state import InitialState

    sim = rollout.sim
    k = int(np.argmax(sim.valid[a]))
    initial = InitialState(
        time_step=0,
        position=np.array(sim.xy[a, k], dtype=np.float64),
        orientation=float(wrap_angle(sim.yaw[a, k])),
        velocity=0.0,
        acceleration=0.0,
        yaw_rate=0.0,
        slip_angle=0.0,
    )
    shape = _shape(float(sim.extent[a, 0]), float(sim.extent[a, 1]))
    return StaticObstacle(obstacle_id, ObstacleType.CONSTRUCTION_ZONE, shape, initial)
