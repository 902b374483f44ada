"""Data-parallel training across processes: torch's DistributedDataParallel under ``torchrun``.

("DDP" elsewhere in this library is the Dream Diffusion Policy; this module is about torch's
DistributedDataParallel.) ``torchrun --nproc-per-node K -m ddp train RECIPE`` starts K processes
with ``RANK`` / ``WORLD_SIZE`` / ``LOCAL_RANK`` set; :func:`process_group` joins them (backend nccl
on CUDA, gloo on the CPU) and :class:`Ranks` says who is who. A plain ``ddp train`` is one process
and touches none of this.

How training uses it (``ddp.train``): a global batch of ``train.batch_size`` samples is split into
``train.micro_batches`` equal micro-batches, each with its own diffusion-noise stream; rank r
computes micro-batches r, r + K, ... and the gradients are averaged across ranks. The update is the
same whatever K divides ``micro_batches`` into, so a run gives the same weights on 1 process or K
(to float rounding) and resumes exactly with another world size.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from ddp.errors import DDPError

__all__ = ["Ranks", "process_group"]


@dataclass(frozen=True)
class Ranks:
    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        """Rank 0: the one that checkpoints, logs and shows progress."""
        return self.rank == 0

    def mine(self, micro_batches: int) -> list[int]:
        """The micro-batch indices this rank computes."""
        return list(range(self.rank, micro_batches, self.world))

    def all_reduce_mean(self, values: list[float], device) -> list[float]:
        if not self.enabled:
            return values
        t = torch.tensor(values, dtype=torch.float64, device=device)
        torch.distributed.all_reduce(t)
        return (t / self.world).tolist()

    def any(self, flag: bool, device) -> bool:
        """Whether ``flag`` holds on some rank (a collective: all ranks call it)."""
        if not self.enabled:
            return bool(flag)
        return self.all_reduce_mean([float(bool(flag))], device)[0] > 0

    def on_main(self, fn, device, what: str):
        """``fn()`` on rank 0 alone, the other ranks told whether it raised (a collective: all ranks call it), so
        that a failure there (a busy output folder, a logger that cannot start) is rank 0's own one-line error
        and every other rank stops with one line too, instead of waiting in the next collective (a hang on
        NCCL, a transport traceback on gloo). Returns ``fn()``'s value on rank 0, None elsewhere. ``what``:
        what rank 0 was doing, for the other ranks' message."""
        if not self.enabled:
            return fn() if self.main else None
        result = None
        if self.main:
            try:
                result = fn()
            except BaseException:
                self.any(True, device)  # the others learn it failed, then stop with their own line
                raise
        if self.any(False, device):
            raise DDPError(f"rank 0 could not {what} (its error says why); rank {self.rank} stops too")
        return result

    def gather(self, obj) -> list:
        """Every rank's ``obj`` (a collective: all ranks call it)."""
        if not self.enabled:
            return [obj]
        out = [None] * self.world
        torch.distributed.all_gather_object(out, obj)
        return out

    def barrier(self) -> None:
        if self.enabled:
            torch.distributed.barrier()


def env_ranks() -> Ranks:
    """The ranks torchrun set in the environment (one process when it did not)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    return Ranks(int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0")))


@contextmanager
def process_group(device: torch.device):
    """Join torchrun's process group for the duration (nothing for one process); yields :class:`Ranks`."""
    ranks = env_ranks()
    if not ranks.enabled or torch.distributed.is_initialized():
        yield ranks
        return
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(ranks.local_rank)
    torch.distributed.init_process_group(backend=backend)
    try:
        yield ranks
    finally:
        torch.distributed.destroy_process_group()
