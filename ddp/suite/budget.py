"""A suite under a time limit (``ddp suite --time-limit 2h30m``): start only the runs that fit, stop the rest in time.

A cluster job or a lent machine has a wall-clock limit; a run killed at that limit loses whatever it had not
checkpointed, and one started ten minutes before it wastes those ten minutes. With a time limit the suite:

* estimates each run's cost from what this suite's stored results cost (:func:`estimate_seconds`), from
  the stored runs of the same task and method, else of the same method: their median training time per
  step times the steps the run still has to train (a run resuming a checkpoint pays only those), plus their
  median evaluation and setup time; a re-evaluation pays only its protocols;
* starts a run only if that estimate fits in the time left, checked when a worker takes the run and
  estimated again then from the results stored by that time (on Ray, the estimate made at submission), so
  that a shorter run later in the queue can still use the end of the budget. A run with nothing to estimate
  from starts while any time is left, and so does one expected to take longer than the whole limit (it needs
  several budgets whatever happens: its checkpoint carries it over, and the next budget sees it resume);
* at the limit stops the runs still going as SIGTERM would (a training run saves its checkpoint), stores
  what finished, writes the table and exits with status 75 (``EX_TEMPFAIL``: run the same command again to
  go on); :class:`SuiteTimeLimit` lists what was stopped and what did not start.
"""

from __future__ import annotations

import math
import re
import statistics
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ddp.errors import DDPError
from ddp.suite.spec import RunSpec
from ddp.suite.store import evaluation_seconds, read_complete

__all__ = ["Deadline", "SuiteTimeLimit", "estimate_seconds", "trains_on", "parse_duration", "stored_results",
           "total_expected", "EXIT_TIME_LIMIT"]

EXIT_TIME_LIMIT = 75  # sysexits.h EX_TEMPFAIL: "temporary failure, user is invited to retry"

_DURATION = re.compile(r"(?:(\d+(?:\.\d+)?)h)?(?:(\d+(?:\.\d+)?)m)?(?:(\d+(?:\.\d+)?)s)?")


def parse_duration(text: str) -> float:
    """Seconds in ``text``: ``5400``, ``90m``, ``1h30m``, ``1.5h``, ``2h5m30s``; anything else raises one line."""
    value = str(text).strip().lower()
    try:
        seconds = float(value)
    except ValueError:
        found = _DURATION.fullmatch(value) if value else None
        if found is None or not any(found.groups()):
            raise DDPError(f"--time-limit: cannot read {text!r} as a duration (e.g. 5400, 90m, 1h30m, 2h5m30s)") from None
        h, m, s = (float(g) if g else 0.0 for g in found.groups())
        seconds = 3600 * h + 60 * m + s
    if not 0 < seconds < threading.TIMEOUT_MAX or not math.isfinite(seconds):
        raise DDPError(f"--time-limit must be a positive, finite duration, got {text!r}")
    return seconds


def _full_cost(result: dict) -> float | None:
    """What a stored run cost from scratch: training (all of it) + its protocols, or its wall time if longer."""
    train = (result.get("train") or {}).get("seconds")
    evals = evaluation_seconds(result)
    wall = result.get("wall_seconds")
    parts = [float(train) + evals] if train is not None else []
    parts += [float(wall)] if wall is not None else []
    return max(parts) if parts else None


def stored_results(results_dir: str | Path) -> list[dict]:
    """Every complete run result in a suite's results folder, whatever recipe made it."""
    return [r for r in (read_complete(p) for p in sorted(Path(results_dir).glob("*.json"))) if r is not None]


def _checkpoint_step(run: RunSpec) -> int | None:
    """The step of the checkpoint this run would resume, or None (none, unreadable, or one set aside)."""
    position = _checkpoint_position(run)
    return None if position is None else position[0]


def _checkpoint_position(run: RunSpec) -> tuple[int, int] | None:
    """``(step, epoch)`` of the checkpoint this run would resume, or None (none, unreadable, or set aside)."""
    out = Path(run.recipe["train"]["output_dir"])
    if not (out / "last.pt").is_file():  # the common case, before importing what reading one needs
        return None
    from ddp.checkpoint import load_checkpoint
    from ddp.suite.superseded import superseded

    try:
        state = load_checkpoint(out / "last.pt", mmap=True)
    except (DDPError, OSError):
        return None
    if superseded(out, run.recipe, run.run_id, state=state) is not None:
        return None
    step, epoch = state.get("step"), state.get("epoch")
    return (int(step), int(epoch) if isinstance(epoch, int) else 0) if isinstance(step, int) else None


def _eval_seconds(result: dict, protocol: str) -> float | None:
    value = ((result.get("protocols") or {}).get(protocol) or {}).get("seconds")
    return None if value is None else float(value)


def _reevaluation(run: RunSpec, stored: list[dict]) -> tuple[float | None, str]:
    """Re-evaluating ``run.reevaluate``: each protocol's stored time on this run, else its median over the
    method's other stored runs."""
    own = next((r for r in stored if r.get("run_id") == run.run_id), {})
    total, borrowed = 0.0, []
    for protocol in run.reevaluate:
        secs = _eval_seconds(own, protocol)
        if secs is None:
            others = [v for v in (_eval_seconds(r, protocol) for r in stored if r.get("method") == run.method)
                      if v is not None]
            if not others:
                return None, f"no stored {run.method} run evaluated {protocol}"
            secs = statistics.median(others)
            borrowed.append(protocol)
        total += secs
    why = "its stored evaluation of those protocols"
    return total, why + (f" ({', '.join(borrowed)}: the median of the stored {run.method} runs)" if borrowed else "")


def estimate_seconds(run: RunSpec, stored: list[dict]) -> tuple[float | None, str]:
    """The expected wall time of ``run`` from the ``stored`` results of its suite, and where it comes from.

    From the stored runs of the same task and method (else of the same method): the median training time per
    step times the steps this run still has to train (its ``train.max_steps``, less its checkpoint's step),
    plus the median of the rest (evaluation, and setup such as demos or calibration: wall time less training
    and evaluation). Without a step budget in the recipe or step counts in the results, the median of the
    whole runs' cost, unscaled."""
    if run.reevaluate:
        return _reevaluation(run, stored)
    same_task = [r for r in stored if r.get("method") == run.method and r.get("task") == run.task]
    pool, what = (same_task, f"{run.task} {run.method}") if same_task else (
        [r for r in stored if r.get("method") == run.method], f"{run.method}")
    costs = [c for c in (_full_cost(r) for r in pool) if c is not None]
    if not costs:
        return None, f"no stored {run.method} run"
    source = f"{len(costs)} stored {what} run{'s' if len(costs) > 1 else ''}"
    per_step, rest = [], []
    for r in pool:
        train = r.get("train") or {}
        if not (train.get("seconds") and train.get("steps")):
            continue
        per_step.append(float(train["seconds"]) / int(train["steps"]))
        evals = evaluation_seconds(r)
        # the last attempt's setup: its wall time less its own training (all of it in older results) and evaluation
        attempt = float(train.get("attempt_seconds", train["seconds"]))
        setup = float(r["wall_seconds"]) - attempt - evals if r.get("wall_seconds") is not None else 0.0
        rest.append(evals + max(setup, 0.0))
    budget = run.recipe.get("train", {}).get("max_steps")
    if not per_step or not isinstance(budget, int) or budget <= 0:
        return statistics.median(costs), f"median of {source}"
    step = min(_checkpoint_step(run) or 0, budget)
    to_go = budget - step
    expected = statistics.median(per_step) * to_go + statistics.median(rest)
    source += f": {statistics.median(per_step):.3g} s/step x {to_go} steps"
    source += f" (its checkpoint is at {step})" if step else ""
    return expected, source + f" + {fmt_minutes(statistics.median(rest))} evaluation and setup"


def trains_on(run: RunSpec) -> bool:
    """Whether starting ``run`` would train (its checkpoint, if any, is short of its step budget and of its
    epochs): only such a run makes progress that outlives a stop (a re-evaluation, or a run whose training is
    done, starts its evaluation over each time). Budgets the recipe does not state count as not reached."""
    if run.reevaluate:
        return False
    position = _checkpoint_position(run)
    if position is None:
        return True
    train = run.recipe.get("train", {})
    for limit, reached in ((train.get("max_steps"), position[0]), (train.get("epochs"), position[1])):
        if isinstance(limit, int) and not isinstance(limit, bool) and limit > 0 and reached >= limit:
            return False
    return True


@dataclass
class Deadline:
    """A wall-clock end (``time.time()``: the same in every process of this machine)."""

    end: float

    @classmethod
    def after(cls, seconds: float) -> Deadline:
        return cls(time.time() + seconds)

    def left(self) -> float:
        return self.end - time.time()

    def allows(self, expected: float | None, limit: float | None = None, trains: bool = True) -> bool:
        """Whether a run expected to take ``expected`` seconds (None: unknown) may start now: while time is left,
        if it fits in that time, or if it could not fit in a whole ``limit`` anyway (within 5 % of it: it
        needs several budgets whatever happens; its checkpoint carries it over, and the next budget sees
        it resuming) and it still ``trains`` (a run with only its evaluation left keeps nothing of a
        stopped attempt: it would start over in every budget)."""
        left = self.left()
        # "longer than the whole limit" with slack: time goes before the first check (reading results, starting
        # workers), and a run just under the limit would otherwise never find that much left in any attempt
        never_fits = trains and limit is not None and expected is not None and expected > 0.95 * limit
        return left > 0 and (expected is None or expected <= left or never_fits)


def total_expected(expected: list[float | None]) -> str:
    """``32 min one after another (4 run(s) without an estimate: no stored run of their method)``: the sum of
    the runs' expected seconds (None: no estimate)."""
    known = [c for c in expected if c is not None]
    unknown = len(expected) - len(known)
    total = fmt_minutes(sum(known)) if known else "unknown"
    return f"{total} one after another" + (
        f" ({unknown} run(s) without an estimate: no stored run of their method)" if unknown else "")


def fmt_elapsed(seconds: float) -> str:
    """``45 s`` or ``19 min 05 s``: a wall time as it happened."""
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s:02d} s" if m else f"{s} s"


def fmt_minutes(seconds: float | None) -> str:
    """``unknown``, ``45 s`` (under two minutes) or ``19 min``."""
    if seconds is None:
        return "unknown"
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


class SuiteTimeLimit(DDPError):
    """The time limit came: ``stopped`` runs were stopped (a training run saved its checkpoint), ``killed``
    ones did not stop within the grace period (their last periodic checkpoint stands), ``skipped`` ones did
    not start (run id -> expected seconds, None: unknown); ``done`` holds every stored result."""

    def __init__(self, limit: float, stopped: list[str], skipped: dict[str, float | None], done: dict[str, dict],
                 killed: list[str] | None = None):
        self.limit, self.stopped, self.skipped, self.done = limit, stopped, skipped, done
        self.killed = list(killed or [])
        parts = []
        if stopped:
            parts.append(f"stopped {len(stopped)} run(s) in progress ({', '.join(stopped)}; a training run saved "
                         "its checkpoint)")
        if self.killed:
            parts.append(f"killed {len(self.killed)} run(s) that did not stop in time ({', '.join(self.killed)}; "
                         "each resumes from its last periodic checkpoint)")
        if skipped:
            parts.append(f"left {len(skipped)} not started (expected " + ", ".join(
                f"{k}: {fmt_minutes(v)}" for k, v in skipped.items()) + ")")
        super().__init__(f"time limit of {fmt_minutes(limit)} reached: " + "; ".join(parts or ["nothing left undone"])
                         + "; run the same command again to go on")
