"""The sampling of several re-plans in lockstep: one denoiser call per diffusion step for all of them.

A :class:`SamplingJob` is one re-plan's guided sampling (Algorithm 2) made ready by the sample stage
(:class:`~ctgpp.policies.stages.sampling.GuidedSampling`): its model window, its first noise, already
drawn from the episode's own generator, and how it advances from x_k to x_{k−1} given the denoiser's
x̂_0 (:func:`~ctgpp.diffusion.guided.guided_step`: its own sampler, guidance loss and generator).
:func:`sample_jobs` runs jobs that share a model and a grid of timesteps together: their windows
collated into one batch of S scenes (agents padded with masked zeros), the context encoded once, and
at every timestep one forward pass over the S·N samples; each job then advances apart. Each job
draws exactly the noise it draws alone, in the same order, so a job's samples are those of the job
alone up to the round-off of the batched arithmetic (``tests/test_batched_generate.py`` measures it).

Who runs a thread's jobs: this thread's pool when one is set (:func:`pooled_by`,
:mod:`ctgpp.policies.pooling`), else :func:`sample_jobs` on the job alone (:func:`run_job`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor

from ctgpp.data.batch import SceneBatch, collate
from ctgpp.data.windows import SceneWindow
from ctgpp.model.denoiser import Denoiser

# (x̂_0 (N, M, F, 2), x_k (N, M, F, 2), k) -> x_{k−1}: a job's own sampler step, guidance and noise
Advance = Callable[[Tensor, Tensor, int], Tensor]


@dataclass(frozen=True, eq=False)
class SamplingJob:
    """One re-plan's sampling of M moving vehicles, N samples each.

    model: the denoiser. window: the scene window it samples in; batch: that window alone (1, M, ...).
    timesteps: the diffusion steps visited, first to last. start: (N, M, F, 2) x_K, the first noise.
    advance: the step from x_k to x_{k−1} (:data:`Advance`).
    """

    model: Denoiser
    window: SceneWindow
    batch: SceneBatch
    timesteps: tuple[int, ...]
    start: Tensor
    advance: Advance

    @property
    def num_samples(self) -> int:
        return int(self.start.shape[0])

    def pool_key(self) -> tuple[int, tuple[int, ...], int]:
        """Jobs with the same key can share a denoiser call: the same model object, timesteps and N."""
        return id(self.model), self.timesteps, self.num_samples


@torch.no_grad()
def sample_jobs(jobs: Sequence[SamplingJob]) -> list[Tensor | Exception]:
    """The clean samples x_0 (N, M, F, 2) of each job (of one :meth:`SamplingJob.pool_key`), or the
    exception its own step raised (its guidance loss, say): that job stops there, the others go on
    with the same batch."""
    if not jobs:
        return []
    model, n = jobs[0].model, jobs[0].num_samples
    if len({job.pool_key() for job in jobs}) > 1:
        raise ValueError("sample_jobs: the jobs need one model, one grid of timesteps and one N")
    batch = jobs[0].batch if len(jobs) == 1 else collate([job.window for job in jobs])
    context = model.encode_context(batch).expand(n)  # (S*N, ...) rows, scene-major
    agents = batch.num_agents
    xs = [job.start for job in jobs]
    out: list[Tensor | Exception | None] = [None] * len(jobs)
    for k in jobs[0].timesteps:
        if all(o is not None for o in out):
            break  # every job has failed
        x = xs[0] if len(jobs) == 1 else torch.cat([_pad_agents(x, agents) for x in xs])  # (S*N, A, F, 2)
        with torch.inference_mode():  # no autograd bookkeeping at all
            steps = torch.full((x.shape[0],), k, dtype=torch.long)
            pred = model(x, steps, batch, context) if len(jobs) == 1 else model(
                x, steps, batch, context, step_rows=n)  # each job's rows as when alone
        for i, job in enumerate(jobs):
            if out[i] is not None:
                continue  # failed: its rows ride along unchanged
            m = job.start.shape[1]
            x0_pred = pred[i * n:(i + 1) * n, :m].clone()  # a normal tensor, which guidance may use
            try:
                xs[i] = job.advance(x0_pred, xs[i], k)
            except Exception as err:  # noqa: BLE001 - the job's own failure, handed to its episode
                out[i] = err
    return [o if o is not None else x for o, x in zip(out, xs, strict=True)]


def _pad_agents(x: Tensor, agents: int) -> Tensor:
    """(N, M, F, 2) -> (N, agents, F, 2), the added agents zero (the batch masks them)."""
    if x.shape[1] == agents:
        return x
    return torch.cat([x, x.new_zeros(x.shape[0], agents - x.shape[1], *x.shape[2:])], dim=1)


# this thread's pool: takes a job and returns its x_0 once sampled with the other episodes' jobs
_POOL = threading.local()


@contextmanager
def pooled_by(submit: Callable[[SamplingJob], Tensor]) -> Iterator[None]:
    """Within the block, this thread's jobs go to ``submit`` (a pool's) instead of running alone."""
    before = getattr(_POOL, "submit", None)
    _POOL.submit = submit
    try:
        yield
    finally:
        _POOL.submit = before


def run_job(job: SamplingJob) -> Tensor:
    """The job's x_0: through this thread's pool when one is set, else sampled alone."""
    submit: Callable[[SamplingJob], Tensor] | None = getattr(_POOL, "submit", None)
    if submit is not None:
        return submit(job)
    (result,) = sample_jobs([job])
    if isinstance(result, Exception):
        raise result
    return result


__all__ = ["Advance", "SamplingJob", "pooled_by", "run_job", "sample_jobs"]
