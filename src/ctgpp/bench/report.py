"""The bench results as markdown tables, a JSON record and a picture of the agent-count curve."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ctgpp.bench.scaling import CallTiming
from ctgpp.bench.scenarios import PresetResult
from ctgpp.eval.table import MOVING_COLUMNS as EVAL_MOVING_COLUMNS
from ctgpp.io.atomic import atomic_path, write_text_atomic
from ctgpp.io.strict_json import dumps_strict
from ctgpp.metrics.moving import POOL_WEIGHT, pooled_mean

REFERENCE_PRESET = "paper"


def _f(value: float, digits: int = 3) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def scenario_table(results: Sequence[PresetResult]) -> str:
    """Seconds per 10-s scenario, speed-up over the paper's preset (same episodes), memory, quality,
    and the quality differences from the paper's preset paired episode by episode. Vehicles: the mean
    count per episode, and in brackets of those moving at the start (sampled; the others held)."""
    reference = next((r for r in results if r.preset == REFERENCE_PRESET), None)
    head = (
        "| preset | sampler | episodes | vehicles (moving) | median s / scenario | mean s | "
        "× faster than paper | denoiser calls / s | peak MiB | fail | rule violation | real | rel real | "
        "fail − paper (± s.e.) | real vs paper |"
    )
    lines = [head, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        mean_s = r.mean("seconds")
        speedup, fail_diff, real_ratio = math.nan, "-", "-"
        if reference is not None:
            speedup = reference.mean("seconds") / mean_s
            if r is not reference:
                diff, se = paired_difference(r, reference, "fail")
                fail_diff = f"{diff:+.3f} ± {se:.3f}"
                real_ratio = f"{100 * (r.mean('real') / reference.mean('real') - 1):+.0f} %"
        vehicles = f"{r.mean('vehicles'):.1f} ({r.mean('moving'):.1f})"
        lines.append(
            f"| {r.preset} | {r.description} | {len(r.episodes)} | {vehicles} | {r.median_seconds:.2f} | "
            f"{mean_s:.2f} | {_f(speedup, 1)} | {r.calls_per_second:.1f} | {r.peak_rss_mib:.0f} | "
            f"{_f(r.mean('fail'))} | {_f(r.mean('rule_violation'))} | {_f(r.mean('real'))} | "
            f"{_f(r.mean('rel_real'))} | {fail_diff} | {real_ratio} |"
        )
    return "\n".join(lines) + "\n"


# the figures over the vehicles moving at the start: ``evaluate``'s second table, at the 10-s horizon
MOVING_COLUMNS = tuple((m, h) for m, h in EVAL_MOVING_COLUMNS if m not in ("ade_5s", "fde_5s"))


def moving_pooled(result: PresetResult, metric: str) -> float:
    """``metric`` of ``metrics.moving`` over all the moving vehicles of a preset's episodes (pooled:
    each episode weighs by the count of vehicles behind its value)."""
    weight = POOL_WEIGHT[metric]
    return pooled_mean(
        (e.moving_metrics.get(metric, math.nan), e.moving_counts.get(weight, 0)) for e in result.episodes
    )


def moving_table(results: Sequence[PresetResult]) -> str:
    """Per preset, the figures over the vehicles that move at the start, pooled over its episodes'
    vehicles: fail / collision / off-road (beyond the map apart), first collision with a held vehicle,
    lane-leave, stop, yaw-rate sign changes per 10 s, ADE / FDE (m) to the log at 10 s, and
    the share of logged turns the simulation follows (``turn_follow``)."""
    lines = [
        "| preset | moving vehicles | " + " | ".join(h for _, h in MOVING_COLUMNS) + " |",
        "|---|---:|" + "---:|" * len(MOVING_COLUMNS),
    ]
    for r in results:
        moving = sum(e.moving_counts.get("moving", 0) for e in r.episodes)
        cells = [_f(moving_pooled(r, metric)) for metric, _ in MOVING_COLUMNS]
        lines.append(f"| {r.preset} | {moving} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def paired_difference(result: PresetResult, reference: PresetResult, metric: str) -> tuple[float, float]:
    """Mean and standard error of ``metric`` of ``result`` minus ``reference`` over the episodes both
    ran (same scene, start and seed; NaN values left out). NaN when none; s.e. 0 for one."""
    ref = {(e.scene, e.start_s, e.seed): getattr(e, metric) for e in reference.episodes}
    diffs = [
        getattr(e, metric) - ref[key]
        for e in result.episodes
        for key in [(e.scene, e.start_s, e.seed)]
        if key in ref and not math.isnan(getattr(e, metric)) and not math.isnan(ref[key])
    ]
    if not diffs:
        return math.nan, math.nan
    mean = sum(diffs) / len(diffs)
    if len(diffs) == 1:
        return mean, 0.0
    var = sum((d - mean) ** 2 for d in diffs) / (len(diffs) - 1)
    return mean, math.sqrt(var / len(diffs))


def agent_table(curve: Sequence[CallTiming]) -> str:
    lines = [
        "| agents | samples | spatial | groups | neighbours | ms / call | ms / agent |",
        "|---:|---:|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {c.agents} | {c.samples} | {c.spatial} | {c.groups} | {c.neighbours or '–'} | {c.ms:.1f} "
        f"| {c.ms / c.agents:.2f} |"
        for c in curve
    ]
    return "\n".join(lines) + "\n"


def batching_table(rows: Sequence[tuple[CallTiming, float]]) -> str:
    lines = [
        "| scenes | samples each | ms batched | ms one by one | ms / scene batched | × faster |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for timing, separate in rows:
        lines.append(
            f"| {timing.scenes} | {timing.samples} | {timing.ms:.1f} | {separate:.1f} | "
            f"{timing.ms / timing.scenes:.1f} | {separate / timing.ms:.2f} |"
        )
    return "\n".join(lines) + "\n"


def plot_agent_curve(curve: Sequence[CallTiming], path: Path) -> Path:
    """ms per call against agents, a line per way of running the spatial attention, with the line
    through the smallest count's (cheapest) ms/agent for reference."""
    fig = Figure(figsize=(5, 3.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for mode in dict.fromkeys(c.spatial for c in curve):  # one line per way, in their order
        points = [c for c in curve if c.spatial == mode]
        ax.plot([c.agents for c in points], [c.ms for c in points], "o-", label=f"measured, {mode}")
    if curve:
        agents = sorted({c.agents for c in curve})
        slope = min(c.ms for c in curve if c.agents == agents[0]) / agents[0]
        ax.plot(agents, [slope * a for a in agents], "--", color="grey", label="linear from the first point")
    ax.set_xlabel("agents in the scene")
    ax.set_ylabel("ms per denoiser call")
    ax.set_title(f"one denoiser call, N = {curve[0].samples if curve else 0} samples")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    return path


def write_report(out: Path, report: dict[str, object], markdown: str) -> tuple[Path, Path]:
    """``bench.json`` (strict JSON: an undefined figure, NaN or infinite, is ``null``) and ``bench.md``
    in ``out``, each written atomically."""
    out.mkdir(parents=True, exist_ok=True)
    record = write_text_atomic(out / "bench.json", dumps_strict(report, indent=2) + "\n")
    return record, write_text_atomic(out / "bench.md", markdown)
