"""Training and evaluation details checked against numbers, not just "it runs".

The LR schedule, gradient clipping, resuming with a changed length, bf16 autocast, tau calibration
on ID rollouts, parallel == serial evaluation (read back from the env), numeric parity of the DP3
encoder and of a FiLM residual block with reference maths, and CLI commands' outputs.
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml
from torch.optim.optimizer import register_optimizer_step_pre_hook

from conftest import TINY, fit_normalizer
from ddp import build
from ddp.checkpoint import load_checkpoint

LR = 1e-3


def expected_factor(k: int, warmup: int, total: int, schedule: str = "cosine") -> float:
    """The schedule written out: linear warm-up (k+1)/W, then cosine decay to 0 at ``total`` (or flat)."""
    if k < warmup:
        return (k + 1) / warmup
    if schedule == "constant":
        return 1.0
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, (k - warmup) / (total - warmup))))


def read_scalar(out_dir, name: str) -> dict[int, float]:
    rows = (out_dir / "logs" / "scalars" / f"{name}.csv").read_text().strip().splitlines()
    steps = [int(r.split(",")[0]) for r in rows]
    assert len(steps) == len(set(steps)), f"{name}.csv logs a step twice: {steps}"
    return {int(r.split(",")[0]): float(r.split(",")[1]) for r in rows}


class OptimiserLRs:
    """The learning rate every optimiser step actually uses (a global step pre-hook)."""

    def __init__(self):
        self.lrs: list[float] = []
        self._handle = register_optimizer_step_pre_hook(self._hook)

    def _hook(self, optimizer, args, kwargs):
        lrs = {g["lr"] for g in optimizer.param_groups}
        assert len(lrs) == 1
        self.lrs.append(lrs.pop())

    def remove(self):
        self._handle.remove()


@pytest.fixture
def optimiser_lrs():
    rec = OptimiserLRs()
    yield rec
    rec.remove()


def _params(exp) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in exp.model.named_parameters()}


# --------------------------------------------------------------------------- 1. LR schedule


@pytest.mark.parametrize("schedule", ["cosine", "constant"])
def test_lr_follows_warmup_then_cosine_or_constant(tiny_recipe, tmp_path, optimiser_lrs, schedule):
    warmup, total = 4, 12
    tiny_recipe["train"].update(lr=LR, warmup_steps=warmup, max_steps=total, epochs=100, log_every_steps=1,
                                lr_schedule=schedule)
    res = build(tiny_recipe).train(output_dir=tmp_path, progress=False)
    assert res.steps == total
    # update k (1-based) runs with lr * factor(k - 1): the optimiser's own lr at each step
    used = optimiser_lrs.lrs
    assert len(used) == total
    for k in range(1, total + 1):
        assert used[k - 1] == pytest.approx(LR * expected_factor(k - 1, warmup, total, schedule), rel=1e-9, abs=1e-15), k
    # anchors written by hand: warm-up 1/4 .. 4/4, then the peak, then half way / the end of the cosine
    assert used[:5] == pytest.approx([2.5e-4, 5e-4, 7.5e-4, 1e-3, 1e-3])
    if schedule == "cosine":
        assert used[8] == pytest.approx(5e-4)  # k = 8: half way through the decay
        assert used[-1] < used[8] < used[4]
    else:
        assert used[4:] == pytest.approx([1e-3] * (total - 4))
    # the CSV log's lr at step k is the lr after k scheduler steps
    logged = read_scalar(tmp_path, "lr")
    assert sorted(logged) == list(range(1, total + 1))
    for k, v in logged.items():
        assert v == pytest.approx(LR * expected_factor(k, warmup, total, schedule), rel=1e-9, abs=1e-15), k
    state = load_checkpoint(tmp_path / "last.pt")
    assert state["lr_scheduler"]["last_epoch"] == total
    assert state["optimizer"]["param_groups"][0]["lr"] == pytest.approx(
        LR * expected_factor(total, warmup, total, schedule), abs=1e-15)


def test_a_max_steps_beyond_the_epochs_ends_the_schedule_where_training_ends(tiny_recipe, tmp_path, optimiser_lrs):
    """max_steps 100 on 2 epochs of 4 batches sized the cosine for 100 steps: training stopped after 8 with the
    learning rate still near its peak, silently."""
    tiny_recipe["train"].update(lr=LR, warmup_steps=0, max_steps=100, epochs=2, log_every_steps=1)
    with pytest.warns(UserWarning, match=r"train.max_steps \(100\) is more than train.epochs \(2\) x 4 batches: "
                                         r"training stops after 8 steps"):
        res = build(tiny_recipe).train(output_dir=tmp_path, progress=False)
    assert res.steps == 8 and len(optimiser_lrs.lrs) == 8
    assert optimiser_lrs.lrs[-1] == pytest.approx(LR * expected_factor(7, 0, 8))  # the cosine's last step
    assert read_scalar(tmp_path, "lr")[8] == pytest.approx(0.0, abs=1e-12)


def test_fine_tuning_loaded_weights_keeps_their_normaliser(tiny_recipe, tmp_path):
    """Weights loaded for fine-tuning learned under their normaliser's scaling: a fresh fit refitted it to the
    new demonstrations, so the encoder saw re-scaled inputs and the policy's actions were un-scaled wrongly."""
    tiny_recipe["train"].update(max_steps=2, epochs=1)
    fresh = build(tiny_recipe)
    assert not bool(fresh.model.normalizer.fitted)
    fresh.train(output_dir=tmp_path / "fresh", progress=False)
    fitted = {k: v.clone() for k, v in fresh.model.normalizer.state_dict().items()}
    assert bool(fresh.model.normalizer.fitted)

    tuned = build(tiny_recipe)
    tuned.load_checkpoint(tmp_path / "fresh" / "last.pt")
    with torch.no_grad():  # the pretrained scaling differs from what these demos would give
        tuned.model.normalizer.action_scale.mul_(0.5)
    pretrained = {k: v.clone() for k, v in tuned.model.normalizer.state_dict().items()}
    tuned.train(output_dir=tmp_path / "tuned", resume=False, progress=False)
    for k, v in tuned.model.normalizer.state_dict().items():
        assert torch.equal(v, pretrained[k]), k
    assert not torch.equal(pretrained["action_scale"], fitted["action_scale"])


# --------------------------------------------------------------------------- 2. gradient clipping


def test_grad_clip_norm_is_applied(tiny_recipe, tmp_path, monkeypatch):
    real_clip = torch.nn.utils.clip_grad_norm_
    calls = []

    def recording_clip(parameters, max_norm, *args, **kwargs):
        parameters = [p for p in parameters if p.grad is not None]
        before = real_clip(parameters, float("inf"))  # only measures (nothing is clipped at inf)
        out = real_clip(parameters, max_norm, *args, **kwargs)
        after = torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in parameters]))
        calls.append({"max_norm": max_norm, "before": float(before), "after": float(after), "n": len(parameters)})
        return out

    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", recording_clip)
    clip = 1e-10  # far below the gradient's norm, and below AdamW's eps: the first update nearly vanishes
    deltas, initial = {}, {}
    for name, value in (("clipped", clip), ("free", None)):
        recipe = copy.deepcopy(tiny_recipe)
        recipe["train"].update(max_steps=1, epochs=100, warmup_steps=1, grad_clip_norm=value, logger="none")
        exp = build(recipe)
        before = initial[name] = _params(exp)
        exp.train(output_dir=tmp_path / name, progress=False)
        after = _params(exp)
        deltas[name] = max((after[k] - before[k]).abs().max().item() for k in before)
        if name == "clipped":
            assert len(calls) == 1, calls  # once per optimiser step
            call = calls[0]
            assert call["max_norm"] == clip
            assert call["n"] == len(before)  # every parameter of the model
            assert call["before"] > 1e3 * clip and call["after"] <= clip * 1.001
        else:
            assert len(calls) == 1  # grad_clip_norm null: no clipping call
    assert all(torch.equal(initial["clipped"][k], initial["free"][k]) for k in initial["free"])  # same start
    # unclipped, Adam's first update is ~lr per weight; clipped to 1e-10, ~lr * 1e-10 / (1e-10 + 1e-8)
    assert deltas["free"] > 1e-4
    assert deltas["clipped"] < 0.05 * deltas["free"], deltas


# --------------------------------------------------------------------------- 3. resume with a changed max_steps

RESUME_WARMUP = 2


@pytest.fixture(scope="module")
def resumed_run(tmp_path_factory):
    """Train 4 steps, then resume the same recipe with max_steps 8; record what each phase did."""
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("resume")
    recipe = copy.deepcopy(TINY)
    recipe["train"].update(lr=LR, warmup_steps=RESUME_WARMUP, max_steps=4, epochs=100, log_every_steps=1)
    rec = OptimiserLRs()
    try:
        first = build(recipe).train(output_dir=out, progress=False)
        first_lrs, rec.lrs = rec.lrs, []
        state4 = load_checkpoint(out / "last.pt")
        recipe["train"]["max_steps"] = 8
        exp = build(recipe)
        steps_seen, orig = [], exp.model.loss

        def counting_loss(batch, generator=None):
            steps_seen.append(len(steps_seen))
            return orig(batch, generator=generator)

        exp.model.loss = counting_loss
        second = exp.train(output_dir=out, progress=False)
        second_lrs = rec.lrs
    finally:
        rec.remove()
    return dict(out=out, first=first, second=second, first_lrs=first_lrs, second_lrs=second_lrs,
                state4=state4, state8=load_checkpoint(out / "last.pt"), second_calls=len(steps_seen))


def test_resume_with_a_longer_max_steps_continues_and_stretches_the_schedule(resumed_run):
    r = resumed_run
    assert r["first"].steps == 4 and r["state4"]["step"] == 4
    assert r["first_lrs"] == pytest.approx([LR * expected_factor(k, RESUME_WARMUP, 4) for k in range(4)])
    # continued from step 4: four more optimiser steps, not eight, and the run ends at 8
    assert r["second_calls"] == 4 and len(r["second_lrs"]) == 4
    assert r["second"].steps == 8 and r["state8"]["step"] == 8
    assert r["state8"]["lr_scheduler"]["last_epoch"] == 8
    # the log: steps 1-4 on the 4-step schedule, 5-8 on the stretched 8-step one (the old one is 0 there)
    logged = read_scalar(r["out"], "lr")
    assert sorted(logged) == list(range(1, 9))
    for k in range(1, 5):
        assert logged[k] == pytest.approx(LR * expected_factor(k, RESUME_WARMUP, 4), abs=1e-15), k
    for k in range(5, 9):
        assert logged[k] == pytest.approx(LR * expected_factor(k, RESUME_WARMUP, 8), abs=1e-15), k
    assert logged[5] > 0.4 * LR  # the 4-step schedule had reached 0
    assert len(read_scalar(r["out"], "loss")) == 8
    # the updates after the first resumed one use the stretched schedule
    assert r["second_lrs"][1:] == pytest.approx([LR * expected_factor(k, RESUME_WARMUP, 8) for k in range(5, 8)])


def test_first_update_after_resume_uses_the_stretched_schedule(resumed_run):
    """The optimiser restores the old schedule's lr; the trainer recomputes it (else update 5 ran at lr 0)."""
    assert resumed_run["second_lrs"][0] == pytest.approx(LR * expected_factor(4, RESUME_WARMUP, 8))


# --------------------------------------------------------------------------- 4. bf16 autocast


@pytest.mark.parametrize("bf16", [True, False])
def test_bf16_autocast_really_runs_the_forward_in_bf16(tiny_recipe, tmp_path, bf16):
    tiny_recipe["train"].update(max_steps=1, epochs=100, autocast_bf16=bf16, logger="none")
    exp = build(tiny_recipe)
    seen = {"encoder": [], "policy": [], "world_model": []}
    layers = {
        "encoder": exp.model.encoder.pointnet[0],  # nn.Linear
        "policy": exp.model.policy_net.unet.down[0].blocks[0].conv1[0],  # nn.Conv1d
        "world_model": exp.model.world_model_net.unet.down[0].blocks[0].conv1[0],
    }
    assert isinstance(layers["encoder"], torch.nn.Linear) and isinstance(layers["policy"], torch.nn.Conv1d)
    for name, layer in layers.items():
        layer.register_forward_hook(lambda m, args, out, name=name: seen[name].append(out.dtype))
    exp.train(output_dir=tmp_path, progress=False)
    want = torch.bfloat16 if bf16 else torch.float32
    for name, dtypes in seen.items():
        assert dtypes and set(dtypes) == {want}, (name, dtypes)
    assert all(p.dtype == torch.float32 for p in exp.model.parameters())  # the weights stay float32


# --------------------------------------------------------------------------- 5. calibration on ID rollouts


def test_tau_is_calibrated_on_id_rollouts_of_the_base_policy(tiny_recipe, tmp_path, monkeypatch):
    import ddp.evaluate as evaluate_mod
    import ddp.eval_runner as runner
    from ddp.detectors.discrepancy import DiscrepancyConfig, DiscrepancyDetector
    from ddp.detectors.never import NeverDetector
    from ddp.protocols.base import get_protocol

    tiny_recipe["env"]["max_episode_steps"] = 24  # the displacement at chunk 1 shows at step 16: a chunk acts after it
    tiny_recipe["eval"] = {"env": {"cube_x": [-0.05, 0.05]}, "calibration_episodes": 3, "seed": 500}
    tiny_recipe["controller"] = {"detector": {"name": "discrepancy", "tau": None, "alpha": 0.5,
                                              "threshold_on": "all"},
                                 "tracker": {"name": "oracle"}}
    exp = build(tiny_recipe)
    nan = float("nan")

    def latents(values):  # latent windows whose D_R-I is exactly ``values`` per chunk
        pred = np.sqrt(np.asarray(values, dtype=np.float64))[:, None, None] * np.ones((1, 2, 4))
        return {"latent_real": np.zeros_like(pred), "latent_pred": pred}

    canned = [
        {"seed": 0, "env": 0, "success": False, "chunks": 4, "first_success_chunk": None,
         "mode": [0.0] * 4, "imagined": [0.0] * 4, "discrepancy": [nan, 0.1, 0.5, 0.2], **latents([nan, 0.1, 0.5, 0.2])},
        {"seed": 1, "env": 0, "success": True, "chunks": 4, "first_success_chunk": 3,
         "mode": [0.0] * 4, "imagined": [0.0] * 4, "discrepancy": [nan, 0.3, 2.0, 0.05],
         **latents([nan, 0.3, 2.0, 0.05])},
        {"seed": 2, "env": 0, "success": False, "chunks": 4, "first_success_chunk": None,
         "mode": [0.0] * 4, "imagined": [0.0] * 4, "discrepancy": [nan, 0.7, 0.4, 0.9], **latents([nan, 0.7, 0.4, 0.9])},
    ]
    calls = []

    def fake_rollouts(exp_, controller, *, episodes, seed, overrides, **kwargs):
        calls.append({"controller": controller, "episodes": episodes, "seed": seed, "overrides": dict(overrides)})
        eps = copy.deepcopy(canned[:episodes])
        if not kwargs.get("record_latents"):  # latent windows are kept for calibration only
            eps = [{k: v for k, v in e.items() if not k.startswith("latent_")} for e in eps]
        return eps

    monkeypatch.setattr(runner, "rollout_episodes", fake_rollouts)
    # split conformal, alpha 0.5, 3 held-out episode maxima (0.5, 2.0, 0.9): the ceil(4 x 0.5) = 2nd smallest
    expected_tau = 0.9

    det = DiscrepancyDetector(DiscrepancyConfig(tau=None, alpha=0.5, threshold_on="all"))  # failing ones too
    tau = runner.calibrate_detector(exp, det, episodes=3, seed=77, progress=False)
    assert tau == pytest.approx(expected_tau, rel=1e-12) and det.tau == tau
    id_env = runner.env_overrides(exp, get_protocol("id"), exp.recipe.eval.max_steps)
    (call,) = calls
    assert call["episodes"] == 3 and call["seed"] == 77
    # ID: the eval env overrides the id protocol uses, and no displacement
    assert call["overrides"] == id_env == {"cube_x": [-0.05, 0.05]}
    assert not call["overrides"].get("displacement", False)
    # the base policy: detector never, no tracker / recovery, a forecast every cycle (D_R-I is measured)
    ctrl = call["controller"]
    assert isinstance(ctrl.detector, NeverDetector) and ctrl.tracker is None and ctrl.recovery is None
    assert ctrl.forecast_every_cycle
    # calibrating on displaced rollouts instead would see other values: the threshold is what ID gave
    assert det.calibration()["reference"] == [pytest.approx(e["discrepancy"], nan_ok=True) for e in canned]

    # through evaluate(): calibration on ID rollouts, then the displaced protocol uses that tau
    calls.clear()
    monkeypatch.setattr(evaluate_mod, "rollout_episodes", fake_rollouts)
    rep = exp.evaluate(["ood_ddp"], episodes=2, output_dir=tmp_path, progress=False)
    calib, protocol = calls
    assert calib["seed"] == 500 + 100_000 and calib["episodes"] == 3
    assert not calib["overrides"].get("displacement", False) and calib["overrides"]["cube_x"] == [-0.05, 0.05]
    assert protocol["overrides"]["displacement"] is True and protocol["seed"] == 500
    assert rep["protocols"]["ood_ddp"]["tau"] == pytest.approx(expected_tau, rel=1e-12)
    assert json.loads((tmp_path / "results.json").read_text())["protocols"]["ood_ddp"]["tau"] == pytest.approx(
        expected_tau, rel=1e-12)


# --------------------------------------------------------------------------- 6. parallel == serial, read from the env


def test_parallel_evaluation_runs_the_same_seeded_episodes_as_serial(tiny_recipe, monkeypatch):
    import ddp.eval_runner as runner

    exp = build(tiny_recipe)
    fit_normalizer(exp)
    overrides = {"max_episode_steps": 16}  # 2 chunks per episode
    orig_summarise = runner._summarise
    first_obs = []

    def recording_summarise(traj, env_index, seed, **kwargs):
        first_obs.append((seed, traj[0]["agent_pos"].clone(), traj[0]["point_cloud"].clone()))
        return orig_summarise(traj, env_index=env_index, seed=seed, **kwargs)

    monkeypatch.setattr(runner, "_summarise", recording_summarise)
    runs, observed = {}, {}
    for parallel in (False, True):
        first_obs.clear()
        ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True)
        runs[parallel] = runner.rollout_episodes(exp, ctrl, episodes=4, seed=1000, overrides=overrides, num_envs=2,
                                                 parallel=parallel, progress=False)
        observed[parallel] = {seed: (pos, pc) for seed, pos, pc in first_obs}
    serial, par = runs[False], runs[True]
    assert [r["seed"] for r in serial] == [r["seed"] for r in par] == [1000, 1001, 1002, 1003]
    assert [r["env"] for r in serial] == [0, 0, 1, 1]
    for a, b in zip(serial, par):
        for key in ("seed", "env", "success", "chunks", "first_success_chunk", "mode", "imagined"):
            assert a[key] == b[key], key
        assert a["chunks"] == 2
        # D_R-I comes from the observations: the same observations give the same values
        assert np.allclose(a["discrepancy"], b["discrepancy"], equal_nan=True, rtol=0, atol=1e-6), a["seed"]
    # the first observation of every reported episode is the one the env gives for that seed
    for seed in (1000, 1001, 1002, 1003):
        ref = runner.make_chunked_env(exp, seed, overrides).reset()
        for parallel in (False, True):
            pos, pc = observed[parallel][seed]
            assert torch.equal(pos, ref["agent_pos"]), (parallel, seed)
            assert torch.equal(pc, ref["point_cloud"]), (parallel, seed)
    # and different seeds really give different first observations (the check above can tell them apart)
    assert not torch.equal(observed[True][1000][0], observed[True][1002][0])


def test_envs_that_do_not_divide_the_episodes_run_the_same_seeds(tiny_recipe, monkeypatch):
    """10 episodes on 3 or 4 envs are seeds 1000-1009, as on one env, each from its own seed's first observation."""
    import ddp.eval_runner as runner

    exp = build(tiny_recipe)
    fit_normalizer(exp)
    overrides = {"max_episode_steps": 8}
    first_obs = {}
    orig_summarise = runner._summarise

    def recording_summarise(traj, env_index, seed, **kwargs):
        first_obs[seed] = traj[0]["agent_pos"].clone()
        return orig_summarise(traj, env_index=env_index, seed=seed, **kwargs)

    monkeypatch.setattr(runner, "_summarise", recording_summarise)
    for num_envs, envs in ((3, [0] * 4 + [1] * 3 + [2] * 3), (4, [0] * 3 + [1] * 3 + [2] * 2 + [3] * 2)):
        first_obs.clear()
        ctrl = exp.make_controller(detector={"name": "never"}, tracker=False)
        runs = runner.rollout_episodes(exp, ctrl, episodes=10, seed=1000, overrides=overrides, num_envs=num_envs,
                                       progress=False)
        assert [r["seed"] for r in runs] == list(range(1000, 1010)), num_envs
        assert [r["env"] for r in runs] == envs
        for seed in range(1000, 1010):
            assert torch.equal(first_obs[seed], runner.make_chunked_env(exp, seed, overrides).reset()["agent_pos"])


# --------------------------------------------------------------------------- 7. DP3 encoder parity


def _randomise_norms(module: torch.nn.Module, seed: int) -> None:
    """Non-trivial affine weights for every LayerNorm / GroupNorm (the defaults 1 / 0 hide mistakes)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, (torch.nn.LayerNorm, torch.nn.GroupNorm)):
                m.weight.copy_(1.0 + 0.5 * torch.randn(m.weight.shape, generator=g))
                m.bias.copy_(0.5 * torch.randn(m.bias.shape, generator=g))


def test_dp3_encoder_matches_reference_maths():
    from ddp.config import from_dict
    from ddp.registry import get

    plugin = get("encoder", "dp3")
    torch.manual_seed(0)
    enc = plugin.factory(from_dict(plugin.config_cls, {}), agent_pos_dim=9, point_dim=3).eval()
    _randomise_norms(enc, 1)
    g = torch.Generator().manual_seed(2)
    pc = torch.randn(2, 3, 40, 3, generator=g)  # [B, T, P, 3]
    pos = torch.randn(2, 3, 9, generator=g)

    with torch.no_grad():
        _check_dp3_parity(enc, pc, pos, g)


def _check_dp3_parity(enc, pc, pos, g):
    linears = [m for m in enc.pointnet if isinstance(m, torch.nn.Linear)]
    norms = [m for m in enc.pointnet if isinstance(m, torch.nn.LayerNorm)]
    assert [(l.in_features, l.out_features) for l in linears] == [(3, 64), (64, 128), (128, 256)]
    assert len(norms) == 3
    h = pc
    for lin, ln in zip(linears, norms):  # per point: Linear -> LayerNorm -> ReLU, x3
        h = F.relu(F.layer_norm(h @ lin.weight.T + lin.bias, (lin.out_features,), ln.weight, ln.bias, ln.eps))
    pooled = h.max(dim=-2).values  # max over the points
    proj, final_ln = enc.projection[0], enc.projection[1]
    point_feat = F.layer_norm(pooled @ proj.weight.T + proj.bias, (64,), final_ln.weight, final_ln.bias, final_ln.eps)
    s1, s2 = [m for m in enc.state_mlp if isinstance(m, torch.nn.Linear)]
    assert len(enc.state_mlp) == 3  # Linear -> ReLU -> Linear (no activation after the last)
    state_feat = F.relu(pos @ s1.weight.T + s1.bias) @ s2.weight.T + s2.bias
    reference = torch.cat([point_feat, state_feat], dim=-1)

    got = enc.encode(pc, pos)
    assert got.shape == (2, 3, 128)
    assert torch.allclose(got, reference, atol=1e-6, rtol=0), (got - reference).abs().max()
    # order invariance over the points (max-pool)
    shuffled = enc.encode(pc[:, :, torch.randperm(40, generator=g)], pos)
    assert torch.allclose(shuffled, got, atol=1e-6, rtol=0)


# --------------------------------------------------------------------------- 8. FiLM residual block parity


def _reference_film_block(block, x, cond, n_groups, predict_scale):
    def conv_block(seq, h):
        conv, gn = seq[0], seq[1]
        h = F.conv1d(h, conv.weight, conv.bias, padding=conv.kernel_size[0] // 2)
        return F.mish(F.group_norm(h, n_groups, gn.weight, gn.bias, gn.eps))

    c_out = block.out_channels
    h = conv_block(block.conv1, x)
    lin = block.film[1]
    film = (F.mish(cond) @ lin.weight.T + lin.bias)[:, :, None]  # Mish first, then Linear; broadcast over time
    if predict_scale:
        assert film.shape[1] == 2 * c_out
        h = film[:, :c_out] * h + film[:, c_out:]  # [scale, bias]
    else:
        assert film.shape[1] == c_out
        h = h + film
    h = conv_block(block.conv2, h)
    if x.shape[1] != c_out:
        res = block.residual
        return h + F.conv1d(x, res.weight, res.bias)
    return h + x


@pytest.mark.parametrize("c_in,c_out,predict_scale", [(6, 16, True), (16, 16, True), (6, 16, False)])
def test_film_residual_block_matches_reference_maths(c_in, c_out, predict_scale):
    from ddp.denoisers.blocks import FiLMResidualBlock

    torch.manual_seed(0)
    block = FiLMResidualBlock(c_in, c_out, 10, kernel_size=5, n_groups=4, predict_scale=predict_scale).eval()
    _randomise_norms(block, 3)
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, c_in, 12, generator=g)
    cond = torch.randn(3, 10, generator=g)
    with torch.no_grad():
        got = block(x, cond)
        reference = _reference_film_block(block, x, cond, 4, predict_scale)
    assert got.shape == (3, c_out, 12)
    assert torch.allclose(got, reference, atol=1e-6, rtol=0), (got - reference).abs().max()


def test_unet_blocks_of_the_recipe_use_film_scale_and_bias(tiny_recipe):
    """The recipe's U-Nets (cond_predict_scale defaults to true) run the block checked above."""
    exp = build(tiny_recipe)
    blk = exp.model.policy_net.unet.down[0].blocks[0]
    assert blk.predict_scale and blk.film[1].out_features == 2 * blk.out_channels
    _randomise_norms(blk, 5)
    g = torch.Generator().manual_seed(6)
    x = torch.randn(2, blk.conv1[0].in_channels, 16, generator=g)
    cond = torch.randn(2, blk.film[1].in_features, generator=g)
    with torch.no_grad():
        assert torch.allclose(blk(x, cond), _reference_film_block(blk, x, cond, 4, True), atol=1e-6, rtol=0)


# --------------------------------------------------------------------------- 9. CLI outputs


def _cli_recipe(tmp_path) -> str:
    recipe = copy.deepcopy(TINY)
    recipe["train"].update(max_steps=3, epochs=100, output_dir=str(tmp_path / "train"), logger="none")
    recipe["eval"] = {"episodes": 1, "protocols": ["id"], "max_steps": 16, "output_dir": str(tmp_path / "eval")}
    recipe["controller"] = {"detector": {"name": "never"}, "tracker": None, "recovery": {"name": "none"},
                            "forecast_every_cycle": True}  # D_R-I in results.json: it depends on the weights
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return str(path)


def test_cli_eval_writes_results_for_the_requested_episodes(tmp_path, capsys):
    from ddp.cli import main

    recipe = _cli_recipe(tmp_path)
    assert main(["train", recipe, "--quiet"]) == 0
    assert "trained 3 steps" in capsys.readouterr().out
    ckpt = tmp_path / "train" / "last.pt"
    assert main(["eval", recipe, "--checkpoint", str(ckpt), "--episodes", "2", "--quiet",
                 "--output-dir", str(tmp_path / "ev")]) == 0
    out = capsys.readouterr().out
    results = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert results["recipe"] == "tiny" and results["episodes"] == 2 and list(results["protocols"]) == ["id"]
    ident = results["protocols"]["id"]
    assert ident["episodes"] == 2 and [e["seed"] for e in ident["per_episode"]] == [1000, 1001]
    assert all(e["chunks"] == 2 for e in ident["per_episode"])  # eval.max_steps 16 = 2 chunks of 8
    assert 0.0 <= ident["success_rate"] <= 1.0
    row = f"| tiny | {100 * ident['success_rate']:.0f} ({ident['successes']}/2) |"
    assert row in out and "| method | id |" in out
    assert (tmp_path / "ev" / "table.md").read_text().splitlines()[-1] == row
    assert f"results: {tmp_path / 'ev'}/results.json" in out


def test_cli_run_trains_then_evaluates_and_prints_a_table(tmp_path, capsys):
    from ddp.cli import main

    recipe = _cli_recipe(tmp_path)
    assert main(["run", recipe, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "[tiny] trained 3 steps" in out
    assert load_checkpoint(tmp_path / "train" / "last.pt")["step"] == 3
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    ident = results["protocols"]["id"]
    assert ident["episodes"] == 1 and len(ident["per_episode"]) == 1  # eval.episodes of the recipe
    lines = out.strip().splitlines()
    assert lines[-3:] == ["| method | id |", "|---|---|",
                          f"| tiny | {100 * ident['success_rate']:.0f} ({ident['successes']}/1) |"]
    # it evaluated the checkpoint it trained (EMA weights): ddp eval of that checkpoint gives the same episode
    assert main(["eval", recipe, "--checkpoint", str(tmp_path / "train" / "last.pt"), "--quiet",
                 "--output-dir", str(tmp_path / "again")]) == 0
    again = json.loads((tmp_path / "again" / "results.json").read_text())["protocols"]["id"]["per_episode"]
    assert again == ident["per_episode"]
    assert any(v is not None for v in again[0]["discrepancy"])


def test_cli_bench_prints_the_latency_lines(tmp_path, capsys):
    from ddp.cli import main

    recipe = _cli_recipe(tmp_path)
    assert main(["bench", recipe, "--repeats", "1", "--no-baseline"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("tiny: batch 1, policy 4 / world model 4 denoising steps, device cpu, ")
    values = {}
    for line in lines[1:]:
        name, value, *unit = line.split()
        values[name] = (float(value), unit)
    for name in ("encoder_ms", "policy_sample_ms", "obs_to_action_ms", "world_model_imagine_ms", "detector_ms",
                 "control_cycle_ms", "train_step_ms"):
        assert name in values and values[name][1] == ["ms"], (name, lines)
        assert values[name][0] > 0 or name == "detector_ms", (name, lines)  # a threshold test can print 0.0 ms
    assert values["train_samples_per_s"][1] == [] and values["train_samples_per_s"][0] > 0


def test_cli_bench_names_each_model_s_own_denoising_steps(tmp_path, capsys):
    """The header read the recipe's policy entry: "None denoising steps" where a recipe left the count to
    the scheduler's default, and never the world model's."""
    from ddp.cli import main

    recipe = _cli_recipe(tmp_path)
    assert main(["bench", recipe, "--repeats", "1", "--no-baseline", "--set",
                 "world_model.scheduler.num_inference_steps=2"]) == 0
    assert capsys.readouterr().out.startswith("tiny: batch 1, policy 4 / world model 2 denoising steps")
    from ddp.schedulers.ddpm import DDPMConfig, DDPMScheduler

    assert DDPMScheduler(DDPMConfig(num_train_timesteps=50, num_inference_steps=None)).inference_steps == 50
    # a flow (FlowPolicy's scheduler) and no world model: the header read a DDPM/DDIM-only attribute
    assert main(["bench", recipe, "--repeats", "1", "--no-baseline", "--set", "policy.scheduler.name=consistency_flow",
                 "--set", "world_model.enabled=false"]) == 0
    assert capsys.readouterr().out.startswith("tiny: batch 1, policy 1 denoising steps")


def test_bench_times_the_in_distribution_cycle(tmp_path, monkeypatch):
    """The cycle timed is the ID one (encode, policy, forecast, D_R-I) whatever D_R-I the random inputs give:
    with tau 1.0 the tiny model read OOD from the second cycle and DDP was timed imagining, beside the
    baseline's ID path."""
    import ddp.detectors.discrepancy as discrepancy
    from ddp import build
    from ddp.bench import bench

    score = discrepancy.residual_score
    # a model whose D_R-I on random inputs is large (a real checkpoint's latents, unlike the tiny model's)
    monkeypatch.setattr(discrepancy, "residual_score", lambda *a, **k: 1e6 * score(*a, **k).abs() + 1e6)
    exp = build(_cli_recipe(tmp_path))
    made = []
    make = exp.make_controller

    def record(**kwargs):
        made.append(make(**kwargs))
        return made[-1]

    monkeypatch.setattr(exp, "make_controller", record)
    bench(exp, repeats=2, warmup=1, train_steps=1)
    assert len(made) == 2
    for ctrl in made:
        assert ctrl.states and not any(s.ood for s in ctrl.states)
        assert ctrl.states[0].has_forecast  # the forecast D_R-I compares with was made (and compared)


def test_cli_bench_compares_with_the_dp3_baseline_in_the_same_process(tmp_path, capsys):
    """By default the recipe and its DP3 baseline (world model off) are timed in alternating rounds, with cost
    ratios that read the same way on every row (samples per second: baseline / recipe)."""
    from ddp.cli import main

    recipe = _cli_recipe(tmp_path)
    assert main(["bench", recipe, "--repeats", "1"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "dp3_baseline" in lines[1] and "ratio" in lines[1]
    rows = {line.split()[0]: line.split()[1:] for line in lines[2:]}
    assert rows["world_model_imagine_ms"][1:] == ["-", "-"]  # the baseline has no world model
    for name in ("obs_to_action_ms", "control_cycle_ms", "train_step_ms", "train_samples_per_s"):
        mine, base, ratio = float(rows[name][0]), float(rows[name][1]), rows[name][2]
        assert base > 0 and ratio.endswith("x")
        cost = base / mine if name.endswith("_per_s") else mine / base  # both: how many times the baseline's cost
        assert float(ratio[:-1]) == pytest.approx(cost, rel=0.1, abs=0.01)  # printed values are rounded


def test_compare_alternates_rounds_and_takes_their_medians(monkeypatch):
    from ddp import bench as bench_mod

    calls = []

    def fake_bench(exp, **kw):
        calls.append(exp)
        n = len(calls)
        return {"obs_to_action_ms": 10.0 * n, "train_samples_per_s": 100.0 / n}

    monkeypatch.setattr(bench_mod, "bench", fake_bench)
    monkeypatch.setattr(bench_mod, "baseline_of", lambda exp: "base")
    rows = bench_mod.compare("ddp", rounds=3)
    # interleaved, not all of one then the other, and neither always first
    assert calls == ["ddp", "base", "base", "ddp", "ddp", "base"]
    mine, base, ratio = rows["obs_to_action_ms"]
    assert (mine, base) == (40.0, 30.0) and ratio == pytest.approx(4 / 3)  # medians of 10/40/50 and 20/30/60
    mine, base, ratio = rows["train_samples_per_s"]
    # medians of 100/25/20 (calls 1, 4, 5) and 50/33.3/16.7 (calls 2, 3, 6); a throughput's cost ratio is
    # baseline / recipe
    assert (mine, base, ratio) == (25.0, pytest.approx(100 / 3), pytest.approx(4 / 3))



# --------------------------------------------------------------------------- world_model.target_refresh_every


def _train_counting_refreshes(recipe, out, max_steps, moved_points: float = 0.0):
    """Train ``recipe`` to ``max_steps``; return the experiment and the step of every target-table refresh.
    ``moved_points``: the demos' point clouds shifted by that much (the same frame count, other frames)."""
    recipe["train"].update(max_steps=max_steps, epochs=100, log_every_steps=1)
    exp = build(recipe)
    if moved_points:
        demos = exp.episodes

        def moved():
            eps = demos()
            eps.steps.set("point_cloud", eps.steps["point_cloud"] + moved_points)
            return eps

        exp.episodes = moved
    refreshed, orig = [], exp.model.refresh_target_table
    exp.model.refresh_target_table = lambda *a, **k: refreshed.append(len(calls)) or orig(*a, **k)
    calls, loss = [], exp.model.loss
    exp.model.loss = lambda batch, generator=None: calls.append(1) or loss(batch, generator=generator)
    exp.train(output_dir=out, progress=False)
    return exp, refreshed


def test_target_table_refreshes_on_schedule_and_resumes_with_its_targets(tmp_path):
    """refresh_every 1 trains like targets encoded with each batch; 3 refreshes at steps 0 and 3, stores
    the table and its step in the checkpoint, and a resume keeps using it until the next refresh is due."""
    torch.set_num_threads(1)
    recipe = copy.deepcopy(TINY)
    recipe["world_model"]["target_gradient"] = False
    encoded, _ = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "encoded", 4)
    recipe["world_model"]["target_refresh_every"] = 1
    every, refreshed = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "every", 4)
    assert refreshed == [0, 1, 2, 3]
    for name, p in _params(encoded).items():
        torch.testing.assert_close(_params(every)[name], p, rtol=1e-4, atol=1e-5, msg=name)
    recipe["world_model"]["target_refresh_every"] = 3
    stale, refreshed = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "stale", 4)
    assert refreshed == [0, 3]
    moved = max((_params(stale)[n] - p).abs().max().item() for n, p in _params(encoded).items())
    assert moved > 1e-6  # step 3's targets were 2 updates old at step 2
    state = load_checkpoint(tmp_path / "stale" / "last.pt")
    assert state["target_table_step"] == 3 and state["target_table"].shape[1] == stale.model.latent_dim
    assert "target_table" not in state["model"]  # not a weight: the model's state_dict is unchanged
    # resumed at step 4 with the table of step 3: no refresh before step 6
    resumed, refreshed = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "stale", 7)
    assert refreshed == [2]  # the third step of this call, i.e. step 6
    assert resumed.model.target_table is None  # kept in the checkpoint, not on the trained model
    # a stored table of other demos (a row count that differs) is refreshed at once
    from ddp.checkpoint import save_checkpoint

    state = load_checkpoint(tmp_path / "stale" / "last.pt")
    state["target_table"] = state["target_table"][:-1]
    save_checkpoint(tmp_path / "stale" / "last.pt", state)
    _, refreshed = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "stale", 8)
    assert refreshed == [0]
    # the same frame count, other frames (demos regenerated in place): refreshed at once too
    _, refreshed = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "stale", 11)
    assert refreshed == [2]  # the table of step 7 kept: next refresh at step 10
    _, refreshed = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "stale", 12, moved_points=0.01)
    assert refreshed == [0]
    # a checkpoint written before the digest was stored keeps its table when the frame count matches
    state = load_checkpoint(tmp_path / "stale" / "last.pt")
    assert state["target_table_step"] == 11
    del state["target_table_frames"]
    save_checkpoint(tmp_path / "stale" / "last.pt", state)
    _, refreshed = _train_counting_refreshes(copy.deepcopy(recipe), tmp_path / "stale", 13, moved_points=0.01)
    assert refreshed == []  # table of step 11 kept: next refresh at step 14


def test_an_interrupted_fit_saves_the_target_table_and_drops_it_from_the_model(tmp_path):
    recipe = copy.deepcopy(TINY)
    recipe["world_model"].update(target_gradient=False, target_refresh_every=2)
    recipe["train"].update(max_steps=6, epochs=100)
    exp = build(recipe)
    loss, calls = exp.model.loss, []

    def interrupted(batch, generator=None):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt  # Ctrl-C during step 4
        return loss(batch, generator=generator)

    exp.model.loss = interrupted
    with pytest.raises(KeyboardInterrupt):
        exp.train(output_dir=tmp_path, progress=False)
    assert exp.model.target_table is None
    state = load_checkpoint(tmp_path / "last.pt")
    assert state["step"] == 3 and state["target_table_step"] == 2 and state["target_table"] is not None
    exp.model.loss = lambda batch, generator=None: (_ for _ in ()).throw(RuntimeError("boom"))
    with pytest.raises(RuntimeError, match="boom"):
        exp.train(output_dir=tmp_path, progress=False)
    assert exp.model.target_table is None


def test_cli_bench_times_a_target_table_step_and_its_refresh(tmp_path, capsys):
    from ddp.cli import main

    recipe = _cli_recipe(tmp_path)
    sets = ["--set", "world_model.target_gradient=false", "--set", "world_model.target_refresh_every=50"]
    assert main(["bench", recipe, "--repeats", "1", *sets]) == 0
    rows = {line.split()[0]: line.split()[1:] for line in capsys.readouterr().out.strip().splitlines()[2:]}
    assert float(rows["train_step_ms"][0]) > 0 and float(rows["train_step_ms"][1]) > 0  # and the DP3 baseline's
    assert float(rows["target_refresh_ms_per_1k_frames"][0]) > 0 and rows["target_refresh_ms_per_1k_frames"][1] == "-"


def test_bench_times_the_trainers_step_as_the_recipe_sets_it():
    """ddp bench's train step ran model.loss on the whole batch whatever train.micro_batches and
    train.autocast_bf16 said: it times the trainer's step (micro-batches, bf16 autocast, clipping) now."""
    from ddp.bench import bench

    recipe = copy.deepcopy(TINY)
    recipe["train"].update(micro_batches=2, autocast_bf16=True, grad_clip_norm=1.0)
    exp = build(recipe)
    seen, loss = [], exp.model.loss

    def recorded(batch, generator=None):
        seen.append((batch.batch_size[0], torch.is_autocast_enabled("cpu")))
        return loss(batch, generator=generator)

    exp.model.loss = recorded
    out = bench(exp, repeats=1, warmup=0, train_steps=1)
    assert out["train_step_ms"] > 0
    assert seen and all(s == (recipe["train"]["batch_size"] // 2, True) for s in seen), seen


def test_bench_leaves_the_callers_model_as_it_was():
    """bench() ran its optimiser steps on random windows against exp.model itself (and left the batch's target
    table on it): bench(exp) on a loaded checkpoint, then an evaluation, evaluated weights trained on noise."""
    from ddp.bench import bench

    recipe = copy.deepcopy(TINY)
    recipe["world_model"].update(target_gradient=False, target_refresh_every=10)
    exp = build(recipe)
    before = {k: v.clone() for k, v in exp.model.state_dict().items()}
    bench(exp, repeats=1, warmup=0, train_steps=1)
    after = exp.model.state_dict()
    assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
    assert exp.model.target_table is None and not exp.model.training
