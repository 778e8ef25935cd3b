"""The cosine schedule and the samplers: one shared contract that DDPM and DDIM both pass."""

from __future__ import annotations

import math

import pytest
import torch

from ctgpp.diffusion import CosineSchedule, DDIMSampler, DDPMSampler, Sampler, sample

SHAPES = [(7,), (2, 5, 4), (1, 3, 52, 2)]


def test_cosine_schedule_matches_the_formula() -> None:
    sched = CosineSchedule(100, 0.008)

    def f(t: float) -> float:
        return math.cos((t / 100 + 0.008) / 1.008 * math.pi / 2) ** 2

    for k in (0, 10, 50, 90):
        assert float(sched.alphas_cumprod[k]) == pytest.approx(f(k + 1) / f(0), rel=1e-9)
    assert torch.all(torch.diff(sched.alphas_cumprod) < 0)
    assert float(sched.betas.max()) <= 0.999
    assert float(sched.alphas_cumprod[-1]) < 1e-4


def test_add_noise_moments_match_alphas_cumprod() -> None:
    sched = CosineSchedule()
    gen = torch.Generator().manual_seed(0)
    x0 = torch.full((200_000,), 1.5, dtype=torch.float64)
    for k in (0, 30, 70, 99):
        noise = torch.randn(x0.shape, generator=gen, dtype=torch.float64)
        x_k = sched.add_noise(x0, noise, k)
        abar = float(sched.alphas_cumprod[k])
        assert float(x_k.mean()) == pytest.approx(1.5 * math.sqrt(abar), abs=0.01)
        assert float(x_k.var()) == pytest.approx(1 - abar, abs=0.01 * max(1 - abar, 0.01) + 1e-4)


def test_add_noise_per_scene_steps_broadcast() -> None:
    sched = CosineSchedule()
    x0, noise = torch.ones(3, 4, 2), torch.zeros(3, 4, 2)
    out = sched.add_noise(x0, noise, torch.tensor([0, 50, 99]))
    for s, k in enumerate((0, 50, 99)):
        assert torch.allclose(out[s], torch.full((4, 2), math.sqrt(float(sched.alphas_cumprod[k]))))


def test_posterior_is_the_bayes_posterior_on_a_hand_case() -> None:
    """q(x_{k−1} | x_k, x_0) ∝ N(x_k; √α_k x_{k−1}, β_k) · N(x_{k−1}; √ᾱ_{k−1} x_0, 1 − ᾱ_{k−1})."""
    sched = CosineSchedule(10)
    k, x0, x_k = 4, torch.tensor([0.7]), torch.tensor([-1.2])
    beta, alpha = float(sched.betas[k]), float(sched.alphas[k])
    abar_prev = float(sched.alphas_cumprod[k - 1])
    precision = alpha / beta + 1 / (1 - abar_prev)
    expected_mean = (
        math.sqrt(alpha) / beta * -1.2 + math.sqrt(abar_prev) / (1 - abar_prev) * 0.7
    ) / precision
    mean, var, log_var = sched.posterior_mean_variance(x0, x_k, k)
    assert float(mean) == pytest.approx(expected_mean, rel=1e-6)
    assert float(var) == pytest.approx(1 / precision, rel=1e-6)
    assert float(log_var) == pytest.approx(math.log(1 / precision), rel=1e-6)


class SamplerContract:
    """What every sampler must do. Subclasses provide ``make`` and ``start``."""

    start: int = 99

    def make(self) -> Sampler:
        raise NotImplementedError

    def test_timesteps_strictly_decrease_to_zero(self) -> None:
        steps = self.make().timesteps
        assert steps[0] == self.start and steps[-1] == 0
        assert all(a > b for a, b in zip(steps, steps[1:], strict=False))

    @pytest.mark.parametrize("shape", SHAPES)
    def test_perfect_denoiser_converges_to_x0(self, shape: tuple[int, ...]) -> None:
        target = torch.linspace(-2.0, 2.0, math.prod(shape)).reshape(shape)
        gen = torch.Generator().manual_seed(1)
        out = sample(lambda x, k: target, shape, self.make(), gen)
        assert out.shape == shape
        assert float((out - target).abs().max()) < 1e-3

    @pytest.mark.parametrize("shape", SHAPES)
    def test_step_and_mean_std_preserve_shapes(self, shape: tuple[int, ...]) -> None:
        sampler = self.make()
        x_k, x0 = torch.randn(shape), torch.randn(shape)
        for k in sampler.timesteps[:2] + sampler.timesteps[-1:]:
            mean, std = sampler.prev_mean_std(x0, x_k, k)
            assert mean.shape == shape and std.shape == shape
            assert torch.all(std >= 0)
            assert sampler.step(x0, x_k, k, torch.Generator().manual_seed(0)).shape == shape

    def test_last_step_adds_no_noise(self) -> None:
        _, std = self.make().prev_mean_std(torch.zeros(4), torch.ones(4), 0)
        assert torch.all(std == 0)

    def test_seed_makes_samples_reproducible(self) -> None:
        def shrink(x: torch.Tensor, k: int) -> torch.Tensor:
            return 0.5 * x

        runs = [sample(shrink, (4, 3), self.make(), torch.Generator().manual_seed(s)) for s in (7, 7, 8)]
        assert torch.equal(runs[0], runs[1])
        assert not torch.allclose(runs[0], runs[2])

    def test_clip_x0_bounds_the_prediction(self) -> None:
        out = sample(
            lambda x, k: torch.full_like(x, 5.0), (3, 2), self.make(), torch.Generator(), clip_x0=(-1, 1)
        )
        assert torch.allclose(out, torch.ones(3, 2), atol=1e-3)


class TestDDPM(SamplerContract):
    def make(self) -> Sampler:
        return DDPMSampler(CosineSchedule())

    def test_visits_every_step_with_the_posterior(self) -> None:
        sampler = self.make()
        assert sampler.timesteps == list(range(99, -1, -1))
        x0, x_k = torch.randn(5), torch.randn(5)
        mean, std = sampler.prev_mean_std(x0, x_k, 40)
        post_mean, post_var, _ = sampler.schedule.posterior_mean_variance(x0, x_k, 40)
        assert torch.allclose(mean, post_mean) and torch.allclose(std**2, post_var.float())


class TestDDIM(SamplerContract):
    def make(self) -> Sampler:
        return DDIMSampler(CosineSchedule(), num_steps=10, eta=0.0)

    def test_deterministic_with_eta_zero(self) -> None:
        sampler = self.make()
        assert len(sampler.timesteps) == 10
        _, std = sampler.prev_mean_std(torch.zeros(3), torch.ones(3), sampler.timesteps[0])
        assert torch.all(std == 0)

    def test_all_steps_with_eta_one_equal_ddpm(self) -> None:
        sched = CosineSchedule()
        ddim, ddpm = DDIMSampler(sched, num_steps=100, eta=1.0), DDPMSampler(sched)
        assert ddim.timesteps == ddpm.timesteps
        x0, x_k = torch.randn(6, dtype=torch.float64), torch.randn(6, dtype=torch.float64)
        for k in (99, 60, 20, 1):
            m1, s1 = ddim.prev_mean_std(x0, x_k, k)
            m2, s2 = ddpm.prev_mean_std(x0, x_k, k)
            assert torch.allclose(m1, m2, atol=1e-6) and torch.allclose(s1, s2, atol=1e-6)

    def test_the_policy_config_passes_eta_to_the_sampler(self) -> None:
        from ctgpp.policies.diffusion import SamplingConfig

        made = SamplingConfig.evenly("ddim", 20, 2, eta=1.0).make(CosineSchedule())
        assert isinstance(made, DDIMSampler) and made.eta == 1.0 and len(made.timesteps) == 20
        _, std = made.prev_mean_std(torch.zeros(3), torch.ones(3), made.timesteps[1])
        assert torch.all(std > 0)
        with pytest.raises(ValueError, match="eta"):
            SamplingConfig(eta=1.5)
        with pytest.raises(ValueError, match="DDPM's is fixed"):
            SamplingConfig("ddpm", eta=0.5)

    def test_rejects_unknown_steps(self) -> None:
        with pytest.raises(ValueError):
            self.make().prev_mean_std(torch.zeros(2), torch.zeros(2), 98)
        with pytest.raises(ValueError):
            DDIMSampler(CosineSchedule(), num_steps=0)


class TestDDIMGrid(SamplerContract):
    """DDIM over given timesteps (99, 75, 40, 0: denser where the noise is high)."""

    def make(self) -> Sampler:
        return DDIMSampler(CosineSchedule(), num_steps=4, timesteps=(99, 75, 40, 0))

    def test_visits_the_given_steps_with_the_ddim_update(self) -> None:
        sampler = self.make()
        assert sampler.timesteps == [99, 75, 40, 0]
        abar = sampler.schedule.alphas_cumprod
        x0, x_k = torch.randn(5, dtype=torch.float64), torch.randn(5, dtype=torch.float64)
        mean, _ = sampler.prev_mean_std(x0, x_k, 75)  # 75 -> 40 by hand: x_40 = √ᾱ40 x0 + √(1 − ᾱ40) ε
        eps = (x_k - abar[75].sqrt() * x0) / (1 - abar[75]).sqrt()
        assert torch.allclose(mean, abar[40].sqrt() * x0 + (1 - abar[40]).sqrt() * eps)
        with pytest.raises(ValueError):
            sampler.prev_mean_std(x0, x_k, 66)  # a step of the evenly spread grid, not of this one

    def test_the_even_grid_given_is_the_default_grid(self) -> None:
        sched = CosineSchedule()
        even = DDIMSampler(sched, num_steps=4)
        given = DDIMSampler(sched, num_steps=4, timesteps=even.timesteps)
        runs = [
            sample(lambda x, k: 0.5 * x, (3, 2), s, torch.Generator().manual_seed(3))
            for s in (even, given)
        ]
        assert torch.equal(runs[0], runs[1])

    @pytest.mark.parametrize(
        "grid",
        [(99, 75, 40), (98, 75, 40, 0), (99, 40, 75, 0), (99, 75, 75, 0), (99, 75, 40, -1), (120, 75, 40, 0)],
    )
    def test_rejects_grids_that_are_not_a_falling_path_from_noise(self, grid: tuple[int, ...]) -> None:
        with pytest.raises(ValueError, match="timesteps"):
            DDIMSampler(CosineSchedule(), num_steps=4, timesteps=grid)
