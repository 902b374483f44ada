"""A run folder whose checkpoint was trained for another recipe: found before the run starts, and set aside.

A suite's run trains in its own folder and resumes the ``last.pt`` it finds there. When the suite file
changes a run's recipe in a way training cannot continue from (the observations, the data, the model: any
key outside ``ddp.train.RESUMABLE``), the stored result is stale and the run has to train again from
scratch. :func:`superseded` says why (``ddp suite --dry-run`` prints it) and :func:`set_aside` renames the
folder to ``<name>.superseded-<UTC time>`` beside it, so that nothing is deleted and the run starts afresh.
A checkpoint that only evaluates differently (``eval``, ``controller``, more steps) still resumes.
"""

from __future__ import annotations

import time
from pathlib import Path

from ddp.errors import CheckpointError

__all__ = ["superseded", "set_aside"]


def superseded(run_dir: str | Path, recipe: dict, source: str | None = None) -> str | None:
    """The recipe keys that keep ``run_dir/last.pt`` from continuing ``recipe`` (``key: old -> new, ...``),
    or None: no checkpoint, one that resumes, or one that training reports on itself (unreadable, or
    lacking its training state)."""
    from ddp.checkpoint import load_checkpoint
    from ddp.schema import validate
    from ddp.train import LAST, describe_changes, resume_conflicts

    path = Path(run_dir) / LAST
    if not path.is_file():
        return None
    try:
        changes = resume_conflicts(path, load_checkpoint(path), validate(recipe, source)[2])
    except CheckpointError:
        return None
    return describe_changes(changes) if changes else None


def set_aside(run_dir: str | Path) -> Path:
    """Rename ``run_dir`` to ``<name>.superseded-<UTC time>`` in the same folder; returns the new path."""
    run_dir = Path(run_dir)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    target = run_dir.with_name(f"{run_dir.name}.superseded-{stamp}")
    n = 1
    while target.exists():  # two in one second
        n += 1
        target = run_dir.with_name(f"{run_dir.name}.superseded-{stamp}-{n}")
    run_dir.rename(target)
    return target
