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
from ctgpp.data.stitching import candidates
from ctgpp.data.waymo_json import SUFFIX, load_waymo_json
from ctgpp.scene.types import AgentTracks

EDGES_M = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)
BACKGROUND_M = (4.0, 6.0)


def nearest_ended(a: AgentTracks, dt_s: float, window_s: float) -> list[tuple[float, int, float, float]]:
    """(distance m, gap steps, heading difference rad, speed m/s) to the nearest carried-on ended
    vehicle track (:func:`ctgpp.data.stitching.candidates`), for each vehicle track that begins with
    one ended in the window."""
    rows = []
    for c in candidates(a, dt_s, window_s):
        k = int(np.argmin(c.miss_m))
        end = int(c.ends[k])
        fastest = max(float(a.speed[end, c.first - c.gap_steps[k]]), float(a.speed[c.begins, c.first]))
        rows.append((float(c.miss_m[k]), int(c.gap_steps[k]), float(c.turn_rad[k]), fastest))
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
