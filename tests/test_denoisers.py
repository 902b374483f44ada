"""Denoisers: one call signature on any leading dims, keys, U-Net layout, parameter counts, round trip."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from ddp.config import from_dict, to_dict
from ddp.errors import RecipeError
from ddp.registry import get

# A small U-Net for fast tests (the layout is the same as the paper's sizes).
SMALL = {"down_dims": [16, 32, 64], "n_groups": 4, "diffusion_step_embed_dim": 16, "kernel_size": 3}
BATCH_SHAPES = [(), (3,), (2, 3)]

# (name, context, horizon): the policy denoises H=16 actions of dim 4 given M=2 latents of 128;
# the world model denoises N=8 latents given the history (2 x 128) and 8 actions of dim 4.
POLICY = ("unet1d", {"input_dim": 4, "global_cond_dim": 256}, 16)
WORLD = ("unet1d_wm", {"input_dim": 128, "global_cond_dim": 32, "local_cond_dim": 256}, 8)
CASES = [POLICY, WORLD]
IDS = ["unet1d", "unet1d_wm"]


def build(name: str, context: dict, options: dict | None = None):
    plugin = get("denoiser", name)
    return plugin.factory(from_dict(plugin.config_cls, {**SMALL, **(options or {})}), **context)


def inputs(context: dict, horizon: int, batch_shape=(), seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    out = {
        "sample": torch.randn(*batch_shape, horizon, context["input_dim"], generator=g),
        "timestep": torch.randint(0, 100, batch_shape, generator=g),
        "global_cond": torch.randn(*batch_shape, context["global_cond_dim"], generator=g),
    }
    if "local_cond_dim" in context:
        out["local_cond"] = torch.randn(*batch_shape, context["local_cond_dim"], generator=g)
    return out


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
@pytest.mark.parametrize("batch_shape", BATCH_SHAPES)
def test_predict_and_forward_shapes(name, context, horizon, batch_shape):
    net = build(name, context)
    x = inputs(context, horizon, batch_shape)
    pred = net.predict(**x)
    assert pred.shape == (*batch_shape, horizon, context["input_dim"])

    td = TensorDict(x, batch_size=batch_shape)
    net(td)
    assert td["prediction"].shape == pred.shape
    torch.testing.assert_close(td["prediction"], pred)


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
def test_leading_dims_are_independent(name, context, horizon):
    """A [2, 3] batch gives per item what the item gives alone (GroupNorm is per sample)."""
    net = build(name, context)
    x = inputs(context, horizon, (2, 3))
    batched = net.predict(**x)
    single = net.predict(**{k: v[1, 2] for k, v in x.items()})
    torch.testing.assert_close(batched[1, 2], single, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
def test_timestep_scalar_float_and_long(name, context, horizon):
    net = build(name, context)
    x = inputs(context, horizon, (3,))
    x["timestep"] = torch.full((3,), 7)
    as_long = net.predict(**x)
    torch.testing.assert_close(net.predict(**{**x, "timestep": 7}), as_long)
    torch.testing.assert_close(net.predict(**{**x, "timestep": torch.tensor(7.0)}), as_long)
    # the step embedding matters, also between fractional steps
    assert not torch.allclose(net.predict(**{**x, "timestep": 7.5}), as_long)
    with pytest.raises(ValueError, match="timestep must be a scalar or have the sample's leading dims"):
        net.predict(**{**x, "timestep": torch.zeros(2)})


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
def test_set_keys_renames_and_rejects_unknown_role(name, context, horizon):
    net = build(name, context).set_keys(sample=("noisy", "a"), global_cond="obs_cond", prediction="eps_hat")
    x = inputs(context, horizon, (2,))
    td = TensorDict({("noisy", "a"): x.pop("sample"), "obs_cond": x.pop("global_cond"), **x}, batch_size=[2])
    net(td)
    assert td["eps_hat"].shape == (2, horizon, context["input_dim"])
    assert "prediction" not in td.keys()
    with pytest.raises(KeyError, match="no key role 'global_cnd'.*did you mean 'global_cond'"):
        net.set_keys(global_cnd="x")


def test_world_model_declares_local_cond_key():
    assert build(*WORLD[:2]).in_keys == ["sample", "timestep", "global_cond", "local_cond"]
    assert build(*POLICY[:2]).in_keys == ["sample", "timestep", "global_cond"]


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
def test_horizon_must_match_the_downsampling(name, context, horizon):
    net = build(name, context)
    x = inputs(context, horizon)
    x["sample"] = torch.randn(18, context["input_dim"])
    with pytest.raises(ValueError, match="horizon 18 must be a multiple of 4 for down_dims of length 3"):
        net.predict(**x)
    two_levels = build(name, context, {"down_dims": [16, 32]})
    x["sample"] = torch.randn(6, context["input_dim"])
    assert two_levels.predict(**x).shape == (6, context["input_dim"])


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
def test_wrong_shapes_raise(name, context, horizon):
    net = build(name, context)
    x = inputs(context, horizon, (2,))
    with pytest.raises(ValueError, match="global_cond must be"):
        net.predict(**{**x, "global_cond": torch.randn(2, 3)})
    with pytest.raises(ValueError, match="sample must be"):
        net.predict(**{**x, "sample": torch.randn(2, horizon, context["input_dim"] + 1)})


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
@pytest.mark.parametrize("options", [{}, {"cond_predict_scale": False}, {"blocks_per_level": 1, "mid_blocks": 1}])
def test_gradients_reach_every_parameter(name, context, horizon, options):
    net = build(name, context, options)
    net.predict(**inputs(context, horizon, (2,))).square().sum().backward()
    for pname, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, pname


def test_world_model_concatenates_the_history_channel_wise():
    name, context, horizon = WORLD
    net = build(name, context)
    x = inputs(context, horizon, (2,))
    base = net.predict(**x)
    # the U-Net's first conv sees local_cond_dim + input_dim channels
    assert net.unet.down[0].blocks[0].conv1[0].in_channels == 256 + 128
    assert net.unet.down[0].blocks[0].conv1[0].out_channels == 16
    # X_in = Repeat(x_obs, N) (+) X_sample, as the first convolution receives it ([B, C, T])
    seen = []
    hook = net.unet.down[0].blocks[0].conv1[0].register_forward_pre_hook(lambda mod, args: seen.append(args[0]))
    net.predict(**x)
    hook.remove()
    x_in = seen[0]
    assert x_in.shape == (2, 256 + 128, horizon)
    torch.testing.assert_close(x_in[:, :256], x["local_cond"][:, :, None].expand(2, 256, horizon))
    torch.testing.assert_close(x_in[:, 256:], x["sample"].transpose(1, 2))
    # a history given per step is concatenated as given
    varied = torch.randn(2, horizon, 256)
    hook = net.unet.down[0].blocks[0].conv1[0].register_forward_pre_hook(lambda mod, args: seen.append(args[0]))
    net.predict(**{**x, "local_cond": varied})
    hook.remove()
    torch.testing.assert_close(seen[1][:, :256], varied.transpose(1, 2))
    # changing the history changes the prediction
    assert not torch.allclose(net.predict(**{**x, "local_cond": x["local_cond"] + 1.0}), base)
    # [*, L] is repeated over the N steps: same as passing it already per step
    per_step = x["local_cond"].unsqueeze(-2).expand(2, horizon, 256)
    torch.testing.assert_close(net.predict(**{**x, "local_cond": per_step}), base)
    with pytest.raises(ValueError, match="needs local_cond"):
        net.predict(**{**x, "local_cond": None})
    with pytest.raises(ValueError, match="local_cond must be"):
        net.predict(**{**x, "local_cond": torch.randn(2, 255)})


def test_world_model_uses_the_actions_as_global_condition():
    name, context, horizon = WORLD
    net = build(name, context)
    x = inputs(context, horizon, (2,))
    assert not torch.allclose(net.predict(**{**x, "global_cond": x["global_cond"] * -1.0}), net.predict(**x))


def test_policy_takes_no_local_cond():
    name, context, horizon = POLICY
    net = build(name, context)
    with pytest.raises(ValueError, match="takes no local_cond"):
        net.predict(**inputs(context, horizon), local_cond=torch.randn(8))


# ---------------------------------------------------------------- parameter counts


def expected_params(
    in_channels, out_channels, global_cond_dim, down_dims, *, kernel=5, embed=128, blocks=2, mid=2, scale=True
):
    """Parameter count of the layout described in the U-Net's docstring, computed by hand."""

    def conv(c_in, c_out, k):
        return c_in * c_out * k + c_out

    def conv_block(c_in, c_out):  # Conv1d + GroupNorm(weight, bias)
        return conv(c_in, c_out, kernel) + 2 * c_out

    cond = embed + global_cond_dim

    def res(c_in, c_out):
        film = cond * (2 if scale else 1) * c_out + (2 if scale else 1) * c_out
        skip = conv(c_in, c_out, 1) if c_in != c_out else 0
        return conv_block(c_in, c_out) + conv_block(c_out, c_out) + film + skip

    total = (embed * 4 * embed + 4 * embed) + (4 * embed * embed + embed)  # step-embedding MLP
    widths = [in_channels, *down_dims]
    for i in range(len(down_dims)):
        total += res(widths[i], widths[i + 1]) + (blocks - 1) * res(widths[i + 1], widths[i + 1])
        if i < len(down_dims) - 1:
            total += conv(widths[i + 1], widths[i + 1], 3)  # downsample
    total += mid * res(down_dims[-1], down_dims[-1])
    for i in reversed(range(1, len(down_dims))):
        total += res(2 * down_dims[i], down_dims[i - 1]) + (blocks - 1) * res(down_dims[i - 1], down_dims[i - 1])
        total += conv(down_dims[i - 1], down_dims[i - 1], 4)  # transposed-conv upsample
    total += conv_block(down_dims[0], down_dims[0]) + conv(down_dims[0], out_channels, 1)
    return total


def n_params(net) -> int:
    return sum(p.numel() for p in net.parameters())


@pytest.mark.parametrize(
    "name, context, options",
    [
        ("unet1d", POLICY[1], {}),
        ("unet1d", POLICY[1], {"cond_predict_scale": False, "blocks_per_level": 1, "mid_blocks": 0}),
        ("unet1d_wm", WORLD[1], {"down_dims": [8, 16], "kernel_size": 5, "blocks_per_level": 3, "mid_blocks": 1}),
    ],
)
def test_small_parameter_counts_match_the_layout(name, context, options):
    net = build(name, context, options)
    cfg = net.config
    in_channels = context["input_dim"] + context.get("local_cond_dim", 0)
    assert n_params(net) == expected_params(
        in_channels,
        context["input_dim"],
        context["global_cond_dim"],
        cfg.down_dims,
        kernel=cfg.kernel_size,
        embed=cfg.diffusion_step_embed_dim,
        blocks=cfg.blocks_per_level,
        mid=cfg.mid_blocks,
        scale=cfg.cond_predict_scale,
    )


# (label, name, context, options, plausible range in millions)
PAPER_SIZES = [
    ("DDP sim policy [256,512,1024]", "unet1d", POLICY[1], {"down_dims": [256, 512, 1024]}, (60, 72)),
    ("DDP sim world model [256,512,1024]", "unet1d_wm", WORLD[1], {"down_dims": [256, 512, 1024]}, (58, 70)),
    ("Simple DDP policy [128,256,384]", "unet1d", POLICY[1], {"down_dims": [128, 256, 384]}, (11, 15)),
    ("Simple DDP world model [128,256,512]", "unet1d_wm", WORLD[1], {"down_dims": [128, 256, 512]}, (15, 19)),
    (
        "Simple DP3 [128,256,384], 1 block/level, 1 mid",
        "unet1d",
        POLICY[1],
        {"down_dims": [128, 256, 384], "blocks_per_level": 1, "mid_blocks": 1},
        (7.0, 7.8),  # DP3 reports ~7.4 M
    ),
    # DP3's own [512,1024,2048] U-Net (~1 GB if built: counted on the meta device)
    ("DP3 [512,1024,2048]", "unet1d", POLICY[1], {"down_dims": [512, 1024, 2048]}, (250, 260)),
]


@pytest.mark.parametrize("label, name, context, options, bounds", PAPER_SIZES, ids=[p[0] for p in PAPER_SIZES])
def test_paper_sizes(label, name, context, options, bounds):
    plugin = get("denoiser", name)
    cfg = from_dict(plugin.config_cls, options)  # the defaults: kernel 5, GroupNorm 8, step embedding 128
    with torch.device("meta"):  # shapes only: no memory, no initialisation cost
        net = plugin.factory(cfg, **context)
    count = n_params(net)
    print(f"{label}: {count:,} parameters")
    in_channels = context["input_dim"] + context.get("local_cond_dim", 0)
    assert count == expected_params(
        in_channels,
        context["input_dim"],
        context["global_cond_dim"],
        cfg.down_dims,
        blocks=cfg.blocks_per_level,
        mid=cfg.mid_blocks,
    )
    assert bounds[0] * 1e6 < count < bounds[1] * 1e6


def test_default_config_is_the_paper_sim_size():
    cfg = get("denoiser", "unet1d").config_cls()
    assert cfg.down_dims == (256, 512, 1024) and cfg.diffusion_step_embed_dim == 128
    assert (cfg.kernel_size, cfg.n_groups, cfg.blocks_per_level, cfg.mid_blocks) == (5, 8, 2, 2)
    assert cfg.cond_predict_scale is True and cfg.condition_type == "film"


# ---------------------------------------------------------------- config


@pytest.mark.parametrize("name, context, horizon", CASES, ids=IDS)
def test_config_round_trip_and_state_dict_reload(name, context, horizon):
    plugin = get("denoiser", name)
    cfg = from_dict(plugin.config_cls, {**SMALL, "cond_predict_scale": False, "mid_blocks": 1})
    again = from_dict(plugin.config_cls, to_dict(cfg))
    assert again == cfg and isinstance(again.down_dims, tuple)
    torch.manual_seed(0)
    net = plugin.factory(cfg, **context)
    torch.manual_seed(1)
    rebuilt = plugin.factory(again, **context)
    x = inputs(context, horizon, (2,))
    assert not torch.equal(rebuilt.predict(**x), net.predict(**x))
    rebuilt.load_state_dict(net.state_dict())
    assert torch.equal(rebuilt.predict(**x), net.predict(**x))


@pytest.mark.parametrize("name", ["unet1d", "unet1d_wm"])
@pytest.mark.parametrize(
    "options, message",
    [
        ({"down_dims": []}, r"down_dims must be non-empty; got \[\]"),
        ({"down_dims": [16, 30]}, r"divisible by n_groups=8; got \[16, 30\]"),
        ({"kernel_size": 4}, "kernel_size must be a positive odd number .*; got 4"),
        ({"diffusion_step_embed_dim": 7}, "diffusion_step_embed_dim must be even and >= 4; got 7"),
        ({"blocks_per_level": 0}, "blocks_per_level must be >= 1; got 0"),
        ({"condition_type": "cross_attention"}, "must be one of 'film'; got 'cross_attention'"),
        ({"down_dim": [8]}, "did you mean 'down_dims'"),
    ],
)
def test_invalid_options_name_the_field(name, options, message):
    with pytest.raises(RecipeError, match=message):
        from_dict(get("denoiser", name).config_cls, options)


@pytest.mark.parametrize("bias", [True, False])
@pytest.mark.parametrize("input_grad", [True, False])
def test_matmul_weight_gradient_conv_matches_torch(bias, input_grad):
    """ddp's Conv1d with its CPU weight gradient as a matmul: the same output and gradients as nn.Conv1d
    (the same parameters, state_dict interchangeable), with and without bias and input gradient."""
    from ddp.denoisers.conv import Conv1d

    torch.manual_seed(0)
    fast = Conv1d(6, 10, 5, padding=2, bias=bias, weight_grad="matmul")
    plain = torch.nn.Conv1d(6, 10, 5, padding=2, bias=bias)
    plain.load_state_dict(fast.state_dict())
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, 6, 7, generator=g)
    upstream = torch.randn(3, 10, 7, generator=g)
    results = []
    for conv in (fast, plain):
        xi = x.clone().requires_grad_(input_grad)
        y = conv(xi)
        y.backward(upstream)
        results.append((y.detach(), xi.grad, [p.grad for p in conv.parameters()]))
        if conv is fast:
            assert "MatmulWeightGrad" in type(y.grad_fn).__name__  # the fast backward really ran
    (y1, gx1, gp1), (y2, gx2, gp2) = results
    torch.testing.assert_close(y1, y2)
    if input_grad:
        torch.testing.assert_close(gx1, gx2)
    else:
        assert gx1 is None and gx2 is None
    for a, b in zip(gp1, gp2):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_unet_weight_gradient_kernels_agree_and_auto_picks_where_matmul_pays():
    """A whole U-Net trains identically (within float rounding) with either weight-gradient kernel; 'auto'
    takes the matmul for large weights and short sequences only; inference and 'onednn' never do."""
    from ddp.denoisers.conv import Conv1d, matmul_pays

    name, context, horizon = WORLD
    fast, plain = build(name, context, {"cpu_weight_grad": "matmul"}), build(name, context, {"cpu_weight_grad": "onednn"})
    plain.load_state_dict(fast.state_dict())
    convs = [m for m in fast.modules() if isinstance(m, Conv1d)]
    assert len(convs) > 10 and all(c.weight_grad == "matmul" for c in convs)  # the option reaches every block
    batch = inputs(context, horizon, (5,), seed=2)
    grads = []
    for net in (fast, plain):
        net.predict(**batch).square().mean().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-6)
    assert matmul_pays(1024 * 1024 * 5, 16) and matmul_pays(512 * 512 * 5, 2)
    assert not matmul_pays(512 * 512 * 5, 8) and not matmul_pays(64 * 64 * 5, 2)
    assert not matmul_pays(128 * 128 * 5, 4)
    conv = Conv1d(256, 256, 5, padding=2)  # 327,680 weights
    assert conv._matmul_grad(torch.randn(2, 256, 2)) and not conv._matmul_grad(torch.randn(2, 256, 4))
    with torch.no_grad():
        assert not conv._matmul_grad(torch.randn(2, 256, 2))
    assert not Conv1d(256, 256, 5, padding=2, weight_grad="onednn")._matmul_grad(torch.randn(2, 256, 2))
    assert not Conv1d(256, 256, 5, padding=2, weight_grad="matmul")._matmul_grad(torch.randn(256, 2))  # unbatched
    with pytest.raises(RecipeError, match="cpu_weight_grad: must be one of"):
        build(name, context, {"cpu_weight_grad": "mkl"})
