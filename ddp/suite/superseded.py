"""A run folder whose checkpoint was trained for another recipe: found before the run starts, and set aside.

A suite's run trains in its own folder and resumes the ``last.pt`` it finds there (a finished run whose
result went stale, or an interrupted one). When the suite file changed the run's recipe in a way training
cannot continue from (any key outside ``ddp.train.RESUMABLE``: the observations, the data, the model, the
optimiser), or changed its step budget (``train.max_steps``, or ``train.epochs`` without one: resumed at
another budget, the cosine schedule would stretch or shrink mid-run, the LR jumping, which is not the run a
fresh recipe trains, though ``ddp train`` allows it), the run has to train again from scratch. :func:`superseded` says why (``ddp suite --dry-run`` prints it) and :func:`set_aside_if_superseded`
renames the folder to ``<name>.superseded-<UTC time>`` beside it, under the folder's run lock, so that
nothing is deleted and no folder is moved while a trainer writes in it. A checkpoint that only evaluates
differently (``eval``, ``controller``), or an interrupted run with the same budget, still resumes.
"""

from __future__ import annotations

import time
from pathlib import Path

from ddp.errors import DDPError

__all__ = ["superseded", "set_aside", "set_aside_if_superseded"]


def superseded(run_dir: str | Path, recipe: dict, source: str | None = None, state: dict | None = None) -> str | None:
    """Why ``run_dir/last.pt`` cannot continue ``recipe`` (``key: old -> new, ...``), or None: no
    checkpoint, one that resumes, or one that training reports on itself (unreadable, no stored recipe,
    or a recipe that does not validate). ``state``: that checkpoint, if the caller loaded it already."""
    from ddp.checkpoint import load_checkpoint, stored_recipe
    from ddp.schema import validate
    from ddp.train import LAST, describe_changes, resume_conflicts

    path = Path(run_dir) / LAST
    if not path.is_file():
        return None
    try:
        state = load_checkpoint(path, mmap=True) if state is None else state
        resolved = validate(recipe, source)[2]
        changes = resume_conflicts(path, state, resolved)
        trained = stored_recipe(path, state).get("train", {})
    except (DDPError, OSError, AttributeError):
        return None
    if changes:
        return describe_changes(changes)
    now = resolved.get("train", {})
    for key in ("max_steps",) if now.get("max_steps") or trained.get("max_steps") else ("max_steps", "epochs"):
        if trained.get(key) != now.get(key):
            return f"train.{key}: {trained.get(key)} -> {now.get(key)} (another step budget)"
    return None


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


def set_aside_if_superseded(run_dir: str | Path, recipe: dict, source: str | None = None) -> tuple[str, Path] | None:
    """Set ``run_dir`` aside if its checkpoint is :func:`superseded`; returns (why, where it went) or None.
    Checked and renamed under the folder's run lock: while another process trains there nothing moves
    (its ``ddp train`` keeps the folder, and this run's training then reports the busy folder)."""
    from ddp.run_dir import RunDirBusy, RunLock
    from ddp.train import LAST

    run_dir = Path(run_dir)
    if not (run_dir / LAST).is_file():
        return None
    try:
        with RunLock(run_dir):
            why = superseded(run_dir, recipe, source)  # again under the lock: the folder may have changed
            return (why, set_aside(run_dir)) if why else None
    except RunDirBusy:
        return None
