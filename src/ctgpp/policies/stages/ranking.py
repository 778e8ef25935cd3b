"""The choice among the N samples (paper §3.4): ranking by the guidance loss (filtration), then, for a
loss that couples vehicles, composing the plan vehicle by vehicle (beyond the paper).

What is ranked is the loss's :meth:`~ctgpp.guidance.base.GuidanceLoss.ranking` — the cost itself, or
for a loss with the realism guards the guards first — on the samples as the earlier stages left them
(steered along a route, capped), so that the plan chosen is the plan executed, up to the brakes.
Unguided, every sample is a plausible future and the first is executed.
"""

from __future__ import annotations

from dataclasses import replace
from typing import ClassVar

from ctgpp.diffusion.filtration import compose, filtration
from ctgpp.policies.stages.base import PlanContext, PlanSet


class Ranking:
    """Filtration: each vehicle's sample with the lowest loss (one sample for the whole scene when the
    loss couples vehicles); the loss of every sample is kept on the plans."""

    name: ClassVar[str] = "rank"

    def run(self, plans: PlanSet, ctx: PlanContext) -> PlanSet:
        if ctx.loss is None or ctx.batch is None:
            return plans
        traj = plans.trajectories(ctx.dt_s)  # (V, N, F, 6)
        loss = ctx.loss(traj, ctx.batch)
        coupled = bool(ctx.loss.couples_agents) or loss.ndim == 1
        chosen = filtration(ctx.loss.ranking(traj, ctx.batch), coupled, traj.shape[0])
        return replace(plans, loss=loss, chosen=chosen)


class Composition:
    """For a loss that couples vehicles, each vehicle may take its trajectory from another sample where
    that lowers the ranked loss of the whole scene (:func:`~ctgpp.diffusion.filtration.compose`);
    without this stage (``GuidanceConfig.compose`` False) the paper's one sample for the scene is kept."""

    name: ClassVar[str] = "compose"

    def run(self, plans: PlanSet, ctx: PlanContext) -> PlanSet:
        loss, batch = ctx.loss, ctx.batch
        if loss is None or batch is None or plans.loss is None or plans.chosen is None:
            return plans
        if not (bool(loss.couples_agents) or plans.loss.ndim == 1):
            return plans
        traj = plans.trajectories(ctx.dt_s)
        chosen = compose(traj, lambda scenes: loss.ranking(scenes, batch), plans.chosen,
                         lambda scene: loss.involved(scene, batch))
        return replace(plans, chosen=chosen)


__all__ = ["Composition", "Ranking"]
