"""The spatial attention run apart over neighbourhood groups (``Denoiser.neighbourhoods``): the groups
of a hand-made mask, the dense outputs kept exactly when the scene is one group, and up to round-off
when copies of a scene lie beyond each other's social radius."""

from __future__ import annotations

import torch

from ctgpp.bench.scaling import tiled_batch
from ctgpp.data.batch import collate
from ctgpp.data.windows import build_window
from ctgpp.model import Denoiser, ModelConfig
from ctgpp.model.attention import neighbourhood_groups
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS, controlled_vehicles

TINY = ModelConfig(d_model=32, heads=2, blocks=2, edge_dim=8, lane_hidden=16)


def test_groups_of_a_hand_made_mask() -> None:
    # 4 agents, 1 context agent (key 4), 2 time steps: 0-1 meet at t=0, agent 2 meets the context
    # agent at t=1, agent 3 meets nobody
    mask = torch.zeros(1, 2, 4, 5, dtype=torch.bool)
    mask[0, :, range(4), range(4)] = True  # the diagonal
    mask[0, 0, 0, 1] = mask[0, 0, 1, 0] = True
    mask[0, 1, 2, 4] = True
    groups = neighbourhood_groups(mask)
    assert groups is not None
    got = [(g[0].tolist(), g[1].tolist()) for g in groups]
    assert got == [([0, 1], [0, 1]), ([2], [2, 4]), ([3], [3])]
    mask[0, 1, 1, 2] = mask[0, 0, 2, 3] = True  # now all agents meet, one group: dense
    assert neighbourhood_groups(mask) is None


def _window(scene: Scene):  # type: ignore[no-untyped-def]
    step = 40
    controlled = controlled_vehicles(scene, step)
    still = scene.agents.speed[controlled, step] < MOVING_SPEED_MPS
    spec = TINY.window_config(max_agents=64, with_future=False)
    return build_window(scene, step, spec, controlled[~still], controlled[still])


def _predict(model: Denoiser, batch, x: torch.Tensor, on: bool) -> torch.Tensor:  # type: ignore[no-untyped-def]
    model.neighbourhoods = on
    k = torch.full((x.shape[0],), 40)
    with torch.no_grad():
        return model(x, k, batch, model.encode_context(batch).expand(x.shape[0] // batch.num_scenes))


def test_one_group_is_exactly_the_dense_attention(scene_0103: Scene) -> None:
    window = _window(scene_0103)
    batch = collate([window])
    torch.manual_seed(0)
    model = Denoiser(TINY).eval()
    x = torch.randn(3, window.num_agents, TINY.future_steps, 2, generator=torch.Generator().manual_seed(1))
    model.neighbourhoods = True
    assert model.encode_context(batch).groups is None  # every vehicle within reach of the others
    assert torch.equal(_predict(model, batch, x, True), _predict(model, batch, x, False))


def test_copies_apart_give_the_dense_outputs_up_to_round_off(scene_0103: Scene) -> None:
    window = _window(scene_0103)
    a = window.num_agents
    tiled = tiled_batch(window, 3 * a - 2)  # two whole copies and a cut one, 300 m apart
    torch.manual_seed(0)
    model = Denoiser(TINY).eval()
    model.neighbourhoods = True
    groups = model.encode_context(tiled).groups
    assert groups is not None and len(groups) >= 3
    assert sorted(torch.cat([g[0] for g in groups]).tolist()) == list(range(3 * a - 2))  # each agent once
    x = torch.randn(2, 3 * a - 2, TINY.future_steps, 2, generator=torch.Generator().manual_seed(2))
    grouped, dense = _predict(model, tiled, x, True), _predict(model, tiled, x, False)
    torch.testing.assert_close(grouped, dense, rtol=1e-5, atol=1e-5)
    assert not torch.equal(dense[:, :a], torch.zeros_like(dense[:, :a]))
