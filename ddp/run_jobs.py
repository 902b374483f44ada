"""``ddp run --jobs N``: train and evaluate several recipes at once, each in its own process and share of cores.

A method and its baselines (DDP and its DP3 ablation, say) are independent runs. Where one run cannot use
all of a machine's cores well (small models on a many-core workstation; not measured yet), running the
recipes side by side should finish sooner than one after another. Not on a 2-core CPU: there the
quickstart's DDP trained at about 190 ms a step on one core beside its DP3 baseline against 148 ms on two
cores alone, and side by side took longer in all (README, "ddp run --jobs").

Each job is ``ddp run RECIPE`` in a child process (the same ``--set``, ``--protocols``, ``--episodes``,
``--no-resume`` and ``--quiet``) with ``train.num_threads`` (unless ``--set``) and
``OMP_NUM_THREADS`` (unless set) at its share of the cores, and ``OMP_WAIT_POLICY=PASSIVE`` (unless set:
OpenMP threads spinning in processes that share cores slow each other down many-fold). Its console output,
progress bars included, is appended to ``<train.output_dir>/run.log`` (``tail -f`` follows it). Each
finished job's summary lines are echoed, and at the end the table of every job that finished, read from the
``results.json`` its evaluation wrote (two recipes that would share a training or evaluation folder are
refused before anything starts).

Stopped with Ctrl-C, SIGTERM or SIGHUP, no queued job starts; the signal is passed on once to the jobs in
progress (a training run writes its checkpoint, as ``ddp run`` does alone: the same command resumes it)
and the command waits for them. A job that fails leaves its error in its log; the others go on. An error in
this process stops the jobs too: none outlives it (short of SIGKILL).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from ddp.errors import DDPError
from ddp.preemption import Preempted, resume_hint
from ddp.recipe import parse_override
from ddp.suite.budget import fmt_elapsed

__all__ = ["Job", "JobsFailed", "plan_jobs", "run_jobs"]

STOP_GRACE_SECONDS = 300  # how long a stopped job may take to save its checkpoint before it is killed
_STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: how a stopped job exits: `ddp run`'s 128 + signal (130 for Ctrl-C), or killed by the signal itself (a SIGKILL,
#: ours after the grace time or the OOM killer's, cut its save short: failed, not stopped)
_STOPPED_CODES = frozenset({*(128 + s for s in _STOPS), *(-s for s in _STOPS)})


@dataclass
class Job:
    """One recipe to run in its own process: what to run and where its log and results land."""

    name: str
    argv: list[str]
    log: Path
    results: Path
    proc: subprocess.Popen | None = field(default=None, repr=False)
    started: float = 0.0
    log_offset: int = 0  # where this attempt's output begins in the log
    signalled: bool = False  # a stop signal was passed on to it


class JobsFailed(DDPError):
    """Some jobs exited with an error (job name -> its exit status and last log line); ``reports`` holds the
    others' evaluation reports."""

    def __init__(self, failed: dict[str, str], reports: dict[str, dict]):
        self.failed, self.reports = failed, reports
        super().__init__(f"{len(failed)} job(s) failed: " + "; ".join(f"{k} ({v})" for k, v in failed.items()))


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity (a Slurm / cgroup job's share of a node), not the
    node's count."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity call on this platform (macOS, Windows)
        return os.cpu_count() or 1


def threads_per_job(jobs: int, cores: int | None = None) -> int:
    """Each of ``jobs`` concurrent jobs' share of the cores this process may use (at least one)."""
    return max(1, (cores or usable_cores()) // jobs)


def plan_jobs(recipes: list[str], overrides: list[str], *, threads: int, protocols: str | None = None,
              episodes: int | None = None, no_resume: bool = False, quiet: bool = False) -> list[Job]:
    """One :class:`Job` per recipe, each built here first (a typo fails before any job starts); two recipes
    that would train into the same folder are refused."""
    from ddp.experiment import build

    extra = [] if any(parse_override(o)[0] == ["train", "num_threads"] for o in overrides) else [
        f"train.num_threads={threads}"]
    jobs, folders = [], {}
    for recipe in recipes:
        r = build(recipe, overrides).recipe
        out = Path(r.train.output_dir.format(name=r.name))
        results = Path(r.eval.output_dir.format(name=r.name))
        for what, folder in (("trains into", out), ("writes its evaluation to", results)):
            if (what, folder.resolve()) in folders:
                raise DDPError(f"{recipe}: {what} {folder}, as {folders[what, folder.resolve()]} does; run them one "
                               "after the other (without --jobs) or give one of them another name or folder")
            folders[what, folder.resolve()] = recipe
        argv = [sys.executable, "-m", "ddp", "run", str(recipe)] + (["--quiet"] if quiet else [])
        argv += [a for o in [*overrides, *extra] for a in ("--set", o)]
        argv += (["--protocols", protocols] if protocols else []) + (["--episodes", str(episodes)] if episodes else [])
        argv += ["--no-resume"] if no_resume else []
        jobs.append(Job(r.name, argv, out / "run.log", results / "results.json"))
    return jobs


def _last_line(path: Path) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1].strip() if lines else ""


def run_jobs(jobs: list[Job], *, parallel: int, threads: int, echo=print) -> dict[str, dict]:
    """Run ``jobs``, ``parallel`` at a time; return job name -> evaluation report, in the jobs' order.

    Raises :class:`JobsFailed` if any failed (after the others finished), ``KeyboardInterrupt`` /
    :class:`~ddp.preemption.Preempted` if stopped (after the jobs in progress saved). Whatever ends it, no
    job outlives it: an error here stops the jobs in progress (SIGTERM: they save) before it propagates."""
    say = echo

    def echo(message: str) -> None:  # a hung-up terminal (SIGHUP, ssh gone) must not cut the stopping short
        try:
            say(message)
        except OSError:
            pass

    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", str(threads))
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    queue, running, stopped = list(jobs), [], []
    reports, failed = {}, {}

    def stop(signum, frame) -> None:  # no new job; the ones in progress stop as ddp run does alone
        if stopped:  # passed on once: they are saving
            return
        stopped.append(signum)
        for job in running:
            job.proc.send_signal(signum)
            job.signalled = True

    previous = {s: signal.signal(s, stop) for s in _STOPS if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        try:
            while queue or running:
                while queue and len(running) < parallel and not stopped:
                    job = queue.pop(0)
                    _start(job, env)
                    running.append(job)
                    echo(f"started {job.name} ({threads} thread{'s' if threads > 1 else ''}; "
                         f"follow it: tail -f {job.log})")
                if stopped or not running:
                    break
                time.sleep(0.2)
                if stopped:  # a job that exits now was stopped, not failed
                    break
                for job in [j for j in running if j.proc.poll() is not None]:
                    running.remove(job)
                    _finish(job, reports, failed, echo)
        except BaseException:
            _stop(running, signal.SIGTERM, reports, failed, echo)
            raise
        if stopped:
            _stop(running, stopped[0], reports, failed, echo)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if stopped:
        left = [j.name for j in queue]
        again = resume_hint(any("--no-resume" in j.argv for j in jobs))
        echo("stopped" + (f"; not started: {', '.join(left)}" if left else "")
             + (f"; failed: {', '.join(failed)} (see above)" if failed else "") + f" ({again})")
        raise KeyboardInterrupt() if stopped[0] == signal.SIGINT else Preempted(stopped[0])
    ordered = {j.name: reports[j.name] for j in jobs if j.name in reports}
    if failed:
        raise JobsFailed(failed, ordered)
    return ordered


def _start(job: Job, env: dict) -> None:
    """Start ``job``'s process, its output appended to its log (a resumed run keeps the earlier attempts')."""
    job.log.parent.mkdir(parents=True, exist_ok=True)
    with open(job.log, "a") as log:  # the child holds its own copy of the descriptor
        log.write(f"== {time.strftime('%Y-%m-%d %H:%M:%S')}: {' '.join(job.argv)}\n")
        log.flush()
        job.log_offset = log.tell()
        # its own session: a Ctrl-C at the terminal reaches this process alone, which passes it on once
        job.proc = subprocess.Popen(job.argv, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    job.started = time.perf_counter()


def _finish(job: Job, reports: dict, failed: dict, echo) -> None:
    """Note a job that exited: its report, or why it failed."""
    took = fmt_elapsed(time.perf_counter() - job.started)
    code = job.proc.returncode
    if code == 0:
        try:
            reports[job.name] = json.loads(job.results.read_text())
        except (OSError, ValueError) as err:
            failed[job.name] = f"its results {job.results} cannot be read: {type(err).__name__}"
            echo(f"failed {job.name} after {took}: {failed[job.name]}")
            return
        with open(job.log, "rb") as log:  # this attempt's part of the log
            log.seek(job.log_offset)
            attempt = log.read().decode(errors="replace")
        for line in attempt.splitlines():
            if line.startswith(f"[{job.name}]"):
                echo(line)
        echo(f"finished {job.name} in {took}")
    else:
        failed[job.name] = f"exit {code}: {_last_line(job.log)}"
        echo(f"failed {job.name} after {took}: exit {code} (log: {job.log})")


def _stop(running: list[Job], signum: int, reports: dict, failed: dict, echo) -> None:
    """Stop the jobs in progress: ``signum`` to each one not yet sent a stop signal (one started as the signal
    came, before the handler could see it), then wait for them to save and exit (killed after
    STOP_GRACE_SECONDS). One that finished meanwhile counts as finished."""
    deadline = time.monotonic() + STOP_GRACE_SECONDS
    for job in running:
        if not job.signalled and job.proc.poll() is None:
            job.proc.send_signal(signum)
            job.signalled = True
    for job in running:
        try:
            job.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            job.proc.kill()
            job.proc.wait()
            failed[job.name] = f"did not stop within {STOP_GRACE_SECONDS} s: killed (it resumes from its last " \
                               f"periodic checkpoint)"
            echo(f"{job.name} {failed[job.name]}; log: {job.log}")
            continue
        code = job.proc.returncode
        if code == 0:
            _finish(job, reports, failed, echo)
        elif code in _STOPPED_CODES:
            echo(f"{job.name} stopped (exit {code}; log: {job.log})")
        else:  # e.g. its checkpoint write refused (exit 2): what it did since its last checkpoint is lost
            failed[job.name] = f"exit {code} while stopping: {_last_line(job.log)}"
            echo(f"{job.name} failed while stopping (exit {code}; log: {job.log})")
    running.clear()
