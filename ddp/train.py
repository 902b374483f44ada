"""The training loop (paper Algorithm 1 lives in DreamDiffusionPolicy.loss).

AdamW, linear warm-up then cosine decay, EMA of the weights, atomic
checkpoints at epoch boundaries (and on Ctrl-C), exact resume: the batch
order of every epoch is a pure function of (seed, epoch) and the diffusion
noise comes from a generator whose state is checkpointed.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ddp.checkpoint import load_checkpoint, save_checkpoint
from ddp.data.sequence import SequenceDataset
from ddp.models.ema import EMA

LAST = "last.pt"


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def warmup_cosine(warmup: int, total: int, schedule: str):
    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / max(1, warmup)
        if schedule == "constant":
            return 1.0
        progress = (step - warmup) / max(1, total - warmup)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))

    return factor


@dataclass
class TrainResult:
    steps: int
    epochs: int
    loss: float
    loss_bc: float
    loss_wm: float
    seconds: float
    samples_per_second: float
    checkpoint: Path


class Trainer:
    """Trains an experiment's model; ``fit()`` resumes from ``<output_dir>/last.pt`` if present."""

    def __init__(self, experiment, output_dir: str | Path | None = None, progress: bool = True):
        self.exp = experiment
        cfg = experiment.recipe.train
        self.cfg = cfg
        self.output_dir = Path(output_dir or cfg.output_dir.format(name=experiment.recipe.name))
        self.progress = progress
        self.device = resolve_device(cfg.device)
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)

    def _batches_per_epoch(self, n: int) -> int:
        return max(1, n // self.cfg.batch_size)

    def _epoch_order(self, epoch: int, n: int) -> torch.Tensor:
        g = torch.Generator().manual_seed(self.exp.recipe.seed * 1_000_003 + epoch)
        return torch.randperm(n, generator=g)

    def fit(self, resume: bool = True) -> TrainResult:
        exp, cfg, model = self.exp, self.cfg, self.exp.model
        pol = exp.recipe.policy
        episodes = exp.episodes()
        length = max(pol.horizon, pol.obs_steps + pol.action_steps)
        dataset = SequenceDataset(
            episodes, length, pad_before=pol.obs_steps - 1, pad_after=pol.action_steps - 1,
            keys=["point_cloud", "agent_pos", "action"],
        )
        ckpt_path = self.output_dir / LAST
        state = load_checkpoint(ckpt_path) if resume and ckpt_path.exists() else None
        if state is None:
            model.normalizer.fit({k: episodes.steps[k] for k in ("action", "agent_pos", "point_cloud")})
        model.to(self.device).train()
        optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
        per_epoch = self._batches_per_epoch(len(dataset))
        total = cfg.max_steps or cfg.epochs * per_epoch
        lr_sched = torch.optim.lr_scheduler.LambdaLR(
            optimizer, warmup_cosine(cfg.warmup_steps, total, cfg.lr_schedule)
        )
        ema = EMA(model, exp.recipe.ema) if exp.recipe.ema.enabled else None
        noise = torch.Generator(device=self.device).manual_seed(exp.recipe.seed)
        step, epoch, batch_in_epoch = 0, 0, 0
        if state is not None:
            model.load_state_dict(state["model"])
            if ema is not None and "ema" in state:
                ema.load_state_dict(state["ema"])
            optimizer.load_state_dict(state["optimizer"])
            lr_sched.load_state_dict(state["lr_scheduler"])
            noise.set_state(state["noise_rng"])
            step, epoch, batch_in_epoch = int(state["step"]), int(state["epoch"]), int(state["batch_in_epoch"])
        logger = self._logger()
        loss_fn = torch.compile(model.loss) if cfg.compile else model.loss
        sums = {"loss": 0.0, "loss_bc": 0.0, "loss_wm": 0.0}
        count, last_means = 0, dict(sums)
        t0, samples = time.perf_counter(), 0
        bar = tqdm(total=total, initial=step, disable=not self.progress, desc=exp.recipe.name, unit="step")

        def checkpoint() -> Path:
            payload = {
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "lr_scheduler": lr_sched.state_dict(),
                "noise_rng": noise.get_state(),
                "step": step,
                "epoch": epoch,
                "batch_in_epoch": batch_in_epoch,
                "recipe": exp.to_yaml(),
            }
            if ema is not None:
                payload["ema"] = ema.state_dict()
            return save_checkpoint(ckpt_path, payload)

        try:
            while epoch < cfg.epochs and step < total:
                order = self._epoch_order(epoch, len(dataset))
                while batch_in_epoch < per_epoch and step < total:
                    idx = order[batch_in_epoch * cfg.batch_size : (batch_in_epoch + 1) * cfg.batch_size]
                    batch = dataset.batch(idx).to(self.device)
                    with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=cfg.autocast_bf16):
                        losses = loss_fn(batch, generator=noise)
                    optimizer.zero_grad(set_to_none=True)
                    losses["loss"].backward()
                    if cfg.grad_clip_norm:
                        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip_norm)
                    optimizer.step()
                    lr_sched.step()
                    if ema is not None:
                        ema.update(model)
                    step += 1
                    batch_in_epoch += 1
                    samples += idx.numel()
                    for k in sums:
                        sums[k] += losses[k].detach().item()
                    count += 1
                    bar.update(1)
                    if step % cfg.log_every_steps == 0 or step == total:
                        means = {k: v / count for k, v in sums.items()}
                        bar.set_postfix({k: f"{v:.4f}" for k, v in means.items()})
                        if logger is not None:
                            for k, v in means.items():
                                logger.log_scalar(k, v, step=step)
                            logger.log_scalar("lr", lr_sched.get_last_lr()[0], step=step)
                        last_means, sums, count = means, {k: 0.0 for k in sums}, 0
                if batch_in_epoch >= per_epoch:
                    epoch, batch_in_epoch = epoch + 1, 0
                    if epoch % cfg.checkpoint_every_epochs == 0:
                        checkpoint()
        except KeyboardInterrupt:
            bar.close()
            checkpoint()
            raise
        bar.close()
        path = checkpoint()
        seconds = time.perf_counter() - t0
        final = {k: v / count for k, v in sums.items()} if count else last_means
        return TrainResult(
            steps=step, epochs=epoch, loss=final["loss"], loss_bc=final["loss_bc"], loss_wm=final["loss_wm"],
            seconds=seconds, samples_per_second=samples / max(seconds, 1e-9), checkpoint=path,
        )

    def _logger(self):
        """torchrl's logger for ``train.logger`` (csv, tensorboard, wandb) or None."""
        kind = self.cfg.logger
        if kind == "none":
            return None
        from torchrl.record.loggers import get_logger

        try:
            return get_logger(kind, logger_name=str(self.output_dir), experiment_name="logs")
        except ImportError as err:
            from ddp.errors import RecipeError

            raise RecipeError(f"logger '{kind}' needs a package that is not installed: {err}",
                              source=self.exp.source, key="train.logger") from None
