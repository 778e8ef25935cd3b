"""The paper's failure case over seeds: when each vehicle reached the rightmost lane, whether the lane
changes came in order, each turn, the sentence and the moving vehicles' fail (default settings).

    python scripts/failure_case.py --seeds 6

(docs/decisions/sequences.md.)
"""

from __future__ import annotations

import argparse
import re

import ctgpp
from ctgpp.api.episode import policy_factory

QUERY = ("vehicle 20 and 21 move to the rightmost lane one by one and then both turn right at the next "
         "intersection")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=6, help="seeds 0 .. N-1")
    args = parser.parse_args()
    scene = ctgpp.load_scene("scene-0553")
    policies = policy_factory()
    for seed in range(args.seeds):
        result = ctgpp.simulate(scene, QUERY, seed=seed, start_s=4.0, duration_s=15.0, policies=policies,
                                echo=lambda line: None)
        parts = result.query["parts"]
        done = [re.search(r"from t = ([0-9.]+) s", part["measured"]) for part in parts[:2]]
        times = ", ".join(f"{v} at {m.group(1)} s" if m else f"{v} never"
                          for v, m in zip((20, 21), done, strict=True))
        print(f"seed {seed}: rightmost lane reached by {times}; in order {parts[1]['satisfied']}; "
              f"turn 20 {parts[2]['satisfied']}, turn 21 {parts[3]['satisfied']}; sentence "
              f"{result.query['satisfied']}; moving fail {result.metrics['fail']:.3f}", flush=True)


if __name__ == "__main__":
    main()
