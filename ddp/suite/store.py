"""The results store of a suite: one JSON per finished run, written atomically; what makes a suite resumable.

``results/suites/<suite>/<task>__<method>__seed<seed>.json`` holds a run's result once it has
finished (success and detection per protocol, the detector's per-chunk traces, training and evaluation wall times). A suite restarted
after an interruption skips every run whose file is there, parses, is complete and was made for the
same recipe (its ``recipe_hash``); anything else (missing, half-written, corrupt, or from a recipe
that has since changed) is run again.
"""

from __future__ import annotations

import json
from pathlib import Path

from ddp import results_json
from ddp.atomic_file import atomic_write
from ddp.errors import DDPError
from ddp.suite.spec import RunSpec

__all__ = ["ResultStore", "evaluation_seconds", "read_complete"]

FORMAT = "ddp-suite-run"


def read_complete(path: str | Path) -> dict | None:
    """The run result stored at ``path``, whatever recipe made it, if it is whole (parses, this store's
    format, marked complete); else None."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(data, dict) and data.get("format") == FORMAT and data.get("complete") is True
    return data if ok else None


def evaluation_seconds(result: dict) -> float:
    """The seconds a stored run spent in its evaluation protocols, all of them (one without a time counts 0)."""
    return sum(float((p or {}).get("seconds") or 0.0) for p in (result.get("protocols") or {}).values())


class ResultStore:
    def __init__(self, directory: str | Path, *, restamp: bool = True):
        """``restamp=False`` reads only (``ddp suite --dry-run``): a result under the old hash is not rewritten."""
        self.directory = Path(directory)
        self.restamp = restamp

    def path(self, run: RunSpec) -> Path:
        return self.directory / f"{run.run_id}.json"

    def _complete(self, run: RunSpec) -> dict | None:
        """The stored result of ``run``, whatever recipe made it, if it is whole; else None."""
        return read_complete(self.path(run))

    def _current(self, run: RunSpec, data: dict | None) -> dict | None:
        """``data`` (a whole stored result of ``run``) if it was made for the run's current recipe, else None.
        One stored under the hash of before version 2 (``RunSpec.legacy_hash``) is restamped with today's hash
        (best effort: a read-only results folder still reads it), so a later change of a setting the hash now
        leaves out (logging, a recipe's eval.episodes the suite overrides) keeps it."""
        if data is None:
            return None
        current = run.recipe_hash
        if data.get("recipe_hash") == current:
            return data
        if data.get("recipe_hash") != run.legacy_hash:
            return None
        data = {**data, "recipe_hash": current}
        if self.restamp:
            try:
                self._write(run, data)
            except OSError:
                pass
        return data

    def load(self, run: RunSpec) -> dict | None:
        """The stored result of ``run`` if it is complete and made for the run's current recipe, else None."""
        return self._current(run, self._complete(run))

    def status(self, run: RunSpec) -> str:
        """``"done"`` (a valid result is stored), ``"stale"`` (one is stored for another recipe: the run goes
        again) or ``"missing"`` (none, or a half-written or corrupt one)."""
        data = self._complete(run)
        if data is None:
            return "missing"
        return "done" if self._current(run, data) is not None else "stale"

    def save(self, run: RunSpec, result: dict) -> Path:
        return self._write(run, {"format": FORMAT, "complete": True, "recipe_hash": run.recipe_hash, **result})

    def _write(self, run: RunSpec, data: dict) -> Path:
        text = results_json.dumps(data)
        try:
            return atomic_write(self.path(run), lambda f: f.write(text), binary=False)
        except OSError as err:  # a full disk, a read-only results folder: one line, not a traceback
            raise DDPError(f"{self.path(run)}: cannot store {run.run_id}'s result ({err.strerror or err}); its "
                           "checkpoint stays, and the suite evaluates it again when started again") from None

    def all(self, runs: list[RunSpec]) -> dict[str, dict]:
        """run_id -> stored result, for the runs that have a valid one."""
        out = {}
        for run in runs:
            data = self.load(run)
            if data is not None:
                out[run.run_id] = data
        return out
