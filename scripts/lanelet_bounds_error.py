"""How far the lanelet bounds that the CommonRoad export rebuilds lie from the recorded ones.

    python scripts/lanelet_bounds_error.py [--data ../shared/data/commonroad-ngsim] [--every 6]

ctgpp's scenes keep lane centerlines, not lane edges; :mod:`ctgpp.io.lane_bounds` rebuilds the edges
at the measured spacing of neighbouring lanes. For every ``--every``-th NGSIM scenario this reads the
recorded lanelets with commonroad-io, rebuilds the bounds from ctgpp's lane graph of the same file,
and prints the distance of each rebuilt bound vertex from the recorded one and the error of each
lane's width (median and 90th percentile, m).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
from commonroad.common.file_reader import CommonRoadFileReader

from ctgpp.data.commonroad import iter_commonroad, load_commonroad
from ctgpp.io.lane_bounds import lane_bounds, lane_widths_m


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/commonroad-ngsim"))
    parser.add_argument("--every", type=int, default=6, help="every n-th scenario (default: 6)")
    args = parser.parse_args()
    logging.getLogger("commonroad").setLevel(logging.ERROR)
    files = iter_commonroad(args.data)[:: args.every]
    vertex_m, width_m = [], []
    for path in files:
        scenario, _ = CommonRoadFileReader(str(path)).open()
        recorded = sorted(scenario.lanelet_network.lanelets, key=lambda ll: ll.lanelet_id)
        lanes = load_commonroad(path).lanes
        widths = lane_widths_m(lanes)
        for lanelet, (left, right), width in zip(recorded, lane_bounds(lanes, widths), widths, strict=True):
            vertex_m += [np.linalg.norm(lanelet.left_vertices - left, axis=1),
                         np.linalg.norm(lanelet.right_vertices - right, axis=1)]
            true = np.median(np.linalg.norm(lanelet.left_vertices - lanelet.right_vertices, axis=1))
            width_m.append(abs(true - width))
    vertices = np.concatenate(vertex_m)
    print(f"{len(files)} scenarios, {len(width_m)} lanelets, {len(vertices)} bound vertices")
    print(f"bound vertex error: median {np.median(vertices):.3f} m, 90th percentile "
          f"{np.percentile(vertices, 90):.3f} m")
    print(f"lane width error:   median {np.median(width_m):.3f} m, 90th percentile "
          f"{np.percentile(width_m, 90):.3f} m")


if __name__ == "__main__":
    main()
