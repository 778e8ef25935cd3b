"""Turns: whether a simulated vehicle turns where its log turns (issue 35, the "Turns" figure).

A controlled vehicle makes a *logged turn* when its logged heading at its last logged step of the
episode (from the start to the end of the window) differs from its logged heading at the start by
more than :data:`LOGGED_TURN_RAD` (60°), the change wrapped to [-180°, 180°): its sign says left (+)
or right (-). The simulation *follows* a logged turn when the simulated heading at that same step (at
the vehicle's last simulated step, where the simulation ends it earlier) differs from the simulated
heading at the start by more than :data:`FOLLOWED_TURN_RAD` (45°), with the same sign.

The log (replay) follows every logged turn by construction; constant velocity none (its heading
never changes). ``metrics.moving.turn_follow`` is the share over the vehicles that move.
"""

from __future__ import annotations

import math

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.interfaces import Rollout
from ctgpp.scene.types import AgentTracks

# A logged turn: 60° is a turn at an intersection or a roundabout exit (about 90° and more), well above
# a lane change (a few degrees of net heading) and the bends of a road followed for 10 s.
LOGGED_TURN_RAD = math.radians(60.0)
# Followed: the simulated vehicle turned the same way by more than 45°, lower than the logged turn's
# 60° so that a wide or late turn (not yet finished at the step the log ends) still counts.
FOLLOWED_TURN_RAD = math.radians(45.0)


def last_valid_steps(valid: np.ndarray, start: int, end: np.ndarray) -> np.ndarray:
    """(C,) the last window index in ``[start, end[c]]`` where ``valid`` (C, T) holds, -1 if none."""
    steps = np.arange(valid.shape[1])
    inside = valid & (steps[None] >= start) & (steps[None] <= np.asarray(end)[:, None])
    return np.where(inside.any(axis=1), valid.shape[1] - 1 - np.argmax(inside[:, ::-1], axis=1), -1)


def heading_changes(tracks: AgentTracks, agents: np.ndarray, start: int, end: np.ndarray) -> np.ndarray:
    """(C,) rad: the wrapped heading change of ``agents`` from window index ``start`` to ``end`` (C,),
    NaN where either step is invalid (or ``end`` is -1)."""
    if not len(agents):
        return np.zeros(0)
    end_ = np.maximum(end, 0)
    change = wrap_angle(tracks.yaw[agents, end_] - tracks.yaw[agents, start])
    ok = (end >= 0) & tracks.valid[agents, start] & tracks.valid[agents, end_]
    return np.where(ok, change, np.nan)


def logged_turns(rollout: Rollout, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each vehicle's logged turn and the step it is measured at: (C,) +1 left, -1 right, 0 none; and
    (C,) the last logged window index from the start (-1 for a vehicle not logged at the start)."""
    log = rollout.log
    last = last_valid_steps(log.valid[agents], rollout.current, np.full(len(agents), log.num_steps - 1))
    change = heading_changes(log, agents, rollout.current, last)
    turned = np.abs(np.nan_to_num(change)) > LOGGED_TURN_RAD
    return np.where(turned, np.sign(np.nan_to_num(change)), 0).astype(np.int64), last


def followed_turns(rollout: Rollout, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C,) each vehicle's logged turn (:func:`logged_turns`) and (C,) bool whether the simulation
    follows it (module docstring; False where the vehicle has no logged turn)."""
    turn, last = logged_turns(rollout, agents)
    sim_last = last_valid_steps(rollout.sim.valid[agents], rollout.current, last)
    change = np.nan_to_num(heading_changes(rollout.sim, agents, rollout.current, sim_last))
    followed = (turn != 0) & (np.sign(change) == turn) & (np.abs(change) > FOLLOWED_TURN_RAD)
    return turn, followed
