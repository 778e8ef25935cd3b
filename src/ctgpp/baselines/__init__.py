"""The paper's baselines as trainable models (issue 7): CTG (agent-level diffusion over each vehicle's
actions, conditioned on a map raster and its own history) and BITS / BITS+opt (a spatial goal planner
and a goal-conditioned policy, candidates ranked by the rule loss, collisions and off-road; BITS+opt
refines the choice against the rule loss). Their closed-loop policies are in :mod:`ctgpp.policies`
(``ctg``, ``bits``)."""

from ctgpp.baselines.bits import BITSModel, bits_loss
from ctgpp.baselines.config import BITSConfig, CTGConfig
from ctgpp.baselines.ctg import CTGDenoiser
from ctgpp.baselines.kinds import KINDS, checkpoint_kind, kind_of, load_model
from ctgpp.baselines.ranking import RankingWeights, rank_candidates
from ctgpp.baselines.raster import RasterBatch, RasterConfig, rasterize, with_raster

__all__ = [
    "BITSConfig",
    "BITSModel",
    "CTGConfig",
    "CTGDenoiser",
    "KINDS",
    "RankingWeights",
    "RasterBatch",
    "RasterConfig",
    "bits_loss",
    "checkpoint_kind",
    "kind_of",
    "load_model",
    "rank_candidates",
    "rasterize",
    "with_raster",
]
