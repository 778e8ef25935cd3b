"""The CTG++ scene-level diffusion denoiser, its config, loss and checkpoints (DESIGN.md, Model)."""

from ctgpp.model.checkpoint import CheckpointError, load_checkpoint, load_config, save_checkpoint
from ctgpp.model.config import ModelConfig
from ctgpp.model.denoiser import Denoiser, DenoiserContext
from ctgpp.model.loss import training_loss
from ctgpp.model.normalization import Normalizer

__all__ = [
    "CheckpointError",
    "Denoiser",
    "DenoiserContext",
    "ModelConfig",
    "Normalizer",
    "load_checkpoint",
    "load_config",
    "save_checkpoint",
    "training_loss",
]
