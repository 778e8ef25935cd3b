"""Guidance: differentiable losses that steer the sampler, the rules library and helpers."""
