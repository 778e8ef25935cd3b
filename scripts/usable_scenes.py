"""How many scenes of a data directory host an episode, per duration: each scene is simulated with
constant velocity (cheap) for every duration, through ctgpp.simulate, as ``ctgpp simulate --data DIR
--scene ID --duration D`` would; a scene counts when the episode runs (vehicles at the start, history
of at least 1 s, shortened from 3 s where the scene is short).

    python scripts/usable_scenes.py data/ngsim 10 8 6 5 4
"""

from __future__ import annotations

import sys
from collections import Counter

import ctgpp
from ctgpp.data.catalog import Catalog


def main(root: str, durations: list[float]) -> None:
    catalog = Catalog.open(root)
    usable: Counter[float] = Counter()
    full_history: Counter[float] = Counter()
    for entry in catalog.entries:
        scene = catalog.load(entry.id)
        for duration in durations:
            try:
                result = ctgpp.simulate(scene, policy="constvel", duration_s=duration)
            except ValueError:
                continue
            usable[duration] += 1
            full_history[duration] += result.record()["history_s"] >= 3.0 - 1e-9
    total = len(catalog.entries)
    print(f"{total} scenes in {catalog.root}")
    for duration in durations:
        print(f"--duration {duration:g}: {usable[duration]} of {total} usable "
              f"({full_history[duration]} with the full 3 s of history)")


if __name__ == "__main__":
    main(sys.argv[1], [float(d) for d in sys.argv[2:]] or [10.0, 5.0])
