"""The training curve picture: train and validation loss against the step."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ctgpp.io.atomic import atomic_path


def plot_curve(history: list[dict[str, Any]], out: Path, title: str = "training") -> Path:
    """Plot ``history`` entries ({step, train_loss, val_loss}) to a PNG, log-scaled loss."""
    fig = Figure(figsize=(7, 4.5), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    steps = [h["step"] for h in history]
    ax.plot(steps, [h["train_loss"] for h in history], "-o", ms=3, label="train (mean since last point)")
    val = [float("nan") if h.get("val_loss") is None else h["val_loss"] for h in history]  # gaps: unmeasured
    ax.plot(steps, val, "-s", ms=3, label="validation (EMA weights)")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss (normalized actions + states)")
    ax.set_title(textwrap.fill(title, 100), fontsize=8)  # a long data note wraps, not clipped
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.tight_layout()
    with atomic_path(Path(out)) as tmp:
        fig.savefig(tmp, format="png")
    return Path(out)
