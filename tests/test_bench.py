"""``ctgpp bench``: tiled scaling scenes are exact copies of a real one, and one whole small run."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import pytest
import torch

from ctgpp.bench.report import paired_difference, scenario_table, write_report
from ctgpp.bench.scaling import tiled_batch
from ctgpp.bench.scenarios import EpisodeTiming, PresetResult
from ctgpp.cli.main import main
from ctgpp.data.batch import collate
from ctgpp.data.windows import build_window
from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.model import Denoiser, ModelConfig
from ctgpp.model.checkpoint import save_checkpoint
from ctgpp.policies.diffusion import SamplingConfig
from ctgpp.policies.presets import preset
from ctgpp.policies.stages import StageConfig
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS, controlled_vehicles

TINY = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=8, lane_hidden=16)


def test_tiled_copies_beyond_the_social_radius_predict_like_the_original(scene_0103: Scene) -> None:
    step = 40
    controlled = controlled_vehicles(scene_0103, step)
    still = scene_0103.agents.speed[controlled, step] < MOVING_SPEED_MPS
    spec = TINY.window_config(max_agents=64, with_future=False)
    window = build_window(scene_0103, step, spec, controlled[~still], controlled[still])
    a, c = window.num_agents, window.context.num_agents
    assert a > 2 and c > 2  # moving vehicles sampled, held and replayed agents as context
    torch.manual_seed(0)
    model = Denoiser(TINY).eval()
    tiled = tiled_batch(window, 3 * a - 2)  # two whole copies and a cut one
    assert tiled.num_agents == 3 * a - 2 and bool(tiled.agent_mask.all())
    assert int(tiled.ctx_mask.sum()) == 3 * c  # every copy brings its context along
    x_one = torch.randn(1, a, TINY.future_steps, 2, generator=torch.Generator().manual_seed(1))
    x = torch.cat([x_one] * 3, dim=1)[:, : 3 * a - 2]
    k = torch.tensor([40])
    with torch.no_grad():
        alone = model(x_one, k, collate([window]))
        copies = model(x, k, tiled)
    torch.testing.assert_close(copies[:, :a], alone, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(copies[:, a : 2 * a], alone, rtol=1e-4, atol=1e-5)


@pytest.mark.model
@pytest.mark.slow
def test_bench_times_a_guided_scenario_and_the_curves(tmp_path: Path) -> None:
    out = tmp_path / "bench"
    argv = ["bench", "--presets", "fast,ddim2-n1", "--episodes", "1", "--seeds", "0,3"]
    argv += ["--agents", "4,8", "--scenes", "1,2"]
    assert main([*argv, "--repeats", "1", "--out", str(out)]) == 0
    report = json.loads((out / "bench.json").read_text(), parse_constant=_no_constant)
    fast, cheap = report["scenarios"]  # each in its own process, the same episodes interleaved
    assert cheap["preset"] == "ddim2-n1" and cheap["peak_rss_mib"] > 0
    assert [(e["start_s"], e["seed"]) for e in cheap["episodes"]] == [
        (e["start_s"], e["seed"]) for e in fast["episodes"]
    ]
    episode, again = fast["episodes"]  # the one start, once per seed
    assert (episode["seed"], again["seed"]) == (0, 3) and episode["start_s"] == again["start_s"]
    steps = preset("fast").sampling.steps
    assert episode["seconds"] > 0 and episode["denoiser_calls"] == 20 * steps  # 20 re-plans × DDIM steps
    assert 0.0 <= episode["fail"] <= 1.0 and fast["peak_rss_mib"] > 0
    assert [c["agents"] for c in report["agents"]] == [4, 8]
    assert [b["scenes"] for b in report["batching"]] == [1, 2]
    assert (out / "agents.png").stat().st_size > 0
    assert "× faster than paper" in (out / "bench.md").read_text()


@pytest.mark.parametrize(
    "argv",
    [
        ["--presets", "warp"], ["--agents", "8,x"], ["--rule", "fly"], ["--episodes", "-1"],
        ["--seeds", "-1"], ["--spatial", "sparse"], ["--spatial", ","], ["--rounds", "0"],
    ],
)
def test_bench_mistakes_exit_2(argv: list[str], tmp_path: Path) -> None:
    assert main(["bench", *argv, "--out", str(tmp_path)]) == 2


def _no_constant(name: str) -> None:
    raise AssertionError(f"bench.json holds the bare constant {name}: not JSON")


def test_bench_json_is_strict_json(tmp_path: Path) -> None:
    """Undefined figures (no moving vehicle: real NaN; an infinite one) are null, never bare NaN."""
    episodes = [_episode(3.0, 0, 0.1, math.nan), _episode(4.0, 0, math.inf, 0.3)]
    result = PresetResult("fast", "", episodes, 1.0, 1)
    report = {"scenarios": [asdict(result)], "mean_real": result.mean("real"), "worst": -math.inf}
    path, _ = write_report(tmp_path / "bench", report, "# bench\n")
    stored = json.loads(path.read_text(), parse_constant=_no_constant)
    first, second = stored["scenarios"][0]["episodes"]
    assert first["real"] is None and first["fail"] == 0.1
    assert second["fail"] is None and second["real"] == 0.3
    assert stored["mean_real"] == 0.3 and stored["worst"] is None
    assert (tmp_path / "bench" / "bench.md").read_text() == "# bench\n"


def _episode(start_s: float, seed: int, fail: float, real: float) -> EpisodeTiming:
    return EpisodeTiming("scene-0103", start_s, seed, 12, 5, 1.0, 100, fail, 0.0, real, 0.2)


def test_quality_differences_are_paired_episode_by_episode() -> None:
    """By hand: fail differences +0.1, +0.3 on the shared episodes (the unshared one left out)."""
    paper = PresetResult("paper", "", [_episode(3.0, 0, 0.1, 0.4), _episode(4.0, 0, 0.2, 0.4)], 1.0, 1)
    episodes = [_episode(3.0, 0, 0.2, 0.5), _episode(4.0, 0, 0.5, 0.5), _episode(5.0, 0, 0.9, 0.5)]
    fast = PresetResult("fast", "", episodes, 1.0, 1)
    diff, se = paired_difference(fast, paper, "fail")
    assert diff == pytest.approx(0.2) and se == pytest.approx(0.1)  # s.d. 0.1414 / sqrt(2)
    table = scenario_table([paper, fast])
    assert "+0.200 ± 0.100" in table and "+25 %" in table  # real 0.5 against 0.4


@pytest.mark.parametrize(
    ("name", "sampling", "guidance"),
    [
        ("ddim@99.75.40.0-n2-lr0.9", SamplingConfig("ddim", 4, 2, (99, 75, 40, 0)), GuidanceConfig(1, 0.9)),
        ("ddim6-n2-lr0.9", SamplingConfig.evenly("ddim", 6, 2), GuidanceConfig(1, 0.9)),
        ("ddim5-n2-lr0.9", SamplingConfig.evenly("ddim", 5, 2), GuidanceConfig(1, 0.9)),
        ("ddim5-n2-lr0.9-r0", SamplingConfig.evenly("ddim", 5, 2), GuidanceConfig(1, 0.9, min_radius=0)),
        (
            "ddpm-n5-scene-r0",
            SamplingConfig.evenly("ddpm", 100, 5),
            GuidanceConfig(1, 0.3, compose=False, min_radius=0),
        ),
        ("ddpm-n5", SamplingConfig.evenly("ddpm", 100, 5), GuidanceConfig(1, 0.3, compose=True)),
        ("ddim10", SamplingConfig.evenly("ddim", 10, 4), GuidanceConfig(1, 0.3)),
        ("ddim4-w2-lr0.5-from80", SamplingConfig.evenly("ddim", 4, 4), GuidanceConfig(2, 0.5, 80)),
        ("ddim20-e1-n2", SamplingConfig.evenly("ddim", 20, 2, eta=1.0), GuidanceConfig(1, 0.3)),
        ("ddim6-e0.5", SamplingConfig.evenly("ddim", 6, 4, eta=0.5), GuidanceConfig(1, 0.3)),
    ],
)
def test_spelled_out_presets(name: str, sampling: SamplingConfig, guidance: GuidanceConfig) -> None:
    chosen = preset(name)
    assert (chosen.sampling, chosen.guidance) == (sampling, guidance)
    if name in ("ddim6-n2-lr0.9", "ddpm-n5-scene-r0"):  # the fast and the paper preset
        named = preset("fast" if name.startswith("ddim") else "paper")
        assert (named.sampling, named.guidance) == (sampling, guidance)


def test_presets_with_the_plan_stages() -> None:
    """``-stages`` runs every plan stage beyond the paper; without it a preset times the sampler alone."""
    assert preset("fast").stages == StageConfig.off() and preset("ddim6-n2").stages == StageConfig.off()
    with_stages = preset("fast-stages")
    assert with_stages.stages == StageConfig() and with_stages.sampling == preset("fast").sampling
    assert preset("ddim6-n2-lr0.9-stages").stages.stages == ("steer", "cap", "brake")


@pytest.mark.parametrize(
    "name",
    [
        "warp", "ddim", "ddim0", "ddim4-stages-stages", "paper-stages-stages",
        "ddim5-n0", "ddim5-n2-n3", "ddim5-x2", "ddim5-w-1", "ddim@99",
        "ddim4-scene-scene", "ddim4-scene2", "ddim6-e1.5", "ddpm-e1",
    ],
)
def test_unknown_presets_are_clear_errors(name: str) -> None:
    with pytest.raises(ValueError, match="sampler preset"):
        preset(name)


@pytest.mark.parametrize("mode", ["groups", "dense"])
def test_bench_spatial_flag_times_the_curve_by_groups(mode: str, tmp_path: Path) -> None:
    """``--spatial groups`` runs the per-agent curve by neighbourhood groups: 24 agents tiled from
    a real window lie in several groups 300 m apart; ``dense`` is one dense attention."""
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "tiny", Denoiser(TINY), TINY, {})
    out = tmp_path / "bench"
    argv = ["bench", "--episodes", "0", "--scenes", "", "--agents", "4,24", "--repeats", "1"]
    argv += ["--checkpoint", str(tmp_path / "tiny"), "--spatial", mode, "--out", str(out)]
    assert main(argv) == 0
    report = json.loads((out / "bench.json").read_text(), parse_constant=_no_constant)
    assert report["spatial"] == [mode]
    groups = [c["groups"] for c in report["agents"]]
    assert groups[1] > 1 if mode == "groups" else groups == [1, 1]
    assert ("by neighbourhood groups" in (out / "bench.md").read_text()) == (mode == "groups")


def test_bench_times_dense_and_gathered_alternating(tmp_path: Path) -> None:
    """``--spatial dense,gathered --rounds 2``: each agent count timed both ways, the gathered one over
    each agent's neighbours only (far fewer than the K keys once the window is tiled)."""
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "tiny", Denoiser(TINY), TINY, {})
    out = tmp_path / "bench"
    argv = ["bench", "--episodes", "0", "--scenes", "", "--agents", "4,24", "--repeats", "1"]
    argv += ["--checkpoint", str(tmp_path / "tiny"), "--spatial", "dense,gathered", "--rounds", "2"]
    assert main([*argv, "--out", str(out)]) == 0
    report = json.loads((out / "bench.json").read_text(), parse_constant=_no_constant)
    assert report["spatial"] == ["dense", "gathered"]
    rows = [(c["agents"], c["spatial"], c["neighbours"] > 0) for c in report["agents"]]
    assert rows == [(4, "dense", False), (4, "gathered", True), (24, "dense", False), (24, "gathered", True)]
    assert all(c["ms"] > 0 for c in report["agents"])
    assert "gathered per agent; 2 rounds" in (out / "bench.md").read_text()
