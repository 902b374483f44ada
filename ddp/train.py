"""The training loop (paper Algorithm 1 lives in DreamDiffusionPolicy.loss).

AdamW, linear warm-up then cosine decay, EMA of the weights, atomic
checkpoints at epoch boundaries (and on Ctrl-C), exact resume: the batch
order of every epoch is a pure function of (seed, epoch) and the diffusion
noise comes from a generator whose state is checkpointed.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import signal
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ddp.checkpoint import load_checkpoint, save_checkpoint, stored_recipe
from ddp.data.sequence import SequenceDataset
from ddp.distributed import env_ranks, process_group
from ddp.errors import CheckpointError, DDPError, RecipeError
from ddp.models.ddp_policy import FRAME_INDEX
from ddp.models.ema import EMA
from ddp.preemption import Preempted, interruption, signals_deferred, stop_requests, stop_signals
from ddp.recipe import recipe_changes
from ddp.run_dir import LOGS_DIR, RunLock, remove_leftovers, set_aside_previous_run, trim_csv_logs

LAST = "last.pt"

#: recipe keys (and sections) that may change when a run resumes; any other change is refused.
#: A changed max_steps / epochs stretches the cosine schedule from the step reached (the LR jumps).
RESUMABLE = (
    "train.max_steps", "train.epochs", "train.checkpoint_every_epochs", "train.log_every_steps",
    "train.num_threads", "train.logger", "train.device", "train.output_dir", "train.compile", "eval", "controller",
)
#: what a checkpoint must hold to resume training from it
RESUME_KEYS = ("model", "optimizer", "lr_scheduler", "noise_rng", "step", "epoch", "batch_in_epoch", "recipe")


def resolve_device(name: str, *, source: str | None = None, key: str = "train.device") -> torch.device:
    """``auto`` (CUDA when available), ``cpu``, ``cuda``, ``cuda:1``, ...; one line if unusable here."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise RecipeError(f"'{name}' is not a torch device (auto, cpu, cuda, cuda:1, mps)", source=source,
                          key=key) from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            build = f"torch {torch.__version__}" + ("" if torch.version.cuda else ", a CPU-only build")
            raise RecipeError(f"'{name}' but CUDA is not available ({build}); use auto or cpu", source=source,
                              key=key)
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise RecipeError(f"'{name}' but this machine has {torch.cuda.device_count()} CUDA device(s)",
                              source=source, key=key)
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise RecipeError(f"'{name}' but MPS is not available here; use auto or cpu", source=source, key=key)
    return device


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def resume_conflicts(path: Path, state: dict, current: dict) -> dict[str, tuple]:
    """The recipe keys that keep checkpoint ``state`` (read from ``path``) from continuing the run of the
    resolved recipe ``current``: ``{key: (stored, current)}``, empty when it can resume."""
    stored = stored_recipe(path, state)  # a stored recipe that is not a mapping no longer passes as "no change"
    task = current.get("task", {})
    return {
        k: v for k, v in recipe_changes(stored, current).items()
        if not any(k == r or k.startswith(r + ".") for r in RESUMABLE)
        # an env section now renders what task says (older recipes stored the env's own default)
        and not (k in ("env.num_points", "env.point_dim") and v[1] == task.get(k.split(".")[1]))
    }


def describe_changes(changes: dict[str, tuple], shown: int = 4) -> str:
    """``key: old -> new, ...`` for the first ``shown`` changes, and how many more."""
    text = ", ".join(f"{k}: {_show(a)} -> {_show(b)}" for k, (a, b) in list(changes.items())[:shown])
    return text + (f" (and {len(changes) - shown} more)" if len(changes) > shown else "")


def check_resumable(path: Path, state: dict, current: dict) -> None:
    """Refuse, in one line, a checkpoint that cannot continue this recipe's run."""
    missing = [k for k in RESUME_KEYS if k not in state]
    if missing:
        raise CheckpointError(f"{path}: cannot resume: the checkpoint lacks {', '.join(missing)}")
    changes = resume_conflicts(path, state, current)
    if changes:
        raise CheckpointError(
            f"{path}: cannot resume: the recipe differs from the run's ({describe_changes(changes)}); use "
            f"--no-resume to start over, or another --output-dir (may change on resume: {', '.join(RESUMABLE)})"
        )


def warmup_cosine(warmup: int, total: int, schedule: str):
    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / max(1, warmup)
        if schedule == "constant":
            return 1.0
        progress = (step - warmup) / max(1, total - warmup)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))

    return factor


def make_optimizer(model: torch.nn.Module, cfg) -> torch.optim.AdamW:
    """The recipe's AdamW (``train.lr``, ``betas``, ``weight_decay``), fused: one kernel for all parameters
    on CPU and CUDA instead of a Python loop over them (identical updates up to float rounding)."""
    return torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay, fused=True)


def frames_digest(steps) -> str:
    """A digest of the frames a target table encodes (``point_cloud`` and ``agent_pos`` of every step): a
    resumed run reuses a checkpointed table only for the same frames."""
    h = hashlib.sha256()
    for key in ("point_cloud", "agent_pos"):
        values = steps[key].detach().cpu().contiguous()
        h.update(f"{key}{tuple(values.shape)}{values.dtype}".encode())
        h.update(memoryview(values.view(torch.uint8).numpy()))  # the bytes as stored, any dtype, no copy
    return h.hexdigest()[:16]


@dataclass
class TrainResult:
    steps: int
    epochs: int
    loss: float
    loss_bc: float
    loss_wm: float  # lambda * L_WM (the loss_* terms sum to the objective)
    wm_error: float  # L_WM unweighted
    seconds: float  # this call's training time
    samples_per_second: float
    checkpoint: Path
    # training time over every call that built the checkpoint (resumes included); None: a checkpoint written
    # before this was recorded is in it
    total_seconds: float | None = None


def same_start(ranks, position: tuple[int, int, int], output_dir) -> None:
    """Every rank starts from the same (step, epoch, batch) (a collective): each reads ``last.pt`` itself,
    so an output folder that is not shared between nodes would resume some ranks and not others."""
    starts = ranks.gather(tuple(position))
    if len(set(starts)) > 1:
        raise CheckpointError(f"{output_dir}: the processes would start from different (step, epoch, batch): "
                              f"{starts} (rank order); train.output_dir must be one folder all ranks share")


class _Objective(torch.nn.Module):
    """The model's training objective as a module (what DistributedDataParallel wraps):
    ``(batch, generator) -> (sum of the loss_* terms, the loss TensorDict)``."""

    def __init__(self, model, loss_fn):
        super().__init__()
        self.model = model
        self.loss_fn = loss_fn

    def forward(self, batch, generator):
        losses = self.loss_fn(batch, generator=generator)
        return sum(losses[k] for k in losses.keys() if k.startswith("loss_")), losses


def check_training_episodes(episodes, keys, min_length: int, source) -> None:
    """The demonstrations train: finite values (one NaN made its dimension's normaliser scale NaN, and every
    loss and checkpoint after it; inf a scale of 0) and episodes long enough for a window (``min_length``
    steps: shorter ones give none; a warning names how many)."""
    bad = episodes.first_nonfinite(keys)
    if bad is not None:
        key, ep, step = bad
        raise DDPError(f"{source}: the training data's '{key}' holds NaN or inf at episode {ep}, step {step}: fix "
                       f"or drop that episode (data section)")
    lengths = torch.diff(episodes.episode_ends, prepend=torch.zeros(1, dtype=torch.long))
    short = int((lengths < min_length).sum())
    if short == len(lengths):
        raise DDPError(f"{source}: no demonstration episode is long enough to train on: a window needs {min_length} "
                       f"steps (the training window less obs_steps - 1 and action_steps - 1 of edge padding), the longest "
                       f"has {int(lengths.max())}")
    if short:
        warnings.warn(f"{short} of {len(lengths)} demonstration episodes are shorter than {min_length} steps and "
                      f"give no training window", UserWarning, stacklevel=3)


class Trainer:
    """Trains an experiment's model; ``fit()`` resumes from ``<output_dir>/last.pt`` if present."""

    def __init__(self, experiment, output_dir: str | Path | None = None, progress: bool = True):
        self.exp = experiment
        cfg = experiment.recipe.train
        self.cfg = cfg
        self.output_dir = Path(output_dir or cfg.output_dir.format(name=experiment.recipe.name))
        self.progress = progress
        self.device = resolve_device(cfg.device, source=experiment.source)
        ranks = env_ranks()
        if ranks.enabled and self.device.type == "cuda":  # one GPU per rank under torchrun
            self.device = torch.device("cuda", ranks.local_rank)
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)

    def _batches_per_epoch(self, n: int) -> int:
        return max(1, n // self.cfg.batch_size)

    def _epoch_order(self, epoch: int, n: int) -> torch.Tensor:
        g = torch.Generator().manual_seed(self.exp.recipe.seed * 1_000_003 + epoch)
        return torch.randperm(n, generator=g)

    def fit(self, resume: bool = True) -> TrainResult:
        """Train (resuming from ``<output_dir>/last.pt`` when ``resume``), holding the directory's lock.

        Under ``torchrun`` every rank trains its share of each batch (``ddp.distributed``); rank 0
        holds the lock, checkpoints, logs and shows progress.
        """
        with process_group(self.device) as ranks, contextlib.ExitStack() as held:
            self.ranks = ranks

            def take_the_folder() -> None:
                held.enter_context(RunLock(self.output_dir))  # released when fit() returns or raises
                remove_leftovers(self.output_dir, LAST)  # temporary files of writes a kill interrupted

            # rank 0 alone; a busy folder stops every rank with one line (a collective: also the barrier)
            ranks.on_main(take_the_folder, self.device, "lock its output folder")
            # SIGTERM / SIGHUP (a scheduler's preemption) end training like Ctrl-C: with a checkpoint
            with stop_signals():
                return self._fit(resume)

    def _fit(self, resume: bool) -> TrainResult:
        exp, cfg, model = self.exp, self.cfg, self.exp.model
        pol = exp.recipe.policy
        episodes = exp.episodes()
        keys = ["point_cloud", "agent_pos", "action"]
        pad_before, pad_after = pol.obs_steps - 1, pol.action_steps - 1
        check_training_episodes(episodes, keys, model.window - pad_before - pad_after, exp.source)
        dataset = SequenceDataset(episodes, model.window, pad_before=pad_before, pad_after=pad_after, keys=keys)
        ckpt_path = self.output_dir / LAST
        if not resume:
            aside = self.ranks.on_main(lambda: set_aside_previous_run(self.output_dir, LAST), self.device,
                                       "set the earlier run aside")
            if aside is not None:
                warnings.warn(f"starting over in {self.output_dir}: the earlier run's checkpoint and logs moved to "
                              f"{aside}", UserWarning, stacklevel=3)
        state = load_checkpoint(ckpt_path) if resume and ckpt_path.exists() else None
        if state is not None:
            check_resumable(ckpt_path, state, exp.resolved)
        # fitted once: weights loaded for fine-tuning (or trained by an earlier call) keep the scaling they learned
        if state is None and not bool(model.normalizer.fitted):
            model.normalizer.fit({k: episodes.steps[k] for k in ("action", "agent_pos", "point_cloud")})
        model.to(self.device).train()
        optimizer = make_optimizer(model, cfg)
        per_epoch = self._batches_per_epoch(len(dataset))
        total = cfg.epochs * per_epoch
        if cfg.max_steps is not None:
            if cfg.max_steps > total and self.ranks.main:
                warnings.warn(f"train.max_steps ({cfg.max_steps}) is more than train.epochs ({cfg.epochs}) x "
                              f"{per_epoch} batches: training stops after {total} steps (raise train.epochs for "
                              f"more)", UserWarning, stacklevel=3)
            total = min(cfg.max_steps, total)  # the cosine schedule ends where training does
        lr_sched = torch.optim.lr_scheduler.LambdaLR(
            optimizer, warmup_cosine(cfg.warmup_steps, total, cfg.lr_schedule)
        )
        ema = EMA(model, exp.recipe.ema) if exp.recipe.ema.enabled else None
        ranks, micro = self.ranks, cfg.micro_batches
        if micro % ranks.world:
            raise RecipeError(f"train.micro_batches ({micro}) must be a multiple of the number of processes "
                              f"({ranks.world})", source=exp.source, key="train.micro_batches")
        if len(dataset) < micro:  # a micro-batch without a window would average an empty loss (NaN)
            raise RecipeError(f"the training data hold {len(dataset)} windows, fewer than train.micro_batches "
                              f"({micro}): use more episodes or fewer micro-batches", source=exp.source,
                              key="train.micro_batches")
        mine = ranks.mine(micro)
        # one diffusion-noise stream per micro-batch (the first one is the single-batch run's)
        noises = {i: torch.Generator(device=self.device).manual_seed(exp.recipe.seed if i == 0 else
                                                                       exp.recipe.seed * 1_000_003 + 7919 * i)
                  for i in mine}
        step, epoch, batch_in_epoch = 0, 0, 0
        # world_model.target_refresh_every: the future targets come from a table of every frame's latent,
        # re-encoded every `refresh` steps (the step of the last refresh is checkpointed with the table)
        refresh = model.target_refresh_every if model.uses_target_table else 0
        table_step = None
        table_frames = frames_digest(dataset.steps) if refresh else None  # which frames the table encodes
        if state is not None:
            self._restore(state, ckpt_path, optimizer=optimizer, lr_sched=lr_sched, ema=ema, noises=noises, total=total)
            step, epoch, batch_in_epoch = int(state["step"]), int(state["epoch"]), int(state["batch_in_epoch"])
            table = state.get("target_table") if refresh else None
            # reused only for the very frames it encoded (else other demos: refresh now)
            stored_frames = state.get("target_table_frames", table_frames)  # checkpoints before the digest: by shape
            if (table is not None and table.shape[0] == dataset.steps.shape[0]
                    and stored_frames == table_frames):
                model.target_table = table.to(self.device)
                table_step = int(state["target_table_step"])
        if cfg.logger == "csv":
            # rows a killed run logged after its last checkpoint (or, killed before its first one, all of them)
            resumed_at = step if state is not None else -1

            def trim() -> None:
                if state is not None or (self.output_dir / LOGS_DIR).is_dir():
                    trim_csv_logs(self.output_dir, resumed_at)

            ranks.on_main(trim, self.device, "trim its logs")
        same_start(ranks, (step, epoch, batch_in_epoch), self.output_dir)
        logger = ranks.on_main(self._logger, self.device, "start its logger")
        loss_fn = torch.compile(model.loss) if cfg.compile else model.loss
        parallel = None
        if ranks.enabled:  # torch's DistributedDataParallel: gradients averaged across ranks in backward
            parallel = torch.nn.parallel.DistributedDataParallel(
                _Objective(model, loss_fn), device_ids=[self.device.index] if self.device.type == "cuda" else None,
            )
        sums = {"loss": 0.0, "loss_bc": 0.0, "loss_wm": 0.0, "wm_error": 0.0}
        count, last_means = 0, {k: float("nan") for k in sums}  # no step in this call (a finished run resumed)
        earlier_seconds = 0.0  # training time of the calls before this one (from the checkpoint; None: unknown)
        if state is not None:
            earlier = state.get("train_seconds")
            earlier_seconds = None if earlier is None else float(earlier)
            last_means.update({k: float(v) for k, v in state.get("losses", {}).items() if k in last_means})
            window = state.get("log_window")
            if window and window.get("count") and window.get("sums"):
                # each rank takes the mean of the saved ranks' sums: the window's mean over the ranks is kept
                # whatever the world size now
                count = int(window["count"])
                sums = {k: float(sum(float(r.get(k, 0.0)) for r in window["sums"]) / len(window["sums"]))
                        for k in sums}
        t0, samples = time.perf_counter(), 0
        bar = tqdm(total=total, initial=step, disable=not (self.progress and ranks.main), desc=exp.recipe.name,
                   unit="step")

        def window_means() -> dict[str, float]:
            """The loss terms averaged over the steps since the last log line, and over the ranks (a collective)."""
            return dict(zip(sums, ranks.all_reduce_mean([v / count for v in sums.values()], self.device)))

        saved_step = step if state is not None else -1
        start_step = step
        # the noise streams as they were at the last step boundary: a checkpoint holds the state of a step
        # boundary, whatever the streams drew since (an interruption in the middle of a step)
        boundary_noise = {i: noises[i].get_state() for i in mine}
        updating = False  # between optimizer.step() and the step counter: the step is half applied
        requested: list[int] = []  # stop signals recorded in the loop (stop_requests), acted on at a boundary
        agreed_stop = False  # every rank stops at this boundary (a collective decided it)

        def checkpoint(raise_deferred: bool = True) -> Path:
            """Write last.pt for the step boundary reached; a signal that arrives during the write is
            raised after it (``raise_deferred``) or, in the loop, recorded for the next boundary."""
            nonlocal saved_step
            # every rank's noise streams and unlogged loss sums (a collective), written by rank 0 only
            streams = {i: g for part in ranks.gather({i: boundary_noise[i].cpu() for i in mine})
                       for i, g in part.items()}
            window = ranks.gather(dict(sums))  # the steps since the last log line, per rank
            if not ranks.main:
                # rank 0 is writing; it says whether the write failed (a collective), so that a failed write
                # ends every rank with one line instead of leaving the others in the next collective
                if ranks.any(False, self.device):
                    raise CheckpointError(f"{ckpt_path}: rank 0 could not write the checkpoint (its error says "
                                          f"why); rank {ranks.rank} stops too")
                saved_step = step
                return ckpt_path
            def payload() -> dict:
                out = {
                    "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "lr_scheduler": lr_sched.state_dict(),
                    "noise_rng": streams[0] if micro == 1 else [streams[i] for i in range(micro)],
                    "step": step,
                    "epoch": epoch,
                    "batch_in_epoch": batch_in_epoch,
                    "recipe": exp.to_yaml(),
                    "train_seconds": None if earlier_seconds is None else earlier_seconds + time.perf_counter() - t0,
                    "losses": dict(last_means),  # the last logged window's loss terms
                    # the window being logged: a resumed run's first row then covers all its steps
                    "log_window": {"count": count, "sums": window},
                }
                if ema is not None:
                    out["ema"] = ema.state_dict()
                if refresh and table_step is not None:  # an exact resume needs the targets of the last refresh
                    out["target_table"] = model.target_table.detach().cpu()
                    out["target_table_step"] = table_step
                    out["target_table_frames"] = table_frames
                return out

            # no signal lands in the middle of the write: a second Ctrl-C is noted and acted on after it
            with signals_deferred() as received:
                try:  # the payload too: an error copying it (a CUDA fault surfacing) must not strand the ranks
                    path = save_checkpoint(ckpt_path, payload())
                except BaseException:
                    ranks.any(True, self.device)  # the other ranks wait for this write: they stop too
                    raise
                saved_step = step
            ranks.any(False, self.device)  # written: the other ranks go on
            if received and raise_deferred:
                raise interruption(received[0])
            requested.extend(received)
            return path

        def stop_at_boundary() -> None:
            """Stop here if a signal was recorded (on any rank: every rank stops at the same step)."""
            nonlocal agreed_stop
            if ranks.any(bool(requested), self.device):
                agreed_stop = True
                raise interruption(requested[0] if requested else signal.SIGTERM)

        # the loop's handlers (stop_requests) and the save's (signals_deferred) are set one after the other: a
        # signal in between is recorded here, not raised before the checkpoint is written
        between: list[int] = []
        with signals_deferred(between):
            try:
                with stop_requests(requested):
                    # a signal that came while the handlers were being swapped: acted on at the first boundary
                    # (it was held until the whole run had ended)
                    requested.extend(between)
                    between.clear()
                    while epoch < cfg.epochs and step < total:
                        order = self._epoch_order(epoch, len(dataset))
                        while batch_in_epoch < per_epoch and step < total:
                            idx = order[batch_in_epoch * cfg.batch_size : (batch_in_epoch + 1) * cfg.batch_size]
                            optimizer.zero_grad(set_to_none=True)
                            if refresh and (table_step is None or step - table_step >= refresh):
                                with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=cfg.autocast_bf16):
                                    model.refresh_target_table(dataset.steps["point_cloud"], dataset.steps["agent_pos"])
                                table_step = step
                            step_losses = self._backward(dataset, idx, noises, loss_fn, parallel, keys=list(sums))
                            if cfg.grad_clip_norm:
                                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip_norm)
                            updating = True  # the update, from the optimiser to the counters, is all or nothing
                            optimizer.step()
                            lr_sched.step()
                            if ema is not None:
                                ema.update(model)
                            step += 1
                            batch_in_epoch += 1
                            boundary_noise = {i: noises[i].get_state() for i in mine}
                            updating = False
                            samples += idx.numel()
                            for k in sums:
                                sums[k] += step_losses[k]
                            count += 1
                            bar.update(1)
                            if step % cfg.log_every_steps == 0 or step == total:
                                means = window_means()
                                bar.set_postfix({k: f"{v:.4f}" for k, v in means.items()})
                                if logger is not None:
                                    for k, v in means.items():
                                        logger.log_scalar(k, v, step=step)
                                    logger.log_scalar("lr", lr_sched.get_last_lr()[0], step=step)
                                last_means, sums, count = means, {k: 0.0 for k in sums}, 0
                            stop_at_boundary()
                        if batch_in_epoch >= per_epoch:
                            epoch, batch_in_epoch = epoch + 1, 0
                            if epoch % cfg.checkpoint_every_epochs == 0:
                                checkpoint(raise_deferred=False)
                                stop_at_boundary()
            except KeyboardInterrupt as stopped:  # Ctrl-C, or Preempted (SIGTERM / SIGHUP)
                # a further signal waits until the checkpoint is written (the save is what it asks for too)
                with signals_deferred() as during_save:
                    bar.close()
                    # Not when the interruption came in the middle of an update (only a second Ctrl-C, or an
                    # exception raised by the code, can do that: signals wait for a step boundary): that step is
                    # half applied, and the last checkpoint stands. Under torchrun only a stop all ranks agreed
                    # on saves: the save is a collective.
                    if saved_step != step and not updating and (agreed_stop or not ranks.enabled):
                        checkpoint(raise_deferred=False)
                    elif updating and ranks.main:
                        warnings.warn(f"training interrupted in the middle of step {step + 1}'s update: not saved; "
                                      f"{ckpt_path} holds step {max(saved_step, 0)}", RuntimeWarning, stacklevel=2)
                # (a SIGTERM recorded in the loop after the Ctrl-C, or by the save's own deferring handler, is in
                # ``requested``; this block's handler catches the rest)
                preempted = [sig for sig in (*requested, *during_save) if sig != signal.SIGINT]
                if preempted and not isinstance(stopped, Preempted):  # Ctrl-C, then the scheduler's SIGTERM while
                    raise Preempted(preempted[0]) from stopped  # saving: exit as preempted (143), so it requeues
                raise
            else:
                # the run is done: a stop asked for from here on waits until the final checkpoint is written
                with signals_deferred(requested):
                    bar.close()
                    if count:  # the steps since the last log line: a collective on every rank, before the save
                        last_means = window_means()
                    # the last epoch's checkpoint, written by this call, holds this step and nothing was logged
                    # since: not written again (a finished run resumed is: its record and recipe are refreshed)
                    written_now = saved_step == step and step > start_step
                    path = ckpt_path if written_now and not count else checkpoint(raise_deferred=False)
                if requested:
                    raise interruption(requested[0])
            finally:  # the target table is saved with each checkpoint (a resume reloads it), never kept on the model
                model.target_table = None
        if between:
            raise interruption(between[0])
        seconds = time.perf_counter() - t0
        return TrainResult(
            steps=step, epochs=epoch, loss=last_means["loss"], loss_bc=last_means["loss_bc"],
            loss_wm=last_means["loss_wm"], wm_error=last_means["wm_error"],
            seconds=seconds, samples_per_second=samples / max(seconds, 1e-9), checkpoint=path,
            total_seconds=None if earlier_seconds is None else earlier_seconds + seconds,
        )

    def _restore(self, state: dict, ckpt_path: Path, *, optimizer, lr_sched, ema, noises: dict, total: int) -> None:
        """Load a checkpoint's model, EMA, optimiser, schedule (recomputed for this recipe's length: a
        changed max_steps / epochs takes effect from the next update) and noise streams."""
        exp, cfg, model = self.exp, self.cfg, self.exp.model
        try:
            model.load_state_dict(state["model"])
            if ema is not None and "ema" in state:
                ema.load_state_dict(state["ema"])
            optimizer.load_state_dict(state["optimizer"])
            lr_sched.load_state_dict(state["lr_scheduler"])
            # the optimiser restored the OLD schedule's lr: recompute it from this schedule at the step reached
            factor = warmup_cosine(cfg.warmup_steps, total, cfg.lr_schedule)(lr_sched.last_epoch)
            for group in optimizer.param_groups:
                group["lr"] = group["initial_lr"] * factor
            lr_sched._last_lr = [g["lr"] for g in optimizer.param_groups]
            saved = state["noise_rng"]
            saved = saved if isinstance(saved, list) else [saved]  # one stream per micro-batch
            try:
                for i, gen in noises.items():
                    gen.set_state(saved[i])
            except RuntimeError:  # saved on another device (train.device may change on resume)
                for i, gen in noises.items():
                    gen.manual_seed(exp.recipe.seed * 1_000_003 + int(state["step"]) + 7919 * i)
                warnings.warn(f"{ckpt_path}: the diffusion-noise generator was saved on another device; "
                              "reseeded from (seed, step): the run goes on, not bit-identical to an "
                              "uninterrupted one", stacklevel=3)
        except (RuntimeError, ValueError, KeyError, TypeError) as err:
            from ddp.checkpoint import describe_mismatch

            raise CheckpointError(f"{ckpt_path}: cannot resume into this recipe's model: "
                                  f"{describe_mismatch(model, state['model']) or str(err).splitlines()[0]}") from None

    def _backward(self, dataset, idx: torch.Tensor, noises: dict, loss_fn, parallel, *, keys: list[str]) -> dict:
        """Gradients of one optimiser step: this rank's micro-batches of the batch ``idx``, each with its
        own noise stream, the objective scaled to the mean over the global batch. Returns the loss terms
        ``keys`` averaged over the micro-batches."""
        cfg, model, ranks = self.cfg, self.exp.model, self.ranks
        mine = list(noises)
        # equal parts when the batch is whole; a batch of a dataset smaller than batch_size splits into parts
        # one window apart, each weighted by its share (it cut every part to the smallest: windows went untrained)
        parts = torch.tensor_split(idx, cfg.micro_batches)
        step_losses = {k: 0.0 for k in keys}
        for j, i in enumerate(mine):
            part = parts[i]
            batch = dataset.batch(part).to(self.device)
            if model.uses_target_table:
                batch.set(FRAME_INDEX, dataset.indices[part].to(self.device))
            # DDP all-reduces (averages over ranks) in the last backward of the step only
            sync = parallel is None or j == len(mine) - 1
            with contextlib.nullcontext() if sync else parallel.no_sync():
                with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=cfg.autocast_bf16):
                    # the objective is the sum of the loss_* terms (TorchRL's convention)
                    if parallel is None:
                        losses = loss_fn(batch, generator=noises[i])
                        objective = sum(losses[k] for k in losses.keys() if k.startswith("loss_"))
                    else:
                        objective, losses = parallel(batch, noises[i])
                # the mean over the global batch, whatever share of it this rank holds; backward outside autocast
                # (torch's advice: a custom backward would otherwise run its ops in bf16)
                (objective * (ranks.world * part.numel() / idx.numel())).backward()
            for k in step_losses:  # weighted so that the mean over ranks (window_means) is the global batch's
                step_losses[k] += losses[k].detach().item() * ranks.world * part.numel() / idx.numel()
        return step_losses

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
