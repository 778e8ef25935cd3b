"""A rollout as a ScenarioNet scenario pickle, the format MetaDrive and ScenarioNet's tools replay.

The scenario is a plain dict ``id, version, length, metadata, tracks, dynamic_map_states,
map_features`` over the rollout's window (logged history, then the simulated future; step
``metadata["current_time_index"]`` is the simulation start, t = 0 s):

- ``tracks[id]``: every agent valid at some step of the window, ``type`` (VEHICLE, PEDESTRIAN,
  CYCLIST, TRAFFIC_CONE or TRAFFIC_BARRIER (a static object longer than 1 m), OTHER), ``state``
  with ``position (T, 3)`` (z = 0: ctgpp scenes are flat), ``heading (T,)``, ``velocity (T, 2)``
  (the speed along the heading), ``valid (T,)`` bool and ``length / width / height (T, 1)``, every
  value zero where the agent is not valid; ``metadata`` with ``object_id``, ``type``,
  ``track_length`` and ctgpp's ``controlled`` / ``vehicle_number`` (-1 for replayed agents).
  ctgpp scenes carry no heights: ``height`` is a nominal value per type (``HEIGHT_M``).
- ``metadata``: ``ts``, ``sample_rate``, ``sdc_id`` (the ego, or vehicle 0 where the scene has no
  ego: MetaDrive drives the sdc), ``coordinate`` "right-handed", ``map``, ``dataset`` "ctgpp", the
  per-object and number summaries ScenarioNet's tools filter on, and ``ctgpp`` (scene, policy, window).
- ``map_features``: every lane (``LANE_SURFACE_STREET``, centerline ``polyline (n, 2)``,
  ``entry_lanes`` / ``exit_lanes`` / ``left_neighbor`` / ``right_neighbor`` from the scene's lane
  graph) and the edges of the drivable area (``ROAD_EDGE_BOUNDARY``, traced from its raster).
- ``dynamic_map_states``: empty (ctgpp scenes hold no traffic-light states).

The pickle references numpy's array globals under their numpy 1.x names (``numpy.core.*``), which
numpy 1.x and 2.x both load (MetaDrive pins numpy 1.x), and nothing else; ctgpp's restricted
unpickler (:mod:`ctgpp.data.safe_pickle`) reads it.
"""

from __future__ import annotations

import io
import pickle
from typing import TYPE_CHECKING, Any

import numpy as np

from ctgpp import __version__
from ctgpp.io.atomic import atomic_path
from ctgpp.io.drivable_edges import drivable_edges
from ctgpp.scene.types import AgentType

if TYPE_CHECKING:
    from pathlib import Path

    from ctgpp.interfaces import Rollout

STATIC_BARRIER_LENGTH_M = 1.0
HEIGHT_M = {"VEHICLE": 1.6, "PEDESTRIAN": 1.75, "CYCLIST": 1.75, "TRAFFIC_CONE": 0.8,
            "TRAFFIC_BARRIER": 1.0, "OTHER": 1.5}
_TYPE_NAMES = {AgentType.VEHICLE: "VEHICLE", AgentType.PEDESTRIAN: "PEDESTRIAN",
               AgentType.CYCLIST: "CYCLIST", AgentType.OTHER: "OTHER"}
MOVING_DISTANCE_M = 1.0  # ScenarioNet's number summary counts an object moving past 1 m


def scenario_description(rollout: Rollout) -> dict[str, Any]:
    """The rollout as a ScenarioNet scenario dict of plain Python and numpy values (module docstring)."""
    sim, scene = rollout.sim, rollout.scene
    n_steps = sim.num_steps
    keep = np.flatnonzero(sim.valid.any(axis=1))  # agents seen in the window
    tracks = {str(sim.ids[a]): _track(rollout, int(a)) for a in keep}
    sdc = _sdc_index(rollout)
    features = _map_features(rollout)
    summary = {key: _object_summary(key, track) for key, track in tracks.items()}
    metadata = {
        "scenario_id": scene.id,
        "id": scene.id,
        "dataset": "ctgpp",
        "map": scene.map_name,
        "coordinate": "right-handed",
        "metadrive_processed": False,
        "sample_rate": float(rollout.dt_s),
        "ts": np.arange(n_steps, dtype=np.float64) * rollout.dt_s,
        "current_time_index": int(rollout.current),
        "sdc_id": str(sim.ids[sdc]),
        "object_summary": summary,
        "number_summary": _number_summary(summary, features),
        "ctgpp": {
            "version": __version__,
            "scene": scene.id,
            "source_dataset": scene.dataset,
            "policy": rollout.policy,
            "first_step": int(rollout.first_step),
            "start_s": float(rollout.start_s),
            "scene_has_ego": bool(scene.ego >= 0),
        },
    }
    return {
        "id": scene.id,
        "version": f"ctgpp {__version__}",
        "length": int(n_steps),
        "metadata": metadata,
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": features,
    }


def write_scenarionet(rollout: Rollout, path: Path) -> Path:
    """Write the rollout's scenario pickle to ``path`` atomically (ScenarioNet's tools list files
    named ``sd_*.pkl``)."""
    data = dumps_numpy1(scenario_description(rollout))
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def dumps_numpy1(value: object) -> bytes:
    """Pickle ``value`` (protocol 4) with numpy arrays referenced as ``numpy.core.multiarray``."""
    buffer = io.BytesIO()
    _Numpy1Pickler(buffer, protocol=4).dump(value)
    return buffer.getvalue()


class _Numpy1Pickler(pickle._Pickler):
    """The pure-Python pickler, writing numpy 2's ``numpy._core.multiarray._reconstruct`` under its
    numpy 1.x module name (numpy 2 still resolves that name; numpy 1.x knows no other)."""

    if TYPE_CHECKING:  # the pure-Python pickler's methods used here, which typeshed leaves out
        def save(self, obj: object) -> None: ...
        def write(self, data: bytes) -> None: ...
        def memoize(self, obj: object) -> None: ...

    def save_global(self, obj: Any, name: str | None = None) -> None:
        if getattr(obj, "__name__", None) == "_reconstruct" and str(obj.__module__).endswith(
            "core.multiarray"
        ):
            self.save("numpy.core.multiarray")
            self.save("_reconstruct")
            self.write(pickle.STACK_GLOBAL)
            self.memoize(obj)
            return
        super().save_global(obj, name)  # type: ignore[misc]  # (not in typeshed either)


def _type_name(kind: int, extent: np.ndarray) -> str:
    if kind == AgentType.STATIC:
        return "TRAFFIC_BARRIER" if extent.max() > STATIC_BARRIER_LENGTH_M else "TRAFFIC_CONE"
    return _TYPE_NAMES.get(AgentType(kind), "OTHER")


def _track(rollout: Rollout, a: int) -> dict[str, Any]:
    """One agent's ScenarioNet track over the window; zeros where it is not valid."""
    sim = rollout.sim
    ok = sim.valid[a]
    n = len(ok)
    kind = _type_name(int(sim.types[a]), sim.extent[a])
    heading = np.where(ok, sim.yaw[a], 0.0)
    position = np.zeros((n, 3))
    position[:, :2] = np.where(ok[:, None], sim.xy[a], 0.0)
    velocity = np.where(ok[:, None], sim.velocity[a], 0.0)  # (T, 2) speed along the heading

    def box(value: float) -> np.ndarray:
        return np.where(ok, value, 0.0)[:, None]  # (T, 1)

    state = {
        "position": position,
        "heading": heading.astype(np.float64),
        "velocity": velocity.astype(np.float64),
        "valid": ok.astype(bool),
        "length": box(float(sim.extent[a, 0])),
        "width": box(float(sim.extent[a, 1])),
        "height": box(HEIGHT_M[kind]),
    }
    metadata = {
        "object_id": str(sim.ids[a]),
        "type": kind,
        "track_length": int(n),
        "controlled": bool(rollout.controlled[a]),
        "vehicle_number": int(rollout.number[a]),
    }
    return {"type": kind, "state": state, "metadata": metadata}


def _sdc_index(rollout: Rollout) -> int:
    """The ego when the scene has one, else the controlled vehicle numbered lowest (vehicle 0)."""
    if rollout.scene.ego >= 0 and rollout.sim.valid[rollout.scene.ego].any():
        return int(rollout.scene.ego)
    numbered = np.flatnonzero(rollout.number >= 0)
    if len(numbered) == 0:
        return int(np.flatnonzero(rollout.sim.valid.any(axis=1))[0])
    return int(numbered[np.argmin(rollout.number[numbered])])


def _map_features(rollout: Rollout) -> dict[str, dict[str, Any]]:
    lanes = rollout.scene.lanes
    ids = [str(i) for i in lanes.ids]
    features: dict[str, dict[str, Any]] = {}
    for i, key in enumerate(ids):
        features[key] = {
            "type": "LANE_SURFACE_STREET",
            "polyline": np.asarray(lanes.lane(i), dtype=np.float64),
            "entry_lanes": [ids[j] for j in lanes.predecessors_of(i)],
            "exit_lanes": [ids[j] for j in lanes.successors_of(i)],
            "left_neighbor": _neighbour(ids, int(lanes.left[i])),
            "right_neighbor": _neighbour(ids, int(lanes.right[i])),
        }
    for k, edge in enumerate(drivable_edges(rollout.scene.drivable)):
        features[f"road_edge_{k}"] = {"type": "ROAD_EDGE_BOUNDARY", "polyline": edge}
    return features


def _neighbour(ids: list[str], j: int) -> list[dict[str, str]]:
    """Waymo-style neighbour list: ``[{"feature_id": id}]`` or empty."""
    return [{"feature_id": ids[j]}] if j >= 0 else []


def _object_summary(key: str, track: dict[str, Any]) -> dict[str, Any]:
    """ScenarioNet's per-object summary: type, length, distance moved, valid steps."""
    state = track["state"]
    ok = state["valid"]
    points = state["position"][ok, :2]
    moved = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0
    first = int(np.argmax(ok))
    run = np.flatnonzero(~ok[first:])
    return {
        "type": track["type"],
        "object_id": key,
        "track_length": int(len(ok)),
        "moving_distance": moved,
        "valid_length": int(ok.sum()),
        "continuous_valid_length": int(run[0] if len(run) else len(ok) - first),
    }


class _PickledSorted(set[str]):
    """A set that pickles as ``set(sorted list)``: the file's bytes do not depend on the string hash
    seed of the process that wrote it (a plain set pickles its items in hash order), and it reads
    back as a plain set, without ctgpp."""

    def __reduce_ex__(self, protocol: Any) -> tuple[type, tuple[list[str]]]:
        return set, (sorted(self),)


def _number_summary(summary: dict[str, dict[str, Any]], features: dict[str, Any]) -> dict[str, Any]:
    """ScenarioNet's scenario counts: objects (moving ones: more than 1 m) by type, map features."""
    each: dict[str, int] = {}
    moving_each: dict[str, int] = {}
    for item in summary.values():
        each[item["type"]] = each.get(item["type"], 0) + 1
        if item["moving_distance"] > MOVING_DISTANCE_M:
            moving_each[item["type"]] = moving_each.get(item["type"], 0) + 1
    return {
        "object_types": _PickledSorted(each),
        "num_objects": len(summary),
        "num_moving_objects": sum(moving_each.values()),
        "num_objects_each_type": each,
        "num_moving_objects_each_type": moving_each,
        "num_traffic_lights": 0,
        "num_traffic_light_types": set(),
        "num_traffic_light_each_step": {},
        "num_map_features": len(features),
        "map_height_diff": 0.0,
    }
