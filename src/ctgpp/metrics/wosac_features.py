"""The per-step features of the Waymo Open Sim Agents Challenge (WOSAC), computed on a scene's tracks.

Definitions follow the challenge's published metric code and paper (Montali et al., "The Waymo Open
Sim Agents Challenge", NeurIPS 2023 Datasets and Benchmarks, arXiv:2305.12032; waymo-open-dataset,
``wdl_limited/sim_agents_metrics``: ``trajectory_features.py``, ``interaction_features.py``,
``map_metric_features.py``, ``metric_features.py``, 2024 version), re-written here in NumPy:

- kinematics (:func:`kinematics`): central differences over one step either side, at the tracks'
  step ``dt``: linear speed |Δxy| / 2dt (m/s), linear acceleration Δspeed / 2dt (m/s², signed),
  angular speed wrap(Δyaw) / 2dt (rad/s), angular acceleration wrap(Δ(half-step yaw change)) / 2dt²
  (rad/s²); undefined (NaN) at the first and last step (speeds) or two steps (accelerations).
- distance to the nearest object (:func:`nearest_object_distance`): the signed distance between
  oriented boxes (m; negative: the penetration depth of overlapping boxes), to every other valid
  agent of the scene (controlled or replayed: vehicles, pedestrians, cyclists, obstacles).
- collision: that distance below 0 (the challenge's ``COLLISION_DISTANCE_THRESHOLD``).
- time to collision (:func:`time_to_collision`): with the box ahead that the object follows (ahead
  of its front, heading within 75°, overlapping its straight trail laterally, and within 10° where
  that overlap is under 0.5 m), the gap over the closing speed at constant speeds, capped at 5 s (5 s
  when there is none or it is not closing). One deviation: the heading difference is wrapped to
  [0, π] (the published code takes the raw difference of headings).
- distance to the road edge (:func:`road_edge_distance`): the signed distance (m, negative on the
  road) of the box's most off-road corner. A project scene keeps no road-edge polylines: every
  converter turns its map into the drivable raster (``Scene.drivable``; Waymo scenes draw it up to
  their road edges, ``data.waymo_json``; nuScenes from its drivable polygons; the others from lanes
  widened), so the edge here is the boundary of that drivable area, read from its signed distance
  field (``DrivableArea.sdf_m``) by bilinear interpolation; a point beyond the raster reads the value
  at its border.
- off-road: that distance above 0 (``OFFROAD_DISTANCE_THRESHOLD``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ctgpp.geometry import bounding_radius, box_corners
from ctgpp.scene.types import AgentTracks, DrivableArea

FAR_M = 1e10  # the distance to "no other valid object"
MAX_TTC_S = 5.0
MAX_HEADING_DIFF = math.radians(75.0)
MAX_HEADING_DIFF_SMALL_OVERLAP = math.radians(10.0)
SMALL_OVERLAP_M = 0.5
NEAREST_RANGE_M = 40.0  # the histogram's top: a nearest object farther than this scores the same


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into [-π, π)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def central_diff(x: np.ndarray) -> np.ndarray:
    """(x[t+1] − x[t−1]) / 2 along the last axis, NaN at the two ends (same shape)."""
    out = np.full(x.shape, np.nan)
    out[..., 1:-1] = (x[..., 2:] - x[..., :-2]) / 2
    return out


def central_and(valid: np.ndarray) -> np.ndarray:
    """valid[t−1] & valid[t+1] along the last axis, False at the two ends: where a central difference
    of valid values is defined."""
    out = np.zeros(valid.shape, dtype=bool)
    out[..., 1:-1] = valid[..., 2:] & valid[..., :-2]
    return out


def kinematics(xy: np.ndarray, yaw: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """Linear and angular speed and acceleration of tracks xy (..., T, 2) m, yaw (..., T) rad at step
    ``dt`` s -> each (..., T): ``linear_speed`` m/s, ``linear_acceleration`` m/s²,
    ``angular_speed`` rad/s, ``angular_acceleration`` rad/s² (NaN where undefined: module docstring)."""
    dxy = np.stack([central_diff(xy[..., 0]), central_diff(xy[..., 1])], axis=-1)  # (..., T, 2) m/step
    speed = np.linalg.norm(dxy, axis=-1) / dt
    # the heading change over two steps wrapped, then halved: a per-step change up to π/2
    dyaw_step = wrap_angle(central_diff(yaw) * 2) / 2
    d2yaw_step = wrap_angle(central_diff(dyaw_step) * 2) / 2
    return {
        "linear_speed": speed,
        "linear_acceleration": central_diff(speed) / dt,
        "angular_speed": dyaw_step / dt,
        "angular_acceleration": d2yaw_step / dt**2,
    }


def kinematic_validity(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where speeds (valid either side) and accelerations (speeds valid either side) are defined,
    from ``valid`` (..., T) -> two (..., T) bool."""
    speed = central_and(valid)
    return speed, central_and(speed)


def box_signed_distance(
    xy_a: np.ndarray, yaw_a: np.ndarray, ext_a: np.ndarray,
    xy_b: np.ndarray, yaw_b: np.ndarray, ext_b: np.ndarray,
) -> np.ndarray:
    """Signed distance (m) between oriented boxes A and B (broadcast; xy (..., 2), yaw (...), extent
    (..., 2) length and width) -> (...): the gap between them when apart, minus the penetration depth
    when they overlap (the signed distance of the origin to the Minkowski difference A − B).

    Overlapping: the largest gap along the four edge normals (all ≤ 0) is the penetration depth.
    Apart: the least distance from a corner of one box to an edge of the other."""
    xy_a, xy_b = np.asarray(xy_a, float), np.asarray(xy_b, float)
    d = xy_b - xy_a
    gaps = []
    for yaw_u, (half_own, half_w_own), other_ext, dyaw in (
        (yaw_a, (ext_a[..., 0] / 2, ext_a[..., 1] / 2), ext_b, yaw_a - yaw_b),
        (yaw_b, (ext_b[..., 0] / 2, ext_b[..., 1] / 2), ext_a, yaw_a - yaw_b),
    ):
        c, s = np.cos(yaw_u), np.sin(yaw_u)
        ac, as_ = np.abs(np.cos(dyaw)), np.abs(np.sin(dyaw))
        lo, wo = other_ext[..., 0] / 2, other_ext[..., 1] / 2
        gaps.append(np.abs(d[..., 0] * c + d[..., 1] * s) - half_own - lo * ac - wo * as_)
        gaps.append(np.abs(-d[..., 0] * s + d[..., 1] * c) - half_w_own - lo * as_ - wo * ac)
    sep = np.max(np.stack(gaps), axis=0)  # (...)
    ca = box_corners(xy_a, yaw_a, ext_a)  # (..., 4, 2)
    cb = box_corners(xy_b, yaw_b, ext_b)
    apart = np.minimum(_corners_to_edges(ca, cb), _corners_to_edges(cb, ca))
    return np.where(sep > 0, apart, sep)


def _corners_to_edges(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Least distance from the 4 ``points`` (..., 4, 2) to the 4 edges of ``polygon`` (..., 4, 2)."""
    start = polygon[..., None, :, :]  # (..., 1, 4, 2)
    edge = np.roll(polygon, -1, axis=-2)[..., None, :, :] - start
    rel = points[..., :, None, :] - start  # (..., 4 points, 4 edges, 2)
    t = np.clip((rel * edge).sum(-1) / np.maximum((edge * edge).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * edge, axis=-1).min(axis=(-1, -2))


def nearest_object_distance(tracks: AgentTracks, agents: np.ndarray, steps: slice) -> np.ndarray:
    """Signed distance (m) from each of ``agents`` (C,) to the nearest other agent valid at each of
    ``steps`` -> (C, T); ``FAR_M`` where no other agent is valid. Exact box distances are computed
    only for the pairs whose bounding circles could make them the nearest (or nearer than
    ``NEAREST_RANGE_M``); a farther nearest object reads as its centre distance, an upper bound."""
    xy, yaw, valid = tracks.xy[:, steps], tracks.yaw[:, steps], tracks.valid[:, steps]  # (A, T, ...)
    n_agents, n_steps = valid.shape
    radius = bounding_radius(tracks.extent)  # (A,)
    centre = np.linalg.norm(xy[None] - xy[agents][:, None], axis=-1)  # (C, A, T)
    usable = valid[None] & (agents[:, None] != np.arange(n_agents))[..., None]  # (C, A, T)
    centre = np.where(usable, centre, np.inf)
    lower = centre - radius[agents][:, None, None] - radius[None, :, None]
    best_upper = np.minimum(centre.min(axis=1), NEAREST_RANGE_M)  # (C, T): nothing beyond matters
    out = np.where(np.isfinite(centre.min(axis=1)), centre.min(axis=1), FAR_M)
    c, a, t = np.nonzero(usable & (lower <= best_upper[:, None, :]))
    if len(c):
        i = agents[c]
        ext = tracks.extent
        dist = box_signed_distance(xy[i, t], yaw[i, t], ext[i], xy[a, t], yaw[a, t], ext[a])  # (K,)
        exact = np.full((len(agents), n_steps), np.inf)
        np.minimum.at(exact, (c, t), dist)
        out = np.where(np.isfinite(exact), exact, out)
    return out


def time_to_collision(tracks: AgentTracks, agents: np.ndarray, speed: np.ndarray, steps: slice) -> np.ndarray:
    """Seconds until each of ``agents`` (C,) reaches the box it follows at constant speeds, capped at
    ``MAX_TTC_S`` (module docstring), at each of ``steps`` -> (C, T). ``speed``: (A, T_window) every
    agent's linear speed (m/s, NaN where undefined: no time to collision is then measured)."""
    xy, yaw, valid = tracks.xy[:, steps], tracks.yaw[:, steps], tracks.valid[:, steps]  # (A, T, ...)
    v = speed[:, steps]  # (A, T)
    length, width = tracks.extent[:, 0], tracks.extent[:, 1]
    d = xy[None] - xy[agents][:, None]  # (C, A, T, 2) other centre minus own
    c, s = np.cos(yaw[agents])[:, None], np.sin(yaw[agents])[:, None]  # (C, 1, T)
    along = d[..., 0] * c + d[..., 1] * s  # (C, A, T)
    across = -d[..., 0] * s + d[..., 1] * c
    dyaw = np.abs(wrap_angle(yaw[None] - yaw[agents][:, None]))  # (C, A, T) in [0, π]
    ac, as_ = np.abs(np.cos(dyaw)), np.abs(np.sin(dyaw))
    lo, wo = (length / 2)[None, :, None], (width / 2)[None, :, None]
    gap = along - (length[agents] / 2)[:, None, None] - lo * ac - wo * as_
    lateral = np.abs(across) - (width[agents] / 2)[:, None, None] - lo * as_ - wo * ac  # < 0: overlap
    follows = (gap > 0) & (dyaw <= MAX_HEADING_DIFF) & (lateral < 0)
    follows &= (lateral < -SMALL_OVERLAP_M) | (dyaw <= MAX_HEADING_DIFF_SMALL_OVERLAP)
    follows &= valid[None]
    gap = np.where(follows, gap, np.inf)
    ahead = np.argmin(gap, axis=1)  # (C, T)
    distance = np.take_along_axis(gap, ahead[:, None], axis=1)[:, 0]
    ahead_speed = np.take_along_axis(np.broadcast_to(v[None], gap.shape), ahead[:, None], axis=1)[:, 0]
    closing = v[agents] - ahead_speed  # (C, T)
    with np.errstate(invalid="ignore", divide="ignore"):
        ttc = np.where((closing > 0) & np.isfinite(distance), distance / closing, MAX_TTC_S)
    return np.minimum(np.nan_to_num(ttc, nan=MAX_TTC_S), MAX_TTC_S)


def road_edge_distance(area: DrivableArea, xy: np.ndarray, yaw: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """Signed distance (m, negative on the drivable area) of each box's most off-road corner: boxes
    xy (..., 2), yaw (...), extent (..., 2) -> (...)."""
    from scipy import ndimage

    corners = box_corners(xy, yaw, extent)  # (..., 4, 2)
    col_row = area.to_pixel(corners)  # (..., 4, 2) continuous (column, row)
    coords = np.stack([col_row[..., 1].ravel(), col_row[..., 0].ravel()])  # (2, N) row, column
    sdf = ndimage.map_coordinates(area.sdf_m, coords, output=np.float64, order=1, mode="nearest")
    return sdf.reshape(corners.shape[:-1]).max(axis=-1)


@dataclass(frozen=True)
class Features:
    """The WOSAC features of the evaluated objects (C,) over the simulated steps (T,) of one world.

    Each array (C, T): the four kinematic features, ``distance_to_nearest_object`` (m),
    ``collision_per_step`` (bool), ``time_to_collision`` (s), ``distance_to_road_edge`` (m),
    ``offroad_per_step`` (bool); ``valid`` (C, T): where the world holds the object. Kinematic values
    are NaN where they are undefined.
    """

    values: dict[str, np.ndarray]
    valid: np.ndarray


def world_features(
    tracks: AgentTracks, agents: np.ndarray, area: DrivableArea, current: int, dt: float
) -> Features:
    """The features of ``agents`` (C,) in ``tracks`` (every agent over an episode's window, index
    ``current`` the start) at the steps after the start. The kinematics use the history too (the
    first simulated step's central difference reaches back to the start)."""
    future = slice(current + 1, tracks.num_steps)
    kin = kinematics(tracks.xy, tracks.yaw, dt)  # every agent (A, W)
    speed_ok, accel_ok = kinematic_validity(tracks.valid)  # a difference across an invalid step: NaN
    for name, ok in (("linear_speed", speed_ok), ("angular_speed", speed_ok),
                     ("linear_acceleration", accel_ok), ("angular_acceleration", accel_ok)):
        kin[name] = np.where(ok, kin[name], np.nan)
    values = {name: value[agents, future] for name, value in kin.items()}
    values["distance_to_nearest_object"] = nearest_object_distance(tracks, agents, future)
    values["collision_per_step"] = values["distance_to_nearest_object"] < 0.0
    values["time_to_collision"] = time_to_collision(tracks, agents, kin["linear_speed"], future)
    extent = np.broadcast_to(tracks.extent[agents, None], tracks.xy[agents, future].shape)  # (C, T, 2)
    edge = road_edge_distance(area, tracks.xy[agents, future], tracks.yaw[agents, future], extent)
    values["distance_to_road_edge"] = edge
    values["offroad_per_step"] = edge > 0.0
    return Features(values, tracks.valid[agents, future].copy())
