"""``ddp run --jobs N``: train and evaluate several recipes at once, each in its own process and share of cores.

A method and its baselines (DDP and its DP3 ablation, say) are independent runs. A small model's training
barely uses a second core (the quickstart's DDP step: 156 ms on two threads, 179 ms on one), so on a
machine with more cores than one run uses, running the recipes side by side finishes sooner than one after
another. Each job is ``ddp run RECIPE`` in a child process (the same ``--set``, ``--protocols``,
``--episodes`` and ``--no-resume``) with ``train.num_threads`` (unless ``--set``) and ``OMP_NUM_THREADS``
set to its share of the cores and ``OMP_WAIT_POLICY=PASSIVE`` (unless set: OpenMP threads spinning in
processes that share cores slow each other down many-fold); its console output goes to
``<train.output_dir>/run.log``. Each finished job's summary lines are echoed, and at the end the table of
every job that finished, read from the ``results.json`` its evaluation wrote.

Stopped with Ctrl-C, SIGTERM or SIGHUP, no queued job starts; the signal is passed on to the jobs in
progress (a training run writes its checkpoint, as ``ddp run`` does alone: the same command resumes it)
and the command waits for them. A job that fails leaves its traceback in its log; the others go on.
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
from ddp.preemption import Preempted

__all__ = ["Job", "JobsFailed", "plan_jobs", "run_jobs"]

STOP_GRACE_SECONDS = 300  # how long a stopped job may take to save its checkpoint before it is killed
_STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@dataclass
class Job:
    """One recipe to run in its own process: what to run and where its log and results land."""

    recipe: str
    name: str
    argv: list[str]
    log: Path
    results: Path
    proc: subprocess.Popen | None = field(default=None, repr=False)
    started: float = 0.0
    signalled: bool = False  # a stop signal was passed on to it


class JobsFailed(DDPError):
    """Some jobs exited with an error (job name -> its exit status and last log line); ``reports`` holds the
    others' evaluation reports."""

    def __init__(self, failed: dict[str, str], reports: dict[str, dict]):
        self.failed, self.reports = failed, reports
        super().__init__(f"{len(failed)} job(s) failed: " + "; ".join(f"{k} ({v})" for k, v in failed.items()))


def threads_per_job(jobs: int, cores: int | None = None) -> int:
    """Each of ``jobs`` concurrent jobs' share of the machine's cores (at least one)."""
    return max(1, (cores or os.cpu_count() or 1) // jobs)


def plan_jobs(recipes: list[str], overrides: list[str], *, threads: int, protocols: str | None = None,
              episodes: int | None = None, no_resume: bool = False) -> list[Job]:
    """One :class:`Job` per recipe, each built here first (a typo fails before any job starts); two recipes
    that would train into the same folder are refused."""
    from ddp.experiment import build

    extra = [] if any(o.split("=", 1)[0].strip() == "train.num_threads" for o in overrides) else [
        f"train.num_threads={threads}"]
    jobs, folders = [], {}
    for recipe in recipes:
        r = build(recipe, overrides).recipe
        out = Path(r.train.output_dir.format(name=r.name))
        if out.resolve() in folders:
            raise DDPError(f"{recipe}: trains into {out}, as {folders[out.resolve()]} does; run them one after "
                           "the other (without --jobs) or give one of them another name")
        folders[out.resolve()] = recipe
        argv = [sys.executable, "-m", "ddp", "run", str(recipe), "--quiet"]
        argv += [a for o in [*overrides, *extra] for a in ("--set", o)]
        argv += (["--protocols", protocols] if protocols else []) + (["--episodes", str(episodes)] if episodes else [])
        argv += ["--no-resume"] if no_resume else []
        jobs.append(Job(str(recipe), r.name, argv, out / "run.log",
                        Path(r.eval.output_dir.format(name=r.name)) / "results.json"))
    return jobs


def _elapsed(seconds: float) -> str:
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s:02d} s" if m else f"{s} s"


def _last_line(path: Path) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1].strip() if lines else ""


def run_jobs(jobs: list[Job], *, parallel: int, threads: int, echo=print) -> dict[str, dict]:
    """Run ``jobs``, ``parallel`` at a time; return job name -> evaluation report, in the jobs' order.

    Raises :class:`JobsFailed` if any failed (after the others finished), ``KeyboardInterrupt`` /
    :class:`~ddp.preemption.Preempted` if stopped (after the jobs in progress saved)."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    queue, running, stopped = list(jobs), [], []
    reports, failed = {}, {}

    def stop(signum, frame) -> None:  # no new job; the ones in progress stop as ddp run does alone
        stopped.append(signum)
        for job in running:
            job.proc.send_signal(signum)
            job.signalled = True

    previous = {s: signal.signal(s, stop) for s in _STOPS if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        while queue or running:
            while queue and len(running) < parallel and not stopped:
                job = queue.pop(0)
                job.log.parent.mkdir(parents=True, exist_ok=True)
                with open(job.log, "w") as log:  # the child holds its own copy of the descriptor
                    # its own session: a Ctrl-C at the terminal reaches this process alone, which passes it on once
                    job.proc = subprocess.Popen(job.argv, stdout=log, stderr=subprocess.STDOUT, env=env,
                                                start_new_session=True)
                job.started = time.perf_counter()
                running.append(job)
                echo(f"started {job.name} ({threads} thread{'s' if threads > 1 else ''}; log: {job.log})")
            if not running:
                break
            time.sleep(0.2)
            for job in [j for j in running if j.proc.poll() is not None]:
                running.remove(job)
                _finish(job, reports, failed, echo)
            if stopped:
                _wait_stopped(running, stopped[0], echo)
                running.clear()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if stopped:
        left = [j.name for j in queue]
        echo("stopped" + (f"; not started: {', '.join(left)}" if left else "") + " (the same command resumes)")
        raise KeyboardInterrupt() if stopped[0] == signal.SIGINT else Preempted(stopped[0])
    ordered = {j.name: reports[j.name] for j in jobs if j.name in reports}
    if failed:
        raise JobsFailed(failed, ordered)
    return ordered


def _finish(job: Job, reports: dict, failed: dict, echo) -> None:
    """Note a job that exited: its report, or why it failed."""
    took = _elapsed(time.perf_counter() - job.started)
    code = job.proc.returncode
    if code == 0:
        reports[job.name] = json.loads(job.results.read_text())
        for line in job.log.read_text(errors="replace").splitlines():
            if line.startswith(f"[{job.name}]"):
                echo(line)
        echo(f"finished {job.name} in {took}")
    else:
        failed[job.name] = f"exit {code}: {_last_line(job.log)}"
        echo(f"failed {job.name} after {took}: exit {code} (log: {job.log})")


def _wait_stopped(running: list[Job], signum: int, echo) -> None:
    """After a stop: wait for the jobs in progress to save and exit (killed after STOP_GRACE_SECONDS). One
    started as the signal came, before the handler could see it, gets the signal now."""
    deadline = time.monotonic() + STOP_GRACE_SECONDS
    for job in running:
        if not job.signalled:
            job.proc.send_signal(signum)
            job.signalled = True
    for job in running:
        try:
            job.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            echo(f"{job.name} did not stop within {STOP_GRACE_SECONDS} s: killed")
            job.proc.kill()
            job.proc.wait()
        echo(f"{job.name} stopped (exit {job.proc.returncode}; log: {job.log})")
