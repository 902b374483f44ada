"""Multi-process training under torchrun (torch DistributedDataParallel, gloo on the CPU)."""

from __future__ import annotations

import copy
import os
import subprocess
import sys

import pytest
import torch
import yaml

from conftest import ROOT, TINY
from ddp import build
from ddp.checkpoint import load_checkpoint


def _recipe(tmp_path) -> str:
    r = copy.deepcopy(TINY)
    r["train"].update(batch_size=16, micro_batches=2, max_steps=3, epochs=100, log_every_steps=1,
                      checkpoint_every_epochs=100)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(r))
    return str(path)


def _torchrun(recipe: str, out, *extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "ddp", "train", recipe, "--set", f"train.output_dir={out}", "--set", "train.num_threads=1",
           "--quiet", *extra]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


def _same_weights(a, b) -> None:
    for part in ("model", "ema"):
        wa, wb = load_checkpoint(a)[part], load_checkpoint(b)[part]
        assert wa.keys() == wb.keys()
        for k in wa:
            torch.testing.assert_close(wa[k], wb[k], rtol=1e-5, atol=1e-6, msg=f"{part}.{k}")


def test_two_processes_train_the_weights_of_one_and_resume_across_world_sizes(tmp_path):
    recipe = _recipe(tmp_path)
    one, two = tmp_path / "one", tmp_path / "two"
    torch.set_num_threads(1)
    build(recipe, [f"train.output_dir={one}"]).train(progress=False)
    done = _torchrun(recipe, two)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("2 processes (torch DistributedDataParallel): trained 3 steps") == 1  # rank 0 only
    _same_weights(one / "last.pt", two / "last.pt")
    # rank 0 alone wrote: one checkpoint, one log row per step, no temporary files
    assert sorted(p.name for p in two.iterdir()) == [".lock", "last.pt", "logs"]  # .lock: the run lock
    rows = (two / "logs" / "scalars" / "loss.csv").read_text().strip().splitlines()
    assert [r.split(",")[0] for r in rows] == ["1", "2", "3"]
    assert len(load_checkpoint(two / "last.pt")["noise_rng"]) == 2  # one stream per micro-batch, both saved
    # each run resumes in the other world size and the two still agree
    build(recipe, [f"train.output_dir={two}", "train.max_steps=5"]).train(progress=False)
    done = _torchrun(recipe, one, "--set", "train.max_steps=5")
    assert done.returncode == 0, done.stderr[-3000:]
    _same_weights(one / "last.pt", two / "last.pt")
    assert load_checkpoint(one / "last.pt")["step"] == 5


def test_micro_batches_must_fit_the_batch_and_the_processes(tmp_path):
    from ddp.errors import RecipeError

    with pytest.raises(RecipeError, match="micro_batches must be >= 1 and divide batch_size"):
        build(_recipe(tmp_path), ["train.micro_batches=3"])
    os.environ.update(WORLD_SIZE="3", RANK="0", LOCAL_RANK="0")
    try:
        from ddp.distributed import env_ranks

        assert env_ranks().mine(6) == [0, 3] and env_ranks().world == 3
    finally:
        for k in ("WORLD_SIZE", "RANK", "LOCAL_RANK"):
            os.environ.pop(k)


def _rank_pid(parent: int, rank: int) -> int | None:
    """The pid of the torchrun worker with ``RANK=rank``: a child of ``parent`` (read from /proc)."""
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/environ", "rb") as f:
                env = f.read().split(b"\0")
        except OSError:
            continue
        if ppid == parent and f"RANK={rank}".encode() in env:
            return int(entry)
    return None


def test_a_sigterm_to_one_rank_stops_every_rank_at_the_same_step_with_a_checkpoint(tmp_path):
    """A stop signal reaching one worker only (not all at the same instant, as a scheduler's do) must not hang
    the others in a collective: the ranks agree at the next step boundary, rank 0 writes the checkpoint of
    that step, every rank exits."""
    import signal
    import time

    r = copy.deepcopy(TINY)
    r["train"].update(batch_size=16, micro_batches=2, max_steps=100000, epochs=100000, log_every_steps=1,
                      checkpoint_every_epochs=100000)
    recipe = tmp_path / "long.yaml"
    recipe.write_text(yaml.safe_dump(r))
    out = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "ddp", "train", str(recipe), "--set", f"train.output_dir={out}", "--set", "train.num_threads=1",
           "--quiet"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own process group: nothing outlives a failure
    try:
        log = out / "logs" / "scalars" / "loss.csv"
        deadline = time.monotonic() + 300
        while not (log.is_file() and len(log.read_text().splitlines()) >= 3):  # training is under way
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-3000:]
            time.sleep(0.2)
        pid = _rank_pid(proc.pid, 1)
        assert pid is not None
        os.kill(pid, signal.SIGTERM)
        proc.wait(timeout=120)  # before: rank 1 left mid-step for the save's collectives, rank 0 hung
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the workers too, if they hung
        except ProcessLookupError:
            pass
        proc.wait()
    state = load_checkpoint(out / "last.pt")
    assert 3 <= state["step"] < 100000 and len(state["noise_rng"]) == 2
    rows = log.read_text().strip().splitlines()
    assert int(rows[-1].split(",")[0]) == state["step"]  # the last logged step is the saved one


def _torchrun_with_rank_0_patch(tmp_path, patch: str, timeout: int = 300) -> tuple[int, str]:
    """Train the tiny recipe on two ranks, ``patch`` (Python source) run at start-up on rank 0 only (a
    sitecustomize); returns (exit code, stderr). A run past ``timeout`` is killed with its ranks: a failure."""
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text("import os\nif os.environ.get('RANK') == '0':\n"
                                           + "".join(f"    {line}\n" for line in patch.splitlines()))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl",
           "PYTHONPATH": os.pathsep.join([str(hook), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "ddp", "train", _recipe(tmp_path), "--set", f"train.output_dir={tmp_path / 'run'}",
           "--set", "train.num_threads=1", "--quiet"]
    run = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           start_new_session=True)
    try:
        _, stderr = run.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, 9)  # torchrun and both ranks
        run.communicate()
        pytest.fail("a rank kept waiting for rank 0")
    return run.returncode, stderr


def test_a_checkpoint_write_that_fails_on_rank_0_stops_every_rank_with_one_line(tmp_path):
    """Rank 0 writes, the others wait for it: a refused write (here: disk full on rank 0's checkpoint) must
    end every rank with a one-line error, not leave them in the next collective."""
    code, stderr = _torchrun_with_rank_0_patch(tmp_path, "import ddp.checkpoint as c\n"
                                                         "def _full(path, write, **kw):\n"
                                                         "    raise OSError(28, 'No space left on device')\n"
                                                         "c.atomic_write = _full")
    out = tmp_path / "run"
    assert code != 0
    assert "ddp: error: " + str(out / "last.pt") + ": cannot write the checkpoint: No space left on device" in stderr
    assert "rank 0 could not write the checkpoint (its error says why); rank 1 stops too" in stderr
    # no traceback through ddp's code on either rank (torchrun prints its own summary of the failure)
    assert f'{os.sep}ddp{os.sep}train.py", line' not in stderr, stderr[-3000:]
    assert not (out / "last.pt").exists()


def test_an_error_building_rank_0s_checkpoint_stops_every_rank(tmp_path):
    """The checkpoint's contents (state dicts copied to the CPU, where a CUDA fault surfaces) were gathered
    before the guarded write: an error there left the other ranks waiting for rank 0's word (torchrun tore
    them down without it; a launcher that only sets RANK / WORLD_SIZE left them until the process group timed
    out)."""
    code, stderr = _torchrun_with_rank_0_patch(tmp_path, "import ddp.models.ema as e\n"
                                                         "def _fault(self, *a, **k):\n"
                                                         "    raise RuntimeError('CUDA error: an illegal memory access')\n"
                                                         "e.EMA.state_dict = _fault", timeout=180)
    assert code != 0 and "illegal memory access" in stderr
    assert "rank 0 could not write the checkpoint (its error says why); rank 1 stops too" in stderr
    assert not (tmp_path / "run" / "last.pt").exists()


def test_a_busy_output_folder_stops_every_rank_with_one_line(tmp_path):
    """Only rank 0 takes the folder's lock: when another ddp train held it, rank 0 said so in one line and
    rank 1, waiting in the barrier, died with a gloo traceback (on NCCL it would hang until torchrun's
    timeout). Every rank now ends with its own line, and nothing of the other run's is touched."""
    from ddp.run_dir import RunLock

    out = tmp_path / "run"
    with RunLock(out):
        done = _torchrun(_recipe(tmp_path), out)
    assert done.returncode != 0
    assert f"ddp: error: {out}: another ddp train (pid {os.getpid()}) is writing there" in done.stderr
    assert "ddp: error: rank 0 could not lock its output folder (its error says why); rank 1 stops too" in done.stderr
    # no traceback through ddp's code on either rank (torchrun prints its own summary of the failure)
    assert f'{os.sep}ddp{os.sep}train.py", line' not in done.stderr, done.stderr[-3000:]
    assert not (out / "last.pt").exists()


def test_ranks_that_would_resume_from_different_steps_are_refused(tmp_path):
    """Each rank reads last.pt itself: where train.output_dir is not shared (one folder per node), some
    ranks would resume and others start afresh, and their collectives would go out of step."""
    from ddp.distributed import Ranks
    from ddp.errors import CheckpointError
    from ddp.train import same_start

    class TwoRanks(Ranks):
        def __init__(self, starts):
            super().__init__(rank=0, world=2)
            self.starts = starts

        def gather(self, obj):
            assert obj == self.starts[0]  # this rank's own position is what it contributes
            return self.starts

    same_start(TwoRanks([(5, 1, 2), (5, 1, 2)]), (5, 1, 2), tmp_path)  # agreed: nothing to say
    same_start(Ranks(), (7, 0, 7), tmp_path)  # one process: nothing to compare
    with pytest.raises(CheckpointError, match=r"different \(step, epoch, batch\): \[\(5, 1, 2\), \(0, 0, 0\)\].*"
                                              "one folder all ranks share"):
        same_start(TwoRanks([(5, 1, 2), (0, 0, 0)]), (5, 1, 2), tmp_path)


def test_micro_batches_of_a_dataset_smaller_than_the_batch_train_every_window(tmp_path, monkeypatch):
    """With fewer windows than batch_size, an epoch's one batch holds them all; it was cut into micro-batches of
    len // micro_batches windows each, so the remainder went untrained every epoch (8 of 15 with 8 parts)."""
    from ddp.data.sequence import SequenceDataset

    r = copy.deepcopy(TINY)
    r["data"]["episodes"] = 1
    r["train"].update(batch_size=256, micro_batches=8, max_steps=1, epochs=1, output_dir=str(tmp_path / "run"))
    exp = build(r)
    seen = []
    batch = SequenceDataset.batch
    monkeypatch.setattr(SequenceDataset, "batch", lambda self, part: seen.extend(part.tolist()) or batch(self, part))
    torch.set_num_threads(1)
    exp.train(progress=False)
    assert len(seen) > 8 and len(seen) % 8 and sorted(seen) == list(range(len(seen)))  # every window once


def test_a_stop_signal_between_the_loops_handlers_and_the_final_saves_still_saves(tmp_path, monkeypatch):
    """The loop's signal handlers are undone before the final save installs its own: a SIGTERM in between
    raised Preempted before the last checkpoint was written (the run's work since its last one was lost)."""
    import signal
    import sys

    import ddp.train as train_mod
    from ddp.preemption import Preempted

    real = train_mod.signals_deferred

    def deferred(received=None):
        if received is not None and received is sys._getframe(1).f_locals.get("requested"):  # the final save's
            os.kill(os.getpid(), signal.SIGTERM)  # arrives before its handlers are set
        return real(received)

    monkeypatch.setattr(train_mod, "signals_deferred", deferred)
    r = copy.deepcopy(TINY)
    r["train"].update(max_steps=2, epochs=100, checkpoint_every_epochs=100, output_dir=str(tmp_path / "run"))
    torch.set_num_threads(1)
    with pytest.raises(Preempted):
        build(r).train(progress=False)
    assert load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 2


def test_uneven_micro_batches_across_ranks_log_the_single_process_losses(tmp_path):
    """A dataset smaller than batch_size splits into micro-batches one window apart, so two ranks hold different
    numbers of windows: the weights and the logged losses must still be the one-process run's (the ranks'
    losses were averaged equally: 1.83805 against 1.83750)."""
    r = copy.deepcopy(TINY)
    r["data"]["episodes"] = 1
    r["train"].update(batch_size=256, micro_batches=8, max_steps=2, epochs=100, log_every_steps=1,
                      checkpoint_every_epochs=100)
    recipe = tmp_path / "tiny.yaml"
    recipe.write_text(yaml.safe_dump(r))
    torch.set_num_threads(1)
    build(str(recipe), [f"train.output_dir={tmp_path / 'one'}"]).train(progress=False)
    done = _torchrun(str(recipe), tmp_path / "two")
    assert done.returncode == 0, done.stderr[-3000:]
    _same_weights(tmp_path / "one" / "last.pt", tmp_path / "two" / "last.pt")
    one, two = (load_checkpoint(tmp_path / d / "last.pt")["losses"] for d in ("one", "two"))
    assert one.keys() == two.keys()
    for k in one:
        assert two[k] == pytest.approx(one[k], rel=1e-5), k
