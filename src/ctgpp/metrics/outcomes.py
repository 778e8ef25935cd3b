"""What happened to each controlled vehicle of a rollout: the one computation behind the figures
over the vehicles that move (``metrics.moving``), the per-vehicle events
(``metrics.events``) and the failure marks on pictures (``viz.events``).

Kinds of vehicles: *moving* — controlled, and faster than 0.5 m/s at the start or carried more than
``MOVED_M`` (2 m) from where it starts in the log or in the simulation: every vehicle that moves in
either counts, so a queue the simulation leaves standing where the log's discharges counts against
it, and so does a parked car it sets off; *held* — controlled and neither (parked, or waiting the
whole episode; the simulator holds the parked ones still under the policies that hold them, the
others it plans). Every other agent is *replayed* from the log (pedestrians, cyclists, static
obstacles, and vehicles that appear after the start). ``real`` keeps its own vehicles: those moving
at the start (``metrics.realism``).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.metrics.collision import collision_contacts, controlled_vehicle_indices, earliest_contacts
from ctgpp.metrics.lane_keeping import lane_leave_steps
from ctgpp.metrics.motion import (
    HORIZONS_S,
    displacement_errors,
    farthest_from_start,
    rollout_yaw_sign_changes,
    stop_steps,
)
from ctgpp.metrics.offroad import beyond_map_steps, first_step, offroad_steps
from ctgpp.metrics.realism import realism_vehicles
from ctgpp.metrics.turns import followed_turns

PARTNER_KINDS = ("held", "moving", "replayed")
MOVED_M = 2.0  # carried this far from its start, a vehicle at rest at the start has moved off


@dataclass(frozen=True, eq=False)
class VehicleOutcomes:
    """Per controlled vehicle (C, in agent order): window step indices, -1 where the event never happens.

    agents (C,) agent indices; moving (C,) bool (the module's note). at_rest (C,) bool: slower than
    0.5 m/s at the start. log_moved_m / sim_moved_m (C,) m: the farthest the log / the simulation
    carries it from its start position (``motion.farthest_from_start``; NaN when the log holds no
    future step of it). hit_step / partner: the first collision (with any
    agent, replayed ones included) and the agent hit then. hit_present_step: the first collision
    with an agent present at the start (valid at the current step): the agents the Waymo Sim Agents
    Challenge simulates, whose scenes hold no agent that enters later. offroad_step: the first
    off-road step of a vehicle that stays on the map (-1 for one beyond the map: it is reported by
    ``beyond_step``, see ``offroad.beyond_map_steps``). lane_step: first step > 2 m from every same-direction
    centerline (``lane_keeping``), measured for the moving vehicles only (-1 for held ones) and up
    to where a vehicle goes beyond the map (-1 when it leaves the lanes there: past the end of the
    mapped road there are none to keep).
    stop_step: first step slower than 0.2 m/s. yaw_changes: yaw-rate sign changes per 10 s.
    ade / fde: {horizon s: (C,) m}, NaN where the log ends before the horizon (``motion``).
    turn: the logged turn, +1 left, -1 right, 0 none (> 60° from the start to the last logged step);
    turn_followed: the simulation turns the same way by > 45° (``turns``).
    """

    agents: np.ndarray
    moving: np.ndarray
    at_rest: np.ndarray
    log_moved_m: np.ndarray
    sim_moved_m: np.ndarray
    hit_step: np.ndarray
    partner: np.ndarray
    hit_present_step: np.ndarray
    offroad_step: np.ndarray
    beyond_step: np.ndarray
    lane_step: np.ndarray
    stop_step: np.ndarray
    yaw_changes: np.ndarray
    ade: dict[float, np.ndarray]
    fde: dict[float, np.ndarray]
    turn: np.ndarray
    turn_followed: np.ndarray

    def partner_kind(self, rollout: Rollout, c: int) -> str | None:
        """Whether vehicle ``c``'s first collision partner is ``held``, ``moving`` or ``replayed``
        (None when it never collides)."""
        j = int(self.partner[c])
        if j < 0:
            return None
        if not rollout.controlled[j]:
            return "replayed"
        return "moving" if self.moving[self.agents == j].any() else "held"


_CACHE: weakref.WeakKeyDictionary[Rollout, VehicleOutcomes] = weakref.WeakKeyDictionary()


def vehicle_outcomes(rollout: Rollout) -> VehicleOutcomes:
    """The outcomes of every controlled vehicle of ``rollout`` (computed once per rollout)."""
    cached = _CACHE.get(rollout)
    if cached is not None:
        return cached
    agents = controlled_vehicle_indices(rollout)
    at_rest = ~np.isin(agents, realism_vehicles(rollout))
    log_moved = farthest_from_start(rollout.log, agents, rollout.current, rollout.future)
    sim_moved = farthest_from_start(rollout.sim, agents, rollout.current, rollout.future)
    moving = ~at_rest | (np.nan_to_num(log_moved) > MOVED_M) | (np.nan_to_num(sim_moved) > MOVED_M)
    contacts = collision_contacts(rollout.sim, agents, rollout.future)  # (c, other, t), each (K,)
    hit_step, partner = earliest_contacts(rollout.sim, agents, rollout.future, contacts)
    ci, aj, t = contacts
    present = rollout.sim.valid[aj, rollout.current]  # (K,) the other is there at the start
    with_present = (ci[present], aj[present], t[present])
    hit_present, _ = earliest_contacts(rollout.sim, agents, rollout.future, with_present)
    beyond = beyond_map_steps(rollout, agents)
    offroad = first_step(offroad_steps(rollout, agents), rollout.future, rollout.sim.num_steps)
    lane = np.full(len(agents), -1, dtype=np.int64)
    lane[moving] = lane_leave_steps(rollout, agents[moving])
    lane = np.where((beyond >= 0) & (lane >= beyond), -1, lane)  # beyond the map there is no lane to keep
    errors = {h: displacement_errors(rollout, agents, h) for h in HORIZONS_S}
    turn, turn_followed = followed_turns(rollout, agents)
    out = VehicleOutcomes(
        agents=agents,
        moving=moving,
        at_rest=at_rest,
        log_moved_m=log_moved,
        sim_moved_m=sim_moved,
        hit_step=hit_step,
        partner=partner,
        hit_present_step=hit_present,
        offroad_step=np.where(beyond >= 0, -1, offroad),
        beyond_step=beyond,
        lane_step=lane,
        stop_step=stop_steps(rollout, agents),
        yaw_changes=rollout_yaw_sign_changes(rollout, agents),
        ade={h: e[0] for h, e in errors.items()},
        fde={h: e[1] for h, e in errors.items()},
        turn=turn,
        turn_followed=turn_followed,
    )
    _CACHE[rollout] = out
    return out
