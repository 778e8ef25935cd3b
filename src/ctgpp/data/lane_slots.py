"""Each agent's lanes chosen for driving: the lane slots of the map the model drives by.

Every agent sees its map in its own frame (origin at its position, x along its heading, y left;
DESIGN.md, Model: Map; sizes in :class:`~ctgpp.data.map_config.MapConfig`). :func:`agent_lanes`
fills L lane slots of P points, in priority order:

1. ahead: the paths along the agent's direction of travel. They start from the lanes it is on (a
   centreline within ``on_lane_m`` whose heading is within ``on_lane_deg`` of the agent's; when there is
   none, the best aligned lane within ``neighbour_m``) and follow successors through intersections, one
   slot per distinct branch (at most ``max_branches``), the straightest first. Each path starts
   ``behind_m`` behind the agent's projection and runs ``(P − 1) · spacing_m − behind_m`` ahead.
2. neighbours: other lanes in the same direction (heading within ``same_direction_deg``) within
   ``neighbour_m``, nearest first, each as its straightest path ahead, sampled like the agent's own.
   Ahead and neighbour paths that retrace an earlier slot (within ``duplicate_m``) are dropped.
3. others: the nearest remaining lanes of any direction (oncoming, crossing), each followed through
   its predecessors and successors (not into lanes already shown) over a window centred on its
   nearest point (moved back where the chain ends first), clipped to ``radius_m``.

Nothing assumes a side of the road: direction and connectivity decide, so left-hand (Singapore) and
right-hand (Boston, NGSIM) traffic are served alike. :func:`agent_lane_slots` also tells each slot's
kind (:class:`SlotKind`).

It runs at every re-plan for all agents at once: the lane graph is prepared once per scene
(:mod:`ctgpp.data.lane_index`), the searches and the resampling are vectorized
(:mod:`ctgpp.data.lane_chains`), and only the walk through the lane graph (a few lane ids per slot)
is Python.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from ctgpp.data.lane_chains import paths_ahead, resample_chains, straight_chain
from ctgpp.data.lane_index import LaneIndex, lane_index, near_lanes
from ctgpp.data.map_config import MapConfig
from ctgpp.geometry import rotate, world_to_local
from ctgpp.scene.types import Scene

HEADING_WEIGHT_M_PER_RAD = 2.0  # ranking the lanes an agent is on: 1 rad off counts as 2 m away
_COARSE_CANDIDATES = 128  # nearest coarse lane points per agent searched for the other lanes


class SlotKind(enum.IntEnum):
    """What fills a lane slot."""

    EMPTY = 0
    AHEAD = 1
    NEIGHBOUR = 2
    OTHER = 3


@dataclass(frozen=True, eq=False)
class LaneSlots:
    """Each agent's lane slots. points (A, L, P, 4): x, y m and cos, sin of the lane direction in the
    agent's frame, zeros where invalid; valid (A, L, P); kind (A, L) :class:`SlotKind`."""

    points: np.ndarray
    valid: np.ndarray
    kind: np.ndarray


def agent_lanes(
    scene: Scene, pose: np.ndarray, config: MapConfig = MapConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Lane slots (A, L, P, 4) float32 and their validity (A, L, P) for agents at ``pose`` (A, 3) world
    x, y m, yaw rad: the format of ``ctgpp.data.windows``' nearest lanes (module docstring)."""
    slots = agent_lane_slots(scene, pose, config)
    return slots.points, slots.valid


def agent_lane_slots(scene: Scene, pose: np.ndarray, config: MapConfig = MapConfig()) -> LaneSlots:
    """:func:`agent_lanes` with the kind of each slot."""
    pose = np.asarray(pose, dtype=np.float64).reshape(-1, 3)
    n_agents, n_slots, n_points = len(pose), config.max_lanes, config.lane_points
    out = LaneSlots(
        points=np.zeros((n_agents, n_slots, n_points, 4), dtype=np.float32),
        valid=np.zeros((n_agents, n_slots, n_points), dtype=bool),
        kind=np.zeros((n_agents, n_slots), dtype=np.int8),
    )
    if n_agents == 0 or n_slots == 0 or n_points == 0 or scene.lanes.num_lanes == 0:
        return out
    index = lane_index(scene.lanes)
    span = (n_points - 1) * config.spacing_m
    chains, start, owner, kind, used = _driving_paths(index, pose, config, span)
    xy, direction, valid = resample_chains(index, chains, start, config.spacing_m, n_points)
    keep = _not_duplicate(xy, valid, owner, config.duplicate_m)
    for k in np.flatnonzero(~keep):
        used[owner[k]].update(chains[k])  # a dropped path's lanes are shown by the slot it retraces
    parts = [(xy[keep], direction[keep], valid[keep], owner[keep], kind[keep])]
    free = n_slots - np.bincount(owner[keep], minlength=n_agents)
    chains, start, owner, kind = _other_lanes(index, pose, config, span, used, free)
    if chains:
        xy, direction, valid = resample_chains(index, chains, start, config.spacing_m, n_points)
        valid &= np.hypot(*np.moveaxis(xy - pose[owner, None, :2], -1, 0)) <= config.radius_m
        parts.append((xy, direction, valid, owner, kind))
    xy, direction, valid, owner, kind = (np.concatenate(p) for p in zip(*parts, strict=True))
    shown = np.flatnonzero(valid.any(axis=1))
    order = shown[np.argsort(owner[shown], kind="stable")]  # each agent's candidates, in priority order
    xy, direction, valid, owner, kind = xy[order], direction[order], valid[order], owner[order], kind[order]
    slot = np.arange(len(owner)) - np.searchsorted(owner, np.arange(n_agents))[owner]
    fits = slot < n_slots
    xy, direction, valid, a, s = xy[fits], direction[fits], valid[fits], owner[fits], slot[fits]
    local = world_to_local(xy, pose[a, None, :2], pose[a, None, 2])  # (K, P, 2)
    pts = np.concatenate([local, rotate(direction, -pose[a, None, 2])], axis=-1)  # (K, P, 4)
    out.points[a, s] = np.where(valid[..., None], pts, 0.0)
    out.valid[a, s] = valid
    out.kind[a, s] = kind[fits]
    return out


def _driving_paths(
    index: LaneIndex, pose: np.ndarray, config: MapConfig, span: float
) -> tuple[list[list[int]], np.ndarray, np.ndarray, np.ndarray, list[set[int]]]:
    """Ahead and neighbour candidates of every agent, in priority order.

    Returns lane chains, their start arc lengths (K,), owner agents (K,), kinds (K,) and per agent the
    set of lanes the chains cover.
    """
    near = near_lanes(index, pose[:, :2], pose[:, 2], config.neighbour_m)
    bounds = np.searchsorted(near.agent, np.arange(len(pose) + 1)).tolist()
    lane, dist, arc = near.lane.tolist(), near.dist_m.tolist(), near.arc_m.tolist()
    turn = near.heading_diff.tolist()
    on_rad, same_rad = math.radians(config.on_lane_deg), math.radians(config.same_direction_deg)
    chains: list[list[int]] = []
    start: list[float] = []
    owner: list[int] = []
    kind: list[int] = []
    used: list[set[int]] = []

    def add(agent: int, first: int, s: float, limit: int, slot_kind: SlotKind, taken: set[int]) -> int:
        reach = s - config.behind_m + span  # the window's end, m from the start of lane ``first``
        if limit == 1:
            full, prepended, _ = straight_chain(index, first, reach, config.behind_m - s)
            paths = [full]
        else:
            back, prepended, _ = straight_chain(index, first, 0.0, config.behind_m - s)
            paths = [back[:-1] + chain for chain in paths_ahead(index, first, reach, limit)]
        for full in paths:
            chains.append(full)
            start.append(s - config.behind_m + prepended)
            owner.append(agent)
            kind.append(slot_kind)
            taken.update(full)
        return len(paths)

    for a in range(len(pose)):
        rows = range(bounds[a], bounds[a + 1])  # nearest first
        # rounded: equal costs keep the rows' order (distance, then lane index) wherever the map lies
        cost = {r: round(dist[r] + HEADING_WEIGHT_M_PER_RAD * turn[r], 4) for r in rows if turn[r] <= on_rad}
        on = sorted((r for r in cost if dist[r] <= config.on_lane_m), key=cost.__getitem__)
        if not on and cost:
            on = [min(cost, key=cost.__getitem__)]  # off every lane: the best aligned one nearby
        taken: set[int] = set()
        n_ahead = 0
        for r in on:
            if n_ahead >= config.max_branches:
                break
            if lane[r] not in taken:
                n_ahead += add(a, lane[r], arc[r], config.max_branches - n_ahead, SlotKind.AHEAD, taken)
        n_side = 0
        for r in rows:
            if n_side >= config.max_neighbours:
                break
            if turn[r] <= same_rad and lane[r] not in taken:
                n_side += add(a, lane[r], arc[r], 1, SlotKind.NEIGHBOUR, taken)
        used.append(taken)
    return chains, np.array(start), np.array(owner, dtype=np.int64), np.array(kind, dtype=np.int8), used


def _not_duplicate(xy: np.ndarray, valid: np.ndarray, owner: np.ndarray, tol_m: float) -> np.ndarray:
    """(K,) bool: False for a candidate that retraces an earlier one of its agent.

    Ahead and neighbour paths are sampled at the same arc lengths relative to the agent, so point i
    of two paths is comparable: a path retraces another when at least 90% of its valid points are
    valid on the other too and none of those lies farther than ``tol_m`` from its counterpart.
    """
    i, j = np.nonzero(np.triu(owner[:, None] == owner[None, :], k=1))  # pairs i < j of one agent
    both = valid[i] & valid[j]  # (Q, P)
    gap = np.hypot(*np.moveaxis(xy[i] - xy[j], -1, 0))  # (Q, P)
    shared = both.sum(axis=1)
    retrace = (shared > 0) & (shared >= 0.9 * valid[j].sum(axis=1)) & ~(both & (gap > tol_m)).any(axis=1)
    keep = np.asarray(valid.any(axis=1))
    keep[j[retrace]] = False
    return keep


def _other_lanes(
    index: LaneIndex, pose: np.ndarray, config: MapConfig, span: float, used: list[set[int]], free: np.ndarray
) -> tuple[list[list[int]], np.ndarray, np.ndarray, np.ndarray]:
    """The nearest lanes not yet shown, ``free[a]`` for agent a: chains, starts, owners, kinds."""
    chains: list[list[int]] = []
    start: list[float] = []
    owner: list[int] = []
    n_coarse = len(index.coarse_lane)
    if n_coarse == 0 or free.max(initial=0) <= 0:
        return chains, np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int8)
    k = min(_COARSE_CANDIDATES + 1, n_coarse)
    dist, hit = index.coarse.query(pose[:, :2], k=list(range(1, k + 1)), distance_upper_bound=config.radius_m)
    dist = np.round(dist, 4)  # ties (lanes meeting at a point) by lane index, not the k-d tree's order
    order = np.lexsort((index.coarse_lane[np.minimum(hit, n_coarse - 1)], dist), axis=-1)
    hit, dist = np.take_along_axis(hit, order, axis=1), np.take_along_axis(dist, order, axis=1)
    found = hit < n_coarse  # (A, k) nearest first
    if k > _COARSE_CANDIDATES:  # one more than used was asked for: cut it and whatever ties it
        found &= dist < dist[:, -1:]
    lane = np.where(found, index.coarse_lane[np.minimum(hit, n_coarse - 1)], -1)
    row = np.broadcast_to(np.arange(len(hit))[:, None], hit.shape)
    first = np.zeros(hit.shape, dtype=bool)  # the nearest coarse point of each lane, per agent
    key = row.ravel() * (index.num_lanes + 1) + lane.ravel() + 1
    first.ravel()[np.unique(key, return_index=True)[1]] = True
    first &= found
    arc = index.coarse_arc[np.minimum(hit, n_coarse - 1)]
    half = 0.5 * span
    for a, (lanes, arcs) in enumerate(zip(_rows(lane, first), _rows(arc, first), strict=True)):
        taken, room = used[a], int(free[a])
        for ln, s in zip(lanes, arcs, strict=True):
            if room <= 0:
                break
            if ln in taken:
                continue
            full, prepended, short = straight_chain(index, ln, s + half, half - s, taken, slide=True)
            chains.append(full)
            start.append(s - half - short + prepended)
            owner.append(a)
            taken.update(full)
            room -= 1
    kinds = np.full(len(chains), SlotKind.OTHER, dtype=np.int8)
    return chains, np.array(start), np.array(owner, dtype=np.int64), kinds


def _rows(values: np.ndarray, mask: np.ndarray) -> list[list]:
    """Per row of ``values`` (R, K), the entries where ``mask`` (R, K), in order, as Python lists."""
    flat = values[mask].tolist()
    ends = np.cumsum(mask.sum(axis=1)).tolist()
    return [flat[b:e] for b, e in zip([0, *ends[:-1]], ends, strict=True)]
