"""Where the paper's failure case can happen: pairs of vehicles for "vehicle A and B move to the
rightmost lane one by one and then both turn right at the next intersection".

For every episode start (``--spacing`` s apart) of every scene of the data directories given, lists
the pairs of controlled vehicles that move at the start (faster than ``--min-speed``), head the same
way, and whose rightmost same-direction lane leads to a right turn (heading change below −30°) at an
intersection within reach: ``--reach-s`` seconds at the vehicle's start speed. Pairs where at least one
vehicle is not in its rightmost lane yet come first (the lane change then has something to do).

    python scripts/failure_case_scenes.py --data embedded --reach-s 9

Prints one line per pair: scene, start, the two numbers, their lanes, the distance to the turn and its
heading change. The candidates are then simulated with ``ctgpp simulate`` to see which are met.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from ctgpp.data.catalog import Catalog
from ctgpp.scene.lane_paths import lanes_beside, turn_path
from ctgpp.scene.lanes import nearest_lane
from ctgpp.sim.closed_loop import episode_config, episode_starts, initial_observation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", action="append", default=[],
                        help="'embedded' or a converted data directory (repeatable)")
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--history", type=float, default=3.0)
    parser.add_argument("--spacing", type=float, default=1.0)
    parser.add_argument("--min-speed", type=float, default=2.0)
    parser.add_argument("--reach-s", type=float, default=7.0)
    args = parser.parse_args()
    found = []
    for data in args.data or ["embedded"]:
        catalog = Catalog.open(None if data == "embedded" else Path(data))
        for entry in catalog.entries:
            scene = catalog.load(entry.id)
            try:
                config = episode_config(scene, args.duration, args.history)
            except ValueError:  # too short for the episode
                continue
            lanes = scene.lanes
            for start in episode_starts(scene, args.spacing, config):
                obs = initial_observation(scene, start, config)
                step, tracks = obs.step, obs.tracks
                fits = []
                for number, agent in enumerate(np.asarray(obs.controlled).tolist()):
                    speed = float(tracks.speed[agent, step])
                    if speed < args.min_speed:
                        continue
                    xy, yaw = tracks.xy[agent, step].astype(np.float64), float(tracks.yaw[agent, step])
                    proj = nearest_lane(lanes, xy, yaw)
                    if proj is None:
                        continue
                    beside = lanes_beside(lanes, proj, "right")
                    right, moves = (beside[-1] if beside else proj), len(beside)
                    turn = turn_path(lanes, right, "right")
                    if turn is None or turn.ahead_m > speed * args.reach_s + 5.0:
                        continue
                    fits.append((number, yaw, proj.lane, right.lane, moves, turn.ahead_m, turn.turn_rad))
                for i, a in enumerate(fits):
                    for b in fits[i + 1:]:
                        same_way = abs(math.remainder(a[1] - b[1], 2 * math.pi)) < math.radians(30)
                        if same_way and a[3] == b[3]:
                            found.append((a[4] + b[4], entry.id, start, a, b))
    for _, scene_id, start, a, b in sorted(found, key=lambda f: -f[0]):
        print(f"{scene_id} start {start:g} s: vehicles {a[0]} and {b[0]}, lanes {a[2]}/{b[2]} -> rightmost "
              f"{a[3]} ({a[4]}, {b[4]} lanes over), turn {a[5]:.0f} / {b[5]:.0f} m ahead, "
              f"{math.degrees(a[6]):.0f}° / {math.degrees(b[6]):.0f}°")
    print(f"{len(found)} pairs")


if __name__ == "__main__":
    main()
