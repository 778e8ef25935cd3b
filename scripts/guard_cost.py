"""The realism guards' cost of one re-plan, unguided and guided, per seed: of the N samples together and
of the plan chosen from them (a sample per vehicle), on a real scene with the vehicles parked at the
start held as the simulator holds them.

    python scripts/guard_cost.py --checkpoint training/ctgpp-v4 --seeds 6

(docs/decisions/sampler.md, the radius floor.)
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ctgpp.data.catalog import Catalog
from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.guidance.context import build_guidance_batch
from ctgpp.guidance.guards import GuardConfig, RealismGuards
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.policies.diffusion import DiffusionPolicy, SamplingConfig
from ctgpp.policies.factory import default_checkpoint
from ctgpp.sim.closed_loop import held_numbers, initial_observation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=default_checkpoint())
    parser.add_argument("--scene", default="scene-0103")
    parser.add_argument("--start", type=float, default=3.0)
    parser.add_argument("--seeds", type=int, default=6)
    args = parser.parse_args()
    scene = Catalog.open().load(args.scene)
    obs = initial_observation(scene, args.start)
    held = held_numbers(obs.scene, obs.tracks, obs.step, obs.controlled, True)
    obs = replace(obs, held=obs.controlled[held])
    guards = RealismGuards(GuardConfig())
    batch = build_guidance_batch(obs, 52)
    model = load_checkpoint(args.checkpoint)[0]
    configs = {
        "none": None,
        "guards, radius as Algorithm 2": GuidanceConfig(min_radius=0.0),
        "guards, radius >= 0.3 (default)": GuidanceConfig(),
        "guards, radius >= 0.3, 3 Adam steps of lr 0.3": GuidanceConfig(inner_steps=3, lr=0.3),
    }
    for name, config in configs.items():
        both, executed = [], []
        for seed in range(args.seeds):
            loss = guards if config is not None else None
            policy = DiffusionPolicy(model, SamplingConfig(), loss, config or GuidanceConfig())
            samples = policy.sample_plans(replace(obs, rng=np.random.default_rng(seed)))
            v = samples.chosen.shape[0]
            plan = samples.trajectories[torch.arange(v), samples.chosen][:, None]  # (V, 1, F, 6)
            both.append(float(guards(samples.trajectories, batch).sum()))
            executed.append(float(guards(plan, batch).sum()))
        print(f"{name}: samples {np.round(both, 2).tolist()}, executed plan {np.round(executed, 2).tolist()}")


if __name__ == "__main__":
    main()
