"""Running a suite's runs: one function per run, and the executors that call it.

:func:`execute_run` trains a run's recipe (resuming its own checkpoint if one is there and can continue
this recipe; a folder whose checkpoint cannot is set aside first, see :mod:`ddp.suite.superseded`),
evaluates it and returns a small result (success and detection summary per protocol, wall times); its
stdout / stderr go to ``<run dir>/log.txt``. :func:`run_suite` skips the runs the store already holds,
calls ``execute_run`` for the rest through the chosen executor and stores each result as soon as
it arrives, printing one line per run started and finished:

* ``sequential`` (default): one run after another in this process;
* ``pool``: ``workers`` processes (``concurrent.futures`` with the spawn start method), each pinned
  to ``cores // workers`` torch threads (the cores of the process's CPU affinity). Interrupted (Ctrl-C, or SIGTERM / SIGHUP as a scheduler
  sends before preempting), it starts no queued run, passes SIGTERM on to the runs in progress (a
  training run saves its checkpoint) and waits for them: no worker outlives the suite;
* ``ray``: each run a Ray task asking for its threads as CPUs (and ``gpus_per_run`` GPUs), on a
  local Ray started here (``ray=True``) or a cluster (``ray="ADDRESS"``); Ray schedules them on
  the resources it has. Workers change to this working directory first: on a cluster every node
  needs the repository (and its data) at the same path.

With a time limit (``time_limit``, ``ddp suite --time-limit``) every executor starts a run only if its
expected cost fits in the time left and stops the runs still going at the limit, as SIGTERM would; the suite
then raises :class:`~ddp.suite.budget.SuiteTimeLimit` (see :mod:`ddp.suite.budget`).

A run that raises leaves its traceback in its ``log.txt``; the suite prints one line, goes on with the
other runs and then raises :class:`SuiteRunsFailed` (``ddp suite`` still writes the table of what
finished, and exits 1). A run is a pure function of its recipe and seed, so the executors give the
same results (tested with one thread per run).
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import time
import traceback
from pathlib import Path

from ddp.errors import DDPError
from ddp.file_lock import exclusive_lock
from ddp.percent import percent
from ddp.preemption import Preempted, interruption, signals_deferred, stop_signals
from ddp.suite.budget import (Deadline, SuiteTimeLimit, estimate_seconds, fmt_elapsed, fmt_minutes, trains_on,
                              stored_results, total_expected)
from ddp.suite.provenance import code_version, process_code
from ddp.suite.spec import RunSpec, SuiteSpec
from ddp.suite.store import ResultStore
from ddp.suite.superseded import set_aside_if_superseded

__all__ = ["SuiteRunsFailed", "execute_run", "run_suite", "traces"]


def _round(value, digits: int = 3):
    """``value`` to ``digits`` significant digits; None for a missing or non-finite one."""
    if value is None or not math.isfinite(value):
        return None
    return float(f"{value:.{digits}g}")


def traces(protocol: dict) -> list[dict] | None:
    """Per episode, what a detection figure needs: the detector's statistic per chunk (3 significant
    digits), the controller's mode per chunk as a string of 0 / 1, the first chunk at which the
    disturbance was visible and the outcome. None when the protocol's detector records no statistic
    (no detector, or the oracle schedule)."""
    from ddp.detection import first_visible

    out = [{"success": bool(e.get("success")), "first_visible": first_visible(e),
            "score": [_round(v) for v in e.get("score") or []],
            "mode": "".join("1" if m >= 0.5 else "0" for m in e.get("mode") or [])}
           for e in protocol.get("per_episode") or []]
    return out if any(v is not None for e in out for v in e["score"]) else None


def _summary(protocol: dict) -> dict:
    out = {k: protocol[k] for k in ("success_rate", "successes", "episodes", "seconds", "tau", "alpha", "task_info")
           if k in protocol}
    if "detection" in protocol:
        out["detection"] = {k: v for k, v in protocol["detection"].items() if k != "per_episode"}
    per_episode = traces(protocol)
    if per_episode is not None:
        out["traces"] = per_episode
    return out


def _check_judged(exp, run: RunSpec, protocols=None) -> None:
    """A suite aggregates success rates: an env whose episodes a person judges (a real robot) has none to give.
    Checked in the env each protocol (``protocols``, default the run's) runs in (``eval.env`` may put a
    simulated recipe on the robot)."""
    from ddp.eval_runner import env_overrides, judges_success
    from ddp.protocols.base import get_protocol

    env = exp.parts.get("env")
    if env is None:
        return
    if protocols is None:
        protocols = list(run.protocols) if run.protocols else list(exp.recipe.eval.protocols)
    if not all(judges_success(exp, env_overrides(exp, get_protocol(p), exp.recipe.eval.max_steps))
               for p in protocols):
        raise DDPError(f"{run.run_id}: env '{env.plugin.name}' cannot judge success (a real robot: a person does), "
                       f"so a suite has no success rate to aggregate; evaluate it with `ddp eval` or `ddp run`")


def execute_run(run: RunSpec, threads: int | None = None, cwd: str | None = None,
                deferred: list[int] | None = None) -> dict:
    """Train and evaluate one run; its console output goes to its log file. Returns its result. A stop signal
    that arrives once the evaluation has returned is held back until the result is made and recorded in
    ``deferred`` (the caller stores the result, then stops), so a finished evaluation is never thrown away."""
    import torch

    if cwd is not None:
        os.chdir(cwd)
    process_code()  # the code this process runs: its first look, unless a pool worker's start took it
    if threads:
        torch.set_num_threads(threads)
    run_dir = Path(run.recipe["train"]["output_dir"])
    # one suite process per run, from its set-aside check to its evaluation (two processes whose selections
    # overlap would evaluate into one folder; the lock sits beside the folder, which may be moved aside)
    with exclusive_lock(run_dir, wait=False, busy="another ddp suite process is running this run (pick other "
                                                   "--tasks / --methods / --seeds, or wait for it)"):
        return _execute_run(run, run_dir, deferred)


def _execute_run(run: RunSpec, run_dir: Path, deferred: list[int] | None) -> dict:
    import torch

    from ddp.experiment import build

    t0 = time.perf_counter()
    if run.reevaluate:
        return _reevaluate_run(run, run_dir, t0)
    moved = set_aside_if_superseded(run_dir, run.recipe, run.run_id)  # before this run's log opens there
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "log.txt", "a") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        if moved is not None:
            print(f"== {run.run_id}: the checkpoint here cannot continue this recipe ({moved[0]}); its folder "
                  f"moved to {moved[1]}, training starts over", flush=True)
        print(f"== {run.run_id} started (threads {torch.get_num_threads()})", flush=True)
        try:
            exp = build(run.recipe)
            _check_judged(exp, run)
            trained = exp.train(resume=True, progress=False)
            exp.load_checkpoint(trained.checkpoint)
            report = exp.evaluate(list(run.protocols) if run.protocols else None, episodes=run.episodes,
                                  progress=False)
            with signals_deferred(deferred):  # the evaluation is done: making its result (git calls) finishes
                result = {
                    "run_id": run.run_id, "suite": run.suite, "task": run.task, "method": run.method,
                    "seed": run.seed, "benchmark": run.benchmark,
                    # seconds: all training behind the checkpoint; attempt_seconds: this call's (the rest of
                    # wall_seconds is setup and evaluation, what a time limit's estimate needs)
                    "train": {"steps": trained.steps, "seconds": trained.total_seconds,
                              "attempt_seconds": trained.seconds, "loss": trained.loss},
                    "episodes": report["episodes"],
                    "protocols": {name: _summary(p) for name, p in report["protocols"].items()},
                    "wall_seconds": time.perf_counter() - t0,
                    "code": code_version(),
                }
                print(f"== {run.run_id} finished", flush=True)
        except BaseException as err:  # the traceback stays with the run (the suite prints one line)
            if isinstance(err, KeyboardInterrupt):
                print(f"== {run.run_id} stopped ({err or 'interrupted'}; a training run saved its checkpoint)", flush=True)
            else:
                traceback.print_exc()
                print(f"== {run.run_id} failed", flush=True)
            raise
    return result


def _reevaluate_run(run: RunSpec, run_dir: Path, t0: float) -> dict:
    """``run.reevaluate``'s protocols from the run's checkpoint (see :mod:`ddp.suite.reevaluate`); returns them
    with the recipe keys changed since training (``changed``), for the suite to merge into the stored result."""
    from ddp.checkpoint import load_checkpoint, stored_recipe
    from ddp.experiment import build
    from ddp.recipe import recipe_changes
    from ddp.run_dir import RunLock
    from ddp.train import LAST

    ckpt = run_dir / LAST
    with RunLock(run_dir), open(run_dir / "log.txt", "a") as log, contextlib.redirect_stdout(log), \
            contextlib.redirect_stderr(log):
        print(f"== {run.run_id} re-evaluating {', '.join(run.reevaluate)} from {ckpt}", flush=True)
        try:
            exp = build(run.recipe)
            _check_judged(exp, run, list(run.reevaluate))  # before the checkpoint loads, as a run before training
            state = load_checkpoint(ckpt)
            trained_with = stored_recipe(ckpt, state)
            exp.load_checkpoint(ckpt, state=state)
            report = exp.evaluate(list(run.reevaluate), episodes=run.episodes, progress=False,
                                  output_dir=str(run_dir / "eval_reevaluated"))
        except BaseException:
            traceback.print_exc()
            print(f"== {run.run_id} failed", flush=True)
            raise
        print(f"== {run.run_id} re-evaluated", flush=True)
    return {"run_id": run.run_id, "protocols": {name: _summary(p) for name, p in report["protocols"].items()},
            "changed": sorted(recipe_changes(trained_with, exp.resolved)),
            "wall_seconds": time.perf_counter() - t0, "code": code_version()}


_STOP = None  # in a pool worker: the suite's stop event (set when the suite is interrupted)
STOP_GRACE_SECONDS = 300  # an interrupted pool waits this long for its runs to save their checkpoints


def _init_worker(stop) -> None:
    """A pool worker: Ctrl-C is the suite's to handle (it passes SIGTERM on to a running run). SIGTERM stops the
    run in progress (see :func:`_pool_run`) and leaves an idle worker alone: a worker that died of it would
    break the pool, whose clean-up then terminates the other workers too, maybe before their runs saved."""
    global _STOP
    _STOP = stop
    process_code()  # the code this worker imports now is what its runs will run
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for signum in (signal.SIGTERM, signal.SIGHUP):  # a handler, not SIG_IGN: stop_signals replaces it in a run
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, lambda signum, frame: None)


class NotStarted:
    """A worker's answer for a run it did not start because it would not fit the time left."""

    def __init__(self, expected: float | None):
        self.expected = expected


def _expected_now(run: RunSpec, expected: float | None, results_dir: str | None) -> float | None:
    """The run's expected seconds from the results stored by now (runs finished since the suite started count),
    else ``expected``, the estimate made when it was queued."""
    if results_dir is None:
        return expected
    fresh = estimate_seconds(run, stored_results(results_dir))[0]
    return expected if fresh is None else fresh


def _start_or_not(run: RunSpec, threads: int | None, end: float | None, expected: float | None, cwd=None,
                  results_dir: str | None = None, limit: float | None = None):
    """``execute_run``, unless a deadline (``end``, wall clock) leaves less time than the run is expected to take
    (re-estimated from ``results_dir`` if given; see :meth:`Deadline.allows` for ``limit``)."""
    if end is not None:
        expected = _expected_now(run, expected, results_dir)
        if not Deadline(end).allows(expected, limit, trains_on(run)):
            return NotStarted(expected)
    return execute_run(run, threads, cwd)


def _pool_run(run: RunSpec, threads: int | None, end: float | None = None, expected: float | None = None,
              results_dir: str | None = None, limit: float | None = None):
    """A pool worker's run; None without running once the suite is stopping (a queued run does not start).
    SIGTERM raises Preempted anywhere in it (setup, training: a checkpoint, evaluation)."""
    with stop_signals():  # the suite sets its stop event before it signals: checked inside, no SIGTERM is missed
        if _STOP is not None and _STOP.is_set():
            return None
        return _start_or_not(run, threads, end, expected, results_dir=results_dir, limit=limit)


class SuiteRunsFailed(DDPError):
    """Some runs of a suite raised; the others finished and are stored (``done``)."""

    def __init__(self, failed: dict[str, str], done: dict[str, dict], also: str = ""):
        self.failed, self.done = failed, done
        names = ", ".join(failed)
        super().__init__(f"{len(failed)} run(s) failed: {names} (the traceback is in each run's log.txt; "
                         "the suite skips the finished runs when started again)" + (f"; also {also}" if also else ""))


def run_suite(suite: SuiteSpec, *, workers: int = 1, threads: int | None = None, progress: bool = True,
              echo=print, ray: bool | str = False, gpus_per_run: float = 0.0,
              reevaluate: list[str] | None = None, time_limit: float | None = None) -> dict[str, dict]:
    """Run what the store does not hold yet; return run_id -> result for every finished run. With
    ``reevaluate``, stale runs only re-evaluate those protocols from their checkpoints (see
    :mod:`ddp.suite.reevaluate`); missing runs still run in full. With ``time_limit`` (seconds), runs start
    only while they fit and stop at the limit (:mod:`ddp.suite.budget`); if that left any undone, raises
    :class:`~ddp.suite.budget.SuiteTimeLimit` after storing what finished."""
    from tqdm import tqdm

    from ddp.suite.reevaluate import merge_reevaluation, plan_reevaluation

    store = ResultStore(suite.results_dir)
    done = store.all(suite.runs)
    todo = [r for r in suite.runs if r.run_id not in done]
    if reevaluate:
        again = {r.run_id: r for r in plan_reevaluation(store, todo, reevaluate)}
        todo = [again.get(r.run_id, r) for r in todo]
    how = "Ray tasks" if ray else ("sequential" if workers == 1 else f"{workers} worker processes")
    redo = sum(1 for r in todo if r.reevaluate)
    echo(f"suite {suite.name}: {len(suite.runs)} runs, {len(done)} already in {suite.results_dir}, "
         f"{len(todo)} to run ({how}" + (f"; {redo} re-evaluating {', '.join(reevaluate)}" if redo else "") + ")")
    if not todo:
        return done
    bar = tqdm(total=len(suite.runs), initial=len(done), desc=f"suite {suite.name}", unit="run", disable=not progress)

    try:  # the bar is closed whatever happens from here
        say = bar.write if progress else echo  # a bar's own write keeps the line above the bar
        limit = _Limit(time_limit, suite.results_dir, say)
        if limit.deadline is not None:
            limit.estimate(todo)
            say(f"time limit {fmt_minutes(time_limit)}: the {len(todo)} runs are expected to take "
                f"{total_expected(list(limit.expected.values()))}; a run starts only if it fits in the time left "
                "(or could never fit in the whole limit)")
        failed: dict[str, str] = {}

        def finished(run: RunSpec, result: dict) -> None:
            rates = ", ".join(f"{p} {percent(v['success_rate'])} %" for p, v in result["protocols"].items())
            took = fmt_elapsed(result["wall_seconds"])
            if run.reevaluate:
                result = merge_reevaluation(store, run, result)
            store.save(run, result)
            done[run.run_id] = result
            say(f"{'re-evaluated' if run.reevaluate else 'finished'} {run.run_id} in {took}: {rates}")
            bar.update(1)

        def failure(run: RunSpec, err: Exception) -> None:
            first = (str(err).strip().splitlines() or [""])[0]
            failed[run.run_id] = f"{type(err).__name__}: {first}"
            say(f"failed {run.run_id}: {failed[run.run_id]} (log: {run.recipe['train']['output_dir']}/log.txt)")

        if ray:
            _run_on_ray(todo, finished, failure, ray=ray, threads=threads or 1, gpus=gpus_per_run, echo=echo,
                        limit=limit)
        elif workers == 1:
            _run_in_turn(todo, finished, failure, threads=threads, echo=echo, limit=limit)
        else:
            _run_on_pool(todo, finished, failure, workers=workers, threads=threads, echo=echo, limit=limit)
    finally:
        bar.close()
    undone = (SuiteTimeLimit(time_limit, limit.stopped, limit.skipped, done, killed=limit.killed)
              if limit.stopped or limit.skipped or limit.killed else None)
    if failed:  # a failed run decides the exit status; the time limit's account goes with it
        raise SuiteRunsFailed(failed, done, also=str(undone) if undone else "")
    if undone is not None:
        raise undone
    return done


class _Limit:
    """What the executors need of a time limit: the deadline (None: no limit) and each run's expected seconds;
    it keeps the runs stopped at the limit (each saved its checkpoint), those killed after the grace period
    (their last periodic checkpoint stands) and those not started (run id -> expected seconds), and ``say``s
    why a run did not start."""

    def __init__(self, seconds: float | None, results_dir, say):
        self.seconds = seconds
        self.deadline = Deadline.after(seconds) if seconds else None
        self.results_dir, self.say = str(results_dir), say
        self.expected: dict[str, float | None] = {}
        self.stopped: list[str] = []
        self.killed: list[str] = []
        self.skipped: dict[str, float | None] = {}

    def estimate(self, runs: list[RunSpec]) -> None:
        """Each run's expected seconds from the results stored now (made again when the run is about to start)."""
        stored = stored_results(self.results_dir)
        self.expected.update({r.run_id: estimate_seconds(r, stored)[0] for r in runs})

    def not_started(self, run: RunSpec, expected: float | None = None) -> None:
        """``run`` did not start at the time limit; ``expected``: its estimate, if newer than this one's."""
        expect = self.expected.get(run.run_id) if expected is None else expected
        self.skipped[run.run_id] = expect
        left = self.deadline.left() if self.deadline is not None else 0.0
        self.say(f"not started {run.run_id}: expected {fmt_minutes(expect)}, {fmt_minutes(max(left, 0.0))} left")

    @property
    def end(self) -> float | None:
        return None if self.deadline is None else self.deadline.end

    def allows(self, run: RunSpec) -> bool:
        """Whether ``run`` may start now; its estimate is made again from the results stored by now."""
        if self.deadline is None:
            return True
        self.expected[run.run_id] = _expected_now(run, self.expected.get(run.run_id), self.results_dir)
        return self.deadline.allows(self.expected[run.run_id], self.seconds, trains_on(run))


def _run_in_turn(todo: list[RunSpec], finished, failure, *, threads: int | None, echo, limit: _Limit) -> None:
    """One run after another in this process. At the time limit this process sends itself SIGTERM if a run is in
    progress: it stops as it would for a scheduler (a training run saves its checkpoint); results are stored with
    signals held back, so a stored result is whole."""
    import threading

    handled: set[str] = set()
    state = {"run": None}  # the run in progress
    guard, fired = threading.Lock(), threading.Event()

    def fire() -> None:  # the timer thread, at the deadline
        with guard:
            fired.set()
            if state["run"] is not None:
                os.kill(os.getpid(), signal.SIGTERM)

    timer = None
    if limit.deadline is not None:
        if threading.current_thread() is not threading.main_thread() or \
                signal.getsignal(signal.SIGTERM) is signal.SIG_IGN:
            echo("the time limit decides which runs start; it cannot stop one in progress here (not the main "
                 "thread, or SIGTERM ignored)")
        else:
            timer = threading.Timer(max(limit.deadline.left(), 0.0), fire)
            timer.daemon = True
    with stop_signals():
        try:
            if timer is not None:
                timer.start()
            try:
                for run in todo:
                    with guard:  # the timer signals only a run in progress: it may not fire between check and start
                        if fired.is_set() or not limit.allows(run):
                            limit.not_started(run)
                            handled.add(run.run_id)
                            continue
                        state["run"] = run
                    echo(f"started {run.run_id} (log: {run.recipe['train']['output_dir']}/log.txt)")
                    held: list[int] = []  # a stop that came while the finished run's result was being made
                    try:
                        result = execute_run(run, threads, deferred=held)
                    except Exception as err:  # the next run still runs; KeyboardInterrupt / Preempted stop it
                        with signals_deferred(held) as received, guard:  # a stop held while it failed: honoured
                            state["run"] = None
                            failure(run, err)
                            handled.add(run.run_id)
                        if received:
                            raise interruption(received[0]) from None
                        continue
                    with signals_deferred(held) as received, guard:  # a result being stored is stored whole
                        state["run"] = None
                        finished(run, result)
                        handled.add(run.run_id)
                    if received:
                        raise interruption(received[0])
            finally:
                if timer is not None:
                    timer.cancel()
                    timer.join()
        except Preempted:
            if not fired.is_set():
                raise
            if state["run"] is not None:
                limit.stopped.append(state["run"].run_id)
                handled.add(state["run"].run_id)
            for run in todo:
                if run.run_id not in handled:
                    limit.not_started(run)


def _run_on_pool(todo: list[RunSpec], finished, failure, *, workers: int, threads: int | None, echo,
                 limit: _Limit, fresh_pools: int = 1) -> None:
    """``workers`` spawned processes. Interrupted (Ctrl-C, SIGTERM, SIGHUP) or at the time limit, the suite
    starts no queued run, passes SIGTERM on to the runs in progress (a training run saves its checkpoint), waits
    for them, then stops: no worker outlives it. A worker that dies (killed, out of memory) breaks the pool and
    ends the runs in progress with it: those fail (their last checkpoint stands), and the queued runs that had
    not started go to a new pool (``fresh_pools`` times)."""
    broken: list[RunSpec] = []
    _pool_once(todo, finished, failure, workers=workers, threads=threads, echo=echo, limit=limit, broken=broken)
    if broken and fresh_pools > 0:
        echo(f"a worker process died: {len(broken)} run(s) that had not started go to a new pool")
        _run_on_pool(broken, finished, failure, workers=workers, threads=threads, echo=echo, limit=limit,
                     fresh_pools=fresh_pools - 1)
    elif broken:
        for run in broken:
            failure(run, RuntimeError("not started: the worker pool broke again (a worker process died)"))


def _pool_once(todo: list[RunSpec], finished, failure, *, workers: int, threads: int | None, echo,
               limit: _Limit, broken: list[RunSpec]) -> None:
    """One process pool over ``todo`` (see :func:`_run_on_pool`); the runs the pool's breaking kept from
    starting are appended to ``broken``."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures import TimeoutError as FuturesTimeout

    from ddp.run_jobs import threads_per_job  # (ddp.run_jobs imports the suite's budget module)

    workers = max(1, min(workers, len(todo)))  # one run left on two workers: it gets both cores
    per = threads or threads_per_job(workers)
    # several processes share the cores: OpenMP threads that spin between ops would steal them
    # (read by each spawned worker when it loads torch; a value the user set is kept; restored after)
    policy = os.environ.get("OMP_WAIT_POLICY")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    ctx = multiprocessing.get_context("spawn")
    stop = ctx.Event()
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(stop,))
    futures: dict = {}
    seen: set = set()
    logged: dict[str, int] = {}
    try:
        with stop_signals():  # SIGTERM / SIGHUP raise Preempted here, like Ctrl-C's KeyboardInterrupt
            for run in todo:
                echo(f"queued {run.run_id} ({per} threads; log: {run.recipe['train']['output_dir']}/log.txt)")
                logged[run.run_id] = _log_size(run)  # what its log held before this attempt
                futures[pool.submit(_pool_run, run, per, limit.end, limit.expected.get(run.run_id),
                                    limit.results_dir, limit.seconds)] = run
            left = None if limit.deadline is None else max(limit.deadline.left(), 0.0)
            arrivals = as_completed(futures, timeout=left)
            while True:
                try:
                    fut = next(arrivals)
                except StopIteration:
                    break
                except FuturesTimeout:  # the time limit (only as_completed's own timeout lands here)
                    break
                seen.add(fut)
                _collect(fut, futures[fut], finished, failure, limit, broken=broken, logged=logged)
            if len(seen) < len(futures):  # the time limit: stop as for SIGTERM, then say what became of each run
                _stop_pool(pool, stop, futures)
                for fut, run in futures.items():
                    if fut in seen:
                        continue
                    if fut.cancelled():  # still queued
                        limit.not_started(run)
                    elif not fut.done():  # its worker did not end within the grace period and was killed
                        limit.killed.append(run.run_id)
                    else:
                        _collect(fut, run, finished, failure, limit, stopping=True)
    except BaseException:  # Ctrl-C, SIGTERM, or an error storing a result: no queued run starts after it
        _stop_pool(pool, stop, futures)
        with signals_deferred():  # runs that finished before the stop (or during its grace period) are stored
            _store_finished(futures, seen, finished)
        raise
    else:
        pool.shutdown(wait=True)
    finally:
        if policy is None:
            os.environ.pop("OMP_WAIT_POLICY", None)


def _store_finished(futures: dict, seen: set, finished) -> None:
    """Store every future not collected yet that holds a finished run's result (the suite is stopping: the
    others are failed, stopped or never ran, and the next invocation runs them; one that cannot be stored is
    left to it too)."""
    for fut, run in futures.items():
        if fut in seen or not fut.done() or fut.cancelled() or fut.exception() is not None:
            continue
        result = fut.result()
        if isinstance(result, dict):  # not a NotStarted
            with contextlib.suppress(Exception):
                finished(run, result)
                seen.add(fut)


def _collect(fut, run: RunSpec, finished, failure, limit: _Limit, stopping: bool = False,
             broken: list | None = None, logged: dict | None = None) -> None:
    """One pool future's outcome: stored, failed or not started; with ``stopping`` (after the time limit's
    SIGTERM) an interrupted run counts as stopped, one whose worker died (killed after the grace period, or
    the pool broken under it: whether it saved is unknown) as killed. Otherwise a broken pool (a worker
    died) fails the runs that had started (their logs say so since ``logged``) and puts the others in
    ``broken``."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        result = fut.result()
    except BaseException as err:
        if stopping and isinstance(err, KeyboardInterrupt):
            limit.stopped.append(run.run_id)
            return
        if stopping and isinstance(err, BrokenProcessPool):
            limit.killed.append(run.run_id)
            return
        if isinstance(err, BrokenProcessPool) and broken is not None:
            if not _started_since(run, (logged or {}).get(run.run_id, 0)):
                broken.append(run)
                return
            err = RuntimeError("its worker process died (killed, or out of memory?), or another run's did and the "
                               "pool ended this one; its last checkpoint stands and the next invocation resumes it")
        if not isinstance(err, Exception):  # Ctrl-C / a SIGTERM from outside: the suite stops
            raise
        failure(run, err)
        return
    if isinstance(result, NotStarted):
        limit.not_started(run, result.expected)
    elif result is None:  # the suite was stopping when a worker took it
        if stopping:
            limit.not_started(run)
    else:
        finished(run, result)


def _stop_pool(pool, stop, futures: dict) -> None:
    """No queued run starts; the runs in progress get SIGTERM (a training run saves its checkpoint) and
    ``STOP_GRACE_SECONDS`` to end; then no worker is left alive."""
    import multiprocessing
    from concurrent.futures import wait

    stop.set()  # a queued run that a worker takes now returns at once
    workers_ = multiprocessing.active_children()  # the pool's workers
    try:
        for child in workers_:  # a run in training saves its checkpoint and stops
            with contextlib.suppress(OSError):
                os.kill(child.pid, signal.SIGTERM)
        for fut in futures:
            fut.cancel()
        wait([f for f in futures if not f.cancelled()], timeout=STOP_GRACE_SECONDS)
    finally:  # a second Ctrl-C, or a grace period gone: no worker outlives the suite either way
        pool.shutdown(wait=False, cancel_futures=True)
        for child in workers_:
            child.join(timeout=5)
            if child.is_alive():
                child.kill()
                child.join(timeout=5)


def _run_on_ray(todo: list[RunSpec], finished, failure, *, ray, threads: int, gpus: float, echo, limit: _Limit) -> None:
    """Submit every run as a Ray task; store results in the order they finish. At the time limit, or when the
    suite is interrupted (Ctrl-C, SIGTERM, SIGHUP), every task left is cancelled: a running one gets
    KeyboardInterrupt (a training run saves its checkpoint) and the grace period to end, then the
    interruption goes on."""
    try:
        import ray as ray_mod
    except ImportError:
        from ddp.errors import DDPError

        raise DDPError('--ray needs Ray: pip install "dream-diffusion-policy[ray]"') from None
    started_here = not ray_mod.is_initialized()
    if started_here:
        address = ray if isinstance(ray, str) else None
        from ddp.run_jobs import usable_cores

        # a local Ray counts the machine's cores, not the ones this process may use (Slurm, taskset): give it those
        cpus = {"num_cpus": usable_cores()} if address is None else {}
        ray_mod.init(address=address, include_dashboard=False, log_to_driver=False, logging_level="ERROR", **cpus)
    try:
        task = ray_mod.remote(num_cpus=threads, num_gpus=gpus, max_retries=0)(_start_or_not)
        pending, logged = {}, {}
        for run in todo:
            echo(f"queued {run.run_id} ({threads} CPUs{f', {gpus:g} GPUs' if gpus else ''}; "
                 f"log: {run.recipe['train']['output_dir']}/log.txt)")
            logged[run.run_id] = _log_size(run)  # what its log held before this attempt
            pending[task.remote(run, threads, limit.end, limit.expected.get(run.run_id), os.getcwd(), None,
                                limit.seconds)] = run
        with stop_signals():  # SIGTERM / SIGHUP raise Preempted here, like Ctrl-C's KeyboardInterrupt
            try:
                while pending:
                    left = None if limit.deadline is None else max(limit.deadline.left(), 0.0)
                    ready, _ = ray_mod.wait(list(pending), num_returns=1, timeout=left)
                    if not ready:  # the time limit
                        _cancel_ray(ray_mod, pending, finished, failure, limit, logged)
                        return
                    for ref in ready:
                        _collect_ray(ray_mod, ref, pending.pop(ref), finished, failure, limit)
            except KeyboardInterrupt:  # Preempted too: the runs in progress save before Ray shuts down
                with signals_deferred():
                    _cancel_ray(ray_mod, pending, finished, failure, limit, logged)
                raise
    finally:
        if started_here:
            ray_mod.shutdown()


def _collect_ray(ray_mod, ref, run: RunSpec, finished, failure, limit: _Limit) -> None:
    try:
        result = ray_mod.get(ref)
    except Exception as err:  # a Ray task error wraps the run's own
        failure(run, getattr(err, "cause", None) or err)
        return
    if isinstance(result, NotStarted):
        limit.not_started(run, result.expected)
    else:
        finished(run, result)


def _log_size(run: RunSpec) -> int:
    log = Path(run.recipe["train"]["output_dir"]) / "log.txt"
    return log.stat().st_size if log.is_file() else 0


def _started_since(run: RunSpec, offset: int) -> bool:
    """Whether ``run``'s log gained the line a run or re-evaluation writes as it starts since it held ``offset``
    bytes."""
    log = Path(run.recipe["train"]["output_dir"]) / "log.txt"
    if not log.is_file():
        return False
    with open(log, "rb") as f:
        f.seek(offset if log.stat().st_size >= offset else 0)  # a shorter log: a new one (its folder set aside)
        text = f.read()
    return any(f"== {run.run_id} {what}".encode() in text for what in ("started", "re-evaluating"))


def _cancel_ray(ray_mod, pending: dict, finished, failure, limit: _Limit, logged: dict[str, int]) -> None:
    """Cancel every pending task, give the running ones ``STOP_GRACE_SECONDS`` to save, then say what became of
    each: finished meanwhile, stopped (its log shows it started in this attempt) or not started."""
    for ref in pending:
        ray_mod.cancel(ref)
    ray_mod.wait(list(pending), num_returns=len(pending), timeout=STOP_GRACE_SECONDS)
    halted = (ray_mod.exceptions.TaskCancelledError, ray_mod.exceptions.GetTimeoutError)
    for ref, run in pending.items():
        try:
            result = ray_mod.get(ref, timeout=0)
        except Exception as err:
            cause = getattr(err, "cause", None)
            if not isinstance(err, halted) and not isinstance(cause, KeyboardInterrupt):
                failure(run, cause or err)  # it had failed on its own
                continue
            if _started_since(run, logged.get(run.run_id, 0)):  # cancelled and interrupted, or not back in time
                (limit.killed if isinstance(err, ray_mod.exceptions.GetTimeoutError) else limit.stopped).append(
                    run.run_id)
            else:
                limit.not_started(run)
            continue
        if isinstance(result, NotStarted):
            limit.not_started(run, result.expected)
        else:
            finished(run, result)
