"""Language models' programs steer real closed-loop simulations (issue 16).

Two programs written against ../shared/docs/LLM-API.md the paper's way (five of the six helpers with
the paper's argument order, ``__init__`` parameters with defaults, weights that decay or grow over
time, a helper loss class used by the main one) come back from a local OpenAI-compatible server as
chat-completion replies and go through ``ctgpp simulate`` exactly as a model's reply does: the LLM
client, the checks, the trial, then every call of sampling in the limited worker process. Each
guided episode is compared with the unguided one of the same scene, start and seed: the quantity the
query asks about moves the asked way.

A query the offline compiler refuses (a speed of 1e12 m/s, out of physical range) goes to the model
when one is configured: the model decides what to make of it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from ctgpp.cli.main import main
from tests.test_llm_client import MODEL, CannedServer, reply

SCENE = "scene-0553"  # at 3 s: vehicle 17 (13 m/s) has a lane to its right; vehicle 18 (8.5 m/s) follows it

# "vehicle 18 should stay at least 25 m behind vehicle 17"
STAY_BEHIND = '''
import torch


class StayBehind(GuidanceLoss):
    """The follower keeps at least gap_m behind the leader along the leader's heading."""

    def __init__(self, follower=18, leader=17, gap_m=25.0, decay_rate=0.98):
        super().__init__()
        self.follower = follower
        self.leader = leader
        self.gap_m = gap_m
        self.decay_rate = decay_rate

    def forward(self, x, data_batch, agt_mask=None):
        if agt_mask is not None:
            x = x[agt_mask]
        pos_pred = x[..., :2]  # (B, N, T, 6) -> (B, N, T, 2)
        yaw_pred = x[..., 3:4]  # (B, N, T, 1)
        pos_world, yaw_world = transform_coord_agents_to_world(pos_pred, yaw_pred, data_batch)
        pos_lead, _ = transform_coord_world_to_agent_i(pos_world, yaw_world, data_batch, self.leader)
        leader = select_agent_ind(pos_lead, self.leader)  # (N, T, 2) in the leader's frame
        follower = select_agent_ind(pos_lead, self.follower)  # (N, T, 2)
        gap = leader[..., 0] - follower[..., 0]  # (N, T) m
        weights = torch.pow(self.decay_rate, torch.arange(x.shape[2], dtype=torch.float))  # (T,)
        return torch.mean(torch.clip(self.gap_m - gap, min=0) * weights, dim=-1)  # (N,)
'''

# "vehicle 17 should change to the lane on its right"
RIGHT_LANE = '''
import torch
from ctgpp.guidance.helpers import get_current_lane_projection, get_right_lane_projection, select_agent_ind


class GentleAcceleration(GuidanceLoss):
    def __init__(self, acc_limit):
        super().__init__()
        self.acc_limit = acc_limit

    def forward(self, x, data_batch, agt_mask=None):
        acc = x[..., 4]  # (B, N, T)
        return torch.clip(torch.abs(acc) - self.acc_limit, min=0).mean(-1)  # (B, N)


class ChangeToRightLane(GuidanceLoss):
    """Vehicle 17 leaves its lane for the one on its right, the later steps weighing more."""

    def __init__(self, target_ind=17, growth=1.03, acc_limit=3.0):
        super().__init__()
        self.target_ind = target_ind
        self.growth = growth
        self.smooth = GentleAcceleration(acc_limit)

    def forward(self, x, data_batch, agt_mask=None):
        if agt_mask is not None:
            x = x[agt_mask]
        pos_pred, yaw_pred = x[..., :2], x[..., 3:4]  # (B, N, T, 2), (B, N, T, 1)
        own = get_current_lane_projection(pos_pred, yaw_pred, data_batch)  # (B, N, T, 3)
        right = get_right_lane_projection(pos_pred, yaw_pred, data_batch)  # (B, N, T, 3)
        target = select_agent_ind(right, self.target_ind)[..., :2]  # (N, T, 2)
        here = select_agent_ind(own, self.target_ind)[..., :2]
        pos = select_agent_ind(pos_pred, self.target_ind)
        weights = self.growth ** torch.arange(x.shape[2], dtype=torch.float)  # (T,)
        to_right = torch.norm(pos - target, dim=-1)  # (N, T)
        to_own = torch.norm(pos - here, dim=-1)
        lane = torch.sum((to_right - 0.2 * to_own) * weights, dim=-1) / weights.sum()  # (N,)
        return lane + select_agent_ind(self.smooth(x, data_batch), self.target_ind)  # (N,)
'''


@pytest.fixture()
def llm_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[CannedServer]:
    """A local OpenAI-compatible server, an empty program cache, no proxy between them."""
    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.setenv("CTGPP_CACHE_DIR", str(tmp_path / "cache"))
    server = CannedServer()
    yield server
    server.close()


EPISODE = ["--scene", SCENE, "--seed", "0", "--guards", "off", "--animation", "none"]


def simulate_with_model(query: str, server: CannedServer, out: Path) -> dict:
    """``ctgpp simulate QUERY`` with the canned model; returns metrics.json."""
    llm = ["--llm-model", MODEL, "--llm-base-url", server.url]
    assert main(["simulate", query, *llm, *EPISODE, "--out", str(out)]) == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def unguided(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("unguided") / "run"
    assert main(["simulate", *EPISODE, "--out", str(out)]) == 0
    return out


def track(out: Path, vehicle: int) -> dict[str, np.ndarray]:
    """Vehicle ``vehicle``'s simulated states from the episode's start (time_s ≥ 0), by time."""
    table = pq.read_table(out / "rollout.parquet")
    columns = {k: table.column(k).to_numpy() for k in ("agent", "time_s", "x", "y", "yaw", "speed")}
    rows = np.flatnonzero((columns["agent"] == vehicle) & (columns["time_s"] >= 0))
    rows = rows[np.argsort(columns["time_s"][rows], kind="stable")]
    return {k: v[rows] for k, v in columns.items() if k != "agent"}


def gap_behind(out: Path, follower: int, leader: int) -> np.ndarray:
    """How far the follower is behind the leader along the leader's heading, per step (m)."""
    f, lead = track(out, follower), track(out, leader)
    assert np.array_equal(f["time_s"], lead["time_s"])
    heading = np.stack([np.cos(lead["yaw"]), np.sin(lead["yaw"])], axis=-1)  # (T, 2)
    offset = np.stack([lead["x"] - f["x"], lead["y"] - f["y"]], axis=-1)
    return (offset * heading).sum(-1)


def lateral_drift(out: Path, vehicle: int) -> np.ndarray:
    """The vehicle's position to the left (+) of its heading at the start, per step (m)."""
    v = track(out, vehicle)
    c, s = np.cos(v["yaw"][0]), np.sin(v["yaw"][0])
    return -s * (v["x"] - v["x"][0]) + c * (v["y"] - v["y"][0])


def test_model_program_keeps_a_vehicle_behind_another(llm_env: CannedServer, unguided: Path,
                                                      tmp_path: Path) -> None:
    query = "vehicle 18 should stay at least 25 m behind vehicle 17"
    llm_env.replies = [reply(STAY_BEHIND)]
    record = simulate_with_model(query, llm_env, tmp_path / "run")
    assert record["query"]["path"] == f"language model {MODEL} (1 round(s))" and len(llm_env.requests) == 1
    assert query in llm_env.requests[0]["messages"][-1]["content"]
    guided, free = gap_behind(tmp_path / "run", 18, 17), gap_behind(unguided, 18, 17)
    # unguided, vehicle 18 (8.5 m/s) starts 12.7 m behind vehicle 17 (13 m/s) and falls back to 25 m
    # after about 2.5 s; guided, it gets there at least half a second sooner and stays further back
    assert (guided >= 25.0).any() and (free >= 25.0).any()
    dt_s = 0.1
    assert np.argmax(guided >= 25.0) * dt_s <= np.argmax(free >= 25.0) * dt_s - 0.5
    assert guided.mean() > free.mean() + 10.0


def test_model_program_moves_a_vehicle_to_the_right_lane(llm_env: CannedServer, unguided: Path,
                                                         tmp_path: Path) -> None:
    query = "vehicle 17 should leave its lane for the one on its right"
    llm_env.replies = [reply(RIGHT_LANE)]
    record = simulate_with_model(query, llm_env, tmp_path / "run")
    assert record["query"]["path"] == f"language model {MODEL} (1 round(s))"
    guided, free = lateral_drift(tmp_path / "run", 17), lateral_drift(unguided, 17)
    # about a lane's width (3.2 m here) further right than the unguided episode, from 5 s on
    later = slice(50, None)
    assert (guided[later] - free[later]).mean() < -2.0


# The model's reading of "vehicle 2 should drive at 1e12 m/s": as fast as a car sensibly goes.
AS_FAST_AS_SENSIBLE = '''
import torch


class DriveFast(GuidanceLoss):
    def __init__(self, target_ind=2, speed=40.0, decay_rate=0.95):
        super().__init__()
        self.target_ind = target_ind
        self.speed = speed
        self.decay_rate = decay_rate

    def forward(self, x, data_batch, agt_mask=None):
        if agt_mask is not None:
            x = x[agt_mask]
        vel = select_agent_ind(x[..., 2:3], self.target_ind)[..., 0]  # (B, N, T, 1) -> (N, T)
        weights = self.decay_rate ** torch.arange(x.shape[2], dtype=torch.float)  # (T,)
        return torch.sum(torch.clip(self.speed - vel, min=0) * weights, dim=-1) / weights.sum()  # (N,)
'''


def test_query_out_of_the_compilers_range_goes_to_the_model(llm_env: CannedServer, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """The compiler refuses 1e12 m/s (exit 2, one line, nothing written); with a model configured the
    query is the model's to read, and its program steers the episode."""
    query = "vehicle 2 should drive at 1e12 m/s"
    short = ["--scene", "0103", "--steps", "1", "--guards", "off", "--animation", "none"]
    assert main(["simulate", query, *short, "--out", str(tmp_path / "offline")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ctgpp: error: speed in '{query}' is 1e+12 m/s: speeds must be 0 to 40 m/s (144 km/h)"]
    assert not (tmp_path / "offline").exists() and llm_env.requests == []

    llm_env.replies = [reply(AS_FAST_AS_SENSIBLE)]
    llm = ["--llm-model", MODEL, "--llm-base-url", llm_env.url]
    assert main(["simulate", query, *llm, *short, "--out", str(tmp_path / "run")]) == 0
    (request,) = llm_env.requests
    assert query in request["messages"][-1]["content"]
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())["query"]
    assert record["path"] == f"language model {MODEL} (1 round(s))" and "class DriveFast" in record["code"]
    assert record["notes"] == []
