"""Schedulers: diffusers parity, registry-wide contract, oracle models, learnability, config errors."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

import ddp
from ddp.config import from_dict, to_dict
from ddp.errors import RecipeError
from ddp.registry import get

SCHEDULERS = ddp.list_plugins("scheduler")
LEADING_SHAPES = [(3, 16, 4), (2, 5, 8, 7)]


def build(name: str, options: dict | None = None):
    plugin = get("scheduler", name)
    return plugin.factory(from_dict(plugin.config_cls, options or {}))


def per_sample(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return t.reshape(-1, *([1] * (x.dim() - 1)))


def smooth_fn(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """A fixed, time-dependent stand-in for a network."""
    return 0.7 * torch.sin(1.3 * x + per_sample(t, x) / 17.0) + 0.2 * x


class TinyDenoiser(nn.Module):
    """MLP on (flattened x, condition, sinusoidal features of the raw t value)."""

    def __init__(self, dim: int, hidden: int = 128, n_freqs: int = 8):
        super().__init__()
        self.register_buffer("freqs", torch.logspace(-2, 0, n_freqs))
        self.net = nn.Sequential(
            nn.Linear(dim + 1 + 2 * n_freqs, hidden),
            nn.SiLU(),
            nn.Linear(hidden, hidden),
            nn.SiLU(),
            nn.Linear(hidden, dim),
        )

    def forward(self, x, t, cond):
        angles = t[:, None] * self.freqs
        h = torch.cat([x.flatten(1), cond[:, None], angles.sin(), angles.cos()], dim=1)
        return self.net(h).view_as(x)


@pytest.fixture(autouse=True)
def _threads():
    """Overrides conftest's ``_threads`` here: every tensor in this file is tiny, so one
    thread is fastest, and two threads on a busy 2-core box slow these loops down ~10x."""
    torch.set_num_threads(1)
    yield


# ------------------------------------------------------------------ registry


def test_builtin_schedulers_registered():
    assert {"ddpm", "ddim", "consistency_flow"} <= set(SCHEDULERS)
    assert ddp.list_plugins("scheduler", "dd*") == ["ddim", "ddpm"]


@pytest.mark.parametrize("name", SCHEDULERS)
def test_loss_is_finite_scalar_with_grads(name):
    sched = build(name)
    torch.manual_seed(0)
    net = TinyDenoiser(dim=16 * 4)
    cond = torch.ones(3)
    x0 = torch.rand(3, 16, 4) * 2 - 1
    loss = sched.loss(lambda x, t: net(x, t, cond), x0, generator=torch.Generator().manual_seed(0))
    assert loss.shape == () and torch.isfinite(loss)
    loss.backward()
    for p in net.parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all()
    assert net.net[0].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("name", SCHEDULERS)
def test_loss_is_seeded(name):
    sched = build(name)
    x0 = torch.rand(4, 6, 2)
    losses = [sched.loss(smooth_fn, x0, generator=torch.Generator().manual_seed(s)).item() for s in (1, 1, 2)]
    assert losses[0] == losses[1]
    assert losses[0] != losses[2]


@pytest.mark.parametrize("shape", LEADING_SHAPES)
@pytest.mark.parametrize("name", SCHEDULERS)
def test_sample_keeps_shape(name, shape):
    sched = build(name)
    seen_t = []

    def model_fn(x, t):
        assert x.shape == shape and t.shape == (shape[0],) and t.dtype == x.dtype
        seen_t.append(t)
        return smooth_fn(x, t)

    noise = torch.randn(shape, generator=torch.Generator().manual_seed(0), requires_grad=True)
    out = sched.sample(model_fn, noise, generator=torch.Generator().manual_seed(1))
    assert out.shape == shape and torch.isfinite(out).all()
    assert not out.requires_grad  # sampling builds no graph
    assert len(seen_t) >= 1


#: options other than the defaults, of every kind a config holds (strings, floats, ints, booleans, None)
NON_DEFAULT = {
    "ddpm": {"beta_schedule": "linear", "variance_type": "fixed_small_log", "clip_sample": False,
             "prediction_type": "sample", "num_inference_steps": 25, "beta_end": 0.03},
    "ddim": {"beta_schedule": "scaled_linear", "set_alpha_to_one": False, "steps_offset": 1,
             "timestep_spacing": "trailing", "eta": 0.5, "num_inference_steps": 7, "clip_sample_range": 2.0},
    "consistency_flow": {"eps": 0.02, "num_segments": 3, "num_inference_steps": 2, "stop_grad_r": True,
                         "time_scale": 49.0},
}


@pytest.mark.parametrize("name", SCHEDULERS)
def test_config_round_trip_rebuilds_identically(name):
    plugin = get("scheduler", name)
    assert name in NON_DEFAULT, f"add non-default options of scheduler {name!r} to NON_DEFAULT"
    cfg = from_dict(plugin.config_cls, NON_DEFAULT[name])
    assert cfg != plugin.config_cls()
    again = from_dict(plugin.config_cls, to_dict(cfg))
    assert again == cfg
    a, b = plugin.factory(cfg), plugin.factory(again)
    noise = torch.randn(2, 4, 3, generator=torch.Generator().manual_seed(0))
    out_a = a.sample(smooth_fn, noise, generator=torch.Generator().manual_seed(5))
    out_b = b.sample(smooth_fn, noise, generator=torch.Generator().manual_seed(5))
    assert torch.equal(out_a, out_b)


# ----------------------------------------------------------- diffusers parity

DDPM_CASES = [
    dict(beta_schedule="squaredcos_cap_v2", num_inference_steps=None, variance_type="fixed_small"),
    dict(beta_schedule="linear", num_inference_steps=10, variance_type="fixed_small_log"),
]
DDIM_CASES = [
    dict(),
    dict(eta=1.0, timestep_spacing="trailing", beta_schedule="scaled_linear"),
    dict(num_inference_steps=7, steps_offset=1, set_alpha_to_one=False, beta_schedule="linear"),
]
TOL = 1e-5


def diffusers_chain(ref, n, model_fn, noise, generator, **step_kwargs):
    ref.set_timesteps(n)
    x = noise
    for k in ref.timesteps:
        out = model_fn(x, torch.full((x.shape[0],), float(k)))
        x = ref.step(out, k, x, generator=generator, **step_kwargs).prev_sample
    return x


def check_parity(mine, ref, n, **step_kwargs):
    x0 = torch.rand(6, 16, 3, generator=torch.Generator().manual_seed(0)) * 4 - 2
    noise = torch.randn(6, 16, 3, generator=torch.Generator().manual_seed(1))
    timesteps = torch.randint(0, 100, (6,), generator=torch.Generator().manual_seed(2))
    assert (mine.add_noise(x0, noise, timesteps) - ref.add_noise(x0, noise, timesteps)).abs().max() <= TOL
    # one step from a noisy sample: both outputs
    k = int(mine.timesteps[0])
    model_output = smooth_fn(noise, torch.full((6,), float(k)))
    ours = mine.step(model_output, k, noise, generator=torch.Generator().manual_seed(3))
    ref.set_timesteps(n)
    theirs = ref.step(model_output, k, noise, generator=torch.Generator().manual_seed(3), **step_kwargs)
    assert (ours.prev_sample - theirs.prev_sample).abs().max() <= TOL
    assert (ours.pred_original_sample - theirs.pred_original_sample).abs().max() <= TOL
    # the full chain, same seeded generator for the variance noise
    ours = mine.sample(smooth_fn, noise, generator=torch.Generator().manual_seed(4))
    theirs = diffusers_chain(ref, n, smooth_fn, noise, torch.Generator().manual_seed(4), **step_kwargs)
    assert torch.equal(mine.timesteps, ref.timesteps)
    assert (ours - theirs).abs().max() <= TOL
    assert ours.abs().max() > 0.1  # not a trivially-zero chain


@pytest.mark.parametrize("case", DDPM_CASES)
@pytest.mark.parametrize("clip_sample", [True, False])
@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_ddpm_matches_diffusers(prediction_type, clip_sample, case):
    diffusers = pytest.importorskip("diffusers")
    opts = dict(case, prediction_type=prediction_type, clip_sample=clip_sample)
    mine = build("ddpm", opts)
    ref_opts = {k: v for k, v in opts.items() if k != "num_inference_steps"}
    ref = diffusers.DDPMScheduler(num_train_timesteps=100, **ref_opts)
    assert torch.equal(mine.alphas_cumprod, ref.alphas_cumprod)
    check_parity(mine, ref, case["num_inference_steps"] or 100)


@pytest.mark.parametrize("case", DDIM_CASES)
@pytest.mark.parametrize("clip_sample", [True, False])
@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_ddim_matches_diffusers(prediction_type, clip_sample, case):
    diffusers = pytest.importorskip("diffusers")
    opts = dict(case, prediction_type=prediction_type, clip_sample=clip_sample)
    mine = build("ddim", opts)
    n = opts.pop("num_inference_steps", 10)
    eta = opts.pop("eta", 0.0)
    beta_schedule = opts.pop("beta_schedule", "squaredcos_cap_v2")
    ref = diffusers.DDIMScheduler(num_train_timesteps=100, beta_schedule=beta_schedule, **opts)
    assert torch.equal(mine.alphas_cumprod, ref.alphas_cumprod)
    check_parity(mine, ref, n, eta=eta)


def test_ddim_steps_to_the_next_timestep_of_an_uneven_trailing_grid():
    """Trailing spacing with K = 100, n = 3 steps through 99, 66, 32: from 66 the sample must reach noise
    level 32, the next step's (diffusers' k - K // n gives 33, and the next call then reads a sample of level
    33 as one of level 32)."""
    ddim = build("ddim", dict(num_inference_steps=3, timestep_spacing="trailing", prediction_type="sample",
                             clip_sample=False))
    assert ddim.timesteps.tolist() == [99, 66, 32]
    x0 = torch.full((1, 4, 2), 0.5)
    eps = torch.randn(1, 4, 2, generator=torch.Generator().manual_seed(0))
    ab = ddim.alphas_cumprod
    x66 = ab[66].sqrt() * x0 + (1 - ab[66]).sqrt() * eps
    out = ddim.step(x0, 66, x66).prev_sample  # the exact clean sample predicted: DDIM lands on level 32 exactly
    torch.testing.assert_close(out, ab[32].sqrt() * x0 + (1 - ab[32]).sqrt() * eps, rtol=1e-5, atol=1e-6)
    last = ddim.step(x0, 32, out).prev_sample
    torch.testing.assert_close(last, x0, rtol=1e-5, atol=1e-6)  # after the last step: the clean sample
    for n in (29, 31, 58, 62, 97):  # K / ratio a hair above n: diffusers' grid gets a step at level -1
        grid = build("ddim", dict(num_inference_steps=n, timestep_spacing="trailing")).timesteps.tolist()
        assert len(grid) == n and grid[0] == 99 and min(grid) >= 0 and grid == sorted(set(grid), reverse=True), n
    leading = build("ddim", dict(num_inference_steps=3))
    assert leading.timesteps.tolist() == [66, 33, 0] and leading._previous(66) == 33 and leading._previous(0) == -1


def test_default_timesteps():
    assert build("ddpm").timesteps.tolist() == list(range(99, -1, -1))
    assert build("ddim").timesteps.tolist() == list(range(90, -1, -10))
    ddpm = build("ddpm")
    ddpm.set_timesteps(4)
    assert ddpm.timesteps.tolist() == [75, 50, 25, 0]
    with pytest.raises(ValueError, match="num_inference_steps"):
        ddpm.set_timesteps(0)


# ---------------------------------------------------------------- oracles


@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
@pytest.mark.parametrize("name", ["ddpm", "ddim"])
def test_diffusion_oracle_samples_the_data_distribution(name, prediction_type):
    """With the exact network for a two-point data set (+mu with probability 0.8, -mu), sampling lands on the
    two points in those proportions, and the intermediate samples have the right spread: the component
    orthogonal to mu carries only noise, with variance 1 - alpha_bar_k (DDPM, by sampling) or scaled by
    exactly sqrt((1 - alpha_bar_k') / (1 - alpha_bar_k)) per step (DDIM, deterministic). A one-point data set
    would not test the steps: its clean-sample prediction is the point whatever the path."""
    sched = build(name, {"prediction_type": prediction_type})
    mu, p = torch.tensor([0.5, -0.25, 0.75]), 0.8
    unit = mu / mu.norm()
    seen = {}

    def oracle(x, t):
        alpha_bar = per_sample(sched.alphas_cumprod[t.long()], x)
        # E[x_0 | x_k] of the mixture: mu tanh(sqrt(alpha_bar) <x, mu> / (1 - alpha_bar) + atanh(2p - 1))
        logit = alpha_bar**0.5 * (x * mu).sum(-1, keepdim=True) / (1 - alpha_bar) + 0.5 * math.log(p / (1 - p))
        x0 = mu * torch.tanh(logit)
        seen[int(t[0])] = x.clone()
        return (x - alpha_bar**0.5 * x0) / (1 - alpha_bar) ** 0.5 if prediction_type == "epsilon" else x0

    noise = torch.randn(8000, 3, generator=torch.Generator().manual_seed(0))
    out = sched.sample(oracle, noise, generator=torch.Generator().manual_seed(1))
    plus, minus = (out - mu).norm(dim=-1) < 1e-3, (out + mu).norm(dim=-1) < 1e-3
    assert bool((plus | minus).all())  # every sample is one of the two points
    assert abs(plus.float().mean().item() - p) < 0.04  # in the data's proportions (4.5 standard errors)

    def orthogonal(x):
        return x - (x @ unit)[:, None] * unit

    levels = sched.timesteps.tolist()
    for k in (70, 50, 30, 10):
        assert k in levels
        alpha_bar = sched.alphas_cumprod[k]
        if name == "ddpm":  # the marginal's noise, from 100 random steps
            var = orthogonal(seen[k]).pow(2).sum(-1).mean() / 2
            assert abs(var / (1 - alpha_bar) - 1) < 0.06, (k, var / (1 - alpha_bar))
        else:  # the ODE scales the noise deterministically, from the first level
            scale = ((1 - alpha_bar) / (1 - sched.alphas_cumprod[levels[0]])) ** 0.5
            torch.testing.assert_close(orthogonal(seen[k]), scale * orthogonal(noise), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("steps", [1, 3])
def test_consistency_flow_oracle(steps):
    """The exact velocity of straight paths to a single point: zero loss, exact one-step sample."""
    sched = build("consistency_flow", {"num_inference_steps": steps})
    a1 = torch.tensor([[0.5, -0.25, 0.75]]).expand(64, 3)
    scale = sched.config.time_scale

    def oracle(x, t_scaled):
        t = per_sample(t_scaled / scale, x)
        return (a1 - x) / (1 - t)  # x_t = t a1 + (1 - t) a0  =>  a1 - a0 = (a1 - x_t) / (1 - t)

    assert sched.loss(oracle, a1, generator=torch.Generator().manual_seed(0)) < 1e-10
    out = sched.sample(oracle, torch.randn(64, 3, generator=torch.Generator().manual_seed(0)))
    assert (out - a1).abs().max() < 1e-5


def test_consistency_flow_segments_and_stop_grad():
    sched = build("consistency_flow")
    t = torch.tensor([0.01, 0.3, 0.5, 0.51, 0.99, 1.0])
    assert sched.segment_ends(t).tolist() == [0.5, 0.5, 0.5, 1.0, 1.0, 1.0]
    assert build("consistency_flow", {"num_segments": 1}).segment_ends(t).tolist() == [1.0] * 6

    # stop_grad_r: same loss value, gradient only through the v_t call
    torch.manual_seed(0)
    net = TinyDenoiser(dim=8)
    cond = torch.zeros(16)
    x0 = torch.rand(16, 4, 2)
    grads = []
    for stop in (False, True):
        net.zero_grad()
        s = build("consistency_flow", {"stop_grad_r": stop})
        loss = s.loss(lambda x, t: net(x, t, cond), x0, generator=torch.Generator().manual_seed(0))
        loss.backward()
        grads.append((loss.item(), net.net[0].weight.grad.clone()))
    assert grads[0][0] == pytest.approx(grads[1][0], rel=1e-6)
    assert not torch.allclose(grads[0][1], grads[1][1])


# ------------------------------------------------------------ learnability

PATTERN = torch.tensor([[0.8, -0.3], [0.5, 0.1], [-0.2, 0.6], [-0.7, -0.5]])
LEARN_CASES = [(name, {}) for name in SCHEDULERS] + [("ddim", {"prediction_type": "sample"})]
RMSE_THRESHOLD = 0.15


def sample_rmse(sched, net, generator) -> float:
    cond = torch.tensor([-1.0, 1.0]).repeat(32)
    noise = torch.randn(64, *PATTERN.shape, generator=generator)
    out = sched.sample(lambda x, t: net(x, t, cond), noise, generator=generator)
    return ((out - cond[:, None, None] * PATTERN) ** 2).mean().sqrt().item()


LEARN_IDS = [f"{n}-{o.get('prediction_type', 'default')}" for n, o in LEARN_CASES]


@pytest.mark.parametrize("name,options", LEARN_CASES, ids=LEARN_IDS)
def test_learns_a_conditional_two_point_distribution(name, options):
    """Condition c in {-1, +1} selects the data point c * PATTERN; 300 Adam steps must reach it."""
    sched = build(name, options)
    torch.manual_seed(0)
    net = TinyDenoiser(dim=PATTERN.numel())
    g = torch.Generator().manual_seed(0)
    assert sample_rmse(sched, net, g) > 2 * RMSE_THRESHOLD  # the untrained model fails the check
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(300):
        cond = torch.randint(0, 2, (64,), generator=g).float() * 2 - 1
        x0 = cond[:, None, None] * PATTERN
        loss = sched.loss(lambda x, t: net(x, t, cond), x0, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert sample_rmse(sched, net, g) < RMSE_THRESHOLD


# ------------------------------------------------------------ config errors

BAD_OPTIONS = [
    ("ddpm", {"num_inference_steps": 0}, "num_inference_steps", "0"),
    ("ddpm", {"num_inference_steps": 101}, "num_inference_steps", "101"),
    ("ddpm", {"num_train_timesteps": 0}, "num_train_timesteps", "0"),
    ("ddpm", {"beta_schedule": "linear", "beta_end": 1.5}, "beta_end", "1.5"),
    ("ddpm", {"clip_sample_range": 0.0}, "clip_sample_range", "0.0"),
    ("ddpm", {"prediction_type": "v_prediction"}, "prediction_type", "'v_prediction'"),
    ("ddim", {"num_inference_steps": 0}, "num_inference_steps", "0"),
    ("ddim", {"eta": -0.5}, "eta", "-0.5"),
    ("ddim", {"eta": 1.5}, "eta", "1.5"),
    ("ddim", {"steps_offset": 10}, "steps_offset", "10"),
    ("ddim", {"timestep_spacing": "linspace"}, "timestep_spacing", "'linspace'"),
    ("consistency_flow", {"num_inference_steps": 0}, "num_inference_steps", "0"),
    ("consistency_flow", {"eps": 1.0}, "eps", "1.0"),
    ("consistency_flow", {"delta": 0.0}, "delta", "0.0"),
    ("consistency_flow", {"num_segments": 0}, "num_segments", "0"),
    ("consistency_flow", {"boundary": 2.0}, "boundary", "2.0"),
    ("consistency_flow", {"alpha": -1.0}, "alpha", "-1.0"),
    ("consistency_flow", {"time_scale": 0}, "time_scale", "0.0"),
]


@pytest.mark.parametrize("name,options,field,value", BAD_OPTIONS)
def test_bad_config_names_field_and_value(name, options, field, value):
    """``value`` is how the message prints the received value."""
    plugin = get("scheduler", name)
    with pytest.raises(RecipeError) as info:
        from_dict(plugin.config_cls, options, key="policy.scheduler", source="recipe.yaml")
    message = str(info.value)
    assert field in message and f"got {value}" in message
    assert message.startswith("recipe.yaml: policy.scheduler")


def test_direct_construction_raises_value_error():
    with pytest.raises(ValueError, match=r"num_inference_steps must be in \[1, num_train_timesteps=100\]; got 0"):
        get("scheduler", "ddim").config_cls(num_inference_steps=0)


@pytest.mark.parametrize("name, options", [("ddim", {"prediction_type": "v_prediction"}),
                                           ("ddim", {"timestep_spacing": "linspace"}),
                                           ("ddpm", {"variance_type": "learned"}),
                                           ("ddpm", {"beta_schedule": "cosine"})])
def test_a_config_built_in_python_refuses_a_choice_it_does_not_have(name, options):
    """Recipes are checked on load; a config built in Python ran the fall-through branch (v_prediction
    trained against x0, linspace ran trailing spacing)."""
    field, value = next(iter(options.items()))
    with pytest.raises(ValueError, match=f"{field} must be one of .*; got '{value}'"):
        get("scheduler", name).config_cls(**options)


def test_ddim_at_eta_one_never_takes_a_negative_root():
    """K 1000, one trailing step, alpha_bar after the last step = alpha_bar_0: sigma^2 equals
    1 - alpha_bar' and rounds past it (NaN samples before the clamp)."""
    plugin = get("scheduler", "ddim")
    sched = plugin.factory(plugin.config_cls(num_train_timesteps=1000, num_inference_steps=1, eta=1.0,
                                             timestep_spacing="trailing", set_alpha_to_one=False,
                                             prediction_type="sample", clip_sample=False))
    x = sched.sample(lambda x, k: torch.zeros_like(x), torch.randn(64, 16, 4), generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(x).all()


@pytest.mark.parametrize("name", ["ddpm", "ddim", "consistency_flow"])
def test_bf16_targets_train_at_the_float32_noise_levels(name):
    """Under bf16 autocast the world model's targets (encoder latents) are bf16: the schedule arithmetic and
    the diffusion steps stay in float32 (in bf16, 1 - alpha_bar was 0 at k = 0, 1 and step 999 read 1000)."""
    plugin = get("scheduler", name)
    options = {} if name == "consistency_flow" else {"num_train_timesteps": 1000}
    sched = plugin.factory(plugin.config_cls(**options))
    x0 = torch.randn(64, 8, 4)
    seen = {}

    def model(x, k):
        seen["x"], seen["k"] = x, k
        return torch.zeros_like(x)

    loss32 = sched.loss(model, x0, generator=torch.Generator().manual_seed(0))
    x32, k32 = seen["x"], seen["k"]
    loss16 = sched.loss(model, x0.to(torch.bfloat16), generator=torch.Generator().manual_seed(0))
    assert seen["k"].dtype == torch.float32 and torch.equal(seen["k"], k32)  # the same steps, exactly
    # the same noised samples up to the targets' own bf16 rounding (x0 rounded to 3 significant digits)
    torch.testing.assert_close(seen["x"].float(), x32, atol=0.02, rtol=0.01)
    torch.testing.assert_close(loss16.float(), loss32, atol=0.01, rtol=0.01)
    if name != "consistency_flow":  # add_noise itself: float32 noise levels, the sample's dtype back
        k = torch.tensor([0, 1, 2, 3])
        noise = torch.ones(4, 1)
        out = sched.add_noise(torch.zeros(4, 1, dtype=torch.bfloat16), noise.to(torch.bfloat16), k)
        assert out.dtype == torch.bfloat16
        want = (1 - sched.alphas_cumprod[k]) ** 0.5
        torch.testing.assert_close(out.float().squeeze(1), want, rtol=0.01, atol=0)
