"""The distributions behind ``real`` and ``rel real``: each method's pooled histograms against the log's.

Every finished episode stores its bin counts (:func:`ctgpp.eval.episode.realism_histograms`) as one
JSON line keyed like its CSV row. Counts add up across episodes, so a method's distribution over a
set is the sum of its episodes' counts, normalized. The logged distribution of a set pools each
(scene, start) once: the log does not depend on the method, rule or seed.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.artist import Artist
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from ctgpp.eval.episode import KEY, STATISTICS
from ctgpp.eval.records import read_json_lines
from ctgpp.io.atomic import atomic_path
from ctgpp.metrics.realism import FEATURES, NUM_BINS, feature_range
from ctgpp.policies.factory import POLICY_NAMES

LOG = "log"
PANELS = tuple((statistic, feature) for statistic in STATISTICS for feature in FEATURES)
TITLES = {"real": "real (own motion)", "rel_real": "rel real (relative motion)"}
LABELS = {
    "lon_acc": "longitudinal acc. (m/s²)",
    "lat_acc": "lateral acc. (m/s²)",
    "jerk": "longitudinal jerk (m/s³)",
}
Pooled = dict[str, dict[str, dict[tuple[str, str], np.ndarray]]]  # set -> method|log -> panel -> (B,)


def read_histograms(path: Path, records: Iterable[dict[str, str]]) -> list[dict[str, Any]]:
    """The histogram lines of ``path`` whose episode is among the finished ``records`` (the last line
    of an episode written twice wins: a run killed between its two lines recomputes it)."""
    finished = {tuple(r[k] for k in KEY) for r in records}
    latest: dict[tuple[str, ...], dict[str, Any]] = {}
    for item in read_json_lines(path):
        key = tuple(str(item.get(k, "")) for k in KEY)
        if key in finished and isinstance(item.get("histograms"), dict):
            latest[key] = item
    return list(latest.values())


def pool(entries: Iterable[dict[str, Any]]) -> Pooled:
    """Summed bin counts (NUM_BINS,) per set, per method (and ``log``), per (statistic, feature)."""
    out: Pooled = {}
    logged: set[tuple[str, str, str]] = set()
    for item in entries:
        per_set = out.setdefault(item["set"], {})
        sides = [(item["method"], "sim")]
        episode = (item["set"], item["scene"], item["start_s"])
        if episode not in logged:
            logged.add(episode)
            sides.append((LOG, "log"))
        for name, side in sides:
            counts = per_set.setdefault(name, {})
            for statistic, feature in PANELS:
                values = np.asarray(item["histograms"][statistic][feature][side], dtype=np.int64)
                panel = (statistic, feature)
                counts[panel] = counts.get(panel, np.zeros(NUM_BINS, np.int64)) + values
    return out


def plot_realism(entries: Iterable[dict[str, Any]], out: Path, sets: Sequence[str] = ()) -> Path | None:
    """Draw one row of panels per set (``sets`` first, in that order), one panel per statistic: the
    log's distribution filled in grey, each method's as a line. Written atomically to ``out`` (PNG);
    None, and nothing written, when there are no entries."""
    pooled = pool(entries)
    if not pooled:
        return None
    order = [s for s in sets if s in pooled] + [s for s in pooled if s not in sets]
    methods = sorted(
        {m for per_set in pooled.values() for m in per_set if m != LOG},
        key=lambda m: (POLICY_NAMES.index(m) if m in POLICY_NAMES else len(POLICY_NAMES), m),
    )
    fig = Figure(figsize=(3.2 * len(PANELS), 2.8 * len(order) + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(order), len(PANELS), squeeze=False)
    for row, set_name in enumerate(order):
        for col, (statistic, feature) in enumerate(PANELS):
            ax = axes[row, col]
            lo, hi = feature_range(feature)
            edges = np.linspace(lo, hi, NUM_BINS + 1)
            log = pooled[set_name].get(LOG, {}).get((statistic, feature))
            if log is not None and log.sum() > 0:
                ax.stairs(log / log.sum(), edges, fill=True, color="0.8", label="log")
            for k, method in enumerate(methods):
                counts = pooled[set_name].get(method, {}).get((statistic, feature))
                if counts is not None and counts.sum() > 0:
                    ax.stairs(counts / counts.sum(), edges, color=f"C{k}", lw=1.4, label=method)
            ax.set_title(f"{set_name}: {TITLES[statistic]}", fontsize=9)
            ax.set_xlabel(LABELS[feature], fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            if col == 0:
                ax.set_ylabel("share of samples", fontsize=8)
    handles: list[Artist] = [Patch(color="0.8", label="log")]
    handles += [Line2D([], [], color=f"C{k}", lw=1.4, label=m) for k, m in enumerate(methods)]
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / fig.get_figheight()))
    with atomic_path(Path(out)) as tmp:
        fig.savefig(tmp, format="png")
    return Path(out)
