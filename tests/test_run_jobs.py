"""``ddp run --jobs N``: recipes side by side in child processes, one table, stoppable like ``ddp run``."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from conftest import ROOT, runnable

from ddp.checkpoint import load_checkpoint
from ddp.cli import main
from ddp.errors import DDPError
from ddp.run_jobs import plan_jobs, threads_per_job


def _recipes(tmp_path: Path, **train) -> tuple[str, str]:
    """A DDP recipe and its DP3 ablation, training into tmp_path/runs/<name>."""
    ddp = runnable(train={"output_dir": str(tmp_path / "runs" / "{name}"), **train},
                   eval={"episodes": 1, "protocols": ["id"], "max_steps": 16,
                         "output_dir": str(tmp_path / "runs" / "{name}" / "eval")})
    dp3 = {**ddp, "name": "tiny_dp3", "world_model": {"enabled": False}}
    paths = []
    for recipe in (ddp, dp3):
        path = tmp_path / f"{recipe['name']}.yaml"
        path.write_text(yaml.safe_dump(recipe))
        paths.append(str(path))
    return paths[0], paths[1]


@pytest.fixture
def child_path(monkeypatch):
    """The children run `python -m ddp` from this checkout."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


def test_jobs_run_side_by_side_and_print_one_table(tmp_path, capsys, child_path):
    a, b = _recipes(tmp_path)
    assert main(["run", a, b, "--jobs", "2", "--quiet"]) == 0
    out = capsys.readouterr().out.splitlines()
    starts = [i for i, line in enumerate(out) if line.startswith("started ")]
    ends = [i for i, line in enumerate(out) if line.startswith("finished ")]
    assert len(starts) == 2 and len(ends) == 2 and max(starts) < min(ends)  # both ran at once
    assert "[tiny] trained 2 steps" in "\n".join(out) and "[tiny_dp3] trained 2 steps" in "\n".join(out)
    for name in ("tiny", "tiny_dp3"):
        ident = json.loads((tmp_path / "runs" / name / "eval" / "results.json").read_text())["protocols"]["id"]
        row = f"| {name} | {100 * ident['success_rate']:.0f} ({ident['successes']}/1) |"
        assert row in out  # the table comes from what each job's evaluation wrote
        assert (tmp_path / "runs" / name / "last.pt").is_file()
        assert "trained 2 steps" in (tmp_path / "runs" / name / "run.log").read_text()
    rows = [line.split(" | ")[0] for line in out if line.startswith("| tiny")]
    assert rows == ["| tiny", "| tiny_dp3"]  # the recipes' order, whichever finished first


def test_each_job_gets_its_share_of_the_cores(tmp_path):
    a, b = _recipes(tmp_path)
    assert threads_per_job(2, cores=16) == 8 and threads_per_job(3, cores=2) == 1
    # the cores this process may use (a Slurm / cgroup job's affinity), not the node's
    import os
    from unittest import mock

    with mock.patch.object(os, "sched_getaffinity", return_value={3, 5, 6, 7}), \
            mock.patch.object(os, "cpu_count", return_value=128):
        assert threads_per_job(2) == 2
    jobs = plan_jobs([a, b], ["train.lr=0.002"], threads=3, episodes=4, no_resume=True)
    for job in jobs:
        sets = [job.argv[i + 1] for i, arg in enumerate(job.argv) if arg == "--set"]
        assert sets == ["train.lr=0.002", "train.num_threads=3"]
        assert job.argv[job.argv.index("--episodes") + 1] == "4" and "--no-resume" in job.argv
        assert "--quiet" not in job.argv  # its log keeps the progress bars
    assert all("--quiet" in j.argv for j in plan_jobs([a, b], [], threads=1, quiet=True))
    jobs = plan_jobs([a, b], ["train.num_threads=5"], threads=3)  # the user's own setting wins
    assert [a for a in jobs[0].argv if a.startswith("train.num_threads")] == ["train.num_threads=5"]
    assert [j.log for j in jobs] == [tmp_path / "runs" / "tiny" / "run.log", tmp_path / "runs" / "tiny_dp3" / "run.log"]


def test_recipes_sharing_a_folder_are_refused(tmp_path, capsys):
    a, b = _recipes(tmp_path)
    with pytest.raises(DDPError, match="trains into .*runs/tiny, as .*tiny.yaml does"):
        plan_jobs([a, a], [], threads=1)
    with pytest.raises(DDPError, match="tiny_dp3.yaml: writes its evaluation to .*shared, as .*tiny.yaml does"):
        plan_jobs([a, b], [f"eval.output_dir={tmp_path / 'shared'}"], threads=1)
    assert main(["run", a, a, "--jobs", "2"]) == 2
    assert "trains into" in capsys.readouterr().err
    assert main(["run", a, a, "--jobs", "0"]) == 2
    assert "--jobs: must be >= 1" in capsys.readouterr().err


def test_a_failed_job_leaves_the_others_table_and_exits_1(tmp_path, capsys, child_path):
    a, b = _recipes(tmp_path)
    bad = yaml.safe_load(Path(b).read_text())
    bad["eval"]["device"] = "cuda:99"  # fails in the child, after training
    Path(b).write_text(yaml.safe_dump(bad))
    assert main(["run", a, b, "--jobs", "2", "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "| tiny | " in captured.out and "| tiny_dp3 |" not in captured.out
    assert "1 job(s) failed: tiny_dp3 (exit 2: ddp: error:" in captured.err
    assert "failed tiny_dp3 after" in captured.out


def _wait_training(tmp_path: Path, *names: str) -> None:
    """Until each named job has logged a training loss (it is past its start-up, in the trainer's hands)."""
    files = [tmp_path / "runs" / n / "logs" / "scalars" / "loss.csv" for n in names]
    deadline = time.monotonic() + 180
    while not all(f.is_file() for f in files):
        assert time.monotonic() < deadline, f"no training loss logged in 180 s: {files}"
        time.sleep(0.2)


def test_a_stopped_run_passes_sigterm_on_and_the_jobs_save(tmp_path, child_path):
    a, b = _recipes(tmp_path, max_steps=100_000, epochs=100_000, checkpoint_every_epochs=100_000)
    proc = subprocess.Popen([sys.executable, "-m", "ddp", "run", a, b, "--jobs", "2", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=os.environ)
    try:
        _wait_training(tmp_path, "tiny", "tiny_dp3")
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:  # never leave 100k-step trainings behind on a CI machine
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, out
    assert "tiny stopped (exit 143" in out and "tiny_dp3 stopped (exit 143" in out
    for name in ("tiny", "tiny_dp3"):  # each wrote its checkpoint where it was stopped
        step = load_checkpoint(tmp_path / "runs" / name / "last.pt")["step"]
        assert 0 < step < 100_000


def test_an_error_here_stops_the_jobs_in_progress(tmp_path, monkeypatch, child_path):
    import ddp.run_jobs as run_jobs_module

    long, short = _recipes(tmp_path, max_steps=100_000, epochs=100_000, checkpoint_every_epochs=100_000)
    quick = yaml.safe_load(Path(short).read_text())
    quick["train"].update(max_steps=2, epochs=1)
    Path(short).write_text(yaml.safe_dump(quick))

    def broken(job, *args):  # something goes wrong here once the short job is done
        _wait_training(tmp_path, "tiny")
        raise RuntimeError("broken")

    monkeypatch.setattr(run_jobs_module, "_finish", broken)
    jobs = plan_jobs([long, short], [], threads=1, quiet=True)
    with pytest.raises(RuntimeError, match="broken"):
        run_jobs_module.run_jobs(jobs, parallel=2, threads=1, echo=lambda line: None)
    assert jobs[0].proc.returncode == 128 + signal.SIGTERM  # stopped like a preempted run, not orphaned
    assert 0 < load_checkpoint(tmp_path / "runs" / "tiny" / "last.pt")["step"] < 100_000


def _saving_job(tmp_path: Path, name: str, save_seconds: float, code: int, argv_extra=()) -> "Job":
    """A stand-in for `ddp run`: on SIGTERM it 'saves' for ``save_seconds``, then exits with ``code``."""
    from ddp.run_jobs import Job

    script = (f"import signal, sys, time\n"
              f"signal.signal(signal.SIGTERM, lambda s, f: (time.sleep({save_seconds}), sys.exit({code})))\n"
              f"open({str(tmp_path / (name + '.ready'))!r}, 'w').close()\n"
              f"time.sleep(120)\n")
    return Job(name, [sys.executable, "-c", script, *argv_extra], tmp_path / name / "run.log",
               tmp_path / name / "results.json")


def _kill_left(jobs) -> None:
    """Kill the stand-in jobs a failed test left running."""
    for j in jobs:
        if j.proc is not None and j.proc.poll() is None:
            j.proc.kill()
            j.proc.wait()


def _stop_once_all_ready(tmp_path: Path, jobs, hung_up: list):
    """An echo that sends this process SIGTERM once every job is up, and from then on writes to a terminal
    that has hung up (OSError EIO), as after an ssh session closed."""
    import errno

    def echo(line: str) -> None:
        if hung_up:
            raise OSError(errno.EIO, "Input/output error")
        if line.startswith("started") and all(j.proc is not None for j in jobs):
            deadline = time.monotonic() + 30
            while not all((tmp_path / f"{j.name}.ready").exists() for j in jobs) and time.monotonic() < deadline:
                time.sleep(0.05)
            hung_up.append(True)
            os.kill(os.getpid(), signal.SIGTERM)

    return echo


def test_a_hung_up_terminal_does_not_cut_the_stop_short(tmp_path):
    """The terminal hangs up (SIGHUP): echoing the first job's stop raised EIO and left the loop, so the second
    job, still saving, was never waited for (nor killed at the grace limit): it outlived its parent."""
    from ddp.preemption import Preempted
    from ddp.run_jobs import run_jobs

    jobs = [_saving_job(tmp_path, "quick", 0.1, 143), _saving_job(tmp_path, "slow", 1.5, 143)]
    try:
        with pytest.raises(Preempted):
            run_jobs(jobs, parallel=2, threads=1, echo=_stop_once_all_ready(tmp_path, jobs, []))
        assert [j.proc.returncode for j in jobs] == [143, 143]  # both saved and were waited for
    finally:
        _kill_left(jobs)


def test_a_job_failing_while_it_stops_is_reported_failed_and_no_resume_is_named(tmp_path):
    """A job whose save failed while stopping (exit 2: a checkpoint write refused) read "stopped", and the
    closing line told a --no-resume run that the same command resumes (it would set the checkpoints aside)."""
    from ddp.preemption import Preempted
    from ddp.run_jobs import run_jobs

    jobs = [_saving_job(tmp_path, "saves", 0.1, 143, ["--no-resume"]), _saving_job(tmp_path, "breaks", 0.1, 2)]
    lines: list[str] = []
    stop = _stop_once_all_ready(tmp_path, jobs, [])

    def echo(line: str) -> None:
        lines.append(line)
        stop(line) if not any("stopped" in ln or "failed" in ln for ln in lines) else None

    try:
        with pytest.raises(Preempted):
            run_jobs(jobs, parallel=2, threads=1, echo=echo)
    finally:
        _kill_left(jobs)
    text = "\n".join(lines)
    assert "saves stopped (exit 143" in text and "breaks failed while stopping (exit 2" in text, text
    assert lines[-1].endswith("; failed: breaks (see above) (rerun without --no-resume to resume)"), text


def test_a_job_killed_after_the_grace_time_is_reported_failed(tmp_path, monkeypatch):
    """A job that did not save within the grace time was killed (SIGKILL: its save cut short) and reported as
    "stopped (exit -9)", like one that saved; the closing line did not name it."""
    import ddp.run_jobs as run_jobs_module
    from ddp.preemption import Preempted

    monkeypatch.setattr(run_jobs_module, "STOP_GRACE_SECONDS", 0.5)
    jobs = [_saving_job(tmp_path, "saves", 0.1, 143), _saving_job(tmp_path, "hangs", 60, 143)]
    lines: list[str] = []
    stop = _stop_once_all_ready(tmp_path, jobs, [])

    def echo(line: str) -> None:
        lines.append(line)
        stop(line) if line.startswith("started") else None  # (the folder's name has "killed" in it)

    try:
        with pytest.raises(Preempted):
            run_jobs_module.run_jobs(jobs, parallel=2, threads=1, echo=echo)
    finally:
        _kill_left(jobs)
    text = "\n".join(lines)
    assert "saves stopped (exit 143" in text and "hangs did not stop within 0.5 s: killed" in text, text
    assert "hangs stopped" not in text and lines[-1].endswith("; failed: hangs (see above) (the same command resumes)"), text


def test_a_stopped_no_resume_run_says_how_to_resume(monkeypatch, capsys):
    """`ddp train R --no-resume`, preempted, said "the same command resumes": rerun as told, it set the
    checkpoint it had just saved aside and started from step 0."""
    import ddp.cli as cli
    from ddp.preemption import Preempted

    def preempted(args):
        raise Preempted(signal.SIGTERM)

    monkeypatch.setattr(cli, "cmd_train", preempted)
    recipe = str(ROOT / "recipes" / "quickstart.yaml")
    for flags, expected in (([], "the same command resumes training"),
                            (["--no-resume"], "rerun without --no-resume to resume training")):
        assert cli.main(["train", recipe, *flags]) == 128 + signal.SIGTERM
        assert expected in capsys.readouterr().err

    def interrupted(args):  # Ctrl-C: the case a person reads
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "cmd_train", interrupted)
    for flags, expected in (([], "the same command resumes)"), (["--no-resume"], "rerun without --no-resume to resume)")):
        assert cli.main(["train", recipe, *flags]) == 130
        assert expected in capsys.readouterr().err
