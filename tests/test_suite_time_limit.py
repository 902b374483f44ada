"""``ddp suite --time-limit``: estimates from stored runs, runs that would not fit left alone, the rest stopped."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

from conftest import ROOT
from ddp.checkpoint import save_checkpoint
from ddp.errors import DDPError
from ddp.suite import ResultStore, SuiteTimeLimit, load_suite, run_suite, select
from ddp.suite.budget import estimate_seconds, parse_duration, stored_results, total_expected


@pytest.mark.parametrize("text, seconds", [("5400", 5400), ("90m", 5400), ("1h30m", 5400), ("1.5h", 5400),
                                           ("2h5m30s", 7530), ("45s", 45), (" 2H ", 7200)])
def test_durations(text, seconds):
    assert parse_duration(text) == pytest.approx(seconds)


@pytest.mark.parametrize("text", ["", "1h30", "ninety", "5m1h", "-5", "0", "0m", "inf", "nan", "1e12"])
def test_bad_durations_are_one_line(text):
    with pytest.raises(DDPError, match="--time-limit") as err:
        parse_duration(text)
    assert "\n" not in str(err.value)


def _fake_result(run, train, evals, wall):
    return {"run_id": run.run_id, "task": run.task, "method": run.method, "seed": run.seed,
            "train": {"steps": 2, "seconds": train, "loss": 0.1}, "wall_seconds": wall,
            "protocols": {f"p{i}": {"success_rate": 1.0, "seconds": s} for i, s in enumerate(evals)}}


def test_estimates_come_from_the_suites_stored_runs(suite_file):
    suite = load_suite(suite_file)
    runs = {r.run_id: r for r in suite.runs}  # every run of the fixture trains 2 steps (train.max_steps)
    store = ResultStore(suite.results_dir)
    store.save(runs["near__ddp__seed0"], _fake_result(runs["near__ddp__seed0"], 100.0, [10.0, 20.0], 125.0))
    store.save(runs["far__ddp__seed0"], _fake_result(runs["far__ddp__seed0"], 200.0, [], 250.0))
    stored = stored_results(suite.results_dir)

    # the same task and method first: 50 s/step x 2 steps + evaluation (30 s) and setup (the wall time beyond: 0)
    assert estimate_seconds(runs["near__ddp__seed1"], stored) == \
        (130.0, "1 stored near ddp run: 50 s/step x 2 steps + 30 s evaluation and setup")
    assert estimate_seconds(runs["far__ddp__seed1"], stored)[0] == 250.0  # 100 s/step x 2 + 50 s of setup
    # else the method's runs on any task; nothing for a method without stored runs
    only_far = [r for r in stored if r["task"] == "far"]
    assert estimate_seconds(runs["near__ddp__seed1"], only_far)[:1] == (250.0,)
    assert estimate_seconds(runs["near__ddp__seed1"], only_far)[1].startswith("1 stored ddp run:")
    assert estimate_seconds(runs["near__dp3__seed1"], stored) == (None, "no stored dp3 run")

    # a larger step budget costs its steps; a run resuming a checkpoint pays only the steps still to go
    run = runs["near__ddp__seed1"]
    longer = dataclasses.replace(run, recipe={**run.recipe, "train": {**run.recipe["train"], "max_steps": 10}})
    assert estimate_seconds(longer, stored)[0] == pytest.approx(50.0 * 10 + 30.0)
    save_checkpoint(suite_file.parent / run.recipe["train"]["output_dir"] / "last.pt", {"step": 1})
    import ddp.checkpoint

    loads, load = [], ddp.checkpoint.load_checkpoint
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ddp.checkpoint, "load_checkpoint", lambda *a, **k: loads.append(a) or load(*a, **k))
        cost, why = estimate_seconds(run, stored)
    assert cost == pytest.approx(80.0) and "x 1 steps (its checkpoint is at 1)" in why
    assert len(loads) == 1  # read once for the superseded check and the step
    # without step counts in the results: the median of the whole runs' cost, unscaled
    bare = [{**r, "train": {"seconds": r["train"]["seconds"]}} for r in stored]
    assert estimate_seconds(runs["far__ddp__seed1"], bare) == (250.0, "median of 1 stored far ddp run")

    # a stored run that resumed: its setup is its last attempt's wall time less that attempt's own training
    far_dp3 = runs["far__dp3__seed0"]
    resumed = _fake_result(far_dp3, 1000.0, [50.0], 400.0)
    resumed["train"]["attempt_seconds"] = 50.0  # 300 s of setup (demos, calibration) in the last attempt
    assert estimate_seconds(runs["far__dp3__seed1"], [resumed])[0] == pytest.approx(500.0 * 2 + 50.0 + 300.0)

    # one re-evaluating protocols pays their stored evaluation; one it never ran: the method's median
    again = dataclasses.replace(runs["near__ddp__seed0"], reevaluate=("p1",))
    assert estimate_seconds(again, stored)[0] == pytest.approx(20.0)
    store.save(runs["far__ddp__seed1"], _fake_result(runs["far__ddp__seed1"], 1.0, [4.0, 6.0], 12.0))
    again = dataclasses.replace(runs["far__ddp__seed0"], reevaluate=("p0", "p1"))
    cost, why = estimate_seconds(again, stored_results(suite.results_dir))
    assert cost == pytest.approx(7.0 + 13.0) and "p0, p1: the median of the stored ddp runs" in why


def test_a_run_that_could_never_fit_starts_while_time_is_left():
    """A run longer than the whole limit needs several budgets whatever happens: it starts (and resumes in the
    next one); a run that fits a whole budget waits for one with room for it."""
    from ddp.suite.budget import Deadline

    fresh = Deadline.after(10.0)
    assert fresh.allows(None, 10.0) and fresh.allows(8.0, 10.0) and fresh.allows(3600.0, 10.0)
    late = Deadline(time.time() + 5.0)
    assert not late.allows(8.0, 10.0) and late.allows(4.0, 10.0) and late.allows(11.0, 10.0)
    assert late.allows(9.6, 10.0)  # within 5 % of the whole limit: no attempt would find that much time left
    assert not Deadline(time.time() - 1.0).allows(None, 10.0) and not Deadline(time.time() - 1).allows(11.0, 10.0)
    # a run with only its evaluation left starts it over in every budget: it never starts if it cannot fit
    assert not fresh.allows(3600.0, 10.0, trains=False) and fresh.allows(8.0, 10.0, trains=False)


def test_only_a_run_with_training_left_counts_as_progressing(tmp_path, monkeypatch):
    from ddp.suite import budget

    monkeypatch.chdir(tmp_path)
    run = dataclasses.replace(_run_stub(tmp_path), recipe={"train": {"output_dir": "runs/x", "max_steps": 10}})
    assert budget.trains_on(run)  # no checkpoint yet
    monkeypatch.setattr(budget, "_checkpoint_position", lambda r: (7, 1))
    assert budget.trains_on(run)
    monkeypatch.setattr(budget, "_checkpoint_position", lambda r: (10, 2))
    assert not budget.trains_on(run)  # trained: only evaluation is left
    assert not budget.trains_on(dataclasses.replace(run, reevaluate=("id",)))
    by_epochs = dataclasses.replace(run, recipe={"train": {"output_dir": "runs/x", "max_steps": 100, "epochs": 2}})
    assert not budget.trains_on(by_epochs)  # its epochs ended it before its step budget
    monkeypatch.setattr(budget, "_checkpoint_position", lambda r: (7, 1))
    assert budget.trains_on(by_epochs)


@pytest.mark.parametrize("first_cost", [2.0, 9.0])
def test_runs_that_do_not_fit_wait_and_the_limit_stops_the_one_in_progress(suite_file, monkeypatch, first_cost):
    """In turn, in this process, a 10 s limit: a run expected to take longer than the time left does not start
    (the next, shorter one still does); a run finished meanwhile informs the estimate of the next of its kind;
    at the limit the run in progress gets SIGTERM, as from a scheduler, and the runs after it do not start;
    what finished is stored and SuiteTimeLimit names the rest."""
    import ddp.suite.runner as runner

    suite = select(load_suite(suite_file), tasks=["near"])  # ddp s0, dp3 s0, ddp s1, dp3 s1
    store = ResultStore(suite.results_dir)
    far_dp3 = next(r for r in load_suite(suite_file).runs if r.run_id == "far__dp3__seed0")
    store.save(far_dp3, _fake_result(far_dp3, 8.0, [], 8.0))  # a dp3 run takes 8 s: it fits 10, not 10 - 3

    calls, stops = [], []

    def fake_run(run, threads=None, deferred=None):
        calls.append(run.run_id)
        if len(calls) == 1:  # the first ddp run (no estimate yet: it starts) takes 3 s, reporting first_cost
            time.sleep(3)
            return _fake_result(run, first_cost, [], first_cost)
        try:  # the second one is still going at the limit
            time.sleep(60)
        except KeyboardInterrupt as err:
            stops.append(type(err).__name__)
            raise
        raise AssertionError("the time limit did not stop the run")

    monkeypatch.setattr(runner, "execute_run", fake_run)
    lines = []
    handler = signal.getsignal(signal.SIGTERM)
    t0 = time.time()
    with pytest.raises(SuiteTimeLimit) as limit:
        run_suite(suite, progress=False, echo=lines.append, time_limit=10.0)
    assert time.time() - t0 < 40
    assert signal.getsignal(signal.SIGTERM) is handler  # the suite's own handler is gone again
    err = limit.value
    assert list(err.done) == ["near__ddp__seed0"] and store.load(suite.runs[0]) is not None
    assert any(line.startswith("not started near__dp3__seed0: expected 8 s, ") for line in lines), lines
    if first_cost == 9.0:  # the first ddp run says a ddp run takes 9 s: the second does not start either
        assert calls == ["near__ddp__seed0"] and stops == [] and err.stopped == []
        assert err.skipped == {"near__dp3__seed0": 8.0, "near__ddp__seed1": 9.0, "near__dp3__seed1": 8.0}
        return
    assert calls == ["near__ddp__seed0", "near__ddp__seed1"] and stops == ["Preempted"]
    assert err.stopped == ["near__ddp__seed1"]
    assert err.skipped == {"near__dp3__seed0": 8.0, "near__dp3__seed1": 8.0}
    assert "time limit of 10 s reached: stopped 1 run(s) in progress (near__ddp__seed1" in str(err)

    # without a limit nothing is skipped: the same suite runs everything it has not stored
    calls.clear()
    monkeypatch.setattr(runner, "execute_run", lambda run, threads=None, **kw: calls.append(run.run_id)
                        or _fake_result(run, 1.0, [1.0], 2.0))
    run_suite(suite, progress=False, echo=lambda *_: None)
    assert calls == ["near__dp3__seed0", "near__ddp__seed1", "near__dp3__seed1"]


def test_an_idle_pool_worker_outlives_sigterm():
    """The pool passes SIGTERM to every worker at the limit; one without a run (its run did not fit) must not
    die of it: a dead worker breaks the pool, whose clean-up terminates the others, maybe mid-save."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from ddp.suite.runner import _init_worker

    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_init_worker, initargs=(ctx.Event(),)) as pool:
        pid = pool.submit(os.getpid).result(timeout=120)
        os.kill(pid, signal.SIGTERM)
        time.sleep(1.0)
        assert pool.submit(os.getpid).result(timeout=60) == pid


def test_ray_tells_a_stopped_run_by_what_its_log_gained_in_this_attempt(tmp_path, monkeypatch):
    """A run's log is appended to across attempts: a queued task cancelled now is not "stopped" because an
    earlier attempt's stop line ends its log."""
    from ddp.suite.runner import _log_size, _started_since

    monkeypatch.chdir(tmp_path)
    run = _run_stub(tmp_path)
    log = tmp_path / run.recipe["train"]["output_dir"] / "log.txt"
    log.parent.mkdir(parents=True)
    log.write_text(f"== {run.run_id} started (threads 1)\n== {run.run_id} stopped (stopped by SIGTERM)\n")
    offset = _log_size(run)
    assert offset > 0 and not _started_since(run, offset)
    with open(log, "a") as f:
        f.write(f"== {run.run_id} started (threads 1)\n")
    assert _started_since(run, offset) and _started_since(run, 0)


def test_a_run_whose_worker_died_at_the_limit_is_not_said_to_have_saved(tmp_path):
    """After the time limit's SIGTERM, a run that raised KeyboardInterrupt saved its checkpoint (stopped); one
    whose worker died under it (the pool broken: killed after the grace period) may not have (killed)."""
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from ddp.suite.runner import _collect, _Limit

    limit = _Limit(10.0, tmp_path, say=lambda *_: None)
    runs = [_run_stub(tmp_path, seed=0), _run_stub(tmp_path, seed=1)]  # two ids: a swap would show
    for run, err in zip(runs, (KeyboardInterrupt(), BrokenProcessPool("a worker died"))):
        fut = Future()
        fut.set_exception(err)
        _collect(fut, run, finished=None, failure=None, limit=limit, stopping=True)
    assert limit.stopped == [runs[0].run_id] and limit.killed == [runs[1].run_id]
    text = str(SuiteTimeLimit(10.0, limit.stopped, {}, {}, killed=limit.killed))
    assert "stopped 1 run(s) in progress (t__m__seed0; a training run saved its checkpoint)" in text
    assert "killed 1 run(s) that did not stop in time (t__m__seed1; each resumes from its last periodic" in text


def test_a_stopping_pool_stores_the_runs_that_finished_before_it_could_collect_them(tmp_path):
    from concurrent.futures import Future

    from ddp.suite.runner import NotStarted, _store_finished

    runs = [_run_stub(tmp_path) for _ in range(5)]
    outcomes = [{"run_id": "a"}, KeyboardInterrupt(), NotStarted(60.0), None, {"run_id": "e"}]
    futures, seen = {}, set()
    for run, outcome in zip(runs, outcomes):
        fut = Future()
        if isinstance(outcome, BaseException):
            fut.set_exception(outcome)
        elif outcome is not None:  # None: still running when the pool was shut down
            fut.set_result(outcome)
        futures[fut] = run
    done_first = list(futures)[4]
    seen.add(done_first)  # collected in the loop already
    stored = []
    _store_finished(futures, seen, lambda run, result: stored.append(result["run_id"]))
    assert stored == ["a"] and list(futures)[0] in seen


def test_an_interrupted_ray_suite_cancels_its_tasks_so_they_save(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM while the driver waits: every task is cancelled (a running one saves its checkpoint)
    and given the grace period before the interruption goes on and Ray shuts down."""
    import sys
    import types

    from ddp.suite import runner

    calls = []

    class Cancelled(Exception):
        pass

    fake = types.SimpleNamespace(
        is_initialized=lambda: True, remote=lambda **kw: (lambda fn: types.SimpleNamespace(
            remote=lambda *a: object())),
        wait=lambda refs, num_returns=1, timeout=None: calls.append(("wait", timeout)) or (
            (_ for _ in ()).throw(KeyboardInterrupt()) if len(calls) == 1 else (refs, [])),
        cancel=lambda ref: calls.append("cancel"),
        get=lambda ref, timeout=None: (_ for _ in ()).throw(Cancelled()),
        exceptions=types.SimpleNamespace(TaskCancelledError=Cancelled, GetTimeoutError=TimeoutError))
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.chdir(tmp_path)
    limit = runner._Limit(None, tmp_path, say=lambda *_: None)
    runs = [_run_stub(tmp_path)]
    with pytest.raises(KeyboardInterrupt):
        runner._run_on_ray(runs, finished=None, failure=None, ray=True, threads=1, gpus=0, echo=lambda *_: None,
                           limit=limit)
    assert calls == [("wait", None), "cancel", ("wait", runner.STOP_GRACE_SECONDS)]
    assert limit.skipped == {runs[0].run_id: None}  # its log shows no start in this attempt


def _run_stub(tmp_path, seed: int = 0):
    from ddp.suite.spec import RunSpec

    return RunSpec(suite="s", task="t", method="m", seed=seed, benchmark="b", protocols=None, episodes=None,
                   recipe={"train": {"output_dir": f"runs/suites/s/t__m__seed{seed}"}})


def test_a_pool_at_its_time_limit_saves_its_runs_and_exits_75(suite_file):
    """`ddp suite --workers 2 --time-limit 30s` on runs that would train for hours: at the limit the two runs in
    training save their checkpoints, the queued ones never start, no worker outlives the suite, and the exit
    status (75) tells a job script to run the same command again."""
    spec = yaml.safe_load(suite_file.read_text())
    spec["set"] = ["train.lr=0.002", "train.max_steps=100000", "train.epochs=100000"]
    spec["methods"] = {"dp3": spec["methods"]["dp3"]}
    suite_file.write_text(yaml.safe_dump(spec, sort_keys=False))
    runs = [suite_file.parent / "runs/suites/tiny_suite" / f"{t}__dp3__seed{k}" for k in (0, 1) for t in ("near", "far")]
    proc = subprocess.Popen([sys.executable, "-m", "ddp", "suite", str(suite_file), "--workers", "2", "--threads", "1",
                             "--quiet", "--time-limit", "30s"], cwd=suite_file.parent, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    children: list[str] = []
    try:
        deadline = time.time() + 25
        while len(children) < 2 and time.time() < deadline and proc.poll() is None:
            time.sleep(0.5)
            children = subprocess.run(["pgrep", "-P", str(proc.pid), "-f", "spawn_main"], capture_output=True,
                                      text=True).stdout.split()
        out = proc.communicate(timeout=300)[0].decode()
    finally:
        if proc.poll() is None:
            proc.kill()
        for c in children:  # whatever failed, leave no worker behind
            with contextlib.suppress(OSError, ValueError):
                os.kill(int(c), signal.SIGKILL)
    assert proc.returncode == 75, out[-2000:]
    assert "Traceback" not in out, out[-3000:]
    assert "time limit of 30 s reached: stopped 2 run(s) in progress" in out, out[-2000:]
    assert "left 2 not started (expected near__dp3__seed1: unknown, far__dp3__seed1: unknown)" in out, out[-2000:]
    assert all((r / "last.pt").exists() for r in runs[:2]), out[-2000:]  # stopped in training: saved
    assert not any((r / "log.txt").exists() for r in runs[2:]), out[-2000:]  # queued: never started
    for _ in range(20):
        alive = [c for c in children if os.path.exists(f"/proc/{c}")]
        if not alive:
            break
        time.sleep(0.5)
    assert not alive, f"workers outlived the suite: {alive}"


@pytest.mark.slow
def test_ray_tasks_at_the_time_limit_are_cancelled_and_save(suite_file):
    """The same on a local Ray: at the limit the running tasks are cancelled (KeyboardInterrupt: training saves
    its checkpoint) and the queued one never starts."""
    pytest.importorskip("ray")
    spec = yaml.safe_load(suite_file.read_text())
    spec["set"] = ["train.lr=0.002", "train.max_steps=100000", "train.epochs=100000"]
    spec["methods"] = {"dp3": spec["methods"]["dp3"]}
    suite_file.write_text(yaml.safe_dump(spec, sort_keys=False))
    suite = select(load_suite(suite_file), seeds=[0, 1], tasks=["near"])
    suite.runs.append(next(r for r in load_suite(suite_file).runs if r.run_id == "far__dp3__seed0"))
    with pytest.raises(SuiteTimeLimit) as limit:
        run_suite(suite, ray=True, threads=1, progress=False, echo=lambda *_: None, time_limit=45.0)
    # Ray runs two one-CPU tasks at once on a two-core machine; the third waits for a CPU and never starts
    stopped, skipped = limit.value.stopped, limit.value.skipped
    assert len(stopped) + len(skipped) == 3 and len(stopped) >= 1
    for run_id in stopped:
        assert (suite_file.parent / "runs/suites/tiny_suite" / run_id / "last.pt").exists(), run_id
    for run_id in skipped:
        assert not (suite_file.parent / "runs/suites/tiny_suite" / run_id / "last.pt").exists(), run_id


def test_the_total_names_the_runs_without_an_estimate():
    assert total_expected([600.0, 1200.0]) == "30 min one after another"
    assert total_expected([600.0, None]) == ("10 min one after another (1 run(s) without an estimate: no stored run "
                                             "of their method)")
    assert total_expected([None, None]).startswith("unknown one after another (2 run(s)")  # not "0 s"


def test_a_worker_that_dies_fails_the_runs_in_progress_and_the_queued_ones_run_on_a_new_pool(suite_file):
    """A worker killed (as the OOM killer does) breaks the process pool, which fails every future it holds:
    the two runs in training fail (their last checkpoint stands), the two queued runs, which never started,
    run on a new pool instead of being reported failed."""
    import os
    import signal
    import threading
    import time

    from ddp.suite import SuiteRunsFailed

    spec = yaml.safe_load(suite_file.read_text())
    slow = ["train.max_steps=100000", "train.epochs=100000"]
    spec["tasks"] = {"slow1": {"recipe": "tiny.yaml", "set": slow}, "slow2": {"recipe": "tiny.yaml", "set": slow},
                     "fast1": "tiny.yaml", "fast2": "tiny.yaml"}
    spec["methods"] = {"dp3": spec["methods"]["dp3"]}
    spec["seeds"] = [0]
    suite_file.write_text(yaml.safe_dump(spec, sort_keys=False))
    suite = load_suite(suite_file)
    slow_logs = [suite_file.parent / r.recipe["train"]["output_dir"] / "logs" for r in suite.runs[:2]]
    killed: list[int] = []

    def kill_a_worker():
        deadline = time.time() + 120
        while not all(p.exists() for p in slow_logs) and time.time() < deadline:
            time.sleep(0.2)  # both slow runs are training
        time.sleep(1)
        import multiprocessing

        workers = [c for c in multiprocessing.active_children() if "SpawnProcess" in c.name]
        if workers:
            os.kill(workers[0].pid, signal.SIGKILL)
            killed.append(workers[0].pid)

    killer = threading.Thread(target=kill_a_worker, daemon=True)
    killer.start()
    lines: list[str] = []
    with pytest.raises(SuiteRunsFailed) as failed:
        run_suite(suite, workers=2, threads=1, progress=False, echo=lines.append)
    killer.join(timeout=5)
    assert killed, "no worker was found to kill"
    assert sorted(failed.value.failed) == ["slow1__dp3__seed0", "slow2__dp3__seed0"], lines
    assert "worker process died" in failed.value.failed["slow1__dp3__seed0"]
    assert sorted(failed.value.done) == ["fast1__dp3__seed0", "fast2__dp3__seed0"], lines
    assert any("2 run(s) that had not started go to a new pool" in line for line in lines), lines


def test_a_stop_while_a_finished_run_makes_its_result_keeps_the_result(suite_file, monkeypatch):
    """SIGTERM (the time limit's own, or a scheduler's) that lands after the evaluation returned, while the
    result is being made (code_version runs git for seconds), stores the result, then stops: the evaluation
    was thrown away and run again by the next invocation."""
    from ddp.preemption import Preempted
    from ddp.suite import runner

    real = runner.code_version

    def slow_git():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.2)
        return real()

    monkeypatch.setattr(runner, "code_version", slow_git)
    suite = select(load_suite(suite_file), tasks=["near"], methods=["dp3"])
    with pytest.raises(Preempted):
        run_suite(suite, workers=1, threads=1, progress=False, echo=lambda *_: None)
    store = ResultStore(suite.results_dir)
    assert store.load(suite.runs[0]) is not None  # stored whole
    assert store.load(suite.runs[1]) is None  # the stop held: the next run never started
    log = (suite_file.parent / suite.runs[0].recipe["train"]["output_dir"] / "log.txt").read_text()
    assert log.rstrip().endswith("finished")


def test_a_local_ray_gets_this_process_s_cores_and_a_cluster_its_own(tmp_path, monkeypatch):
    """A local Ray counted the machine's cores: under Slurm or taskset it ran that many runs at once on the
    few this job may use. A cluster address keeps the cluster's own count."""
    import sys
    import types

    import ddp.run_jobs
    from ddp.suite import runner

    inits = []
    fake = types.SimpleNamespace(is_initialized=lambda: False, init=lambda **kw: inits.append(kw),
                                 remote=lambda **kw: (lambda fn: None), shutdown=lambda: None)
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.setattr(ddp.run_jobs, "usable_cores", lambda: 3)
    limit = runner._Limit(None, tmp_path, say=lambda *_: None)
    for ray in (True, "ray://head:10001"):
        runner._run_on_ray([], finished=None, failure=None, ray=ray, threads=1, gpus=0, echo=lambda *_: None,
                           limit=limit)
    assert inits[0]["num_cpus"] == 3 and inits[0]["address"] is None
    assert "num_cpus" not in inits[1] and inits[1]["address"] == "ray://head:10001"


@pytest.mark.parametrize(("runs", "workers", "threads", "per"), [(1, 2, None, 4), (3, 2, None, 2), (3, 2, 1, 1)])
def test_the_pool_gives_each_run_its_share_of_the_cores(runs, workers, threads, per, tmp_path, monkeypatch):
    """Each run's threads are the usable cores over the workers the pool really starts: one run left on two
    workers gets every core (it got half); --threads overrides."""
    import concurrent.futures

    import ddp.run_jobs
    from ddp.suite import runner

    started, given = [], []

    class Pool:  # the spawned process pool, in this process: records each run's threads
        def __init__(self, max_workers, **kw):
            started.append(max_workers)

        def submit(self, fn, run, threads, *rest):
            given.append(threads)
            fut = concurrent.futures.Future()
            fut.set_result({"run": run.run_id})
            return fut

        def shutdown(self, **kw):
            pass

    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", Pool)
    monkeypatch.setattr(ddp.run_jobs, "usable_cores", lambda: 4)
    limit = runner._Limit(None, tmp_path, say=lambda *_: None)
    done = []
    runner._pool_once([_run_stub(tmp_path)] * runs, lambda run, result: done.append(result), None,
                      workers=workers, threads=threads, echo=lambda *_: None, limit=limit, broken=[])
    assert started == [min(workers, runs)] and given == [per] * runs and len(done) == runs
