"""Atomic file writes: a temp file in the same folder, flushed and fsynced, renamed over the target, and the
folder fsynced so that the rename is durable too.

A reader (or a crash) sees the old file or the new one, never half of one. Used for checkpoints and
detector calibrations.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable, IO

__all__ = ["atomic_write"]


def atomic_write(path: str | os.PathLike, write: Callable[[IO], None], *, binary: bool = True) -> Path:
    """Call ``write(file)`` on a temp file beside ``path``, then rename it to ``path``; returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        try:  # mkstemp makes it 0600: give it the mode an open() would
            os.fchmod(fd, 0o666 & ~_umask())
        except OSError:  # a filesystem that refuses (e.g. NFS with squashed owners): the write still goes on
            pass
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)  # the rename itself survives a power loss once the folder's entry is on disk
    return path


def _umask() -> int:
    """The process's umask, read without changing it where Linux shows it (another thread may be creating
    files); elsewhere by setting it and setting it straight back."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # a platform or filesystem without directory handles: the rename stands as it is
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
