"""Training: the joint loss drops, checkpoints round-trip, resume equals an uninterrupted run."""

import math
import os

import pytest
import torch

from ddp import build
from ddp.checkpoint import load_checkpoint, save_checkpoint
from ddp.errors import CheckpointError
from ddp.experiment import experiment_from_checkpoint


def test_joint_loss_drops_on_a_tiny_dataset(tiny_recipe, tmp_path):
    tiny_recipe["train"].update(epochs=100, max_steps=120, lr=2e-3, warmup_steps=10, log_every_steps=1000)
    exp = build(tiny_recipe)
    history = []
    orig = exp.model.loss

    def recording_loss(batch, generator=None):
        out = orig(batch, generator=generator)
        history.append((out["loss_bc"].item(), out["loss_wm"].item()))
        return out

    exp.model.loss = recording_loss
    exp.train(output_dir=tmp_path, progress=False)
    first = torch.tensor(history[:15]).mean(0)
    last = torch.tensor(history[-15:]).mean(0)
    assert len(history) == 120
    assert last[0] < 0.5 * first[0], (first, last)  # L_BC
    assert last[1] < 0.5 * first[1], (first, last)  # L_WM


def _weights(exp):
    return {k: v.clone() for k, v in exp.model.state_dict().items()}


def test_resume_after_interruption_equals_uninterrupted_run(tiny_recipe, tmp_path):
    full = build(tiny_recipe)
    res = full.train(output_dir=tmp_path / "full", progress=False)
    assert res.epochs == 3 and res.steps > 3
    reference = _weights(full)
    ref_ema = load_checkpoint(tmp_path / "full/last.pt")["ema"]

    interrupted = build(tiny_recipe)
    orig, calls = interrupted.model.loss, {"n": 0}

    def failing_loss(batch, generator=None):
        calls["n"] += 1
        out = orig(batch, generator=generator)  # the step's noise is drawn: the checkpoint must not keep it
        if calls["n"] == res.steps // 2 + 1:
            raise KeyboardInterrupt
        return out

    interrupted.model.loss = failing_loss
    with pytest.raises(KeyboardInterrupt):
        interrupted.train(output_dir=tmp_path / "resumed", progress=False)
    assert load_checkpoint(tmp_path / "resumed/last.pt")["step"] == res.steps // 2

    resumed = build(tiny_recipe)
    res2 = resumed.train(output_dir=tmp_path / "resumed", progress=False)
    assert res2.steps == res.steps
    for k, v in _weights(resumed).items():
        assert torch.equal(v, reference[k]), k
    ema = load_checkpoint(tmp_path / "resumed/last.pt")["ema"]
    assert all(torch.equal(ema[k], ref_ema[k]) for k in ref_ema)
    # the training time adds up over the two calls; a finished run resumed again keeps its record
    first = load_checkpoint(tmp_path / "resumed/last.pt")["train_seconds"]
    assert res2.total_seconds >= first > res2.seconds > 0  # the first call's time is in both
    res3 = build(tiny_recipe).train(output_dir=tmp_path / "resumed", progress=False)
    assert res3.steps == res.steps and res3.total_seconds >= first and res3.loss == pytest.approx(res2.loss)
    # a checkpoint from before the time was recorded: unknown (None), not a wrong number
    state = load_checkpoint(tmp_path / "resumed/last.pt")
    del state["train_seconds"]
    torch.save(state, tmp_path / "resumed/last.pt")
    res4 = build(tiny_recipe).train(output_dir=tmp_path / "resumed", progress=False)
    assert res4.total_seconds is None and load_checkpoint(tmp_path / "resumed/last.pt")["train_seconds"] is None


def test_a_resumed_run_logs_the_same_rows_as_an_uninterrupted_one(tiny_recipe, tmp_path):
    """Killed between two log lines, after an epoch's checkpoint: the steps since the last row were lost from
    the window (the resumed run's first row averaged fewer steps). The checkpoint keeps the window's sums."""
    tiny_recipe["train"].update(log_every_steps=1000, checkpoint_every_epochs=1)  # one row: the last step's
    full = build(tiny_recipe)
    res = full.train(output_dir=tmp_path / "full", progress=False)
    per_epoch = res.steps // res.epochs
    interrupted = build(tiny_recipe)
    orig, calls = interrupted.model.loss, {"n": 0}

    def failing_loss(batch, generator=None):
        calls["n"] += 1
        if calls["n"] == per_epoch + 1:  # after the first epoch's checkpoint, before any row
            raise KeyboardInterrupt
        return orig(batch, generator=generator)

    interrupted.model.loss = failing_loss
    with pytest.raises(KeyboardInterrupt):
        interrupted.train(output_dir=tmp_path / "resumed", progress=False)
    assert load_checkpoint(tmp_path / "resumed/last.pt")["log_window"]["count"] == per_epoch
    build(tiny_recipe).train(output_dir=tmp_path / "resumed", progress=False)
    rows = {name: (tmp_path / name / "logs" / "scalars" / "loss.csv").read_text().strip().splitlines()
            for name in ("full", "resumed")}
    assert rows["resumed"] == rows["full"] and len(rows["full"]) == 1, rows  # the mean over every step


@pytest.mark.parametrize("where", ["sigterm_after_the_noise_draws", "interrupt_during_the_ema_update"])
def test_an_interruption_inside_a_step_never_checkpoints_half_a_step(where, tiny_recipe, tmp_path):
    """A scheduler's SIGTERM lands wherever the step is, mostly in its forward / backward: training stops at
    the next step boundary, so the checkpoint holds weights, optimiser, EMA, noise streams and step counter
    of one and the same step, and the resumed run equals the uninterrupted one. An interruption raised in
    the middle of the update itself (a second Ctrl-C) saves nothing: the last checkpoint stands."""
    import signal

    from ddp.models.ema import EMA
    from ddp.preemption import Preempted

    full = build(tiny_recipe)
    res = full.train(output_dir=tmp_path / "full", progress=False)
    reference = _weights(full)
    stop_at = res.steps // 2 + 1  # the call (= step) in which the interruption lands

    interrupted = build(tiny_recipe)
    calls = {"n": 0}
    if where == "sigterm_after_the_noise_draws":
        orig = interrupted.model.loss

        def loss(batch, generator=None):
            out = orig(batch, generator=generator)  # the step's noise is drawn
            calls["n"] += 1
            if calls["n"] == stop_at:
                os.kill(os.getpid(), signal.SIGTERM)
            return out

        interrupted.model.loss = loss
        with pytest.raises(Preempted):
            interrupted.train(output_dir=tmp_path / "resumed", progress=False)
        assert load_checkpoint(tmp_path / "resumed/last.pt")["step"] == stop_at  # the step finished first
    else:
        orig_update = EMA.update

        def update(self, model):
            calls["n"] += 1
            if calls["n"] == stop_at:  # the optimiser has stepped, the counters have not
                raise KeyboardInterrupt
            return orig_update(self, model)

        EMA.update = update
        try:
            with pytest.raises(KeyboardInterrupt), pytest.warns(RuntimeWarning, match="not saved"):
                interrupted.train(output_dir=tmp_path / "resumed", progress=False)
        finally:
            EMA.update = orig_update
        assert load_checkpoint(tmp_path / "resumed/last.pt")["step"] < stop_at  # an epoch's checkpoint stands

    resumed = build(tiny_recipe)
    assert resumed.train(output_dir=tmp_path / "resumed", progress=False).steps == res.steps
    for k, v in _weights(resumed).items():
        assert torch.equal(v, reference[k]), k


def test_a_signal_while_the_loop_s_handlers_are_installed_stops_at_the_first_boundary(tiny_recipe, tmp_path,
                                                                                       monkeypatch):
    """A SIGTERM landing after the save's deferring handlers are set but before the loop's are was recorded and
    raised only once the whole run had ended (a scheduler's preemption ignored until its SIGKILL)."""
    import contextlib
    import signal

    import ddp.train as train_module
    from ddp.preemption import Preempted

    real = train_module.stop_requests

    @contextlib.contextmanager
    def late(requested):
        os.kill(os.getpid(), signal.SIGTERM)  # lands in the deferring handler, before the loop's own
        with real(requested) as r:
            yield r

    monkeypatch.setattr(train_module, "stop_requests", late)
    e = build(tiny_recipe)
    with pytest.raises(Preempted):
        e.train(output_dir=tmp_path / "run", progress=False)
    state = load_checkpoint(tmp_path / "run/last.pt")
    assert state["step"] <= 1  # stopped at the first step boundary, not after the whole run


def test_the_final_checkpoint_is_not_written_twice(tiny_recipe, tmp_path, monkeypatch):
    """A last epoch that is a checkpoint epoch wrote last.pt, then the end of the run wrote it again."""
    import ddp.train as train_module

    writes, real = [], train_module.save_checkpoint
    monkeypatch.setattr(train_module, "save_checkpoint", lambda path, payload: writes.append(payload["step"]) or
                        real(path, payload))
    tiny_recipe["train"].update(epochs=2, checkpoint_every_epochs=1, log_every_steps=1, max_steps=None)
    res = build(tiny_recipe).train(output_dir=tmp_path / "a", progress=False)
    assert writes == [res.steps // 2, res.steps]
    writes.clear()  # steps logged since the last checkpoint: the final one writes them
    tiny_recipe["train"].update(epochs=3, checkpoint_every_epochs=2, log_every_steps=1000)
    res = build(tiny_recipe).train(output_dir=tmp_path / "b", progress=False)
    assert writes == [2 * res.steps // 3, res.steps]


@pytest.mark.parametrize("when", ["during_the_save", "before_the_step_ends"])
def test_a_sigterm_after_ctrl_c_exits_as_preempted(when, tiny_recipe, tmp_path, monkeypatch):
    """Ctrl-C, then the scheduler's SIGTERM (while the save runs, or before the step the Ctrl-C landed in
    ends): the job exited as interrupted (130), not preempted (143), so a requeue-on-preemption policy
    dropped it. The checkpoint is written either way."""
    import signal

    import ddp.train as train_module
    from ddp.preemption import Preempted

    real = train_module.save_checkpoint

    def save(path, payload):
        os.kill(os.getpid(), signal.SIGTERM)  # deferred until the write is done
        return real(path, payload)

    # a test runner started in the background (nohup, CI) inherits SIGINT ignored, and training keeps an
    # ignored signal ignored: give it Python's own handler, as an interactive shell does
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    exp = build(tiny_recipe)
    orig, calls = exp.model.loss, {"n": 0}

    def loss(batch, generator=None):
        calls["n"] += 1
        if calls["n"] == 3 and when == "during_the_save":
            monkeypatch.setattr(train_module, "save_checkpoint", save)
            raise KeyboardInterrupt  # Ctrl-C in the forward pass, before the update
        if calls["n"] == 3:  # both recorded by the loop's handler, acted on at the step's end
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGTERM)
        return orig(batch, generator=generator)

    exp.model.loss = loss
    try:
        with pytest.raises(Preempted) as stopped:
            try:
                exp.train(output_dir=tmp_path / "run", progress=False)
            except Preempted:
                raise
            except KeyboardInterrupt as err:  # (not let through: it would stop pytest itself)
                raise AssertionError("the run exited as interrupted, not preempted") from err
    finally:
        signal.signal(signal.SIGINT, previous)
    assert stopped.value.signum == signal.SIGTERM and isinstance(stopped.value.__cause__, KeyboardInterrupt)
    assert load_checkpoint(tmp_path / "run/last.pt")["step"] == (2 if when == "during_the_save" else 3)


def test_checkpoint_round_trip_gives_identical_outputs(tiny_recipe, tmp_path):
    exp = build(tiny_recipe)
    exp.train(output_dir=tmp_path, progress=False)
    exp.load_checkpoint(tmp_path / "last.pt")  # EMA weights
    again = experiment_from_checkpoint(tmp_path / "last.pt")
    assert again.to_yaml() == exp.to_yaml()
    hist = torch.randn(2, 2, exp.model.latent_dim)
    a = exp.model.eval().sample_actions(hist, generator=torch.Generator().manual_seed(0))
    b = again.model.eval().sample_actions(hist, generator=torch.Generator().manual_seed(0))
    assert torch.equal(a, b)
    acts = torch.randn(2, 8, 4)
    assert torch.equal(
        exp.model.imagine(hist, acts, generator=torch.Generator().manual_seed(1)),
        again.model.imagine(hist, acts, generator=torch.Generator().manual_seed(1)),
    )
    raw = experiment_from_checkpoint(tmp_path / "last.pt", ema=False)
    assert not torch.equal(raw.model.sample_actions(hist, generator=torch.Generator().manual_seed(0)), a)


def test_truncated_and_foreign_files_are_refused(tmp_path):
    good = save_checkpoint(tmp_path / "good.pt", {"model": {"w": torch.ones(1000)}, "step": 1})
    assert load_checkpoint(good)["step"] == 1
    blob = good.read_bytes()
    (tmp_path / "trunc.pt").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(CheckpointError, match="trunc.pt: not a readable checkpoint"):
        load_checkpoint(tmp_path / "trunc.pt")
    (tmp_path / "text.pt").write_text("hello")
    with pytest.raises(CheckpointError, match="text.pt: not a readable checkpoint"):
        load_checkpoint(tmp_path / "text.pt")
    torch.save({"weights": torch.ones(2)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="foreign.pt: not a ddp checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")
    torch.save({"format": "ddp-checkpoint", "version": 1, "obj": torch.nn.Linear(1, 1)}, tmp_path / "pickled.pt")
    with pytest.raises(CheckpointError, match="pickled.pt: refused to load"):
        load_checkpoint(tmp_path / "pickled.pt")
    with pytest.raises(CheckpointError, match="missing.pt: checkpoint not found"):
        load_checkpoint(tmp_path / "missing.pt")


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch):
    path = save_checkpoint(tmp_path / "c.pt", {"step": 1})

    def broken_save(obj, f, *a, **k):
        f.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(CheckpointError, match=r"c\.pt: cannot write the checkpoint: disk full$"):
        save_checkpoint(path, {"step": 2})
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 1
    assert os.listdir(tmp_path) == ["c.pt"]
    # the file is fsynced before the rename and its folder after it (the rename is durable)
    synced, real_fsync = [], os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.path.isdir(f"/proc/self/fd/{fd}")), real_fsync(fd)))
    save_checkpoint(path, {"step": 3})
    assert synced == [False, True] and load_checkpoint(path)["step"] == 3


def test_a_refused_checkpoint_write_is_one_line_and_training_says_so(tiny_recipe, tmp_path, monkeypatch):
    """Disk full, a file where the folder should be, torch's zip writer failing: one line naming the file
    (they were tracebacks: OSError / FileExistsError / RuntimeError)."""
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("x")
    with pytest.raises(CheckpointError, match=r"not_a_folder/last\.pt: cannot write the checkpoint: File exists"):
        save_checkpoint(blocker / "last.pt", {"step": 1})

    def zip_writer_fails(obj, f, *a, **k):
        raise RuntimeError("[enforce fail at inline_container.cc:595] . PytorchStreamWriter failed writing file "
                           "data/0: file write failed\nmore")

    monkeypatch.setattr(torch, "save", zip_writer_fails)
    with pytest.raises(CheckpointError, match=r"cannot write the checkpoint: .*file write failed$"):
        save_checkpoint(tmp_path / "c.pt", {"step": 1})
    monkeypatch.setattr(torch, "save", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("unrelated")))
    with pytest.raises(RuntimeError, match="unrelated"):  # not every RuntimeError is a failed write
        save_checkpoint(tmp_path / "c.pt", {"step": 1})
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["not_a_folder"]  # no temporary file left behind

    def disk_full(obj, f, *a, **k):
        raise OSError(28, "No space left on device")

    tiny_recipe["train"].update(max_steps=2, epochs=100)
    exp = build(tiny_recipe)
    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(CheckpointError, match=r"last\.pt: cannot write the checkpoint: No space left on device$"):
        exp.train(output_dir=tmp_path / "run", progress=False)


def test_atomic_files_get_the_mode_an_open_would_give(tmp_path):
    """mkstemp makes its temp file 0600; a checkpoint, calibration or suite result must not stay unreadable
    to the group (a shared results folder) where the umask allows it."""
    old = os.umask(0o022)
    try:
        path = save_checkpoint(tmp_path / "c.pt", {"step": 1})
        assert os.stat(path).st_mode & 0o777 == 0o644
        os.umask(0o077)
        path = save_checkpoint(tmp_path / "d.pt", {"step": 1})
        assert os.stat(path).st_mode & 0o777 == 0o600
    finally:
        os.umask(old)


def test_weights_of_another_recipe_are_refused(tiny_recipe, tmp_path):
    exp = build(tiny_recipe)
    exp.train(output_dir=tmp_path, progress=False)
    tiny_recipe["policy"]["denoiser"]["down_dims"] = [8, 16]
    other = build(tiny_recipe)
    with pytest.raises(CheckpointError, match="weights do not fit this recipe's model"):
        other.load_checkpoint(tmp_path / "last.pt")


def test_training_logs_through_torchrl_csv_logger(tiny_recipe, tmp_path):
    tiny_recipe["train"].update(epochs=1, log_every_steps=1)
    exp = build(tiny_recipe)
    res = exp.train(output_dir=tmp_path, progress=False)
    rows = (tmp_path / "logs" / "scalars" / "loss.csv").read_text().strip().splitlines()
    assert len(rows) == res.steps and rows[-1].startswith(f"{res.steps},")
    assert (tmp_path / "logs" / "scalars" / "lr.csv").exists()


def test_bf16_autocast_option_trains(tiny_recipe, tmp_path):
    tiny_recipe["train"].update(epochs=1, autocast_bf16=True, logger="none")
    res = build(tiny_recipe).train(output_dir=tmp_path, progress=False)
    assert res.steps > 0 and math.isfinite(res.loss)
    assert not (tmp_path / "logs").exists()


def test_scheduler_check_reads_only_what_the_weights_learned(tiny_recipe, tmp_path, monkeypatch):
    """The trained-settings check (a checkpoint under another prediction_type loaded and acted wrongly) skips a
    disabled world model's scheduler (DP3, FlowPolicy), a flow's training-only options, and a stored recipe it
    cannot read; atomic directories survive a filesystem that refuses fsync."""
    import copy
    import errno
    import os

    import ddp.atomic_file
    from ddp import build
    from ddp.recipe import dump_yaml

    def changes(recipe, edit):
        exp = build(recipe)
        stored = copy.deepcopy(exp.resolved)
        edit(stored)
        return exp._scheduler_changes("ck.pt", {"recipe": dump_yaml(stored)})

    def prediction(section, value):
        return lambda r: r[section]["scheduler"].update(prediction_type=value)

    assert list(changes(copy.deepcopy(tiny_recipe), prediction("policy", "epsilon"))) == [
        "policy.scheduler.prediction_type"]
    assert list(changes(copy.deepcopy(tiny_recipe), prediction("world_model", "epsilon"))) == [
        "world_model.scheduler.prediction_type"]
    no_wm = copy.deepcopy(tiny_recipe)
    no_wm["world_model"]["enabled"] = False
    assert changes(no_wm, prediction("world_model", "epsilon")) == {}  # no world-model weights to misread
    flow = copy.deepcopy(tiny_recipe)
    flow["policy"]["scheduler"] = {"name": "consistency_flow"}
    assert changes(flow, lambda r: r["policy"]["scheduler"].update(num_segments=3, delta=0.02)) == {}
    assert list(changes(flow, lambda r: r["policy"]["scheduler"].update(time_scale=50.0))) == [
        "policy.scheduler.time_scale"]
    assert build(tiny_recipe)._scheduler_changes("ck.pt", {"recipe": "a: [unclosed"}) == {}

    def refusing(fd):
        raise OSError(errno.EINVAL, "fsync not supported")

    monkeypatch.setattr(ddp.atomic_file.os, "fsync", refusing)
    written = ddp.atomic_file.atomic_directory(tmp_path / "d", lambda tmp: (tmp / "f").write_text("x"))
    assert (written / "f").read_text() == "x" and os.listdir(tmp_path) == ["d"]


def test_weights_trained_on_another_task_load_with_a_warning(tiny_recipe, tmp_path):
    """A drawer-open checkpoint loaded into a recipe of another env or task (the weights fit) loaded silently:
    `ddp eval <recipe> --checkpoint <wrong run>` filed one task's policy under another's results."""
    import warnings

    import yaml

    from ddp.checkpoint import load_checkpoint

    exp = build(tiny_recipe)
    exp.train(output_dir=tmp_path, progress=False)
    state = load_checkpoint(tmp_path / "last.pt")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same task: no warning
        build(tiny_recipe).load_checkpoint(tmp_path / "last.pt", state=state)
    stored = yaml.safe_load(state["recipe"])
    stored["env"] = {**stored["env"], "name": "metaworld", "task": "drawer-open"}
    state["recipe"] = yaml.safe_dump(stored)
    with pytest.warns(UserWarning, match=r"trained on another environment or task than this recipe's \(env.name: "
                                         r"'metaworld' -> 'synthetic_reach'; env.task: 'drawer-open' -> None\)"):
        build(tiny_recipe).load_checkpoint(tmp_path / "last.pt", state=state)
