"""ctgpp: language-guided traffic simulation with scene-level diffusion (CTG++)."""

__version__ = "0.1.0"
