"""Arguments and helpers shared by several sub-commands.

The model's, sampler's and guards' configuration classes import torch: they are imported inside the
functions that need them, so that the light commands (``scenes``, ``show``, ``rules``) start without it."""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ctgpp.data.catalog import Catalog

if TYPE_CHECKING:
    from ctgpp.diffusion.guided import GuidanceConfig
    from ctgpp.guidance.guards import GuardConfig
    from ctgpp.language.llm.client import LLMConfig
    from ctgpp.policies.diffusion import SamplingConfig
    from ctgpp.policies.stages import StageConfig


MAX_QUERY_CHARS = 300  # the playground's limit too (ctgpp.serve.schema.MAX_SENTENCE_CHARS)


def check_query(query: str | None, option: str = "query") -> None:
    """Raise a one-line ValueError naming ``option`` for a query longer than :data:`MAX_QUERY_CHARS`
    or one with no words."""
    if query is None:
        return
    if not query.strip():
        raise ValueError(f"the {option} is empty: say what the traffic should do, e.g. "
                         "\"vehicle 1 should collide with vehicle 2\"")
    if len(query) > MAX_QUERY_CHARS:
        raise ValueError(f"the {option} is {len(query)} characters long, more than the {MAX_QUERY_CHARS} "
                         "allowed: say what the traffic should do in a sentence or two")


def check_seed(seed: int, option: str = "--seed") -> None:
    """Raise a one-line ValueError naming ``option`` unless ``seed`` is a non-negative integer that numpy
    and torch accept (below 2**32)."""
    if not 0 <= seed < 2**32:
        raise ValueError(f"{option} must be an integer from 0 to {2**32 - 1} (got {seed})")


def add_data_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        metavar="DIR",
        help="directory of converted scenes (default: the embedded nuScenes v1.0-mini scenes)",
    )


def add_episode_args(parser: argparse.ArgumentParser, what: str = "") -> None:
    """``--duration`` and ``--history``: how long an episode runs and the log it starts from
    (:func:`ctgpp.sim.closed_loop.episode_config`); ``what`` ends the duration's help."""
    from ctgpp.sim.closed_loop import DURATION_S, HISTORY_S, MIN_HISTORY_S

    parser.add_argument(
        "--duration",
        type=float,
        default=DURATION_S,
        metavar="SEC",
        help=f"simulated seconds (default: {DURATION_S:g}){' ' + what if what else ''}",
    )
    parser.add_argument(
        "--history",
        type=float,
        default=None,
        metavar="SEC",
        help=f"logged seconds before the start (default: {HISTORY_S:g}, shortened down to "
        f"{MIN_HISTORY_S:g} where the scene is too short for it and --duration)",
    )


def add_model_args(parser: argparse.ArgumentParser) -> None:
    """Checkpoint and sampler options of the ctgpp policy."""
    from ctgpp.policies.diffusion import SamplingConfig

    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        metavar="DIR",
        help="CTG++ checkpoint directory (default: the one shipped with ctgpp)",
    )
    parser.add_argument(
        "--sampler",
        choices=["ddim", "ddpm"],
        default=SamplingConfig.sampler,
        help="diffusion sampler (ddpm: all K steps, as in the paper)",
    )
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help="DDIM steps, spread evenly (default: the fast preset's 6: k = 99, 79, 59, 40, 20, 0)",
    )
    parser.add_argument(
        "--grid",
        default=None,
        metavar="K,K,...",
        help="the DDIM steps visited, from 99 (pure noise) down, e.g. 99,59,29,11,3,0, instead of --steps "
        "(default: --steps spread evenly)",
    )
    parser.add_argument(
        "--samples", type=int, default=SamplingConfig.num_samples, help="samples per plan (N)"
    )
    parser.add_argument(
        "--eta",
        type=float,
        default=SamplingConfig.eta,
        help="DDIM's noise between steps: 0 deterministic, 1 as DDPM's over the visited steps",
    )


def add_guidance_args(parser: argparse.ArgumentParser) -> None:
    """Guidance strength of Algorithm 2: the inner Adam steps and their learning rate."""
    from ctgpp.diffusion.guided import GuidanceConfig

    parser.add_argument(
        "--guide-lr", type=float, default=GuidanceConfig.lr, help="guidance Adam learning rate"
    )
    parser.add_argument(
        "--guide-radius",
        type=float,
        default=GuidanceConfig.min_radius,
        metavar="R",
        help="the smallest clip radius of a guidance step (GuidanceConfig.min_radius; "
        f"default {GuidanceConfig.min_radius:g})",
    )
    parser.add_argument(
        "--guide-steps",
        type=int,
        default=GuidanceConfig.inner_steps,
        help="guidance steps per denoising step",
    )
    parser.add_argument(
        "--filtration",
        choices=["compose", "scene"],
        default="compose" if GuidanceConfig.compose else "scene",
        help="for a rule that couples vehicles: compose the plan vehicle by vehicle from the N samples "
        "(default) or keep one sample for the whole scene (the paper)",
    )


def add_guard_args(parser: argparse.ArgumentParser, default: str) -> None:
    """The realism guards (``--guards``, ``--no-guards``): ``default`` "on" for simulate, "off" for
    the paper's protocol."""
    from ctgpp.guidance.guards import GUARD_NAMES

    parser.add_argument(
        "--guards",
        default=default,
        metavar="on|off|" + ",".join(GUARD_NAMES),
        help=f"realism guards of the diffusion policies (default: {default}): every vehicle the rule or "
        "query does not send elsewhere stays on the road (offroad), out of collisions with every agent "
        "(collision), in its lane (lane) and, where the query does not set its pace, no further behind "
        "the vehicle ahead than drivers are (follow); a comma-separated subset runs only those",
    )
    parser.add_argument(
        "--no-guards", dest="guards", action="store_const", const="off", help="the same as --guards off"
    )


def add_stage_args(parser: argparse.ArgumentParser, default: str) -> None:
    """The plan stages beyond the paper (``--stages``): ``default`` "on" for simulate, "off" for the
    paper's protocol; independent of ``--guards``."""
    from ctgpp.policies.stages import SWITCHABLE

    parser.add_argument(
        "--stages",
        default=default,
        metavar="on|off|" + ",".join(SWITCHABLE),
        help=f"plan stages of the diffusion policies after sampling (default: {default}): a query's turn "
        "steered along its lane path (steer), its speed limit held exactly (cap), a chosen plan braked for "
        "what is ahead (brake); a comma-separated subset runs only those. metrics.json lists what each did",
    )


def stage_config(args: argparse.Namespace) -> StageConfig:
    """The ``--stages`` choice (ValueError naming the stages for an unknown one)."""
    from ctgpp.api.episode import parse_stages

    return parse_stages(args.stages)


def add_llm_args(parser: argparse.ArgumentParser) -> None:
    """The language model that writes the query's loss (``--llm-*``; none: the offline compiler)."""
    parser.add_argument(
        "--llm-model",
        default=None,
        help="language model name (default: env CTGPP_LLM_MODEL; none: the offline query compiler)",
    )
    parser.add_argument(
        "--llm-base-url", default=None, help="OpenAI-compatible endpoint (default: env OPENAI_BASE_URL)"
    )
    parser.add_argument(
        "--llm-timeout",
        type=float,
        default=None,
        metavar="SEC",
        help="seconds one request may take; a request that times out is not sent again (default: env "
        "CTGPP_LLM_TIMEOUT, else 600: a cold prompt on a small CPU server takes minutes)",
    )
    parser.add_argument(
        "--llm-max-tokens",
        type=int,
        default=None,
        metavar="N",
        help="longest reply in tokens (default: env CTGPP_LLM_MAX_TOKENS, else 1024)",
    )
    parser.add_argument(
        "--llm-mode",
        default=None,
        choices=["program", "structured", "auto"],
        help="what the model is asked for: a loss program (program, the paper's path), calls of the "
        "behaviour registry as schema-constrained JSON (structured: fast with a small local model; the "
        "offline compiler's reading is the fallback and is compared), or structured calls only where "
        "the offline compiler refuses the sentence (auto) (default: env CTGPP_LLM_MODE, else program)",
    )


def llm_config(args: argparse.Namespace) -> LLMConfig | None:
    """The ``--llm-*`` choice over the environment; None: the offline compiler."""
    from ctgpp.language.llm.client import LLMConfig

    return LLMConfig.resolve(
        base_url=args.llm_base_url,
        model=args.llm_model,
        timeout_s=args.llm_timeout,
        max_tokens=args.llm_max_tokens,
        mode=args.llm_mode,
    )


def guard_config(args: argparse.Namespace) -> GuardConfig:
    """The ``--guards`` choice (ValueError naming the guards for an unknown one)."""
    from ctgpp.guidance.guards import GuardConfig

    try:
        return GuardConfig.parse(args.guards)
    except ValueError as err:
        raise ValueError(f"--guards {args.guards}: {err}") from None


def guidance_config(args: argparse.Namespace) -> GuidanceConfig:
    from ctgpp.diffusion.guided import GuidanceConfig

    if args.guide_steps < 0 or not (math.isfinite(args.guide_lr) and args.guide_lr > 0):
        raise ValueError(
            "--guide-steps must be ≥ 0 and --guide-lr positive "
            f"(got --guide-steps {args.guide_steps} --guide-lr {args.guide_lr:g})"
        )
    if not (math.isfinite(args.guide_radius) and args.guide_radius >= 0):
        raise ValueError(f"--guide-radius must be a number ≥ 0 (got {args.guide_radius:g})")
    compose = args.filtration == "compose"
    return GuidanceConfig(args.guide_steps, args.guide_lr, compose=compose, min_radius=args.guide_radius)


def sampling_config(args: argparse.Namespace) -> SamplingConfig:
    from ctgpp.diffusion.ddim import check_grid
    from ctgpp.model.config import ModelConfig
    from ctgpp.policies.diffusion import SamplingConfig

    if (args.steps is not None and args.steps < 1) or args.samples < 1:
        raise ValueError("--steps and --samples must be positive")
    if not 0.0 <= args.eta <= 1.0:
        raise ValueError(f"--eta must lie in [0, 1] (got {args.eta:g})")
    if args.eta > 0.0 and args.sampler != "ddim":
        raise ValueError("--eta is DDIM's noise: it needs --sampler ddim (DDPM's noise is fixed)")
    grid = getattr(args, "grid", None)
    if grid is not None:
        if args.steps is not None or args.sampler != "ddim":
            raise ValueError("--grid names DDIM's steps: it takes neither --steps nor --sampler ddpm")
        try:
            steps = tuple(int(k) for k in grid.split(","))
        except ValueError:
            raise ValueError(f"--grid {grid}: expected diffusion steps such as 99,59,29,11,3,0") from None
        check_grid(steps, len(steps), ModelConfig.diffusion_steps)  # the presets' K = 100
        return SamplingConfig("ddim", len(steps), args.samples, steps, args.eta)
    if args.steps is None:
        return SamplingConfig(args.sampler, num_samples=args.samples, eta=args.eta)
    return SamplingConfig.evenly(args.sampler, args.steps, args.samples, args.eta)


def open_catalog(args: argparse.Namespace) -> Catalog:
    return Catalog.open(args.data)


def split_spec(spec: str, default_root: Path | None = None) -> tuple[Path | None, str]:
    """``[DIR:]SPLIT`` as (data directory, split): a bare SPLIT is of ``default_root`` (None: the
    embedded data). The split is what follows the last colon, so DIR may hold colons itself."""
    root, _, split = spec.rpartition(":")
    if not split:
        raise ValueError(f"{spec!r} names no split: expected [DIR:]SPLIT (mini_val, data/ngsim:heldout)")
    return (Path(root) if root else default_root), split


def print_table(header: list[str], rows: Sequence[Sequence[object]]) -> None:
    """A plain aligned text table on stdout."""
    cells = [header] + [[_fmt(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for k, row in enumerate(cells):
        print("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
        if k == 0:
            print("  ".join("-" * w for w in widths))


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.3f}" if value == value else "-"
    return str(value)
