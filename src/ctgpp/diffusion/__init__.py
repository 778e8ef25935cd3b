"""Diffusion over action trajectories: the cosine schedule and the DDPM / DDIM samplers."""

from ctgpp.diffusion.ddim import DDIMSampler
from ctgpp.diffusion.ddpm import DDPMSampler
from ctgpp.diffusion.schedule import CosineSchedule, Sampler, randn_like, sample

__all__ = ["CosineSchedule", "DDIMSampler", "DDPMSampler", "Sampler", "randn_like", "sample"]
