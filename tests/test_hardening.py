"""Nothing lost, nothing run that nobody trusted: resume checks, the run-dir lock, preemption signals,
leftovers, log trimming, checkpoint plugin trust, strict results.json, shadowed plugin packages."""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import ROOT, runnable
from ddp import build, registry
from ddp.checkpoint import load_checkpoint, save_checkpoint
from ddp.errors import CheckpointError, RecipeError
from ddp.experiment import experiment_from_checkpoint
from ddp.run_dir import RunDirBusy, RunLock


def tiny(tmp_path: Path, **train) -> dict:
    return runnable(train={"output_dir": str(tmp_path / "run"), "epochs": 1000, "checkpoint_every_epochs": 1000,
                           "max_steps": None, **train})


def steps_logged(run: Path) -> list[int]:
    return [int(line.split(",")[0]) for line in (run / "logs" / "scalars" / "loss.csv").read_text().splitlines()]


# ---------------------------------------------------------------- resume
def test_resume_accepts_the_documented_keys_and_refuses_others(tmp_path):
    r = tiny(tmp_path, max_steps=2)
    build(r).train(progress=False)
    # max_steps, eval.* and controller.* may change on resume
    r2 = copy.deepcopy(r)
    r2["train"]["max_steps"] = 4
    r2["eval"]["episodes"] = 3
    res = build(r2).train(progress=False)
    assert res.steps == 4 and load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 4
    stored = yaml.safe_load(load_checkpoint(tmp_path / "run" / "last.pt")["recipe"])
    assert stored["eval"]["episodes"] == 3  # the checkpoint now holds the recipe it continued with
    r3 = copy.deepcopy(r2)
    r3["train"]["lr"] = 0.003
    r3["world_model"]["weight"] = 0.5
    with pytest.raises(CheckpointError, match=r"train.lr: 0.001 -> 0.003.*world_model.weight: 1.0 -> 0.5.*--no-resume"):
        build(r3).train(progress=False)
    assert load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 4  # untouched
    assert build(r3).train(progress=False, resume=False).steps == 4  # --no-resume starts over


def test_one_trainer_per_output_dir(tmp_path):
    r = tiny(tmp_path, max_steps=2)
    with RunLock(tmp_path / "run"):
        with pytest.raises(RunDirBusy, match=rf"another ddp train \(pid {os.getpid()}\) is writing there"):
            build(r).train(progress=False)
    assert build(r).train(progress=False).steps == 2  # released: the next trainer gets it
    with RunLock(tmp_path / "run"):  # and fit() released it too
        pass


def test_leftover_temporary_files_are_removed(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    stale = [run / ".last.pt.abc123.tmp", run / ".last.pt.zz.tmp"]
    for f in stale:
        f.write_bytes(b"half a checkpoint")
    keep = run / "notes.tmp"
    keep.write_text("mine")
    build(tiny(tmp_path, max_steps=2)).train(progress=False)
    assert not any(f.exists() for f in stale) and keep.exists()


def test_csv_logs_do_not_repeat_steps_after_resume(tmp_path):
    r = tiny(tmp_path, max_steps=10)
    build(r).train(progress=False)
    run = tmp_path / "run"
    assert steps_logged(run) == [5, 10]
    # a killed run logged steps 15 and 20 after its last checkpoint (step 10)
    with open(run / "logs" / "scalars" / "loss.csv", "a") as f:
        f.write("15,0.5\n20,0.4\n")
    r["train"]["max_steps"] = 20
    build(r).train(progress=False)
    assert steps_logged(run) == [5, 10, 15, 20]


def test_starting_over_sets_the_earlier_run_aside(tmp_path):
    """--no-resume in a used directory: the earlier checkpoint and logs move to previous/<time>/ (nothing
    deleted; a plain ddp train cannot resume the earlier run if the new one dies before its first checkpoint),
    and the new run's log starts at its own steps."""
    r = tiny(tmp_path, max_steps=10)
    build(r).train(progress=False)
    run = tmp_path / "run"
    with pytest.warns(UserWarning, match="the earlier run's checkpoint and logs moved to"):
        build(r).train(progress=False, resume=False)
    (aside,) = (run / "previous").iterdir()
    assert load_checkpoint(aside / "last.pt")["step"] == 10 and steps_logged(aside) == [5, 10]
    assert steps_logged(run) == [5, 10] and load_checkpoint(run / "last.pt")["step"] == 10
    # a shorter run started over, then resumed: trimming its log past step 5 leaves previous/ as it was
    r["train"]["max_steps"] = 5
    with pytest.warns(UserWarning, match="moved to"):
        build(r).train(progress=False, resume=False)
    build(r).train(progress=False)
    assert steps_logged(run) == [5] and steps_logged(aside) == [5, 10]


def test_a_run_killed_before_its_first_checkpoint_leaves_no_rows_behind(tmp_path):
    r = tiny(tmp_path, max_steps=10)
    run = tmp_path / "run"
    (run / "logs" / "scalars").mkdir(parents=True)
    (run / "logs" / "scalars" / "loss.csv").write_text("5,0.9\n")  # logged, then killed: no last.pt
    build(r).train(progress=False)
    assert steps_logged(run) == [5, 10]


def test_second_ctrl_c_during_the_save_cannot_break_it(tmp_path, monkeypatch):
    import ddp.train as train_mod

    exp = build(tiny(tmp_path, max_steps=50))
    real_loss, real_save = exp.model.loss, train_mod.save_checkpoint
    calls = {"n": 0}

    def loss(batch, generator=None):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt  # the first Ctrl-C, during step 4
        return real_loss(batch, generator=generator)

    def save(path, payload):
        os.kill(os.getpid(), signal.SIGINT)  # the second Ctrl-C, in the middle of the write
        time.sleep(0.05)
        return real_save(path, payload)

    monkeypatch.setattr(exp.model, "loss", loss)
    monkeypatch.setattr(train_mod, "save_checkpoint", save)
    with pytest.raises(KeyboardInterrupt):
        exp.train(progress=False)
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    assert state["step"] == 3  # the save completed, with the steps done before the interrupt
    assert not list((tmp_path / "run").glob(".last.pt.*.tmp"))


def test_preempted_crosses_a_process_boundary():
    """A suite's pool worker sends the run's Preempted back pickled; it must arrive as itself (it broke the pool)."""
    import pickle

    from ddp.preemption import Preempted

    back = pickle.loads(pickle.dumps(Preempted(signal.SIGHUP)))
    assert isinstance(back, Preempted) and back.signum == signal.SIGHUP and str(back) == "stopped by SIGHUP"


def test_a_stop_after_the_last_step_still_writes_the_final_checkpoint(tmp_path, monkeypatch):
    """A SIGTERM that lands after the last optimiser step, before the final save (here while the progress bar
    closes), waits for the save: the run is stopped with every step kept (it exited without a checkpoint)."""
    import ddp.train as train_mod
    from ddp.preemption import Preempted

    real_tqdm = train_mod.tqdm

    class Bar(real_tqdm):
        def close(self):
            if not getattr(self, "_sent", False):  # the bar closes once, after the last step
                self._sent = True
                os.kill(os.getpid(), signal.SIGTERM)
            return super().close()

    monkeypatch.setattr(train_mod, "tqdm", Bar)
    exp = build(tiny(tmp_path, max_steps=10))
    with pytest.raises(Preempted):
        exp.train(progress=False)
    assert load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 10


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_preemption_signal_saves_and_resumes(tmp_path, sig):
    r = tiny(tmp_path, max_steps=100_000, epochs=100_000, checkpoint_every_epochs=100_000, log_every_steps=1)
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump(r))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # a test runner started under nohup passes SIGHUP on ignored, and ddp keeps it ignored: restore it
    proc = subprocess.Popen([sys.executable, "-m", "ddp", "train", str(recipe), "--quiet"], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))
    log = tmp_path / "run" / "logs" / "scalars" / "loss.csv"
    deadline = time.time() + 120
    while time.time() < deadline and not (log.exists() and len(log.read_text().splitlines()) >= 3):
        time.sleep(0.2)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"stopped by {signal.Signals(sig).name}" in lines[0], err
    step = load_checkpoint(tmp_path / "run" / "last.pt")["step"]
    assert step >= 3
    r["train"]["max_steps"] = step + 2
    assert build(r).train(progress=False).steps == step + 2  # resumes where it stopped


# ---------------------------------------------------------------- checkpoints and plugin code
PLUGIN = """
import os
from dataclasses import dataclass
from pathlib import Path

import ddp
from ddp.detectors.never import NeverDetector

Path(os.environ["DDP_TEST_MARKER"]).write_text("imported")


@dataclass
class MarkerConfig:
    pass


@ddp.register("detector", "marker_detector", config=MarkerConfig)
class MarkerDetector(NeverDetector):
    '''never, from a plugin module'''
    def __init__(self, config):
        super().__init__(None)
"""


def test_checkpoint_recipes_import_no_plugin_code_without_trust(tmp_path, monkeypatch):
    (tmp_path / "marker_plugin_mod.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    marker = tmp_path / "imported.txt"
    monkeypatch.setenv("DDP_TEST_MARKER", str(marker))
    r = tiny(tmp_path, max_steps=1)
    exp = build(r)
    exp.train(progress=False)
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    recipe = yaml.safe_load(state["recipe"])
    recipe["plugins"] = ["marker_plugin_mod"]
    save_checkpoint(tmp_path / "sent.pt", {**{k: v for k, v in state.items() if k not in ("format", "version")},
                                           "recipe": yaml.safe_dump(recipe)})
    with pytest.warns(UserWarning, match=r"not importing the plugin modules its recipe lists \(marker_plugin_mod\)"):
        exp2 = experiment_from_checkpoint(tmp_path / "sent.pt")
    assert not marker.exists() and "marker_plugin_mod" not in sys.modules
    assert exp2.plugin_modules == ()
    recipe["controller"]["detector"] = {"name": "marker_detector"}
    save_checkpoint(tmp_path / "needs.pt", {**{k: v for k, v in state.items() if k not in ("format", "version")},
                                            "recipe": yaml.safe_dump(recipe)})
    with pytest.warns(UserWarning), pytest.raises(RecipeError, match="plugin modules were not imported"):
        experiment_from_checkpoint(tmp_path / "needs.pt")
    try:
        exp3 = experiment_from_checkpoint(tmp_path / "needs.pt", trust_plugins=True)
        assert marker.read_text() == "imported" and exp3.plugin_modules == ("marker_plugin_mod",)
    finally:
        registry.unregister("detector", "marker_detector")
        sys.modules.pop("marker_plugin_mod", None)


def test_results_json_is_strict_json(tmp_path):
    r = tiny(tmp_path, max_steps=1)
    exp = build(r)
    exp.train(progress=False)
    report = exp.evaluate(["id"], episodes=1, output_dir=tmp_path / "eval", progress=False)
    assert any(v != v for v in report["protocols"]["id"]["per_episode"][0]["discrepancy"])  # NaN in memory

    def refuse(name):
        raise AssertionError(f"bare {name} in results.json")

    data = json.loads((tmp_path / "eval" / "results.json").read_text(), parse_constant=refuse)
    assert data["protocols"]["id"]["per_episode"][0]["discrepancy"][0] is None


def test_a_folder_shadowing_a_plugin_package_is_named(tmp_path, monkeypatch):
    site, work = tmp_path / "site", tmp_path / "work"
    pkg = site / "shadowed_ddp_plugin"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "detector.py").write_text(textwrap.dedent(PLUGIN).replace("marker_detector", "shadowed_detector"))
    dist = site / "shadowed_ddp_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: shadowed-ddp-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[ddp.plugins]\nshadowed = shadowed_ddp_plugin.detector\n")
    (work / "shadowed_ddp_plugin").mkdir(parents=True)
    (work / "shadowed_ddp_plugin" / "__init__.py").write_text("")  # e.g. a checkout's folder of the same name
    monkeypatch.setenv("DDP_TEST_MARKER", str(tmp_path / "m.txt"))
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.syspath_prepend(str(work))  # `python -m` puts the working directory first
    monkeypatch.chdir(work)
    monkeypatch.setattr(registry, "_entry_points_loaded", False)
    monkeypatch.setattr(registry, "_failed", {})
    try:
        with pytest.warns(UserWarning, match="failed to import"):
            with pytest.raises(RecipeError) as err:
                registry.get("detector", "shadowed_detector")
        assert f"resolves to {work / 'shadowed_ddp_plugin'}" in str(err.value)
        assert "shadows the installed package" in str(err.value) and "\n" not in str(err.value)
    finally:
        for mod in [m for m in sys.modules if m.startswith("shadowed_ddp_plugin")]:
            sys.modules.pop(mod)
        registry.unregister("detector", "shadowed_detector")


def test_a_signal_set_to_be_ignored_stays_ignored():
    """Under nohup SIGHUP is ignored: training must not turn it into a stop."""
    from ddp.preemption import signals_deferred, stop_signals

    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with stop_signals():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL  # SIGTERM is still handled
        with signals_deferred() as received:
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(0.05)
        assert received == []
    finally:
        signal.signal(signal.SIGHUP, previous)


def test_resume_accepts_an_env_that_now_follows_the_task(tmp_path):
    """Older checkpoints stored the env's own num_points default; the env now renders task.num_points."""
    r = tiny(tmp_path, max_steps=2)
    build(r).train(progress=False)
    ckpt = tmp_path / "run" / "last.pt"
    state = load_checkpoint(ckpt)
    stored = yaml.safe_load(state["recipe"])
    stored["env"]["num_points"] = 128  # what an older version resolved for an env section without num_points
    save_checkpoint(ckpt, {**{k: v for k, v in state.items() if k not in ("format", "version")},
                           "recipe": yaml.safe_dump(stored)})
    r["train"]["max_steps"] = 3
    assert build(r).train(progress=False).steps == 3


def test_calibration_ignores_nonfinite_discrepancies(tiny_recipe, monkeypatch):
    import ddp.eval_runner as runner
    from ddp.detectors.discrepancy import DiscrepancyConfig, DiscrepancyDetector

    exp = build(tiny_recipe)

    def episode(values):  # chunk scores -> latent windows whose D_R-I is exactly those values
        pred = np.sqrt(np.asarray(values, dtype=np.float64))[:, None, None] * np.ones((1, 2, 4))
        return {"latent_real": np.zeros_like(pred), "latent_pred": pred, "success": True}

    canned = [episode([float("nan"), 0.1, float("inf"), 0.3]), episode([float("nan"), 0.2])]
    monkeypatch.setattr(runner, "rollout_episodes", lambda *a, **k: canned)
    det = DiscrepancyDetector(DiscrepancyConfig(alpha=0.4))  # 2 episodes: the 2nd smallest maximum
    tau = runner.calibrate_detector(exp, det, episodes=2, seed=0, progress=False)
    assert tau == pytest.approx(0.3)  # the inf chunk is dropped, not the threshold
    assert det.calibration()["reference"][0][2] != det.calibration()["reference"][0][2]  # NaN in the reference