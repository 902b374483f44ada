"""``exclusive_lock(path)``: an exclusive ``flock`` on ``<path.parent>/.<path.name>.lock``, beside what it
guards (a demo cache, a suite's report, a suite run's folder, which may be moved aside while held). The
kernel drops it when the process dies, so a killed process never leaves anything locked."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from ddp.errors import DDPError


class LockBusy(DDPError):
    """Another process holds the lock (``exclusive_lock(..., wait=False)``)."""


@contextlib.contextmanager
def exclusive_lock(path: str | os.PathLike, *, wait: bool = True, busy: str = "another process holds it"):
    """Hold the lock of ``path`` for the ``with`` block: wait for it, or (``wait=False``) raise
    :class:`LockBusy` ``"<path>: <busy>"`` at once."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path.parent / f".{path.name}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            raise LockBusy(f"{path}: {busy}") from None
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
