"""The denoiser on a real nuScenes window: invariances, masking, checkpoints and a training smoke test."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch
from torch import Tensor

from ctgpp.data.batch import SceneBatch, collate
from ctgpp.data.windows import build_window
from ctgpp.diffusion import CosineSchedule, DDIMSampler, sample
from ctgpp.model import (
    CheckpointError,
    Denoiser,
    ModelConfig,
    load_checkpoint,
    save_checkpoint,
    training_loss,
)
from ctgpp.model.attention import GatedSpatialAttention, MaskedAttention, softmax_last
from ctgpp.model.denoiser import repeat_samples
from ctgpp.scene.types import Scene

TINY = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=8, lane_hidden=16)
AGENT_AXIS_FIELDS = ("agent_mask", "pose", "extent", "hist", "hist_valid", "fut", "fut_valid", "fut_actions")
MAP_FIELDS = ("lanes", "lanes_valid", "drivable")


@pytest.fixture(scope="module")
def batch(scene_0103: Scene) -> SceneBatch:
    return collate([build_window(scene_0103, 60, TINY.window_config(max_agents=64))])


def make_model(config: ModelConfig = TINY, seed: int = 0) -> Denoiser:
    torch.manual_seed(seed)
    return Denoiser(config).eval()


def noisy_input(batch: SceneBatch, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(batch.num_scenes, batch.num_agents, TINY.future_steps, 2, generator=gen)
    return x, torch.full((batch.num_scenes,), 37)


def predict(model: Denoiser, batch: SceneBatch, x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return model(x, k, batch)


def transformed(batch: SceneBatch, angle: float, shift: tuple[float, float]) -> SceneBatch:
    """The same scene rotated by ``angle`` about the origin and shifted: only world poses change."""
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[c, -s], [s, c]])

    def move(pose: Tensor) -> Tensor:
        return torch.cat([pose[..., :2] @ rot.T + torch.tensor(shift), pose[..., 2:] + angle], dim=-1)

    return dataclasses.replace(batch, pose=move(batch.pose), ctx_pose=move(batch.ctx_pose))


def with_extra_agent(batch: SceneBatch, values: dict[str, torch.Tensor]) -> SceneBatch:
    """``batch`` with one more agent appended, its per-agent tensors taken from ``values``."""
    fields = {n: torch.cat([getattr(batch, n), values[n][:, None]], dim=1) for n in AGENT_AXIS_FIELDS}
    for n in MAP_FIELDS:
        fields[n] = torch.cat([getattr(batch, n), values[n][:, None]], dim=1)
    return dataclasses.replace(batch, **fields)


def test_output_shape_and_real_agents_only(batch: SceneBatch) -> None:
    x, k = noisy_input(batch)
    out = predict(make_model(), batch, x, k)
    assert out.shape == x.shape and torch.isfinite(out).all()
    assert batch.num_agents > 5


def test_agent_centric_outputs_are_invariant_to_rotating_the_scene(batch: SceneBatch) -> None:
    x, k = noisy_input(batch)
    moved = transformed(batch, 0.7, (35.0, -12.0))
    model = make_model()
    assert torch.allclose(predict(model, batch, x, k), predict(model, moved, x, k), atol=1e-4)


def test_scene_centric_outputs_change_when_rotating_the_scene(batch: SceneBatch) -> None:
    x, k = noisy_input(batch)
    model = make_model(dataclasses.replace(TINY, scene_centric=True))
    diff = predict(model, batch, x, k) - predict(model, transformed(batch, 0.7, (35.0, -12.0)), x, k)
    assert float(diff.abs().max()) > 1e-3


def test_padded_agents_with_garbage_do_not_affect_real_agents(batch: SceneBatch) -> None:
    gen = torch.Generator().manual_seed(3)
    garbage = {
        n: (torch.rand(getattr(batch, n)[:, 0].shape, generator=gen) > 0.5)
        if getattr(batch, n).dtype == torch.bool
        else torch.randn(getattr(batch, n)[:, 0].shape, generator=gen) * 1e3
        for n in (*AGENT_AXIS_FIELDS, *MAP_FIELDS)
    }
    garbage["agent_mask"] = torch.zeros(batch.num_scenes, dtype=torch.bool)
    garbage["hist"][..., 0, 0] = float("nan")
    padded = with_extra_agent(batch, garbage)
    x, k = noisy_input(batch)
    x_padded = torch.cat([x, torch.randn(1, 1, TINY.future_steps, 2) * 1e3], dim=1)
    model = make_model()
    out, out_padded = predict(model, batch, x, k), predict(model, padded, x_padded, k)
    assert torch.allclose(out, out_padded[:, :-1], atol=1e-5)
    assert torch.all(out_padded[:, -1] == 0)


def test_agent_beyond_the_social_radius_does_not_affect_others(batch: SceneBatch) -> None:
    """A copy of agent 0 moved 2 km away is invisible to the others; 4 m to the side it is not."""

    def copy_of_agent0(offset: tuple[float, float]) -> SceneBatch:
        values = {n: getattr(batch, n)[:, 0].clone() for n in (*AGENT_AXIS_FIELDS, *MAP_FIELDS)}
        values["pose"][:, :2] += torch.tensor(offset)
        return with_extra_agent(batch, values)

    x, k = noisy_input(batch)
    x_more = torch.cat([x, x[:, :1]], dim=1)
    model = make_model()
    out = predict(model, batch, x, k)
    far = predict(model, copy_of_agent0((2000.0, 0.0)), x_more, k)
    near = predict(model, copy_of_agent0((0.0, 4.0)), x_more, k)
    assert torch.allclose(out, far[:, :-1], atol=1e-5)
    assert float((out - near[:, :-1]).abs().max()) > 1e-3


def test_no_edge_variant_differs_from_the_edge_model(batch: SceneBatch) -> None:
    x, k = noisy_input(batch)
    model = make_model()
    no_edge = Denoiser(dataclasses.replace(TINY, use_edges=False)).eval()
    no_edge.load_state_dict(model.state_dict())
    assert float((predict(model, batch, x, k) - predict(no_edge, batch, x, k)).abs().max()) > 1e-4


def test_fully_masked_rows_give_finite_outputs_and_gradients(scene_0103: Scene) -> None:
    windows = TINY.window_config(max_agents=64)
    # two windows with different agent counts
    batch = collate([build_window(scene_0103, 60, windows), build_window(scene_0103, 150, windows)])
    assert not batch.agent_mask.all()
    lanes_valid = batch.lanes_valid.clone()
    lanes_valid[0, 0] = False  # an agent with no lanes at all
    hist_valid = batch.hist_valid.clone()
    hist_valid[0, 1, :-1] = False  # an agent seen only at the current step
    batch = dataclasses.replace(batch, lanes_valid=lanes_valid, hist_valid=hist_valid)
    model = make_model()
    x = torch.randn(2, batch.num_agents, TINY.future_steps, 2, requires_grad=True)
    out = model(x, torch.tensor([0, 99]), batch)
    out.square().sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(x.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_save_load_gives_identical_outputs_and_samples(batch: SceneBatch, tmp_path: Path) -> None:
    model = make_model()
    save_checkpoint(tmp_path / "ckpt", model, TINY, {"steps": 3, "losses": [1.0, 0.5]})
    loaded, config, extra = load_checkpoint(tmp_path / "ckpt")
    assert config == TINY and extra == {"steps": 3, "losses": [1.0, 0.5]}
    x, k = noisy_input(batch)
    assert torch.equal(predict(model, batch, x, k), predict(loaded, batch, x, k))
    sampler = DDIMSampler(CosineSchedule(), num_steps=4)
    shape = (1, batch.num_agents, TINY.future_steps, 2)
    samples = []
    for net in (model, loaded):
        with torch.no_grad():
            ctx = net.encode_context(batch)
            fn = lambda x_k, k, net=net, ctx=ctx: net(x_k, k, batch, ctx)  # noqa: E731
            samples.append(sample(fn, shape, sampler, torch.Generator().manual_seed(5)))
    assert torch.equal(samples[0], samples[1])


def test_checkpoint_errors_are_clear(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="config.json"):
        load_checkpoint(tmp_path)
    save_checkpoint(tmp_path, make_model(), TINY, {})
    header = json.loads((tmp_path / "config.json").read_text())
    header["model"]["d_model"] = 48
    (tmp_path / "config.json").write_text(json.dumps(header))
    with pytest.raises(CheckpointError, match="wrong shape"):
        load_checkpoint(tmp_path)
    (tmp_path / "model.safetensors").unlink()
    with pytest.raises(CheckpointError, match="model.safetensors"):
        load_checkpoint(tmp_path)


def test_config_round_trip_and_unknown_keys() -> None:
    data = json.loads(json.dumps(TINY.to_dict()))
    assert ModelConfig.from_dict(data) == TINY
    with pytest.raises(ValueError, match="d_modle"):
        ModelConfig.from_dict({**data, "d_modle": 64})
    with pytest.raises(ValueError):
        ModelConfig(d_model=30, heads=4)


@pytest.mark.slow
def test_a_few_adam_steps_lower_the_training_loss(batch: SceneBatch) -> None:
    fields = (*AGENT_AXIS_FIELDS, *MAP_FIELDS)
    batch = dataclasses.replace(batch, **{n: getattr(batch, n)[:, :8] for n in fields})  # 8 agents: fast
    torch.manual_seed(0)
    model = Denoiser(TINY)
    sched = CosineSchedule(TINY.diffusion_steps, TINY.cosine_s)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)

    def eval_loss() -> float:
        with torch.no_grad():
            return sum(
                training_loss(model, sched, batch, torch.Generator().manual_seed(s))[0].item()
                for s in range(3)
            )

    before = eval_loss()
    gen = torch.Generator().manual_seed(11)
    for _ in range(30):
        loss, stats = training_loss(model, sched, batch, gen)
        assert math.isfinite(stats["loss"]) and stats["valid_steps"] > 0
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert eval_loss() < 0.7 * before


def test_context_encoded_once_and_expanded_matches_a_repeated_batch(scene_0103: Scene) -> None:
    window = build_window(scene_0103, 40, TINY.window_config(max_agents=64))
    model = make_model()
    x = torch.randn(3, window.num_agents, 52, 2, generator=torch.Generator().manual_seed(3))
    k = torch.tensor([5, 50, 90])
    with torch.no_grad():
        repeated = model(x, k, collate([window] * 3))
        expanded = model(x, k, collate([window]), model.encode_context(collate([window])).expand(3))
    torch.testing.assert_close(expanded, repeated)


def reference_spatial_attention(
    layer: GatedSpatialAttention, x: Tensor, edges: Tensor, mask: Tensor, context: Tensor | None = None
) -> Tensor:
    """The paper's edge-aware attention written out pair by pair with einsum (edges (S, T, A, K, E)),
    over the agents' own keys and then the context tokens (S, T, C, d), if any."""
    s, t, a, d = x.shape
    h = layer.norm(x)
    q = layer.q(h).view(s, t, a, layer.heads, layer.head_dim)
    keys = h if context is None else torch.cat([h, layer.norm(context)], dim=2)  # (S, T, K, d)
    k, v = layer.kv(keys).view(s, t, keys.shape[2], 2, layer.heads, layer.head_dim).unbind(dim=3)
    key = k[:, :, None] + torch.einsum("hde,stije->stijhd", layer.key_edge, edges)  # (S, T, A_i, K_j, h, dh)
    value = v[:, :, None] + torch.einsum("hed,stije->stijhd", layer.value_edge, edges)
    logits = torch.einsum("stihd,stijhd->stijh", q, key) / math.sqrt(layer.head_dim)
    weights = torch.softmax(logits.masked_fill(~mask[..., None], float("-inf")), dim=3)
    msg = layer.out(torch.einsum("stijh,stijhd->stihd", weights, value).reshape(s, t, a, d))
    g = torch.sigmoid(layer.gate(torch.cat([h, msg], dim=-1)))
    return g * msg + (1 - g) * x


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("n_context", [0, 4])
def test_spatial_attention_matches_the_pairwise_formula(shared: bool, n_context: int) -> None:
    torch.manual_seed(0)
    layer = GatedSpatialAttention(16, 4, 8)
    s, t, a = 3, 5, 6
    x = torch.randn(s, t, a, 16)
    rows = 1 if shared else s
    edges = torch.randn(rows, t, a, a + n_context, 8)
    mask = (torch.rand(edges.shape[:-1]) < 0.5) | torch.eye(a, a + n_context, dtype=torch.bool)
    context = torch.randn(rows, t, n_context, 16)
    with torch.no_grad():
        fast = layer(x, edges, mask, layer.context_keys(context) if n_context else None)
        edges_s, mask_s = edges.expand(s, -1, -1, -1, -1), mask.expand(s, -1, -1, -1)
        slow = reference_spatial_attention(layer, x, edges_s, mask_s, context.expand(s, -1, -1, -1))
    torch.testing.assert_close(fast, slow, rtol=1e-5, atol=1e-5)


def test_last_block_on_future_tokens_only_is_exact(scene_0103: Scene) -> None:
    """The last block skips the history tokens' outputs: the prediction equals running every block on
    all tokens and reading out the future ones."""
    model = make_model(ModelConfig(blocks=2))
    batch = collate([build_window(scene_0103, 40, model.config.window_config(max_agents=64))])
    x = torch.randn(1, batch.agent_mask.shape[1], 52, 2, generator=torch.Generator().manual_seed(8))
    k = torch.tensor([30])
    ctx = model.encode_context(batch)
    with torch.no_grad():
        got = model(x, k, batch, ctx)
        spy: list[Tensor] = []
        handle = model.blocks[0].register_forward_hook(lambda _m, _i, out: spy.append(out))
        model(x, k, batch, ctx)
        handle.remove()
        whole = model.blocks[1](spy[0], ctx, ctx.map_keys[1], ctx.context_keys[1])  # every token
        want = model.out(model.out_norm(whole[:, :, model.config.history_steps :]))
    assert whole.shape[2] == 83 and got.shape[2] == 52
    torch.testing.assert_close(got, want * batch.agent_mask[..., None, None])


def test_folded_keys_attend_as_the_attention_itself() -> None:
    """Folding fixed keys into the projections changes nothing: outputs and gradients are equal,
    rows without keys included (they get zeros)."""
    torch.manual_seed(2)
    layer = MaskedAttention(16, 4)
    query, context = torch.randn(5, 9, 16, requires_grad=True), torch.randn(5, 6, 16)
    mask = torch.rand(5, 6) < 0.5
    mask[0], mask[1] = False, True  # a row with no key at all, a row with every key
    want = layer(query, context, mask)
    got = layer.attend(query, layer.fold(context, mask))
    torch.testing.assert_close(got, want)
    assert (got[0] == 0).all()
    (g_want,) = torch.autograd.grad(want.square().sum(), query)
    (g_got,) = torch.autograd.grad(got.square().sum(), query)
    torch.testing.assert_close(g_got, g_want)


@pytest.mark.parametrize("keys", [1, 8, 12, 16, 33])
def test_softmax_last_equals_torch_softmax_with_masked_keys(keys: int) -> None:
    torch.manual_seed(keys)
    logits = 30 * torch.randn(2, 7, 3, keys, keys)  # large logits: the max must be subtracted
    mask = (torch.rand(logits.shape) < 0.6) | torch.eye(keys, dtype=torch.bool)
    logits = logits.masked_fill(~mask, float("-inf"))
    weights = softmax_last(logits.clone())
    torch.testing.assert_close(weights, torch.softmax(logits, dim=-1))
    assert torch.isfinite(weights).all() and (weights[~mask] == 0).all()


def test_context_of_several_scenes_expands_scene_major(scene_0103: Scene) -> None:
    config = TINY.window_config(max_agents=64)
    windows = [build_window(scene_0103, 40, config), build_window(scene_0103, 90, config)]
    model = make_model()
    a = max(w.num_agents for w in windows)
    x = torch.randn(4, a, 52, 2, generator=torch.Generator().manual_seed(4))
    k = torch.tensor([5, 50, 90, 20])
    with torch.no_grad():
        repeated = model(x, k, collate([windows[0], windows[0], windows[1], windows[1]]))
        batch = collate(windows)
        expanded = model(x, k, batch, model.encode_context(batch).expand(2))
    torch.testing.assert_close(expanded, repeated)


def test_lane_segment_tokens_see_only_their_own_stretch() -> None:
    """With G segments each lane token pools its own P / G consecutive points: bending the path
    beyond the first stretch changes the later tokens only; one segment pools the whole lane."""
    from ctgpp.model.lane_encoder import LaneEncoder

    torch.manual_seed(0)
    encoder = LaneEncoder(16, 16, segments=4)
    x = torch.linspace(0.0, 39 * 2.5, 40)
    straight = torch.stack([x, torch.zeros(40), torch.ones(40), torch.zeros(40)], dim=-1)[None, None, None]
    bent = straight.clone()
    bent[..., 20:, 1] = (x[20:] - x[19]) * 0.5  # the path turns left halfway along
    valid = torch.ones(1, 1, 1, 40, dtype=torch.bool)
    with torch.no_grad():
        a, a_valid = encoder(straight, valid)
        b, _ = encoder(bent, valid)
    assert a.shape == (1, 1, 4, 16) and a_valid.all()
    assert torch.equal(a[..., :2, :], b[..., :2, :])  # points 0..19: the first two stretches
    assert (a[..., 2:, :] - b[..., 2:, :]).abs().amax() > 1e-3
    whole = LaneEncoder(16, 16, segments=1)
    whole.load_state_dict(encoder.state_dict())  # the same parameters, one token per lane
    with torch.no_grad():
        one, _ = whole(straight, valid)
    assert one.shape == (1, 1, 1, 16)
    part = valid.clone()
    part[..., 10:] = False  # only the first stretch is mapped: the later tokens are invalid, zero
    with torch.no_grad():
        c, c_valid = encoder(straight, part)
    assert c_valid[0, 0].tolist() == [True, False, False, False] and (c[..., 1:, :] == 0).all()
    with pytest.raises(ValueError, match="segments"):
        LaneEncoder(16, 16, segments=3)(straight, valid)


def test_lane_segments_legacy_default_and_checks() -> None:
    assert ModelConfig().lane_segments == 8 and ModelConfig().tokens_per_lane == 8
    old = {k: v for k, v in TINY.to_dict().items() if k != "lane_segments"}
    assert ModelConfig.from_dict(old).lane_segments == 1  # a checkpoint from before keeps one token
    assert ModelConfig(context=None, map=None).tokens_per_lane == 1
    with pytest.raises(ValueError, match="lane_segments"):
        ModelConfig(lane_segments=3)  # 40 points do not split into 3 stretches


def test_expanded_context_gives_the_former_outputs_bit_for_bit(scene_0103: Scene) -> None:
    """What ``expand`` copies once (the folded lane keys laid out by rows, the context keys per sample)
    changes no bit of a prediction against the former views, which every call copied itself."""
    model = make_model(dataclasses.replace(TINY, blocks=2))  # the last block reads only future tokens
    batch = collate([build_window(scene_0103, 40, TINY.window_config(max_agents=64))])
    n = 3
    x = torch.randn(n, batch.num_agents, 52, 2, generator=torch.Generator().manual_seed(9))
    ctx = model.encode_context(batch)
    assert ctx.context_keys is not None and ctx.context_keys[0].shape[2] > 0  # context agents present
    fast = ctx.expand(n)
    views = tuple(keys.map(lambda v: repeat_samples(v, n)) for keys in ctx.map_keys)
    former = dataclasses.replace(fast, map_keys=views, sample_context_keys=None)
    with torch.no_grad():
        got = model(x, torch.full((n,), 30), batch, fast)
        want = model(x, torch.full((n,), 30), batch, former)
    assert torch.equal(got, want)


def test_a_context_expanded_twice_predicts_as_one_expanded_once(scene_0103: Scene) -> None:
    """Expanding an expanded context (2 then 3 samples a scene) repeats each scene's rows 6 times, the
    context keys per sample included."""
    model = make_model()
    batch = collate([build_window(scene_0103, 40, TINY.window_config(max_agents=64))])
    x = torch.randn(6, batch.num_agents, 52, 2, generator=torch.Generator().manual_seed(10))
    ctx = model.encode_context(batch)
    with torch.no_grad():
        twice = model(x, torch.full((6,), 30), batch, ctx.expand(2).expand(3))
        once = model(x, torch.full((6,), 30), batch, ctx.expand(6))
    assert torch.equal(twice, once)
