"""``--engine ray`` (issue 37, item 3) on a real 2-node Ray cluster started on this machine (Ray's own
multi-node test cluster, one CPU a node). ``generate``: the index holds the same rows as with
``--engine local`` (apart from the timings), and a Ray worker killed in the middle of a task (SIGKILL)
is retried: the run completes with every scenario once. ``evaluate``: the same episode rows as the
local run. Skipped without Ray (``pip install "ctgpp[ray]"``; CI installs it)."""

from __future__ import annotations

import os
import pickle
import signal
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from ctgpp.cli.main import main
from ctgpp.eval.runner import read_records
from ctgpp.generate.run import Engine, Plan, generate
from ctgpp.generate.worker import Settings, TaskResult
from ctgpp.policies.diffusion import SamplingConfig

ray = pytest.importorskip("ray")
cluster_utils = pytest.importorskip("ray.cluster_utils")

SENTENCES = ("vehicle 1 should collide with vehicle 2",)
SEEDS = range(5)


def _settings() -> Settings:
    from ctgpp.api.episode import parse_stages
    from ctgpp.diffusion.guided import GuidanceConfig
    from ctgpp.guidance.guards import GuardConfig

    return Settings("ctgpp", None, SamplingConfig(), GuidanceConfig(), GuardConfig.parse("on"),
                    parse_stages("on"), duration_s=2.0, history_s=None)


def _rows(out: Path) -> list[dict]:
    """The index's rows without their timings."""
    rows = pq.read_table(out / "index.parquet").to_pylist()
    return [{k: v for k, v in row.items() if k != "seconds"} for row in rows]


def _running_ray_tasks() -> list[int]:
    """The pids of Ray workers running a task of ours now (Ray titles them ``ray::run_task``)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    if f.read().startswith(b"ray::run_task"):
                        pids.append(int(entry))
            except OSError:
                continue
    return pids


@pytest.fixture(scope="module")
def cluster():
    made = cluster_utils.Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    made.add_node(num_cpus=1)
    made.wait_for_nodes()
    yield made
    made.shutdown()


@pytest.mark.model
@pytest.mark.slow
@pytest.mark.skipif(not os.path.isdir("/proc"), reason="finds Ray's worker processes in /proc (Linux)")
def test_ray_rows_are_the_local_rows_and_a_killed_worker_loses_nothing(tmp_path: Path, cluster) -> None:
    plan = Plan(SENTENCES, ["scene-0103"], list(SEEDS), chunk=1)
    killed: list[int] = []

    def kill_one(result: TaskResult) -> None:  # after the first result: the other node is mid-task
        if not killed:
            running = _running_ray_tasks()
            assert running, "no Ray worker was running a task to kill"
            os.kill(running[0], signal.SIGKILL)
            killed.append(running[0])

    generate(plan, _settings(), tmp_path / "ray", Engine("ray", address=cluster.address), progress=False,
             on_result=kill_one)
    assert killed
    generate(plan, _settings(), tmp_path / "local", progress=False)
    rows = _rows(tmp_path / "ray")
    assert [r["seed"] for r in rows] == list(SEEDS)  # every scenario, once
    assert rows == _rows(tmp_path / "local")  # bit for bit, apart from the timings
    for row in rows:  # the same scenario (the pickles' memo may share other objects: Ray copied the scene)
        local = pickle.loads((tmp_path / "local" / row["file"]).read_bytes())
        _assert_same(pickle.loads((tmp_path / "ray" / row["file"]).read_bytes()), local, row["file"])


def _assert_same(a: object, b: object, where: str) -> None:
    """``a`` and ``b`` hold the same values (numpy arrays bit for bit, with their dtypes)."""
    assert type(a) is type(b), where
    if isinstance(a, dict):
        assert list(a) == list(b), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and np.array_equal(a, b), where
    else:
        assert a == b or (a != a and b != b), where


@pytest.mark.model
@pytest.mark.slow
def test_evaluate_on_ray_writes_the_local_rows(tmp_path: Path, cluster) -> None:
    common = ["evaluate", "--methods", "ctgpp,constvel", "--split", "mini_val", "--duration", "2",
              "--spacing", "100"]
    ray_args = ["--engine", "ray", "--ray-address", cluster.address]
    assert main([*common, *ray_args, "--out", str(tmp_path / "ray")]) == 0
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in a Ray worker
    try:
        assert main([*common, "--out", str(tmp_path / "local")]) == 0
    finally:
        torch.set_num_threads(threads)
    ray_rows = read_records(tmp_path / "ray" / "episodes.csv")
    local_rows = read_records(tmp_path / "local" / "episodes.csv")
    assert len(ray_rows) == 4  # 2 scenes × 2 methods, each once
    def order(row: dict[str, str]) -> list[str]:
        return [row["scene"], row["method"], row["seed"]]

    assert sorted(ray_rows, key=order) == sorted(local_rows, key=order)
