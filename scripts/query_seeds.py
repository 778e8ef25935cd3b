"""How often one query is met over seeds, per sampler preset: ``ctgpp.simulate`` with the realism
guards on (as ``ctgpp simulate``), the query's verdict, whether any other moving vehicle collided and
the fail rate of all vehicles (and of the moving ones).

    python scripts/query_seeds.py "vehicle 1 should collide with vehicle 2" --scene scene-0103 \\
        --presets ddim@99.75.40.0-n2-lr0.9,ddim6-n2-lr0.9 --seeds 10

(docs/decisions/sampler.md.)
"""

from __future__ import annotations

import argparse
import time

import ctgpp
from ctgpp.policies.presets import preset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("query")
    parser.add_argument("--scene", default="scene-0103")
    parser.add_argument(
        "--presets", default="fast", help="comma-separated sampler presets (ctgpp bench's spelling)"
    )
    parser.add_argument("--seeds", type=int, default=10, help="seeds 0 .. N-1")
    parser.add_argument("--checkpoint", default=None, help="CTG++ checkpoint (default: the shipped one)")
    args = parser.parse_args()
    scene = ctgpp.load_scene(args.scene)
    for name in args.presets.split(","):
        chosen = preset(name)
        met = clean = 0
        start = time.monotonic()
        for seed in range(args.seeds):
            result = ctgpp.simulate(
                scene, args.query, seed=seed, sampling=chosen.sampling, guidance=chosen.guidance,
                checkpoint=args.checkpoint,
            )
            named = set(result.query.get("vehicles") or [])
            others = sorted(
                e["vehicle"]
                for e in result.events
                if e.get("moving") and e.get("collision") and e["vehicle"] not in named
            )
            met += bool(result.query.get("satisfied"))
            clean += not others
            print(
                f"{name} seed {seed}: met {result.query.get('satisfied')}, "
                f"other vehicles colliding {others}, "
                f"fail of all vehicles {result.metrics['fail']:.3f} "
                f"(moving {result.metrics['moving_fail']:.3f}); "
                f"{'; '.join(p['measured'] for p in result.query.get('parts', []))}",
                flush=True,
            )
        seconds = (time.monotonic() - start) / args.seeds
        print(
            f"{name}: query met in {met} of {args.seeds}, no other collision in {clean}; "
            f"{seconds:.1f} s a seed"
        )


if __name__ == "__main__":
    main()
