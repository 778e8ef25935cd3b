"""The highest simulated speed of one vehicle after a time, in rollouts ``ctgpp simulate`` wrote: how a
query's speed limit held (issue 33: a capped turn).

    python scripts/capped_speed.py --vehicle 3 --limit 3 --from-s 0.8 OUT_DIR [OUT_DIR ...]

Prints, per directory, the vehicle's speed at the start, its highest speed from ``--from-s`` on (the
first time it could be under the limit braking at the action bound: 10 m/s² from its speed at the
start) and whether that is at or under the limit; the last line counts the directories where it is.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pyarrow.parquet as pq


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="+", type=Path)
    parser.add_argument("--vehicle", type=int, required=True)
    parser.add_argument("--limit", type=float, required=True, help="m/s")
    parser.add_argument("--from-s", type=float, default=0.0, help="judge speeds from this time on (s)")
    args = parser.parse_args()
    held = 0
    for out in args.dirs:
        table = pq.read_table(out / "rollout.parquet").to_pydict()
        rows = sorted((t, v) for t, a, v in zip(table["time_s"], table["agent"], table["speed"], strict=True)
                      if a == args.vehicle and t >= 0)
        late = max(v for t, v in rows if t >= args.from_s - 1e-9)
        ok = late <= args.limit + 1e-6
        held += ok
        print(f"{out}: start {rows[0][1]:.2f} m/s, max from {args.from_s:g} s {late:.2f} m/s, "
              f"at or under {args.limit:g} m/s: {ok}")
    print(f"at or under the limit from {args.from_s:g} s: {held} / {len(args.dirs)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
