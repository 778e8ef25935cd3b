"""The spatial attention over each agent's gathered neighbours (``Denoiser.spatial = "gathered"``,
issue 37 item 5): the lists of a hand-made mask, and the dense outputs and gradients up to round-off
on real windows of the embedded nuScenes data, tiled, padded and with an agent alone."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch import Tensor

from ctgpp.bench.scaling import tiled_batch
from ctgpp.data.batch import SceneBatch, collate
from ctgpp.data.windows import SceneWindow, build_window
from ctgpp.model import Denoiser, ModelConfig
from ctgpp.model.inputs import edge_features, neighbour_features, prepare_inputs
from ctgpp.model.neighbours import SpatialMode, find_neighbours, neighbour_lists, worth_gathering
from ctgpp.scene.types import Scene

TINY = ModelConfig(d_model=32, heads=2, blocks=2, edge_dim=8, lane_hidden=16)


def test_lists_of_a_hand_made_mask() -> None:
    # 3 agents (agent 2 a padding agent), 2 context agents (keys 3, 4), 2 time steps
    keep = torch.zeros(1, 2, 3, 5, dtype=torch.bool)
    keep[0, :, range(3), range(3)] = True  # the diagonal
    keep[0, 0, 0, [1, 4]] = True  # agent 0 meets agent 1 and context agent 4 at t=0
    keep[0, 1, 1, 3] = True  # agent 1 meets context agent 3 at t=1
    keep[0, :, 2, [0, 3, 4]] = True  # the padding agent lies near everyone: not kept
    index, valid = neighbour_lists(keep, torch.tensor([[True, True, False]]))
    assert index.shape == (1, 2, 3, 3)
    assert index[0, 0].tolist() == [[0, 1, 4], [1, 1, 1], [2, 2, 2]]  # padded with the agent itself
    assert valid[0, 0].tolist() == [[True, True, True], [True, False, False], [True, False, False]]
    assert index[0, 1].tolist() == [[0, 0, 0], [1, 3, 1], [2, 2, 2]]
    assert valid[0, 1].sum(-1).tolist() == [1, 2, 1]


def _window(scene: Scene, step: int = 40) -> SceneWindow:
    return build_window(scene, step, TINY.window_config(max_agents=64))


def _model() -> Denoiser:
    torch.manual_seed(0)
    return Denoiser(TINY).eval()


def _predict(model: Denoiser, batch: SceneBatch, x: Tensor, mode: SpatialMode) -> Tensor:
    model.spatial = mode
    k = torch.tensor([7, 60] * (x.shape[0] // 2))
    with torch.no_grad():
        return model(x, k, batch, model.encode_context(batch).expand(x.shape[0] // batch.num_scenes))


def _noise(batch: SceneBatch, rows: int, seed: int) -> Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(rows, batch.num_agents, TINY.future_steps, 2, generator=gen)


def test_neighbour_edges_are_those_of_the_dense_mask(scene_0103: Scene) -> None:
    inputs = prepare_inputs(collate([_window(scene_0103)]), TINY)
    feats, mask = edge_features(inputs, TINY)
    index, valid = find_neighbours(inputs, TINY)
    assert torch.equal(valid.sum(-1), mask.sum(-1))  # every kept key listed once
    assert torch.equal(torch.gather(mask, 3, index)[valid], valid[valid])
    gathered = torch.gather(feats, 3, index[..., None].expand(*index.shape, 7))
    assert torch.equal(neighbour_features(inputs, TINY, index), gathered)


def test_gathered_gives_the_dense_outputs_on_real_windows_with_padding(scene_0103: Scene) -> None:
    windows = [_window(scene_0103, 40), _window(scene_0103, 150)]  # different agent counts: padding
    batch = collate(windows)
    assert not batch.agent_mask.all() and batch.ctx_mask.any()  # padding agents, context agents
    model = _model()
    x = _noise(batch, 4, seed=1)  # two samples a scene
    dense, gathered = _predict(model, batch, x, "dense"), _predict(model, batch, x, "gathered")
    torch.testing.assert_close(gathered, dense, rtol=1e-5, atol=1e-5)
    assert torch.all(gathered[2:, ~batch.agent_mask[1]] == 0)
    assert float(dense.abs().max()) > 0.1


def test_gathered_gives_the_dense_outputs_on_a_tiled_window_with_an_agent_alone(scene_0103: Scene) -> None:
    window = _window(scene_0103)
    a = window.num_agents
    tiled = tiled_batch(window, 3 * a - 2)  # two whole copies and a cut one, 300 m apart
    pose = tiled.pose.clone()
    pose[0, a, :2] += torch.tensor([5000.0, 0.0])  # the second copy's first agent far from everyone
    tiled = dataclasses.replace(tiled, pose=pose)
    model = _model()
    model.spatial = "gathered"
    near = model.encode_context(tiled).neighbours
    assert near is not None
    assert torch.all((~near.padding[0, :, a]).sum(-1) == 1)  # only itself at every step
    keys = tiled.num_agents + tiled.ctx_mask.shape[1]  # the K keys of all copies
    assert near.index.shape[-1] < keys // 2
    x = _noise(tiled, 2, seed=2)
    dense, gathered = _predict(model, tiled, x, "dense"), _predict(model, tiled, x, "gathered")
    torch.testing.assert_close(gathered, dense, rtol=1e-5, atol=1e-5)
    assert float((dense[:, a] - dense[:, 0]).abs().max()) > 1e-3  # alone, it plans otherwise


def test_gradients_flow_as_through_the_dense_attention(scene_0103: Scene) -> None:
    batch = collate([_window(scene_0103)])
    model = _model().train()
    grads = {}
    for mode in ("dense", "gathered"):
        model.spatial = mode
        model.zero_grad()
        x = _noise(batch, 1, seed=3).requires_grad_(True)
        model(x, torch.tensor([30]), batch).square().sum().backward()
        assert x.grad is not None and float(x.grad.abs().max()) > 0
        grads[mode] = {"x": x.grad.clone()} | {
            name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None
        }
    assert grads["dense"].keys() == grads["gathered"].keys()
    assert "blocks.0.spatial.key_edge" in grads["gathered"] and "edge_mlp.0.weight" in grads["gathered"]
    for name, dense in grads["dense"].items():  # sums of many terms: round-off scales with the largest
        scale = float(dense.abs().max())
        assert float((grads["gathered"][name] - dense).abs().max()) <= 1e-5 * scale + 1e-7, name


@pytest.mark.parametrize(
    ("most", "keys", "gather"), [(22, 88, True), (22, 89, True), (22, 56, False), (1, 3, False)]
)
def test_the_auto_rule(most: int, keys: int, gather: bool) -> None:
    assert worth_gathering(most, keys) == gather


def test_auto_gathers_on_a_large_tiled_window_and_not_on_a_crowded_one(scene_0103: Scene) -> None:
    window = _window(scene_0103)
    model = _model()
    model.spatial = "auto"
    assert model.encode_context(tiled_batch(window, 4 * window.num_agents)).neighbours is not None
    crowd = collate([window])  # one window: everybody is within everybody's radius
    assert model.encode_context(crowd).neighbours is None
