"""DreamDiffusionPolicy: shapes, the joint loss of Algorithm 1, DP3 equivalence, EMA."""

import pytest
import torch
from tensordict import TensorDict

from conftest import fit_normalizer
from ddp import build
from ddp.models.ema import ema_decay
from ddp.schema import EMAConfig


def batch_of(exp, batch_size=6, seed=0):
    from ddp.data.sequence import SequenceDataset

    ds = SequenceDataset(exp.episodes(), 16, pad_before=1, pad_after=7, keys=["point_cloud", "agent_pos", "action"])
    idx = torch.randperm(len(ds), generator=torch.Generator().manual_seed(seed))[:batch_size]
    return ds.batch(idx)


@pytest.fixture
def exp(tiny_recipe):
    e = build(tiny_recipe)
    fit_normalizer(e)
    return e


def test_loss_terms_and_total(exp):
    out = exp.model.loss(batch_of(exp), generator=torch.Generator().manual_seed(1))
    assert set(out.keys()) == {"loss", "loss_bc", "loss_wm", "wm_error"}
    assert torch.allclose(out["loss"], out["loss_bc"] + 1.0 * out["loss_wm"])
    assert out["loss_bc"] > 0 and out["loss_wm"] > 0


def test_world_model_weight_scales_the_total(tiny_recipe):
    tiny_recipe["world_model"]["weight"] = 0.25
    e = build(tiny_recipe)
    out = e.model.loss(batch_of(e), generator=torch.Generator().manual_seed(1))
    # TorchRL's convention: the loss_* keys sum to the objective, so loss_wm carries lambda
    objective = sum(out[k] for k in out.keys() if k.startswith("loss_"))
    assert torch.allclose(out["loss"], objective) and torch.allclose(out["loss"], out["loss_bc"] + 0.25 * out["wm_error"])
    assert torch.allclose(out["loss_wm"], 0.25 * out["wm_error"]) and not out["wm_error"].requires_grad


def _encoder_grad(model, loss):
    model.zero_grad(set_to_none=True)
    loss.backward()
    return torch.cat([p.grad.flatten() for p in model.encoder.parameters() if p.grad is not None])


def test_gradients_from_both_losses_reach_the_encoder(exp):
    m, batch = exp.model, batch_of(exp)
    g_bc = _encoder_grad(m, m.loss(batch, generator=torch.Generator().manual_seed(0))["loss_bc"])
    g_wm = _encoder_grad(m, m.loss(batch, generator=torch.Generator().manual_seed(0))["loss_wm"])
    assert g_bc.abs().sum() > 0 and g_wm.abs().sum() > 0
    n_enc = sum(p.numel() for p in m.encoder.parameters())
    assert g_bc.numel() == n_enc and g_wm.numel() == n_enc  # every encoder parameter gets a gradient
    assert not torch.allclose(g_bc, g_wm)
    # world-model targets are encoded too: the future observations influence L_WM
    batch2 = batch.clone()
    batch2["point_cloud"][:, 2:] += 0.05
    l1 = m.loss(batch, generator=torch.Generator().manual_seed(0))["loss_wm"]
    l2 = m.loss(batch2, generator=torch.Generator().manual_seed(0))["loss_wm"]
    assert not torch.allclose(l1, l2)


def test_lambda_zero_and_no_world_model_equal_dp3(tiny_recipe):
    tiny_recipe["world_model"]["weight"] = 0.0
    ddp0 = build(tiny_recipe)
    tiny_recipe["world_model"]["enabled"] = False
    dp3 = build(tiny_recipe)
    assert dp3.model.world_model_net is None
    # same shared weights (built from the same seed, loaded explicitly anyway)
    dp3.model.load_state_dict({k: v for k, v in ddp0.model.state_dict().items() if not k.startswith("world_model")})
    batch = batch_of(ddp0)
    out0 = ddp0.model.loss(batch, generator=torch.Generator().manual_seed(3))
    out1 = dp3.model.loss(batch, generator=torch.Generator().manual_seed(3))
    assert torch.equal(out0["loss"], out1["loss"]) and torch.equal(out0["loss_bc"], out1["loss_bc"])
    g0 = _encoder_grad(ddp0.model, out0["loss"])
    g1 = _encoder_grad(dp3.model, out1["loss"])
    torch.testing.assert_close(g0, g1, rtol=1e-5, atol=1e-7)  # encoder batch differs (M vs M+N frames)


def test_a_model_without_world_model_trains_on_windows_of_its_horizon(tiny_recipe, tmp_path):
    """FlowPolicy's shapes (horizon 4 = M + N - 1): windows of H frames, as DP3's and FlowPolicy's own code
    cut them (one more window per episode end than M + N frames would give); with a world model, M + N."""
    from ddp.data.sequence import SequenceDataset

    tiny_recipe["policy"].update(horizon=4, obs_steps=2, action_steps=3)
    tiny_recipe["world_model"]["denoiser"]["down_dims"] = [16]  # no halving: it denoises N = 3 latents
    with_wm = build(tiny_recipe)
    assert with_wm.model.window == 5
    tiny_recipe["world_model"]["enabled"] = False
    tiny_recipe["train"].update(max_steps=1, output_dir=str(tmp_path), logger="none")
    e = build(tiny_recipe)
    assert e.model.window == 4
    fit_normalizer(e)
    ds = SequenceDataset(e.episodes(), e.model.window, pad_before=1, pad_after=2,
                         keys=["point_cloud", "agent_pos", "action"])
    out = e.model.loss(ds.batch(torch.arange(4)), generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(out["loss"])
    assert e.train(progress=False).steps == 1


@pytest.mark.parametrize("batch_shape", [(2,), (2, 3)])
def test_inference_shapes_over_batch_dims(exp, batch_shape):
    m = exp.model.eval()
    pc = torch.rand(*batch_shape, 2, 64, 3)
    pos = torch.rand(*batch_shape, 2, 9)
    td = m(TensorDict({"point_cloud": pc, "agent_pos": pos}, batch_size=batch_shape))
    assert td["latent"].shape == (*batch_shape, 2, m.latent_dim)
    assert td["action_chunk"].shape == (*batch_shape, 16, 4)
    assert td["action"].shape == (*batch_shape, 8, 4)
    assert torch.equal(td["action"], td["action_chunk"][..., 1:9, :])
    future = m.imagine(td["latent"], td["action"])
    assert future.shape == (*batch_shape, 8, m.latent_dim)


def test_sampling_is_seeded(exp):
    m = exp.model.eval()
    hist = torch.randn(3, 2, m.latent_dim)
    a1 = m.sample_actions(hist, generator=torch.Generator().manual_seed(5))
    a2 = m.sample_actions(hist, generator=torch.Generator().manual_seed(5))
    a3 = m.sample_actions(hist, generator=torch.Generator().manual_seed(6))
    assert torch.equal(a1, a2) and not torch.equal(a1, a3)


def test_imagine_without_world_model_raises(tiny_recipe):
    tiny_recipe["world_model"]["enabled"] = False
    m = build(tiny_recipe).model
    with pytest.raises(RuntimeError, match="no world model"):
        m.imagine(torch.zeros(1, 2, m.latent_dim), torch.zeros(1, 8, 4))


def test_normalizer_maps_to_unit_range_and_back(exp):
    n = exp.model.normalizer
    act = exp.episodes().steps["action"]
    z = n.normalize("action", act)
    assert z.min() >= -1 - 1e-5 and z.max() <= 1 + 1e-5
    assert torch.allclose(n.unnormalize("action", z), act, atol=1e-5)
    # statistics live in the state dict
    assert "normalizer.action_scale" in exp.model.state_dict() and bool(n.fitted)


def test_ema_decay_schedule():
    cfg = EMAConfig(power=0.75, max_value=0.9999)
    assert ema_decay(1, cfg) == 0.0
    assert ema_decay(2, cfg) == pytest.approx(1 - 2 ** -0.75)
    assert ema_decay(10_000_000, cfg) == 0.9999
    assert ema_decay(5, EMAConfig(update_after_step=10)) == 0.0


def test_ema_updates_follow_dp3_warm_up():
    """DP3's EMAModel.step takes the decay of the updates made before it, then counts: its first two
    updates copy the weights and the third averages with 1 - 2 ** -0.75 (ddp ran one update ahead)."""
    from ddp.models.ema import EMA

    model = torch.nn.Linear(2, 2)
    ema = EMA(model, EMAConfig())
    assert [ema.update(model) for _ in range(3)] == [0.0, 0.0, pytest.approx(1 - 2 ** -0.75)]
    assert int(ema.optimization_step) == 3


def test_ema_tracks_the_weights(exp):
    from ddp.models.ema import EMA

    m = exp.model
    ema = EMA(m, exp.recipe.ema)
    p0 = next(ema.module.parameters()).clone()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(1.0)
    ema.update(m)  # first update: decay 0 -> copy
    assert torch.allclose(next(ema.module.parameters()), p0 + 1.0)
    ema.update(m)  # the second too (DP3's warm-up)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(1.0)
    d = ema.update(m)
    assert 0 < d < 1
    assert torch.allclose(next(ema.module.parameters()), p0 + 1.0 + (1 - d))


@pytest.mark.parametrize("target_gradient", [True, False])
def test_world_model_target_gradient_option(tiny_recipe, target_gradient):
    tiny_recipe["world_model"]["target_gradient"] = target_gradient
    e = build(tiny_recipe)
    batch = batch_of(e)
    pc = batch["point_cloud"].clone().requires_grad_(True)
    batch["point_cloud"] = pc
    e.model.loss(batch, generator=torch.Generator().manual_seed(0))["loss_wm"].backward()
    future_grad = pc.grad[:, 2:10].abs().sum()
    assert (future_grad > 0) == target_gradient  # Algorithm 1: the future targets are encoded with gradients
    assert pc.grad[:, :2].abs().sum() > 0


def test_world_model_targets_are_exactly_the_n_frames_after_the_history(tiny_recipe):
    """L_WM's targets are frames M .. M+N-1 (every one of them, none after): the gradient through the target
    encoding reaches exactly those frames."""
    tiny_recipe["world_model"]["target_gradient"] = True
    e = build(tiny_recipe)
    M, N = e.model.obs_steps, e.model.action_steps
    batch = batch_of(e)
    pc = batch["point_cloud"].clone().requires_grad_(True)
    batch["point_cloud"] = pc
    e.model.loss(batch, generator=torch.Generator().manual_seed(0))["loss_wm"].backward()
    per_frame = pc.grad.abs().sum(dim=(0, 2, 3))
    assert bool((per_frame[: M + N] > 0).all()), per_frame
    assert bool((per_frame[M + N :] == 0).all()), per_frame


def test_world_model_conditions_on_the_executed_actions_only(exp):
    """W_phi(O_curr, a_t) in training: a_t is the executed chunk actions[M-1 : M-1+N] (the one DP3 executes),
    so actions before it or after it leave L_WM bit for bit, each action in it changes it."""
    M, N = exp.model.obs_steps, exp.model.action_steps
    batch = batch_of(exp)

    def wm_error(b):
        return exp.model.loss(b, generator=torch.Generator().manual_seed(0))["wm_error"]

    base = wm_error(batch)
    for index, changes in ((0, False), (M - 1, True), (M + N - 2, True), (M + N - 1, False)):
        other = batch.clone()
        other["action"][:, index] += 0.3
        assert (not torch.equal(wm_error(other), base)) == changes, index


def test_imagine_conditions_the_world_model_as_training_does(exp):
    """imagine(encode(history), executed actions) hands the world model's denoiser the same global and local
    conditions as loss() does for the same window: a train / inference mismatch would pass every loss test."""
    M, N = exp.model.obs_steps, exp.model.action_steps
    batch = batch_of(exp, batch_size=2)
    seen = []
    predict = exp.model.world_model_net.predict
    exp.model.world_model_net.predict = lambda x, t, *cond: seen.append(cond) or predict(x, t, *cond)
    exp.model.eval()
    with torch.no_grad():
        exp.model.loss(batch, generator=torch.Generator().manual_seed(0))
        latent = exp.model.encode(batch["point_cloud"][:, :M], batch["agent_pos"][:, :M])
        exp.model.imagine(latent, batch["action"][:, M - 1 : M - 1 + N], generator=torch.Generator().manual_seed(0))
    training, imagined = seen[0], seen[1]
    assert len(training) == len(imagined) and len(training) > 0
    for a, b in zip(training, imagined):
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-5), (a.shape, (a - b).abs().max())


@pytest.mark.parametrize("target_gradient", [True, False])
def test_world_model_batch_fraction_uses_only_the_first_samples_futures(tiny_recipe, target_gradient):
    tiny_recipe["world_model"].update(target_gradient=target_gradient, batch_fraction=0.5)
    e = build(tiny_recipe)
    fit_normalizer(e)
    batch = batch_of(e, batch_size=6)  # L_WM on ceil(0.5 * 6) = 3 samples
    seen = []
    predict = e.model.world_model_net.predict
    e.model.world_model_net.predict = lambda x, t, *cond: seen.append(x.shape[0]) or predict(x, t, *cond)

    def loss_wm(b):
        return e.model.loss(b, generator=torch.Generator().manual_seed(0))["loss_wm"]

    base = loss_wm(batch)
    assert seen == [3]
    other = batch.clone()
    other["point_cloud"][3:, 2:] += 0.5  # the futures of the samples left out of L_WM
    assert torch.equal(loss_wm(other), base)
    other = batch.clone()
    other["point_cloud"][:3, 2:] += 0.5  # the futures L_WM is computed on
    assert not torch.allclose(loss_wm(other), base)
    pc = batch["point_cloud"].clone().requires_grad_(True)
    batch["point_cloud"] = pc
    loss_wm(batch).backward()
    assert (pc.grad[:3, 2:10].abs().sum() > 0) == target_gradient and pc.grad[3:, 2:10].abs().sum() == 0
    assert pc.grad[:3, :2].abs().sum() > 0 and pc.grad[3:, :2].abs().sum() == 0  # L_WM's history conditioning too


def test_world_model_batch_fraction_counts_samples_without_float_error(tiny_recipe):
    """0.28 x 25 is 7.000000000000001 in floats: the ceiling took 8 samples where the option says 7."""
    tiny_recipe["world_model"]["batch_fraction"] = 0.28
    e = build(tiny_recipe)
    fit_normalizer(e)
    seen = []
    predict = e.model.world_model_net.predict
    e.model.world_model_net.predict = lambda x, t, *cond: seen.append(x.shape[0]) or predict(x, t, *cond)
    e.model.loss(batch_of(e, batch_size=25), generator=torch.Generator().manual_seed(0))
    assert seen == [7]


def test_world_model_batch_fraction_is_validated(tiny_recipe):
    from ddp.errors import RecipeError

    tiny_recipe["world_model"]["batch_fraction"] = 0.0
    with pytest.raises((RecipeError, ValueError), match="batch_fraction"):
        build(tiny_recipe)


def _windows(exp, batch_size=6, seed=0):
    """A training batch with its ``frame_index`` (the window steps' rows in the frames), and the dataset."""
    from ddp.data.sequence import SequenceDataset
    from ddp.models.ddp_policy import FRAME_INDEX

    ds = SequenceDataset(exp.episodes(), 16, pad_before=1, pad_after=7, keys=["point_cloud", "agent_pos", "action"])
    idx = torch.randperm(len(ds), generator=torch.Generator().manual_seed(seed))[:batch_size]
    batch = ds.batch(idx)
    batch.set(FRAME_INDEX, ds.indices[idx])
    return batch, ds


@pytest.mark.parametrize("batch_fraction", [1.0, 0.5])
def test_target_table_gives_the_targets_the_batch_would_encode(tiny_recipe, batch_fraction):
    """world_model.target_refresh_every: future targets looked up in a table of every frame's latent equal
    the same encoder's latents of the batch's future frames (same loss); a stale table changes L_WM only."""
    tiny_recipe["world_model"].update(target_gradient=False, batch_fraction=batch_fraction)
    encoded = fit_normalizer(build(tiny_recipe))
    tiny_recipe["world_model"]["target_refresh_every"] = 5
    table = build(tiny_recipe)
    table.model.load_state_dict(encoded.model.state_dict())
    batch, ds = _windows(encoded)

    def losses(e):
        return e.model.loss(batch, generator=torch.Generator().manual_seed(0))

    with pytest.raises(RuntimeError, match="frame_index"):  # no table yet
        losses(table)
    table.model.refresh_target_table(ds.steps["point_cloud"], ds.steps["agent_pos"], frames_per_call=7)
    assert table.model.target_table.shape == (ds.steps.shape[0], table.model.latent_dim)
    base, looked_up = losses(encoded), losses(table)
    for k in ("loss_bc", "loss_wm"):
        torch.testing.assert_close(looked_up[k], base[k], rtol=1e-5, atol=1e-6)
    # the encoder moves on, the table does not: the targets are stale (L_WM differs), the history is not (L_BC)
    with torch.no_grad():
        for p in table.model.encoder.parameters():
            p.mul_(1.05)
        for p in encoded.model.encoder.parameters():
            p.mul_(1.05)
    base, stale = losses(encoded), losses(table)
    torch.testing.assert_close(stale["loss_bc"], base["loss_bc"], rtol=1e-5, atol=1e-6)
    assert not torch.allclose(stale["loss_wm"], base["loss_wm"], rtol=1e-3)
    table.model.refresh_target_table(ds.steps["point_cloud"], ds.steps["agent_pos"])
    torch.testing.assert_close(losses(table)["loss_wm"], base["loss_wm"], rtol=1e-5, atol=1e-6)


def test_target_refresh_needs_detached_targets(tiny_recipe):
    from ddp.errors import RecipeError

    tiny_recipe["world_model"].update(target_gradient=True, target_refresh_every=10)
    with pytest.raises((RecipeError, ValueError), match="target_gradient"):
        build(tiny_recipe)
