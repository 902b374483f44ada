"""Latency of the DDP control cycle and training throughput (``ddp bench``).

``obs_to_action_ms`` is encode + policy sampling; ``control_cycle_ms`` the whole controller call with
the world-model forecast inline (on the CPU single-threaded, as the background forecast runs, so that
both give the same forecast bit for bit: with several threads the cycle is dearer than encode + policy +
``world_model_imagine_ms``, which use every thread); ``controller_latency_ms`` the controller call with
the forecast made in the background while the chunk executes (``controller.async_forecast``): what a
robot waits for, timed until the call returns its actions (on a GPU, not until the forecast it then
launched has finished: the controller copies the actions to the CPU, which waits for them, and the
observation comes from the CPU, as an env's does).

Medians of many runs after warm-up, at batch 1, CUDA-synchronised on a GPU.
Numbers, not assertions: compare them across runs in the same process. :func:`compare`
times the recipe and its DP3 baseline (the same recipe with the world model disabled, as
``recipes/methods/dp3.yaml`` does; the same code paths otherwise, so training fast paths that
serve both are in both) in alternating rounds in this process, and gives the cost ratios.
"""

from __future__ import annotations

import copy
import math
import statistics
import time

import torch


def _timed(fn, *, repeats: int, warmup: int, device: torch.device, before=None, sync_after: bool = True) -> float:
    """Median milliseconds of ``fn()``; ``before()`` runs untimed ahead of each call."""
    for _ in range(warmup):
        if before is not None:
            before()
        fn()
    times = []
    for _ in range(repeats):
        if before is not None:
            before()
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        fn()
        if device.type == "cuda" and sync_after:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return 1000 * statistics.median(times)


def bench(exp, *, repeats: int = 20, warmup: int = 3, device: str = "cpu", train_steps: int = 5) -> dict[str, float]:
    """Milliseconds per call of each stage, and training samples per second."""
    from tensordict import TensorDict

    from ddp.models.ema import EMA
    from ddp.train import make_optimizer, resolve_device

    dev = resolve_device(device, key="--device")
    model = exp.model.to(dev).eval()
    r = exp.recipe
    M, N, P, D = r.policy.obs_steps, r.policy.action_steps, r.task.num_points, r.task.agent_pos_dim
    pc = torch.rand(1, M, P, r.task.point_dim, device=dev)
    pos = torch.rand(1, M, D, device=dev)
    g = torch.Generator(device=dev).manual_seed(0)
    out: dict[str, float] = {}
    with torch.inference_mode():
        latent = model.encode(pc, pos)
        out["encoder_ms"] = _timed(lambda: model.encode(pc, pos), repeats=repeats, warmup=warmup, device=dev)
        out["policy_sample_ms"] = _timed(lambda: model.sample_actions(latent, generator=g), repeats=repeats,
                                         warmup=warmup, device=dev)
        # what a robot waits for when nothing else is on the critical path: encode, then sample the chunk
        out["obs_to_action_ms"] = _timed(lambda: model.sample_actions(model.encode(pc, pos), generator=g),
                                         repeats=repeats, warmup=warmup, device=dev)
        actions = model.executed_actions(model.sample_actions(latent, generator=g))
        if model.has_world_model:
            out["world_model_imagine_ms"] = _timed(lambda: model.imagine(latent, actions, generator=g),
                                                   repeats=repeats, warmup=warmup, device=dev)
    # the in-distribution cycle (encode, policy, forecast, D_R-I), whatever D_R-I the random inputs give: a
    # threshold no statistic reaches (tau 1.0 read OOD from the second cycle on random latents, so DDP was
    # timed imagining while the baseline's "never" detector ran its ID path)
    detector = {"name": "discrepancy", "tau": 1e30} if model.has_world_model else {"name": "never"}
    ctrl = exp.make_controller(detector=detector, tracker=False, async_forecast=False)
    # the observation as an env delivers it, on the CPU (the controller moves it to the model's device): its
    # actions come back to the CPU before the next forecast is launched, so the timed call's last copy waits
    # for the policy only (an observation on the GPU would send them back there, behind the forecast's kernels)
    td = TensorDict({"point_cloud": pc.cpu(), "agent_pos": pos.cpu(), "chunk_index": torch.ones(1, 1, dtype=torch.long)},
                    batch_size=[1])
    ctrl(td.clone())  # a first cycle so that D_R-I has a forecast to compare with
    window = (1, model.obs_steps, model.encoder.out_dim)
    det_td = TensorDict({("ddp", "latent_real"): torch.rand(window),
                         ("ddp", "latent_pred"): torch.rand(window), "chunk_index": torch.ones(1, 1, dtype=torch.long)},
                        batch_size=[1], device=dev)  # on the timed device, as the controller's latents are
    out["detector_ms"] = _timed(lambda: ctrl.detector(det_td), repeats=repeats, warmup=warmup, device=dev)
    out["control_cycle_ms"] = _timed(lambda: ctrl(td.clone()), repeats=repeats, warmup=warmup, device=dev)
    # what the robot waits for with the next forecast made in the background while the chunk executes
    # (controller.async_forecast): the previous cycle's forecast has finished before the timed call
    live = exp.make_controller(detector=detector, tracker=False, async_forecast=True)
    # (no device-wide synchronise after the call: it would wait for the background forecast's kernels too; the
    # actions the call returns are on the CPU, so the policy's kernels are done when it returns)
    out["controller_latency_ms"] = _timed(lambda: live(td.clone()), repeats=repeats, warmup=warmup, device=dev,
                                          before=live.wait_forecast, sync_after=False)
    live.close()
    # training throughput on random windows of the recipe's shapes, on a copy: the optimiser steps on noise and
    # the batch's target table must not reach the caller's model (bench(exp) on a loaded checkpoint, then eval)
    model = copy.deepcopy(model)
    model.train()
    B = r.train.batch_size
    T = model.window
    batch = TensorDict({
        "point_cloud": torch.rand(B, T, P, r.task.point_dim, device=dev),
        "agent_pos": torch.rand(B, T, D, device=dev),
        "action": torch.rand(B, T, r.task.action_dim, device=dev) * 2 - 1,
    }, batch_size=[B], device=dev)
    if model.uses_target_table:
        # world_model.target_refresh_every: the batch's own B x T frames stand in for the training frames.
        # train_step_ms then excludes the table's refresh (all training frames, every K steps), timed apart:
        # amortised, a step costs refresh_ms_per_1k_frames * frames / 1000 / K more
        from ddp.models.ddp_policy import FRAME_INDEX

        frames = B * T
        batch.set(FRAME_INDEX, torch.arange(frames, device=dev).reshape(B, T))
        flat_pc, flat_pos = batch["point_cloud"].reshape(frames, P, -1), batch["agent_pos"].reshape(frames, D)
        def refresh():  # as the trainer refreshes it: under bf16 autocast where the recipe trains so
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=r.train.autocast_bf16):
                model.refresh_target_table(flat_pc, flat_pos)

        refresh_ms = _timed(refresh, repeats=train_steps, warmup=1, device=dev)
        out["target_refresh_ms_per_1k_frames"] = refresh_ms * 1000.0 / frames
    opt = make_optimizer(model, r.train)
    ema = EMA(model, r.ema) if r.ema.enabled else None

    # the trainer's step as the recipe sets it: compile, bf16 autocast, micro-batches, gradient clipping
    cfg = r.train
    loss_fn = torch.compile(model.loss) if cfg.compile else model.loss  # compiled in the untimed warm-up step
    micro = max(1, min(cfg.micro_batches, B))

    def step():
        opt.zero_grad(set_to_none=True)
        for part in batch.split(math.ceil(B / micro)):
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=cfg.autocast_bf16):
                loss = loss_fn(part)["loss"] * (part.batch_size[0] / B)
            loss.backward()
        if cfg.grad_clip_norm:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip_norm)
        opt.step()
        if ema is not None:
            ema.update(model)

    ms = _timed(step, repeats=train_steps, warmup=1, device=dev)
    out["train_step_ms"] = ms
    out["train_samples_per_s"] = 1000.0 * B / ms
    model.eval()
    return out


def baseline_of(exp):
    """The DP3 baseline of a recipe: the same parts, sizes and code paths (the CPU fast paths included), world
    model disabled. ``benchmarks/train_step.py`` also times both with the fast paths off (its "eager" columns)."""
    from ddp.experiment import Experiment
    from ddp.recipe import apply_overrides

    data = apply_overrides(exp.resolved, ["world_model.enabled=false", "controller.detector={name: never}"])
    return Experiment(data, f"{exp.source} (DP3 baseline)", trust_plugins=bool(exp.plugin_modules))


def compare(exp, *, repeats: int = 20, warmup: int = 3, device: str = "cpu", train_steps: int = 5,
            rounds: int = 3) -> dict[str, tuple[float, float | None, float | None]]:
    """``{stage: (recipe, dp3_baseline, cost ratio)}``; the baseline is None for stages it lacks.

    The two are timed in ``rounds`` alternating rounds (each a :func:`bench` of ``repeats`` calls), and each
    stage's value is the median over the rounds, so that a slow spell of a shared machine reaches both alike.
    The ratio reads the same way for every row, the recipe's cost over the baseline's: times for ms rows,
    baseline / recipe for throughput rows (``*_per_s``)."""
    base_exp = baseline_of(exp)
    mine_runs, base_runs = [], []
    for i in range(max(1, rounds)):  # the order alternates too: neither always runs first (a cold cache, a warm one)
        for which, runs in ((exp, mine_runs), (base_exp, base_runs))[:: 1 if i % 2 == 0 else -1]:
            runs.append(bench(which, repeats=repeats, warmup=warmup, device=device, train_steps=train_steps))
    mine = {k: statistics.median(r[k] for r in mine_runs) for k in mine_runs[0]}
    base = {k: statistics.median(r[k] for r in base_runs) for k in base_runs[0]}
    rows = {}
    for k, v in mine.items():
        b = base.get(k)
        ratio = None if not b or not v else (b / v if k.endswith("_per_s") else v / b)
        rows[k] = (v, b, ratio)
    return rows
