"""How often a vehicle's track ends and another begins where it would be: the evidence for the
constants of ``ctgpp.data.stitching`` (read on a training split only).

For every vehicle track that begins after a scene's first step and every vehicle track that ended in
the ``--window`` seconds before, the distance between the new track's first position and the ended
track's last position carried on at its last speed and heading; counted by gap and distance, for the
nearest ended track of each new one, beside the background: the pairs at 4–6 m scaled by area to the
disc of each distance.

    python scripts/fragments.py --source ../shared/data/waymo-gpudrive --split train

The scenes are read from the GPUDrive files as they are, unstitched.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ctgpp.data.splits import waymo_split
from ctgpp.data.waymo_json import SUFFIX, load_waymo_json
from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentTracks, AgentType

EDGES_M = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)
BACKGROUND_M = (4.0, 6.0)


def nearest_ended(a: AgentTracks, dt_s: float, window_s: float) -> list[tuple[float, int, float, float]]:
    """(distance m, gap steps, heading difference rad, speed m/s) to the nearest carried-on ended
    vehicle track, for each vehicle track that begins after step 0 with one ended in the window."""
    has = a.valid.any(axis=1)
    first = np.where(has, a.valid.argmax(axis=1), -1)
    last = np.where(has, a.valid.shape[1] - 1 - a.valid[:, ::-1].argmax(axis=1), -1)
    vehicle = has & (a.types == AgentType.VEHICLE)
    rows = []
    for b in np.flatnonzero(vehicle & (first > 0)):
        s = int(first[b])
        ends = np.flatnonzero(vehicle & (last < s) & (last >= s - round(window_s / dt_s)))
        if not len(ends):
            continue
        e = last[ends]
        heading = a.yaw[ends, e]
        carried = a.xy[ends, e] + (a.speed[ends, e] * (s - e) * dt_s)[:, None] * np.stack(
            [np.cos(heading), np.sin(heading)], axis=-1)
        miss = np.linalg.norm(carried - a.xy[b, s], axis=-1)
        k = int(np.argmin(miss))
        turn = abs(float(wrap_angle(a.yaw[b, s] - heading[k])))
        fastest = max(float(a.speed[ends[k], e[k]]), float(a.speed[b, s]))
        rows.append((float(miss[k]), int(s - e[k]), turn, fastest))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, required=True, help="a folder of GPUDrive .json.gz files")
    parser.add_argument("--split", default="train")
    parser.add_argument("--window", type=float, default=5.0, help="seconds back an ended track may lie")
    args = parser.parse_args()
    rows: list[tuple[float, int, float, float]] = []
    for path in sorted(args.source.glob(f"*{SUFFIX}")):
        scene = load_waymo_json(path, stitch=False)
        if waymo_split(scene.id) == args.split:
            rows.extend(nearest_ended(scene.agents, scene.dt_s, args.window))
    r = np.asarray(rows).reshape(-1, 4)
    print(f"{args.source} {args.split}: {len(r)} new vehicle tracks with an ended one "
          f"within {args.window:g} s")
    lo, hi = BACKGROUND_M
    for name, sel in (("at rest", r[:, 3] <= 1.0), ("moving", r[:, 3] > 1.0)):
        for g0 in range(1, round(args.window * 10), 10):
            g1 = g0 + 9
            x = r[sel & (r[:, 1] >= g0) & (r[:, 1] <= g1)]
            counts = np.histogram(x[:, 0], EDGES_M)[0]
            density = np.sum((x[:, 0] >= lo) & (x[:, 0] < hi)) / (np.pi * (hi**2 - lo**2))  # per m²
            bins = zip(EDGES_M, EDGES_M[1:], counts, strict=False)
            cells = ", ".join(f"{a:g}-{b:g} m: {c}" for a, b, c in bins)
            within = int(np.sum(x[:, 0] <= 1.5))
            print(f"  {name}, gap {g0 / 10:g}-{g1 / 10:g} s: {cells}; within 1.5 m {within}, "
                  f"background {density * np.pi * 1.5**2:.1f}")
    close = r[r[:, 0] <= 1.5]
    turned = int(np.sum(close[:, 2] > np.radians(30)))
    print(f"  within 1.5 m: {len(close)}, of them turned by over 30°: {turned}")


if __name__ == "__main__":
    main()
