"""The Python API: load a scene, simulate it, read the result.

>>> import ctgpp
>>> scene = ctgpp.load_scene("scene-0103")
>>> result = ctgpp.simulate(scene, "vehicle 1 should collide with vehicle 2", seed=0)
>>> result.query["satisfied"], result.metrics["fail"]

:func:`load_scene` and :func:`simulate` live in :mod:`ctgpp.api.episode`, :class:`Result` in
:mod:`ctgpp.api.result`, :func:`compare` (results side by side) in :mod:`ctgpp.api.comparison`.
They are imported on first use, so that ``import ctgpp`` stays light (no
torch until a simulation needs it).
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ctgpp.api.comparison import Comparison, compare
    from ctgpp.api.episode import default_scene_id, load_scene, simulate
    from ctgpp.api.result import Result

_WHERE = {
    "load_scene": "ctgpp.api.episode",
    "simulate": "ctgpp.api.episode",
    "default_scene_id": "ctgpp.api.episode",
    "Result": "ctgpp.api.result",
    "compare": "ctgpp.api.comparison",
    "Comparison": "ctgpp.api.comparison",
}

__all__ = ["Comparison", "Result", "compare", "default_scene_id", "load_scene", "simulate"]


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'ctgpp.api' has no attribute {name!r}")
    return getattr(import_module(_WHERE[name]), name)
