"""A training run's output directory: one trainer at a time, no leftovers, logs that match the checkpoint.

* :class:`RunLock` holds an exclusive ``flock`` on ``<output_dir>/.lock`` while a
  trainer writes there; a second trainer (in any process) gets one line naming
  the holder's pid. The kernel drops the lock when its process dies, so a
  killed run never leaves the directory locked.
* :func:`remove_leftovers` deletes the temporary files of checkpoint writes that
  a kill interrupted (``.last.pt.*.tmp``); only called under the lock.
* :func:`trim_csv_logs` drops CSV log rows past the step a run resumes from, so
  that the steps a killed run logged after its last checkpoint are not repeated.
* :func:`set_aside_previous_run` moves an earlier run's checkpoint and logs to
  ``previous/<time>/`` when a run starts over (``--no-resume``) in its directory.
"""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

from ddp.errors import DDPError

LOCK_FILE = ".lock"
LOGS_DIR = "logs"  # the trainer's logger writes under <output_dir>/logs


class RunDirBusy(DDPError):
    """Another trainer holds the output directory."""


class RunLock:
    """``with RunLock(dir):`` exclusive use of a run directory (non-blocking; raises RunDirBusy)."""

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)
        self._fd: int | None = None

    def acquire(self) -> "RunLock":
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / LOCK_FILE
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RunDirBusy(
                f"{self.directory}: another ddp train (pid {holder}) is writing there; wait for it or use "
                "another --output-dir"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def remove_leftovers(directory: str | os.PathLike, checkpoint_name: str) -> list[Path]:
    """Delete ``.<checkpoint_name>.*.tmp`` files (interrupted atomic writes); return what was removed."""
    removed = []
    for tmp in Path(directory).glob(f".{checkpoint_name}.*.tmp"):
        tmp.unlink(missing_ok=True)
        removed.append(tmp)
    return removed


def trim_csv_logs(directory: str | os.PathLike, step: int) -> int:
    """Drop ``step,value`` rows with ``step > step`` from every CSV scalar log under ``directory``.

    Returns the number of rows dropped. Rows that do not start with an integer step are kept.
    """
    dropped = 0
    for csv in (Path(directory) / LOGS_DIR).glob("**/scalars/*.csv"):  # not previous/: earlier runs' logs
        kept = []
        lines = csv.read_text().splitlines(keepends=True)
        for line in lines:
            head = line.split(",", 1)[0].strip()
            if head.lstrip("-").isdigit() and int(head) > step:
                dropped += 1
                continue
            kept.append(line)
        if len(kept) != len(lines):
            tmp = csv.with_suffix(".csv.tmp")
            tmp.write_text("".join(kept))
            os.replace(tmp, csv)
    return dropped


def set_aside_previous_run(directory: str | os.PathLike, checkpoint_name: str) -> Path | None:
    """A run starting over in a used directory (``--no-resume``): the earlier run's checkpoint, the files
    named after it (``last.calibration.json``) and its logs move to ``previous/<UTC time>/``. Nothing is
    deleted, a later plain ``ddp train`` cannot resume the earlier run should the new one be killed before
    its first checkpoint, and the new logs do not continue the old ones. Returns that folder, or None when
    there was nothing to move. Only called under the directory's lock."""
    directory = Path(directory)
    stem = Path(checkpoint_name).stem
    moved = [p for p in directory.glob(f"{stem}.*") if p.is_file()]
    if (directory / LOGS_DIR).is_dir():
        moved.append(directory / LOGS_DIR)
    if not moved:
        return None
    target = directory / "previous" / time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    while target.exists():  # two fresh starts within a second
        target = target.with_name(target.name + "+")
    target.mkdir(parents=True)
    for path in moved:
        os.replace(path, target / path.name)
    return target
