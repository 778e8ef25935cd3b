"""What running a language model's loss in its limited worker costs per closed-loop episode.

    python scripts/loss_overhead.py [--scene scene-0553] [--seeds 0,1,2] [--queries 2] [--ways ...]
    python scripts/loss_overhead.py --calls 5 [--calls-per-replan 7]

The same 10-s guided episodes (the default ``fast`` sampler, realism guards off so that only the
query's loss steers) are simulated four ways, interleaved episode by episode (the order rotating
with the seed) so that the host's drift falls on all alike: unguided; the offline compiler's loss
for the query; the language model's program loaded in the main process (what ctgpp did before
issue 16, no limits); and the same program as :class:`ctgpp.language.llm.remote.RemoteLoss`, every call
made in the limited worker process (what ``ctgpp simulate`` does now). Programs are written the
paper's way (../shared/docs/LLM-API.md). Prints a markdown table: wall seconds per episode (median,
mean), CPU seconds per episode (the main process and, for the worker's way, the worker process: the
figure a busy shared machine does not distort), the loss calls per episode, and the worker's cost
over the in-process program per episode and per call; and the one-time cost of starting the worker
and loading the program into it.

With ``--calls R`` it times only the loss's share of an episode, R times per way, alternating: the
calls one 10-s episode makes (20 re-plans, each with a new batch, ``--calls-per-replan`` calls of
forward and gradient on x (B, N = 2, T, 6) of the scene's logged future) — the figure that the
denoiser's cost and a busy machine's noise do not swamp.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from ctgpp.data.catalog import Catalog
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import GuidanceBatch, build_guidance_batch
from ctgpp.guidance.guards import GuardConfig
from ctgpp.language.compiler import compile_query
from ctgpp.language.llm.remote import RemoteLoss
from ctgpp.language.query import probe_x
from ctgpp.language.sandbox.checks import LossChecker
from ctgpp.language.sandbox.program import load_loss_class
from ctgpp.policies.factory import make_policy
from ctgpp.policies.presets import preset
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import episode_bounds, initial_observation, simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout's tests/, for the programs
from tests.support import model_programs  # noqa: E402

# query for the offline compiler -> the language model's program for it, the paper's way: the replies
# tests/test_llm_steering.py runs through ctgpp simulate on the same scene (tests/support/model_programs.py)
QUERIES = {
    "vehicle 18 should stay at least 25 m behind vehicle 17": model_programs.STAY_BEHIND,
    "vehicle 17 should change to the right lane": model_programs.RIGHT_LANE,
}
WAYS = ("unguided", "compiler", "in-process", "worker")


@dataclass
class Way:
    """The episodes of one way of steering: seconds and loss calls per episode."""

    name: str
    seconds: list[float] = field(default_factory=list)
    cpu_seconds: list[float] = field(default_factory=list)
    calls: list[int] = field(default_factory=list)


def cpu_seconds(pid: int | None) -> float:
    """CPU seconds (user + system) process ``pid`` has used so far; 0 for no process."""
    if pid is None:
        return 0.0
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def episode(
    scene: Scene, start_s: float, seed: int, loss: GuidanceLoss | None, worker: int | None
) -> tuple[float, float, int]:
    """Wall seconds of one guided closed-loop episode with the fast sampler, guards off, the CPU seconds
    of this process and of process ``worker`` (None: none), and the calls the sampler made to ``loss``."""
    fast = preset("fast")
    policy = make_policy("ctgpp", None, fast.sampling, loss, fast.guidance, GuardConfig.off())
    calls = [0]

    def count(*_: object) -> None:
        calls[0] += 1

    hook = None if loss is None else loss.register_forward_pre_hook(count)
    began, cpu = time.perf_counter(), time.process_time() + cpu_seconds(worker)
    simulate(scene, policy, start_s, seed=seed)
    seconds, cpu = time.perf_counter() - began, time.process_time() + cpu_seconds(worker) - cpu
    if hook is not None:
        hook.remove()
    return seconds, cpu, calls[0]


def loss_of(way: str, query: str, code: str, n_vehicles: int, remote: RemoteLoss) -> GuidanceLoss | None:
    """The loss that steers an episode of ``way`` (a fresh one but for the worker's, loaded once)."""
    if way == "compiler":
        return compile_query(query, n_vehicles).loss
    if way == "in-process":
        return load_loss_class(code)()
    return remote if way == "worker" else None


def episode_of_calls(
    batch: GuidanceBatch, x0: Tensor, loss: GuidanceLoss, per_replan: int, worker: int | None
) -> tuple[float, float]:
    """Wall and CPU seconds (this process and process ``worker``) of the loss calls of one episode:
    20 re-plans, each with a new batch (as the sampler's), ``per_replan`` calls of cost and gradient."""
    gen = torch.Generator().manual_seed(0)
    began, cpu = time.perf_counter(), time.process_time() + cpu_seconds(worker)
    for _ in range(20):
        fresh = replace(batch, memo={})  # a new batch object: the worker is sent it again
        for _ in range(per_replan):
            x = (x0 + 0.1 * torch.randn(x0.shape, generator=gen)).requires_grad_()
            (grad,) = torch.autograd.grad(loss(x, fresh).sum(), x)
    return time.perf_counter() - began, time.process_time() + cpu_seconds(worker) - cpu


def time_calls(scene: Scene, start_s: float, code: str, remote: RemoteLoss, pid: int | None, args) -> str:
    """The ``--calls`` measurement, as markdown."""
    obs = initial_observation(scene, start_s)
    batch = build_guidance_batch(obs)
    x0 = probe_x(obs).repeat(1, preset("fast").sampling.num_samples, 1, 1)  # (B, 1, T, 6) -> (B, N, T, 6)
    losses = {"in-process": (load_loss_class(code)(), None), "worker": (remote, pid)}
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in losses}
    for k in range(args.calls):
        for name in list(losses) if k % 2 == 0 else list(losses)[::-1]:
            loss, worker = losses[name]
            times[name].append(episode_of_calls(batch, x0, loss, args.calls_per_replan, worker))
            wall, cpu = times[name][-1]
            print(f"repeat {k} {name}: {wall:.3f} s, CPU {cpu:.3f} s", file=sys.stderr)
    calls = 20 * args.calls_per_replan
    lines = [
        f"The loss calls of one 10-s episode ({calls}: 20 re-plans x {args.calls_per_replan}, each a new "
        f"batch; x {tuple(x0.shape)}), {args.calls} times per way, alternating ({scene.id} from "
        f"{start_s:g} s).",
        "",
        "| way | median wall s / episode | median CPU s / episode | wall ms / call |",
        "|---|---:|---:|---:|",
    ]
    for name, rows in times.items():
        wall = statistics.median(r[0] for r in rows)
        cpu = statistics.median(r[1] for r in rows)
        lines.append(f"| {name} | {wall:.3f} | {cpu:.3f} | {1000 * wall / calls:.2f} |")
    extra = [w[0] - i[0] for w, i in zip(times["worker"], times["in-process"], strict=True)]
    lines += [
        "",
        f"worker − in-process: {statistics.median(extra):+.3f} s of wall time per episode (median).",
    ]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default=model_programs.SCENE, help="scene id of the embedded data")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds, one episode each per query")
    parser.add_argument("--queries", type=int, default=len(QUERIES), help="how many of the queries, in order")
    parser.add_argument(
        "--ways", default=",".join(WAYS), help=f"comma-separated, of {', '.join(WAYS)}, run in this order"
    )
    parser.add_argument("--threads", type=int, default=2, help="torch threads of the main process")
    parser.add_argument("--calls", type=int, default=0, metavar="R", help="time only the loss calls, R times")
    parser.add_argument(
        "--calls-per-replan", type=int, default=7, help="with --calls (7: the fast sampler's)"
    )
    args = parser.parse_args()
    chosen = tuple(dict.fromkeys(args.ways.split(",")))  # in the order given
    if not {"in-process", "worker"} <= set(chosen) <= set(WAYS) or not 1 <= args.queries <= len(QUERIES):
        parser.error(f"--ways must include in-process and worker; --queries is 1 to {len(QUERIES)}")
    queries = dict(list(QUERIES.items())[: args.queries])
    torch.set_num_threads(args.threads)
    scene = Catalog.open().load(args.scene)
    start = episode_bounds(scene)[0]
    n_vehicles = len(initial_observation(scene, start).controlled)
    seeds = [int(s) for s in args.seeds.split(",")]
    ways = {name: Way(name) for name in chosen}
    setup_s: list[float] = []
    for query, code in queries.items():
        began = time.perf_counter()
        checker = LossChecker()
        checker.start()
        remote = RemoteLoss(code, checker)  # starts the worker, loads the program there
        setup_s.append(time.perf_counter() - began)
        if args.calls:
            print(time_calls(scene, start, code, remote, checker.pid, args))
            print(f"Starting the worker and loading the program: {setup_s[-1]:.2f} s.")
            remote.close()
            continue
        for k, seed in enumerate(seeds):
            for name in chosen[k % len(chosen) :] + chosen[: k % len(chosen)]:  # the order rotates
                loss = loss_of(name, query, code, n_vehicles, remote)
                pid = checker.pid if name == "worker" else None
                seconds, cpu, calls = episode(scene, start, seed, loss, pid)
                ways[name].seconds.append(seconds)
                ways[name].cpu_seconds.append(cpu)
                ways[name].calls.append(calls)
                line = f"{query!r} seed {seed} {name}: {seconds:.2f} s, CPU {cpu:.2f} s, {calls} loss calls"
                print(line, file=sys.stderr)
        remote.close()
    if not args.calls:
        print(table(ways, setup_s, scene.id, start, queries))
    return 0


def table(ways: dict[str, Way], setup_s: list[float], scene_id: str, start_s: float, queries: dict) -> str:
    """The markdown table of the run."""
    inproc, worker = ways["in-process"], ways["worker"]
    calls = statistics.mean(worker.calls)
    episodes = len(worker.seconds)
    lines = [
        f"{episodes} episodes per way ({scene_id} from {start_s:g} s; {'; '.join(queries)}), interleaved.",
        "",
        "| way | median s / episode | mean s | mean CPU s / episode | loss calls / episode |",
        "|---|---:|---:|---:|---:|",
    ]
    for way in ways.values():
        mean_calls = statistics.mean(way.calls) if way.name != "unguided" else 0
        median, mean = statistics.median(way.seconds), statistics.mean(way.seconds)
        cpu = statistics.mean(way.cpu_seconds)
        lines.append(f"| {way.name} | {median:.2f} | {mean:.2f} | {cpu:.2f} | {mean_calls:.0f} |")
    lines.append("")
    pairs = (("wall", worker.seconds, inproc.seconds), ("CPU", worker.cpu_seconds, inproc.cpu_seconds))
    for what, a, b in pairs:
        extra = [w - i for w, i in zip(a, b, strict=True)]  # paired by episode
        spread = f" ± {statistics.stdev(extra) / len(extra) ** 0.5:.2f}" if len(extra) > 1 else ""
        lines.append(
            f"worker − in-process, {what}: {statistics.mean(extra):+.2f}{spread} s per episode "
            f"({100 * statistics.mean(extra) / statistics.mean(b):+.0f} %), "
            f"{1000 * statistics.mean(extra) / calls:+.1f} ms per loss call."
        )
    lines.append(f"Starting the worker and loading the program: {statistics.mean(setup_s):.2f} s per run.")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
