"""Atomic file writes: a temp file in the same folder, flushed and fsynced, renamed over the target, and the
folder fsynced so that the rename is durable too.

A reader (or a crash) sees the old file or the new one, never half of one. Used for checkpoints and
detector calibrations. :func:`atomic_directory` does the same for a directory (episode data, demo caches,
zarr stores): written in full beside the target, then moved onto it, the earlier one moved aside first and
deleted only once the new one is in place (put back if the move fails). Between those two renames (a few
microseconds) the path does not exist: a reader that finds nothing there should wait for the writer's
lock, where there is one, and look again.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Callable, IO

__all__ = ["atomic_directory", "atomic_write"]


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


def _fsync_tree(root: Path) -> None:
    """Every file and directory under ``root`` (``root`` included) flushed to disk."""
    for folder, _, files in os.walk(root):
        for name in files:
            try:
                fd = os.open(os.path.join(folder, name), os.O_RDONLY)
            except OSError:
                continue
            try:
                os.fsync(fd)
            except OSError:  # a filesystem refusing fsync (some FUSE mounts): the write stands as it is
                pass
            finally:
                os.close(fd)
        _fsync_dir(Path(folder))


def atomic_directory(path: str | os.PathLike, write: Callable[[Path], None]) -> Path:
    """``write(tmp)`` fills a new directory beside ``path``, which then replaces ``path``: a reader sees the
    earlier directory or the new one, whole; an error (or a crash) before the move leaves the earlier one.
    A symbolic link is followed: the directory it points to is the one replaced."""
    path = Path(path).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it private; a directory gets what mkdir would give
        write(tmp)
        _fsync_tree(tmp)  # on disk before the rename: a power loss could otherwise leave the new name on files
        # that were sized but never filled (memory-mapped leaves read as zeros of the right size)
        old = None
        if path.exists():  # moved aside, not deleted, until the new directory is in place
            old = path.with_name(f".{path.name}.old-{uuid.uuid4().hex[:8]}")
            os.rename(path, old)
        try:
            os.rename(tmp, path)
        except BaseException:
            if old is not None:
                os.rename(old, path)  # the earlier directory back in place
            raise
        _fsync_dir(path.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path
