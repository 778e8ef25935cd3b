"""Rollouts as scenarios other simulators replay: ScenarioNet/MetaDrive pickles, CommonRoad XML.

``export(rollout, kind, path)`` is the one entry point (the CLI's ``--export`` and the Python API
call it); :mod:`ctgpp.io.scenarionet_export` and :mod:`ctgpp.io.commonroad_export` say what each
file holds. Each file is written atomically.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ctgpp.interfaces import Rollout

EXPORT_KINDS = ("scenarionet", "commonroad")


class MissingDependencyError(ImportError, ValueError):
    """An export needs an optional package that is not installed (a one-line user error in the CLI)."""


def check_export_kind(kind: str) -> None:
    """Raise a one-line ``ValueError`` for an unknown kind and :class:`MissingDependencyError` when
    the kind's writer is not installed, before any work is done."""
    if kind not in EXPORT_KINDS:
        raise ValueError(f"unknown export kind {kind!r}: expected one of {', '.join(EXPORT_KINDS)}")
    if kind == "commonroad" and importlib.util.find_spec("commonroad") is None:
        raise MissingDependencyError(
            "--export commonroad needs the optional dependency commonroad-io: pip install 'ctgpp[commonroad]'"
        )


def export_name(kind: str, scene_id: str) -> str:
    """The file name an export of ``scene_id`` gets in an output directory: ``sd_ctgpp_<scene>.pkl``
    (ScenarioNet's tools list ``sd_*.pkl`` files) or ``<scene>.cr.xml``."""
    check_export_kind(kind)
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in scene_id)
    return f"sd_ctgpp_{safe}.pkl" if kind == "scenarionet" else f"{safe}.cr.xml"


def export(rollout: Rollout, kind: str, path: Path | str) -> Path:
    """Write ``rollout`` as a ``kind`` scenario ("scenarionet" or "commonroad") to ``path``; a
    directory gets the file :func:`export_name`. Returns the file written."""
    check_export_kind(kind)
    path = Path(path)
    if path.is_dir():
        path = path / export_name(kind, rollout.scene.id)
    if kind == "scenarionet":
        from ctgpp.io.scenarionet_export import write_scenarionet

        return write_scenarionet(rollout, path)
    from ctgpp.io.commonroad_export import write_commonroad

    return write_commonroad(rollout, path)
