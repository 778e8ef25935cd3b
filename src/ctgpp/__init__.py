"""ctgpp: language-guided traffic simulation with scene-level diffusion (CTG++).

The Python API (:mod:`ctgpp.api`)::

    import ctgpp

    scene = ctgpp.load_scene("scene-0103")                 # or load_scene(ID, data="data/ngsim")
    result = ctgpp.simulate(scene, "vehicle 1 should collide with vehicle 2", seed=0)
    result.metrics["fail"], result.query["satisfied"]      # metrics, the query's verdict
    result.to_arrow()                                      # the rollout (also arrays(), to_pandas())
    result.plot("scene.png"); result.animate("rollout.gif")
    print(ctgpp.compare(result, other))                    # two results' metrics side by side

``load_scene``, ``simulate``, ``compare`` and ``Result`` are imported on first use: ``import ctgpp``
imports no torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

if TYPE_CHECKING:
    from ctgpp.api import Result, compare, load_scene, simulate

__all__ = ["Result", "__version__", "compare", "load_scene", "simulate"]


def __getattr__(name: str) -> Any:
    if name in ("Result", "compare", "load_scene", "simulate"):
        import ctgpp.api

        return getattr(ctgpp.api, name)
    raise AttributeError(f"module 'ctgpp' has no attribute {name!r}")
