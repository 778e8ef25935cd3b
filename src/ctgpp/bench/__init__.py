"""``ctgpp bench``: closed-loop scenario timings of sampler presets and denoiser scaling curves."""
