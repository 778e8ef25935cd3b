"""Every traffic policy (the CTG++ diffusion policy, log replay, constant velocity, the CTG and BITS
baselines), their factory by name, the sampler presets, and the plan stages from the denoiser's
samples to the executed plan (:mod:`ctgpp.policies.stages`)."""
