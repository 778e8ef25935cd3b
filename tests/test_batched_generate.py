"""Batched simulation on one machine (issue 37, item 2): several seeds of one scene start simulated
together, one denoiser call per diffusion step for all of them, give exactly the scenarios of the
seeds simulated one at a time.

Exactly, not to a tolerance: each episode's noise comes from its own generator, and the batched
forward pass computes every scene's rows bit for bit as the scene alone. The one layer that did not
(the step embedding's MLP: a matrix product of a few rows comes out differently in the last bit with
the number of rows, 2e-7 in x̂_0 at the first call) runs per scene (``Denoiser.forward(step_rows=)``).
Without that the first x̂_0 differed by 4e-7 and the closed loop, which picks samples by their loss,
turned it into rollouts 0.7–6 m apart after 10 s with other metrics, so a tolerance would not do.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from ctgpp.api.episode import load_scene, policy_factory, simulate
from ctgpp.api.result import Result
from ctgpp.cli.main import main
from ctgpp.data.batch import collate
from ctgpp.diffusion.guided import GuidanceConfig, guidance_radii, guided_step
from ctgpp.diffusion.schedule import randn_like
from ctgpp.policies.diffusion import DiffusionPolicy
from ctgpp.policies.pooling import SamplingPool
from ctgpp.policies.stages.lockstep import SamplingJob, sample_jobs
from ctgpp.policies.stages.sampling import model_window
from ctgpp.sim.closed_loop import initial_observation

SENTENCE = "vehicle 1 should collide with vehicle 2"
SCENE = "scene-0103"


def test_the_pool_returns_every_episode_in_order_and_raises_the_first_error() -> None:
    assert SamplingPool().run([lambda: 1, lambda: 2, lambda: 3]) == [1, 2, 3]

    def fails(what: str) -> int:
        raise ValueError(what)

    with pytest.raises(ValueError, match="first"):
        SamplingPool().run([lambda: 1, lambda: fails("first"), lambda: fails("second")])


def _job(policy: DiffusionPolicy, scene_id: str, seed: int, fail_at: int | None = None) -> SamplingJob:
    """The unguided sampling of every vehicle of ``scene_id`` at 3 s, N = 2, its noise
    from a generator of ``seed``; its step raises at diffusion step ``fail_at``."""
    obs = initial_observation(load_scene(scene_id), 3.0)
    window = model_window(obs, np.ones(len(obs.controlled), dtype=bool), policy.model.config)
    gen = torch.Generator().manual_seed(seed)
    sampler, config = policy.sampler, GuidanceConfig()
    radii = guidance_radii(sampler, config)

    def advance(x0: torch.Tensor, x: torch.Tensor, k: int) -> torch.Tensor:
        if k == fail_at:
            raise RuntimeError(f"step {k}")
        return guided_step(x0, x, k, sampler, None, radii[k], config, gen)

    start = randn_like(torch.empty(2, window.num_agents, policy.model.config.future_steps, 2), gen)
    return SamplingJob(policy.model, window, collate([window]), tuple(sampler.timesteps), start, advance)


@pytest.mark.model
def test_jobs_of_scenes_with_other_vehicle_counts_sample_as_alone() -> None:
    """Two scenes of 12 and 33 vehicles in one call per step, the first padded with 21 masked
    agents: each job's samples are those it gives alone up to round-off, 1.2e-6 at most here (in
    normalized actions up to 3); the padded agents lengthen the softmax sums of the spatial
    attention, which then come out differently in the last bit (seeds of one scene start, as
    ``generate`` pools them, have the same vehicles: nothing is padded and they agree exactly, the
    test below). A job whose own step fails gets its error; the other's samples stay as they were."""
    policy = policy_factory()("ctgpp")
    assert isinstance(policy, DiffusionPolicy)
    scenes = (SCENE, "scene-0916")
    alone = [sample_jobs([_job(policy, scene, seed)])[0] for seed, scene in enumerate(scenes)]
    jobs = [_job(policy, scene, seed) for seed, scene in enumerate(scenes)]
    assert jobs[0].start.shape[1] != jobs[1].start.shape[1]
    together = sample_jobs(jobs)
    for a, b in zip(alone, together, strict=True):
        assert isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)
        torch.testing.assert_close(a, b, rtol=0.0, atol=1e-5)
    assert not torch.equal(alone[1], torch.zeros_like(alone[1]))
    fail_at = policy.sampler.timesteps[2]
    failing = sample_jobs([_job(policy, SCENE, 0), _job(policy, scenes[1], 1, fail_at=fail_at)])
    assert isinstance(failing[1], RuntimeError) and str(failing[1]) == f"step {fail_at}"
    assert isinstance(failing[0], torch.Tensor) and torch.equal(failing[0], together[0])


def _same(a: Result, b: Result) -> None:
    """Two episodes' results agree bit for bit: the rollout, every metric, the verdict, the stages."""
    for name in ("xy", "yaw", "speed", "valid"):
        assert np.array_equal(getattr(a.rollout.sim, name), getattr(b.rollout.sim, name)), name
    assert a.metrics.keys() == b.metrics.keys()
    for name, value in a.metrics.items():
        other = b.metrics[name]
        assert value == other or (math.isnan(value) and math.isnan(other)), name
    assert a.query == b.query and a.events == b.events
    assert a.rollout.stage_changes == b.rollout.stage_changes


@pytest.mark.model
def test_three_seeds_together_are_the_three_seeds_one_at_a_time() -> None:
    """scene-0103, guarded and with every stage (the defaults), the query steering vehicles 1 and 2,
    10 s: 3 seeds through one pool sample each re-plan in one group of 3 (one denoiser call per step
    for all, a third of the calls), and every result is the one-at-a-time result bit for bit."""
    scene, factory = load_scene(SCENE), policy_factory()
    seeds = (0, 1, 2)
    forwards: list[int] = []  # the rows of every denoiser call

    def one(seed: int) -> Result:
        return simulate(scene, SENTENCE, (), "ctgpp", seed, policies=factory)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as generate's workers
    try:
        alone = [one(seed) for seed in seeds]
        hook = factory.model.register_forward_hook(lambda m, args, out: forwards.append(int(out.shape[0])))
        pool = SamplingPool()
        try:
            together = pool.run([lambda seed=seed: one(seed) for seed in seeds])
        finally:
            hook.remove()
    finally:
        torch.set_num_threads(threads)
    assert pool.groups == [3] * 20  # 10 s, a re-plan every 0.5 s, every one sampled for the 3 at once
    assert forwards == [3 * 2] * (20 * 6)  # 6 DDIM steps per re-plan, each 3 seeds × 2 samples
    assert [r.query["satisfied"] for r in together] == [r.query["satisfied"] for r in alone]
    for a, b in zip(alone, together, strict=True):
        _same(a, b)


def _library(out: Path) -> tuple[list[dict], dict[str, bytes]]:
    """The index's rows without their timings, and every scenario file's bytes by name."""
    table = pq.read_table(out / "index.parquet").to_pylist()
    rows = [{k: v for k, v in row.items() if k != "seconds"} for row in table]
    return rows, {p.name: p.read_bytes() for p in sorted((out / "scenarios").iterdir())}


@pytest.mark.model
def test_generate_with_seeds_together_writes_the_library_of_one_at_a_time(tmp_path: Path) -> None:
    """``generate --batch-seeds 3`` and ``--batch-seeds 1`` write the same index rows (but timings)
    and the same ScenarioNet files, byte for byte; a batch of 0 is a one-line error."""
    common = ["generate", SENTENCE, "--scene", SCENE, "--seeds", "0-2", "--duration", "3"]
    assert main([*common, "--batch-seeds", "3", "--out", str(tmp_path / "together")]) == 0
    assert main([*common, "--batch-seeds", "1", "--out", str(tmp_path / "alone")]) == 0
    together, alone = _library(tmp_path / "together"), _library(tmp_path / "alone")
    assert [row["seed"] for row in together[0]] == [0, 1, 2]
    assert together == alone
    assert main([*common, "--batch-seeds", "0", "--out", str(tmp_path / "none")]) == 2
