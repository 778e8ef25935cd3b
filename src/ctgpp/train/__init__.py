"""Training the denoiser: the loop, EMA weights, resumable state, the training record."""
