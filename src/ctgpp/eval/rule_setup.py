"""The 8 rules of the evaluation (DESIGN.md, Rules of the evaluation; paper Table 1, appendix E),
made concrete for one episode from the log at its start, as :class:`~ctgpp.behaviours.rule_spec.RuleSpec`
(a rule given by name and parameters is :func:`~ctgpp.behaviours.rule_spec.spec_for`).

Choices the paper leaves open, fixed here:

- Pairs (keep distance, collision): both vehicles valid and faster than 2 m/s in the log at 0 s;
  10–30 m apart and heading difference under 108° (collision) / 36° (keep distance) at 0 s and at
  2 s in the log; the pair closest at 0 s wins. The follower is the one behind: the other lies ahead
  of it along its heading at 0 s.
- Speed limit: the 75% quantile of the logged speeds above 0.5 m/s of the controlled vehicles over
  the episode's log window (3 s history + 10 s), so one number per episode.
- Target speed: 50% of each controlled vehicle's logged speed at every scene step (NaN, no target,
  where the log is invalid), a (B, scene steps) table.
- Goal waypoint: for every vehicle moving (> 0.5 m/s) at the start, its logged position 7.5 s later
  or, when the track ends earlier, its last valid one; with the target speed of rule 5.
- Stop region: for every vehicle faster than 2 m/s at the start whose log is valid 4 s later, a
  disc of radius 3 m around that logged position, with no off-road.
"""

from __future__ import annotations

import numpy as np

from ctgpp.behaviours import RuleMeasure
from ctgpp.behaviours.rule_spec import RuleSpec, loss_params, spec_for
from ctgpp.geometry import wrap_angle
from ctgpp.guidance import CompositeLoss, GuidanceLoss, make_loss
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

EVALUATION_RULES = (
    "keep_distance",
    "collision",
    "no_collision",
    "speed_limit",
    "target_speed",
    "no_offroad",
    "goal_waypoint",
    "stop_region",
)
PAIR_MIN_SPEED_MPS = 2.0
PAIR_RANGE_M = (10.0, 30.0)
PAIR_MAX_HEADING_DEG = {"collision": 108.0, "keep_distance": 36.0}
PAIR_CHECK_STEPS = 20  # 2 s
SPEED_QUANTILE = 0.75
TARGET_FRACTION = 0.5
GOAL_STEPS = 75  # 7.5 s
STOP_STEPS = 40  # 4 s
STOP_RADIUS_M = 3.0
LOG_WINDOW = (30, 100)  # steps of history and of simulation around the start


def evaluation_rules() -> list[str]:
    """The names of the 8 evaluation rules, in the paper's order."""
    return list(EVALUATION_RULES)


def setup_rule(name: str, scene: Scene, start_step: int, controlled: np.ndarray) -> RuleSpec | None:
    """Evaluation rule ``name`` for an episode of ``scene`` starting at ``start_step`` whose
    controlled vehicles are ``controlled`` (V,) agent indices in displayed order. None when the
    episode does not qualify (no pair, no moving vehicle): skip it for this rule."""
    log = scene.agents
    if name in ("keep_distance", "collision"):
        pair = select_pair(scene, start_step, controlled, PAIR_MAX_HEADING_DEG[name])
        if pair is None:
            return None
        follower, leader = pair
        if name == "keep_distance":
            lo, hi = PAIR_RANGE_M
            desc = f"vehicle {follower} keeps {lo:g}-{hi:g} m behind vehicle {leader}"
            return spec_for(name, {"follower": follower, "leader": leader, "min_m": lo, "max_m": hi}, desc)
        desc = f"vehicles {follower} and {leader} collide"
        return spec_for(name, {"vehicle_a": follower, "vehicle_b": leader}, desc)
    if name in ("no_collision", "no_offroad"):
        return spec_for(name, {}, name.replace("_", " "))
    if name == "speed_limit":
        lo, hi = start_step - LOG_WINDOW[0], start_step + LOG_WINDOW[1] + 1
        speeds = log.speed[controlled, lo:hi][log.valid[controlled, lo:hi]]
        moving = speeds[speeds > MOVING_SPEED_MPS]
        if moving.size == 0:
            return None
        limit = float(np.quantile(moving, SPEED_QUANTILE))
        return spec_for(name, {"limit_mps": limit}, f"speed limit {limit:.2f} m/s")
    if name == "target_speed":
        params = {"speed_mps": _target_table(scene, controlled), "absolute_steps": True}
        return spec_for(name, params, "50% of each vehicle's logged speed")
    if name == "goal_waypoint":
        return _goal_rule(scene, start_step, controlled)
    if name == "stop_region":
        return _stop_rule(scene, start_step, controlled)
    raise ValueError(f"unknown evaluation rule {name!r}; the rules are: {', '.join(EVALUATION_RULES)}")


def select_pair(
    scene: Scene, start_step: int, controlled: np.ndarray, max_heading_deg: float
) -> tuple[int, int] | None:
    """The closest qualifying pair (module docstring) as displayed numbers (follower, leader)."""
    log = scene.agents
    later = start_step + PAIR_CHECK_STEPS
    if later >= log.num_steps:
        return None
    best: tuple[float, int, int] | None = None
    ok = log.valid[controlled, start_step] & log.valid[controlled, later]
    ok &= log.speed[controlled, start_step] > PAIR_MIN_SPEED_MPS
    cand = np.flatnonzero(ok)  # displayed numbers
    for n, i in enumerate(cand):
        for j in cand[n + 1 :]:
            a, b = controlled[i], controlled[j]
            qualifies = True
            for t in (start_step, later):
                dist = float(np.linalg.norm(log.xy[a, t] - log.xy[b, t]))
                dyaw = abs(float(wrap_angle(log.yaw[a, t] - log.yaw[b, t])))
                qualifies &= PAIR_RANGE_M[0] <= dist <= PAIR_RANGE_M[1]
                qualifies &= np.degrees(dyaw) < max_heading_deg
            dist0 = float(np.linalg.norm(log.xy[a, start_step] - log.xy[b, start_step]))
            if qualifies and (best is None or dist0 < best[0]):
                best = (dist0, int(i), int(j))
    if best is None:
        return None
    _, first, second = best
    a, b = controlled[first], controlled[second]
    ahead = log.xy[b, start_step] - log.xy[a, start_step]
    yaw_a = log.yaw[a, start_step]
    b_ahead_of_a = ahead[0] * np.cos(yaw_a) + ahead[1] * np.sin(yaw_a) > 0
    return (first, second) if b_ahead_of_a else (second, first)


def _target_table(scene: Scene, controlled: np.ndarray) -> np.ndarray:
    """(V, scene steps) 50% of the logged speeds, NaN where the log is invalid."""
    log = scene.agents
    return np.where(log.valid[controlled], TARGET_FRACTION * log.speed[controlled], np.nan)


def _target_speed(scene: Scene, controlled: np.ndarray) -> GuidanceLoss:
    return make_loss("target_speed", **loss_params({"speed_mps": _target_table(scene, controlled),
                                                     "absolute_steps": True}))


def _goal_rule(scene: Scene, start_step: int, controlled: np.ndarray) -> RuleSpec | None:
    log = scene.agents
    vehicles, goals = [], []
    for v, a in enumerate(controlled):
        if log.speed[a, start_step] <= MOVING_SPEED_MPS:
            continue
        steps = np.arange(start_step + 1, min(start_step + GOAL_STEPS, log.num_steps - 1) + 1)
        valid = steps[log.valid[a, steps]]
        if valid.size:
            vehicles.append(v)
            goals.append(log.xy[a, valid[-1]])
    if not vehicles:
        return None
    xy = np.array(goals)
    goal = make_loss("goal_waypoint", vehicle=vehicles, x=list(xy[:, 0]), y=list(xy[:, 1]))
    loss = CompositeLoss([(goal, 1.0), (_target_speed(scene, controlled), 1.0)])
    desc = f"{len(vehicles)} vehicles reach their logged position 7.5 s ahead, at 50% of the logged speed"
    table = _target_table(scene, controlled)
    measures = {
        "goal_waypoint": RuleMeasure("goal_waypoint", {"vehicle": vehicles, "x": xy[:, 0], "y": xy[:, 1]}),
        "target_speed": RuleMeasure("target_speed", {"speed_mps": table, "absolute_steps": True}),
    }
    return RuleSpec("goal_waypoint", loss, measures, (), desc)


def _stop_rule(scene: Scene, start_step: int, controlled: np.ndarray) -> RuleSpec | None:
    log = scene.agents
    at = start_step + STOP_STEPS
    if at >= log.num_steps:
        return None
    ok = (log.speed[controlled, start_step] > PAIR_MIN_SPEED_MPS) & log.valid[controlled, at]
    vehicles = [int(v) for v in np.flatnonzero(ok)]
    if not vehicles:
        return None
    xy = log.xy[controlled[vehicles], at]  # (G, 2)
    params = {"vehicle": vehicles, "x": xy[:, 0], "y": xy[:, 1], "radius_m": STOP_RADIUS_M}
    stop = make_loss("stop_region", **{**params, "x": list(xy[:, 0]), "y": list(xy[:, 1])})
    loss = CompositeLoss([(stop, 1.0), (make_loss("no_offroad"), 1.0)])
    desc = f"{len(vehicles)} vehicles stop within {STOP_RADIUS_M:g} m of their logged position 4 s ahead"
    measures = {"stop_region": RuleMeasure("stop_region", params), "no_offroad": RuleMeasure("no_offroad")}
    return RuleSpec("stop_region", loss, measures, (), desc)
