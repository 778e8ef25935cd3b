"""The terms each data set is used under (its licence), for what a trained model records about its data.

A model trained on data carries that data's terms: the checkpoint's record names them
(``data_terms``), and the README says which data trained the shipped model. Data sets are named as
:attr:`ctgpp.scene.types.Scene.dataset` names them; terms as ``../shared/data/README.md`` states them.
"""

from __future__ import annotations

from collections.abc import Iterable

DATA_TERMS = {
    "nuscenes": "nuScenes: nuScenes terms of use, CC BY-NC-SA 4.0 (non-commercial)",
    "ngsim": "NGSIM: US Department of Transportation public data",
    "interaction": "INTERACTION: the INTERACTION dataset terms (non-commercial research, no redistribution)",
    "waymo": "Waymo Open Motion: the Waymo Open Dataset terms (non-commercial)",
}
UNKNOWN_TERMS = "{dataset}: terms not known to ctgpp (check the data's own licence)"


def terms_of(datasets: Iterable[str]) -> list[str]:
    """The terms of each distinct data set in ``datasets`` (sorted by name), one line each."""
    return [DATA_TERMS.get(name, UNKNOWN_TERMS.format(dataset=name)) for name in sorted(set(datasets))]


__all__ = ["DATA_TERMS", "terms_of"]
