"""Encoders: shapes on any leading dims, keys, DP3 architecture facts, config round trip."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from ddp.config import from_dict, to_dict
from ddp.encoders.dp3 import DP3EncoderConfig
from ddp.errors import RecipeError
from ddp.registry import get

AGENT_POS_DIM = 4
N_POINTS = 32
BATCH_SHAPES = [(), (3,), (2, 3)]


def build(name: str, options: dict | None = None, agent_pos_dim: int = AGENT_POS_DIM, point_dim: int = 3):
    plugin = get("encoder", name)
    return plugin.factory(from_dict(plugin.config_cls, options or {}), agent_pos_dim=agent_pos_dim, point_dim=point_dim)


def inputs(batch_shape, channels: int = 3, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(*batch_shape, N_POINTS, channels, generator=g),
        torch.randn(*batch_shape, AGENT_POS_DIM, generator=g),
    )


@pytest.mark.parametrize("name", ["dp3", "state_mlp"])
@pytest.mark.parametrize("batch_shape", BATCH_SHAPES)
def test_encode_and_forward_shapes(name, batch_shape):
    enc = build(name)
    pc, pos = inputs(batch_shape)
    latent = enc.encode(pc, pos)
    assert latent.shape == (*batch_shape, enc.out_dim)
    assert enc.out_dim == 128

    td = TensorDict({"point_cloud": pc, "agent_pos": pos}, batch_size=batch_shape)
    out = enc(td)
    assert out["latent"].shape == (*batch_shape, 128)
    torch.testing.assert_close(out["latent"], latent)


def test_leading_dims_are_independent():
    """Encoding a [2, 3] batch equals encoding each item alone."""
    enc = build("dp3")
    pc, pos = inputs((2, 3))
    batched = enc.encode(pc, pos)
    single = enc.encode(pc[1, 2], pos[1, 2])
    torch.testing.assert_close(batched[1, 2], single, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", ["dp3", "state_mlp"])
def test_set_keys_renames_and_rejects_unknown_role(name):
    enc = build(name).set_keys(agent_pos="proprio", latent=("obs", "z"))
    assert "proprio" in enc.in_keys and ("obs", "z") in enc.out_keys
    pc, pos = inputs((3,))
    td = TensorDict({"point_cloud": pc, "proprio": pos}, batch_size=[3])
    if name == "dp3":
        enc.set_keys(point_cloud="pc")
        td.rename_key_("point_cloud", "pc")
    enc(td)
    assert td["obs", "z"].shape == (3, 128)
    assert "latent" not in td.keys()
    with pytest.raises(KeyError, match="no key role 'agent_poz'.*did you mean 'agent_pos'"):
        enc.set_keys(agent_poz="x")


def test_state_mlp_reads_no_point_cloud():
    enc = build("state_mlp")
    assert enc.in_keys == ["agent_pos"]
    td = TensorDict({"agent_pos": torch.randn(5, AGENT_POS_DIM)}, batch_size=[5])
    assert enc(td)["latent"].shape == (5, 128)
    assert build("state_mlp", {"out_dim": 32}).encode(None, torch.randn(AGENT_POS_DIM)).shape == (32,)


def test_dp3_architecture_matches_dp3():
    enc = build("dp3")
    linears = [m for m in enc.pointnet if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(3, 64), (64, 128), (128, 256)]
    # each PointNet linear is followed by LayerNorm then ReLU
    kinds = [type(m) for m in enc.pointnet]
    assert kinds == [nn.Linear, nn.LayerNorm, nn.ReLU] * 3
    projection = enc.projection[0]
    assert isinstance(projection, nn.Linear) and (projection.in_features, projection.out_features) == (256, 64)
    assert isinstance(enc.projection[1], nn.LayerNorm)
    state = [type(m) for m in enc.state_mlp]
    assert state == [nn.Linear, nn.ReLU, nn.Linear]  # no final activation
    assert (enc.state_mlp[0].in_features, enc.state_mlp[-1].out_features) == (AGENT_POS_DIM, 64)
    assert enc.out_dim == 64 + 64


def test_dp3_options_change_the_architecture():
    plain = build("dp3", {"use_layernorm": False, "final_norm": "none"})
    assert not any(isinstance(m, nn.LayerNorm) for m in plain.pointnet.modules())
    assert isinstance(plain.projection[1], nn.Identity)
    wide = build("dp3", {"pointnet_channels": [32, 96], "out_channels": 48, "state_channels": [16, 8]})
    assert wide.out_dim == 56
    assert wide.encode(*inputs((2,))).shape == (2, 56)


def test_dp3_max_pool_is_permutation_invariant():
    enc = build("dp3")
    pc, pos = inputs((2,))
    perm = torch.randperm(N_POINTS, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(enc.encode(pc[:, perm], pos), enc.encode(pc, pos), rtol=1e-5, atol=1e-6)
    # and it does depend on the points
    assert not torch.allclose(enc.encode(pc * 2.0, pos), enc.encode(pc, pos))


def test_dp3_color_uses_six_channels():
    with pytest.raises(ValueError, match="set task.point_dim to 6"):
        build("dp3", {"use_color": True})  # colour needs xyz+rgb clouds
    enc = build("dp3", {"use_color": True}, point_dim=6)
    assert enc.pointnet[0].in_features == 6
    pc, pos = inputs((2,), channels=6)
    base = enc.encode(pc, pos)
    recoloured = pc.clone()
    recoloured[..., 3:] = torch.rand_like(recoloured[..., 3:])
    assert not torch.allclose(enc.encode(recoloured, pos), base)
    with pytest.raises(ValueError, match=r"point_cloud must be \[\*, P, 6\]"):
        enc.encode(*inputs((2,), channels=3))


def test_dp3_without_color_ignores_rgb_channels():
    enc = build("dp3")
    pc, pos = inputs((2,), channels=6)
    torch.testing.assert_close(enc.encode(pc, pos), enc.encode(pc[..., :3].contiguous(), pos))


def test_dp3_rejects_mismatched_leading_dims():
    enc = build("dp3")
    pc, _ = inputs((2, 3))
    with pytest.raises(ValueError, match="agent_pos must be"):
        enc.encode(pc, torch.randn(3, AGENT_POS_DIM))


@pytest.mark.parametrize("name", ["dp3", "state_mlp"])
def test_gradients_reach_every_parameter(name):
    enc = build(name)
    enc.encode(*inputs((4,))).square().sum().backward()
    for pname, p in enc.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, pname


@pytest.mark.parametrize(
    "name, options",
    [("dp3", {"use_color": True, "final_norm": "none", "state_channels": [32, 16]}), ("state_mlp", {"hidden": [8]})],
)
def test_config_round_trip_and_state_dict_reload(name, options):
    plugin = get("encoder", name)
    cfg = from_dict(plugin.config_cls, options)
    again = from_dict(plugin.config_cls, to_dict(cfg))
    assert again == cfg
    torch.manual_seed(0)
    enc = plugin.factory(cfg, agent_pos_dim=AGENT_POS_DIM, point_dim=6)
    torch.manual_seed(1)
    rebuilt = plugin.factory(again, agent_pos_dim=AGENT_POS_DIM, point_dim=6)
    pc, pos = inputs((3,), channels=6)
    assert not torch.equal(rebuilt.encode(pc, pos), enc.encode(pc, pos))
    rebuilt.load_state_dict(enc.state_dict())
    assert torch.equal(rebuilt.encode(pc, pos), enc.encode(pc, pos))


@pytest.mark.parametrize(
    "name, options, message",
    [
        ("dp3", {"pointnet_channels": []}, r"pointnet_channels must be a non-empty list of positive widths; got \[\]"),
        ("dp3", {"out_channels": 0}, "out_channels must be positive; got 0"),
        ("dp3", {"final_norm": "batchnorm"}, "must be one of 'layernorm', 'none'; got 'batchnorm'"),
        ("state_mlp", {"out_dim": -1}, "out_dim must be positive; got -1"),
        ("state_mlp", {"hiden": [4]}, "did you mean 'hidden'"),
    ],
)
def test_invalid_options_name_the_field(name, options, message):
    with pytest.raises(RecipeError, match=message):
        from_dict(get("encoder", name).config_cls, options)


def test_bad_agent_pos_dim_raises():
    with pytest.raises(ValueError, match="agent_pos_dim must be positive; got 0"):
        build("dp3", agent_pos_dim=0)


def latents_and_gradients(encoders, pc, pos):
    """Each encoder's latents and its parameters' gradients of one fixed weighted sum of them."""
    outs, grads = [], []
    for enc in encoders:
        enc.zero_grad()
        out = enc.encode(pc, pos)
        (out * torch.arange(out.numel()).reshape(out.shape).sin()).sum().backward()
        outs.append(out.detach())
        grads.append(torch.cat([p.grad.flatten() for p in enc.parameters()]))
    return outs, grads


@pytest.mark.parametrize("block", [N_POINTS, 3 * N_POINTS, 5 * N_POINTS + 7])
def test_point_blocks_give_the_unblocked_latents_and_gradients(block):
    """points_per_block runs the PointNet on whole frames at a time (cache blocking): the latents and the
    gradients equal the all-at-once forward's, whatever the block size and leading dims."""
    torch.manual_seed(0)
    plain = build("dp3", {"points_per_block": 0})
    blocked = build("dp3", {"points_per_block": block})
    blocked.load_state_dict(plain.state_dict())
    pc, pos = inputs((4, 5), seed=3)
    outs, grads = latents_and_gradients((plain, blocked), pc, pos)
    torch.testing.assert_close(outs[1], outs[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-5)  # summed in another order
    for empty in ((0, 2), (5, 0)):  # no frames at all: an empty latent of the right shape, blocked or not
        assert blocked.encode_points(torch.randn(*empty, N_POINTS, 3)).shape == (*empty, 64)
        assert plain.encode_points(torch.randn(*empty, N_POINTS, 3)).shape == (*empty, 64)
    with pytest.raises(RecipeError, match="points_per_block must be >= 0"):
        build("dp3", {"points_per_block": -1})


@pytest.mark.parametrize("n_points", [128, 256])
def test_winners_only_backward_gives_the_dense_latents_and_gradients(n_points):
    """pool_backward 'winners' recomputes, with gradient, only the points that win the max-pool in some
    channel: the latents equal the dense forward's and the parameter gradients match, also with duplicated
    points (exact ties) and frames where a channel's maximum is 0; 'auto' takes it on the CPU from 256
    points per frame, and a forward without gradient never does."""
    torch.manual_seed(0)
    dense = build("dp3", {"pool_backward": "dense", "points_per_block": 3 * n_points})
    winners = build("dp3", {"pool_backward": "winners" if n_points < 256 else "auto", "points_per_block": 3 * n_points})
    winners.load_state_dict(dense.state_dict())
    g = torch.Generator().manual_seed(1)
    pc = torch.randn(4, 5, n_points, 3, generator=g)
    pc[0, 0, 1::2] = pc[0, 0, 0::2]  # every point twice: exact ties in every channel
    pc[1, 2] = pc[1, 2, :1]  # one point repeated: a single distinct winner
    pos = torch.randn(4, 5, AGENT_POS_DIM, generator=g)
    calls = []
    original = winners._winners
    winners._winners = lambda frames: calls.append(frames.shape) or original(frames)  # encode takes the path
    outs, grads = latents_and_gradients((dense, winners), pc, pos)
    assert calls == [(20, n_points, 3)]
    torch.testing.assert_close(outs[1], outs[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-5)
    frames = pc.reshape(-1, n_points, 3)
    assert winners._winners_backward(frames)
    kept = winners._winners(frames)
    assert kept.shape[1] < n_points  # fewer rows through the backward
    assert not dense._winners_backward(frames)
    with torch.no_grad():
        assert not winners._winners_backward(frames)
    assert winners.encode_points(torch.randn(0, 2, n_points, 3)).shape == (0, 2, 64)
    cloud = pc.clone().requires_grad_()  # a cloud that needs its own gradient gets it (the dense path)
    winners.encode_points(cloud).sum().backward()
    assert cloud.grad is not None and cloud.grad.abs().sum() > 0
    auto = build("dp3", {"pool_backward": "auto"})
    assert auto._winners_backward(torch.randn(2, 256, 3)) and not auto._winners_backward(torch.randn(2, 128, 3))
    with pytest.raises(RecipeError, match="pool_backward: must be one of"):
        build("dp3", {"pool_backward": "sparse"})
    with pytest.raises(ValueError, match="pool_backward must be"):
        DP3EncoderConfig(pool_backward="winner")


def test_indexed_max_pool_gives_amax_latents_and_gradients():
    """Training (parameters need gradients, the cloud does not) pools with max(dim) and its index scatter;
    latents and parameter gradients equal amax's (DP3's pooling), ties from duplicated points and
    all-clamped channels included; a cloud that needs its own gradient gets amax's even split among ties."""
    torch.manual_seed(0)
    enc = build("dp3", {"pool_backward": "dense", "points_per_block": 2 * N_POINTS})
    g = torch.Generator().manual_seed(2)
    pc = torch.randn(3, 4, N_POINTS, 3, generator=g)
    pc[0, 0, 1::2] = pc[0, 0, 0::2]  # every point twice: a tie in every channel
    pc[1, 1] = pc[1, 1, :1]  # one point repeated
    pos = torch.randn(3, 4, AGENT_POS_DIM, generator=g)
    reference = build("dp3", {"points_per_block": 0})  # DP3's encoder: per-point MLP, amax over the points
    reference.load_state_dict(enc.state_dict())
    reference.encode_points = lambda points: reference.projection(reference.pointnet(points).amax(dim=-2))
    outs, grads = latents_and_gradients((enc, reference), pc, pos)
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=1e-6)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-5)
    weights = torch.arange(enc.config.out_channels).sin()
    cloud = pc[0, 0].clone().requires_grad_()  # the cloud's own gradient: the tied twins share it evenly
    (enc.encode_points(cloud) * weights).sum().backward()  # (a plain sum of a LayerNorm is constant)
    torch.testing.assert_close(cloud.grad[0::2], cloud.grad[1::2])
    assert cloud.grad.abs().sum() > 0
