"""The BITS and BITS+opt policies: sample goals, roll out the goal-conditioned policy, rank, (refine).

Per re-plan: each controlled vehicle's goal distribution gives M goals (Gumbel top-k: M distinct
cells drawn without replacement, or the M most likely), the policy turns each into an action
trajectory through the unicycle, :func:`ctgpp.baselines.ranking.rank_candidates` picks one per
vehicle with the rule loss, collisions and off-road; BITS+opt then runs Adam on the chosen actions
against the rule loss (:func:`ctgpp.baselines.ranking.optimize_actions`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ctgpp.baselines.bits import BITSModel, goal_actions
from ctgpp.baselines.kinds import load_model
from ctgpp.baselines.ranking import (
    RankingWeights,
    collision_cost,
    offroad_cost,
    optimize_actions,
    rank_candidates,
)
from ctgpp.baselines.raster import observation_raster, with_raster
from ctgpp.data.batch import collate
from ctgpp.data.windows import WindowConfig, build_window
from ctgpp.diffusion.guided import action_trajectories
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.geometry import local_to_world
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import build_guidance_batch
from ctgpp.guidance.prediction import known_tracks
from ctgpp.interfaces import Observation, Plan
from ctgpp.model.checkpoint import CheckpointError


@dataclass(frozen=True)
class BITSPlanConfig:
    """num_goals (M) candidates per vehicle, drawn from the goal distribution (``sample_goals``) or
    its M most likely cells; ranking weights; ``opt_steps`` > 0 makes BITS+opt (Adam, ``opt_lr`` on
    normalized actions)."""

    num_goals: int = 8
    sample_goals: bool = True
    weights: RankingWeights = RankingWeights()
    opt_steps: int = 0
    opt_lr: float = 0.05


@dataclass(frozen=True, eq=False)
class BITSCandidates:
    """One re-plan. goals (V, M, 2) m and actions (V, M, F, 2) per candidate, current (V, 4) states in
    each vehicle's frame, trajectories (V, M, F, 6) the guidance contract's x, costs (V, M) without
    the rule, chosen (V,), planned (V, F, 2) the executed actions (after BITS+opt's refinement)."""

    goals: Tensor
    actions: Tensor
    current: Tensor
    trajectories: Tensor
    costs: Tensor
    chosen: Tensor
    planned: Tensor


class BITSPolicy:
    """BITS (``opt_steps`` = 0) or BITS+opt in closed loop, optionally steered by a rule."""

    hold_stationary = True

    def __init__(
        self,
        model: BITSModel,
        config: BITSPlanConfig = BITSPlanConfig(),
        guidance: GuidanceLoss | None = None,
    ) -> None:
        self.model = model.eval()
        self.config = config
        self.guidance = guidance
        self.name = "bits+opt" if config.opt_steps > 0 else "bits"

    @classmethod
    def from_checkpoint(
        cls, path: Path, config: BITSPlanConfig = BITSPlanConfig(), guidance: GuidanceLoss | None = None
    ) -> BITSPolicy:
        model, _, _, kind = load_model(path)
        if kind != "bits":
            raise CheckpointError(f"{path} holds a {kind!r} model, not BITS")
        return cls(model, config, guidance)  # type: ignore[arg-type]

    @torch.no_grad()
    def candidates(self, obs: Observation) -> BITSCandidates:
        """Goals, candidate trajectories, costs and the choice of every controlled vehicle."""
        cfg = self.model.config
        windows = WindowConfig(cfg.history_steps, cfg.future_steps, max_agents=len(obs.controlled))
        # the simulated past, never the logged future: what a plan at obs.step knows (no peeking)
        seen = replace(obs.scene, agents=known_tracks(obs.tracks, obs.step, obs.controlled, obs.scene.dt_s))
        window = build_window(seen, obs.step, windows, agent_index=obs.controlled)
        batch = with_raster(collate([window]), observation_raster(obs, cfg.raster()))
        ctx = self.model.encode(batch)
        gen = torch.Generator().manual_seed(int(obs.rng.integers(2**31)))
        logits = ctx.goal_logits[0]  # (V, K)
        m = min(self.config.num_goals, logits.shape[-1])
        score = logits
        if self.config.sample_goals:  # Gumbel top-k: M cells without replacement
            u = torch.rand(logits.shape, generator=gen).clamp(1e-9, 1 - 1e-9)
            score = logits - torch.log(-torch.log(u))
        cells = torch.topk(score, m, dim=-1).indices  # (V, M)
        cells = torch.gather(cells, 1, torch.argsort(torch.gather(logits, 1, cells), dim=1, descending=True))
        goals = torch.gather(ctx.goal_xy[0], 1, cells[..., None].expand(-1, -1, 2))  # (V, M, 2)
        actions = goal_actions(self.model, ctx, goals[None])[0]  # (V, M, F, 2)
        current = ctx.current[0]  # (V, 4)
        traj = action_trajectories(actions.transpose(0, 1), current, cfg.dt_s)  # (V, M, F, 6)
        data_batch = build_guidance_batch(obs, cfg.future_steps)
        w = self.config.weights
        costs = w.collision * collision_cost(traj, data_batch) + w.offroad * offroad_cost(traj, data_batch)
        chosen = rank_candidates(traj, costs, self.guidance, data_batch, w.rule)
        planned = actions[torch.arange(len(chosen)), chosen]  # (V, F, 2)
        if self.guidance is not None and self.config.opt_steps > 0:
            planned = optimize_actions(
                planned, current, self.guidance, data_batch, self.model.normalizer, cfg.dt_s,
                self.config.opt_steps, self.config.opt_lr,
            )  # fmt: skip
        return BITSCandidates(goals, actions, current, traj, costs, chosen, clip_actions(planned))

    def plan(self, obs: Observation) -> Plan:
        c = self.candidates(obs)
        local = rollout(c.current.double(), c.planned.double(), obs.scene.dt_s).numpy()  # (V, F, 4)
        tr, idx, step = obs.tracks, obs.controlled, obs.step
        xy = local_to_world(local[..., :2], tr.xy[idx, step][:, None], tr.yaw[idx, step][:, None])
        yaw = local[..., 3] + tr.yaw[idx, step][:, None]
        states = np.concatenate([xy, local[..., 2:3], yaw[..., None]], axis=-1)
        states = states[:, : obs.horizon_steps]
        return Plan(states=states, valid=np.ones(states.shape[:2], dtype=bool))
