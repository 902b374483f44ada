"""``ddp suite``: expansion, the resumable store, the executors, the aggregation."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import pytest
import torch
import yaml

from conftest import ROOT, TINY
from ddp.errors import RecipeError
from ddp.suite import ResultStore, aggregate, load_suite, run_suite, select, write_suite_report
from ddp.suite.report import wilson


def test_expansion(suite_file):
    suite = load_suite(suite_file)
    assert [r.run_id for r in suite.runs] == [  # seed-major: every task and method once before repeats
        f"{t}__{m}__seed{s}" for s in (0, 1) for t in ("near", "far") for m in ("ddp", "dp3")
    ]
    run = suite.runs[0]
    assert run.recipe["name"] == "tiny_suite_near_ddp_s0" and run.recipe["seed"] == 0
    assert run.recipe["train"]["output_dir"] == "runs/suites/tiny_suite/near__ddp__seed0"
    assert run.recipe["train"]["lr"] == 0.002 and run.protocols == ("id", "ood_base")
    dp3 = next(r for r in suite.runs if r.method == "dp3")
    assert dp3.recipe["world_model"]["enabled"] is False and dp3.protocols == ("id", "ood_tracking")
    assert dp3.recipe["world_model"]["denoiser"] == TINY["world_model"]["denoiser"]  # merged, the base ignored
    far = next(r for r in suite.runs if r.task == "far")
    assert far.recipe["env"]["displacement_delta"] == [0.3, 0, 0] and far.benchmark == "synthetic"
    assert run.benchmark == "tiny_suite"
    assert len({r.recipe_hash for r in suite.runs}) == len(suite.runs)


def test_how_a_run_is_evaluated_is_not_part_of_its_hash(suite_file):
    run = load_suite(suite_file).runs[0]

    def variant(**eval_settings):
        recipe = copy.deepcopy(run.recipe)
        recipe["eval"].update(eval_settings)
        return type(run)(**{**run.__dict__, "recipe": recipe})

    assert variant(num_envs=10, parallel=True, video=True, device="cpu").recipe_hash == run.recipe_hash
    assert variant(max_steps=8).recipe_hash != run.recipe_hash  # what is measured
    assert variant(calibration_episodes=60).recipe_hash != run.recipe_hash
    # the recipe's own protocol list and episode count, where the suite sets them, are not what runs
    assert run.protocols is not None and run.episodes is None  # the fixture's suite sets protocols only
    assert variant(protocols=["id"]).recipe_hash == run.recipe_hash
    assert variant(episodes=3).recipe_hash != run.recipe_hash  # the recipe's episode count is what runs
    fixed = type(run)(**{**run.__dict__, "episodes": 5})  # a suite that sets episodes: 5
    assert type(run)(**{**fixed.__dict__, "recipe": variant(episodes=3).recipe}).recipe_hash == fixed.recipe_hash
    # how often training checkpoints and logs
    trained = copy.deepcopy(run.recipe)
    trained["train"].update(checkpoint_every_epochs=1, log_every_steps=1, logger="none")
    assert type(run)(**{**run.__dict__, "recipe": trained}).recipe_hash == run.recipe_hash


def test_an_env_option_written_at_its_neutral_default_is_the_same_run(suite_file):
    """recipes/metaworld/quickstart_ddp.yaml spells out pause_fingers: false; the CPU suites' stored runs of it
    (hashed without the key) stay done. Any other value, or an option without a neutral default, is another run."""
    pytest.importorskip("metaworld")
    run = load_suite(suite_file).runs[0]

    def with_env(**env):
        recipe = copy.deepcopy(run.recipe)
        recipe["env"] = {"name": "metaworld", "task": "push", **env}
        return type(run)(**{**run.__dict__, "recipe": recipe})

    base = with_env()
    assert with_env(pause_fingers=False).recipe_hash == base.recipe_hash
    assert with_env(visible_sites=[]).recipe_hash == base.recipe_hash
    assert with_env(pause_fingers=True).recipe_hash != base.recipe_hash
    assert with_env(visible_sites=["goal"]).recipe_hash != base.recipe_hash
    assert with_env(num_points=512).recipe_hash != base.recipe_hash  # no neutral default: written is another run
    assert with_env(pause_fingers=False).legacy_hash != base.legacy_hash  # version 1 stays what it was


def test_results_stored_under_the_first_hash_are_kept_and_restamped(suite_file, tmp_path):
    """Results stored before hash version 2 (every committed suite result) stay done, and are restamped, so a
    later change of a setting the hash now leaves out does not make them stale."""
    suite = load_suite(suite_file)
    run = suite.runs[0]
    store = ResultStore(tmp_path)
    store.save(run, {"task": run.task, "protocols": {}})
    old = json.loads(store.path(run).read_text())
    store.path(run).write_text(json.dumps({**old, "recipe_hash": run.legacy_hash}))
    assert run.legacy_hash != run.recipe_hash
    assert store.status(run) == "done" and store.load(run)["recipe_hash"] == run.recipe_hash
    assert json.loads(store.path(run).read_text())["recipe_hash"] == run.recipe_hash  # restamped on disk
    store.path(run).write_text(json.dumps({**old, "recipe_hash": run.legacy_hash}))
    reader = ResultStore(tmp_path, restamp=False)  # ddp suite --dry-run: reads, writes nothing
    assert reader.status(run) == "done"
    assert json.loads(store.path(run).read_text())["recipe_hash"] == run.legacy_hash
    store.load(run)
    recipe = copy.deepcopy(run.recipe)
    recipe["eval"]["protocols"] = ["id"]  # overridden by the suite's protocols
    recipe["train"]["log_every_steps"] = 1
    assert store.status(type(run)(**{**run.__dict__, "recipe": recipe})) == "done"
    recipe["train"]["lr"] = 1.0  # what is measured
    assert store.status(type(run)(**{**run.__dict__, "recipe": recipe})) == "stale"


def test_select_runs_a_part_and_names_the_closest_label(suite_file):
    suite = load_suite(suite_file)
    part = select(suite, methods=["dp3"], seeds=[1])
    assert [r.run_id for r in part.runs] == ["near__dp3__seed1", "far__dp3__seed1"]
    assert [r.run_id for r in select(suite, tasks=["far"]).runs] == [
        "far__ddp__seed0", "far__dp3__seed0", "far__ddp__seed1", "far__dp3__seed1"]
    assert select(suite).runs == suite.runs
    with pytest.raises(RecipeError, match="'dp' is not in the suite; did you mean 'dp3'"):
        select(suite, methods=["dp"])
    with pytest.raises(RecipeError, match="seeds.*7 is not in the suite"):
        select(suite, seeds=[7])


def test_task_protocols_keep_those_a_task_supports(suite_file):
    data = yaml.safe_load(suite_file.read_text())
    data["tasks"]["far"]["protocols"] = ["id"]
    suite_file.write_text(yaml.safe_dump(data, sort_keys=False))
    suite = load_suite(suite_file)
    assert {r.protocols for r in suite.runs if r.task == "far"} == {("id",)}
    assert {r.protocols for r in suite.runs if r.task == "near" and r.method == "ddp"} == {("id", "ood_base")}


@pytest.mark.parametrize("edit, message", [
    ({"taks": {}}, "unknown key 'taks'; did you mean 'tasks'"),
    ({"seeds": [0, 0]}, "repeats a seed"),
    ({"seeds": "0"}, "non-empty list of integers"),
    ({"protocols": ["id", "odd"]}, "unknown protocol 'odd'"),
    ({"set": ["train.lrr=1"]}, "train.lrr"),
    ({"methods": {"x": {"overlay": "missing.yaml"}}}, "overlay file not found"),
    ({"output_dir": "/scratch"}, "unknown key 'output_dir'; did you mean 'results_dir'"),  # run folders are fixed
    # labels name <task>__<method>__seed<k> files: 'a__b' x 'c' and 'a' x 'b__c' would share one
    ({"methods": {"b__c": {}}}, r"methods.b__c.*without '__'"),
    ({"methods": {"_dp3": {}}}, r"methods._dp3.*or an '_' at either end"),  # 'x_' x 'dp3' = 'x' x '_dp3'
    ({"tasks": {"near_": "tiny.yaml"}}, r"tasks.near_.*or an '_' at either end"),
    ({"results_dir": 5}, r"results_dir: must be a folder path, got 5"),
    ({"tasks": {"near/x": "tiny.yaml"}}, r"tasks.near/x.*letters, digits"),
    ({"methods": {"dp3,ddp": {}}}, r"methods.dp3,ddp.*letters, digits"),
    # protocols the run would refuse after training: named twice, or DDP's on a model without a world model
    ({"methods": {"dp3": {"overlay": "dp3.yaml", "protocols": ["id", "ood_ddp_oracle"]}}},
     r"methods.dp3.protocols: protocol ood_ddp_oracle is DDP's"),
    ({"methods": {"ddp": {"protocols": ["id", "ood_base", "id"]}}}, r"methods.ddp.protocols: protocol id is named twice"),
])
def test_bad_suite_files_are_one_line(suite_file, edit, message):
    data = yaml.safe_load(suite_file.read_text())
    data.update(edit)
    suite_file.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(RecipeError, match=message) as err:
        load_suite(suite_file)
    assert "\n" not in str(err.value)


def test_dry_run_says_which_runs_are_stored_stale_or_resume(suite_file, capsys):
    from ddp.cli import main

    suite = load_suite(suite_file)
    done, stale, resumed = suite.runs[:3]
    store = ResultStore(suite.results_dir)
    store.save(done, {**_result(done.task, done.method, done.seed, {"id": 1.0}), "train": {"seconds": 600.0},
                      "wall_seconds": 650.0})
    store.save(stale, _result(stale.task, stale.method, stale.seed, {"id": 1.0}))
    data = json.loads(store.path(stale).read_text())
    store.path(stale).write_text(json.dumps({**data, "recipe_hash": "0" * 16}))  # made for another recipe
    out = suite_file.parent / resumed.recipe["train"]["output_dir"]
    out.mkdir(parents=True)
    (out / "last.pt").write_bytes(b"")
    assert main(["suite", str(suite_file), "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"{done.run_id}: done;")
    assert lines[1].startswith(f"{stale.run_id}: stale (its recipe changed: runs again);")
    assert lines[2].startswith(f"{resumed.run_id}: to run, resumes {resumed.recipe['train']['output_dir']}/last.pt;")
    assert lines[3].startswith(f"{suite.runs[3].run_id}: to run;")
    assert lines[3].endswith("; expected unknown (no stored dp3 run)")  # what a time limit would go by
    assert lines[4].endswith("; expected 11 min (median of 1 stored near ddp run)")
    assert lines[-1].startswith("8 runs: 1 done, 7 to run (1 stale, 1 resuming a checkpoint, 0 setting one aside)")
    assert lines[-1].endswith("; expected 32 min one after another (4 run(s) without an estimate: no stored run of "
                              "their method)")
    assert not (suite_file.parent / "runs/suites/tiny_suite/near__ddp__seed0/log.txt").exists()  # nothing ran


def test_the_report_labels_stored_runs_as_the_suite_file_does_now(suite_file, capsys):
    """A task moved to another benchmark in the suite file is averaged there, not under the label its stored
    results were written with (the benchmark is no part of a run's identity: they stay done)."""
    from ddp.cli import main

    suite = load_suite(suite_file)
    store = ResultStore(suite.results_dir)
    for run in suite.runs:
        store.save(run, _result(run.task, run.method, run.seed, {"id": 1.0}, bench=run.benchmark))
    data = yaml.safe_load(suite_file.read_text())
    data["tasks"]["far"]["benchmark"] = "tiny_suite"  # was synthetic
    suite_file.write_text(yaml.safe_dump(data, sort_keys=False))
    assert main(["suite", str(suite_file), "--report"]) == 0
    table = json.loads((suite.results_dir / "table.json").read_text())
    assert table["benchmarks"] == {"tiny_suite": ["near", "far"]}


def _same_weights(dir_a: str, dir_b: str) -> None:
    """Two runs' checkpoints hold the same trained (and EMA) weights: the success rates of 2-step models on
    one short episode are 0 whatever ran, so they alone could not tell executors apart."""
    from ddp.checkpoint import load_checkpoint

    a, b = load_checkpoint(Path(dir_a) / "last.pt"), load_checkpoint(Path(dir_b) / "last.pt")
    for part in ("model", "ema"):
        assert a[part].keys() == b[part].keys()
        for k in a[part]:
            torch.testing.assert_close(a[part][k], b[part][k], rtol=1e-6, atol=1e-7, msg=f"{dir_b}: {part}.{k}")


def test_runs_resume_and_executors_agree(suite_file, monkeypatch):
    import ddp.suite.runner as runner

    suite = load_suite(suite_file)
    calls = []
    real = runner.execute_run
    monkeypatch.setattr(runner, "execute_run", lambda run, threads=None, **kw: calls.append(run.run_id) or real(run, 1, **kw))
    done = run_suite(suite, progress=False, echo=lambda *_: None)
    assert sorted(done) == sorted(r.run_id for r in suite.runs) and len(calls) == 8
    store = ResultStore(suite.results_dir)
    first = store.load(suite.runs[0])
    assert first["protocols"]["id"]["episodes"] == 1 and first["train"]["steps"] == 2
    # what to check out to redo it (the tests run in a git checkout of the package)
    assert first["code"]["ddp"] and len(first["code"]["commit"]) == 40
    assert (suite_file.parent / "runs/suites/tiny_suite/near__ddp__seed0/log.txt").read_text().count("finished") == 1

    # a finished run is not run again; a missing, half-written or stale result is
    calls.clear()
    store.path(suite.runs[1]).unlink()
    store.path(suite.runs[2]).write_text(store.path(suite.runs[2]).read_text()[:40])
    stale = json.loads(store.path(suite.runs[3]).read_text())
    stale["recipe_hash"] = "0" * 16
    store.path(suite.runs[3]).write_text(json.dumps(stale))
    run_suite(suite, progress=False, echo=lambda *_: None)
    assert calls == [suite.runs[i].run_id for i in (1, 2, 3)]

    # a process pool gives the same results as the sequential run
    monkeypatch.setattr(runner, "execute_run", real)
    seq = ResultStore(suite.results_dir).all(suite.runs)
    suite.results_dir = suite.results_dir.parent / "pool"
    for r in suite.runs:  # fresh run dirs: nothing to resume
        r.recipe["train"]["output_dir"] += "_pool"
        r.recipe["eval"]["output_dir"] += "_pool"
    pooled = run_suite(suite, workers=2, threads=1, progress=False, echo=lambda *_: None)
    for i, run in enumerate(suite.runs):
        a, b = seq[run.run_id], pooled[run.run_id]
        # runs 1-3 resumed a finished training above: they report the loss and time the checkpoint recorded
        assert a["train"]["loss"] == pytest.approx(b["train"]["loss"], rel=1e-6), run.run_id
        assert a["train"]["steps"] == 2 and a["train"]["seconds"] > 0
        assert {p: v["success_rate"] for p, v in a["protocols"].items()} == \
            {p: v["success_rate"] for p, v in b["protocols"].items()}
        _same_weights(run.recipe["train"]["output_dir"].removesuffix("_pool"), run.recipe["train"]["output_dir"])

    # and so does a local Ray (one CPU per run), on the first task
    pytest.importorskip("ray")
    ray_suite = copy.deepcopy(suite)
    ray_suite.runs = [r for r in ray_suite.runs if r.task == "near"]
    ray_suite.results_dir = suite.results_dir.parent / "ray"
    for r in ray_suite.runs:
        r.recipe["train"]["output_dir"] = r.recipe["train"]["output_dir"].replace("_pool", "_ray")
        r.recipe["eval"]["output_dir"] = r.recipe["eval"]["output_dir"].replace("_pool", "_ray")
    on_ray = run_suite(ray_suite, ray=True, threads=1, progress=False, echo=lambda *_: None)
    for run in ray_suite.runs:
        a, b = pooled[run.run_id], on_ray[run.run_id]
        assert a["train"]["loss"] == pytest.approx(b["train"]["loss"], rel=1e-6), run.run_id
        _same_weights(run.recipe["train"]["output_dir"].replace("_ray", "_pool"), run.recipe["train"]["output_dir"])
        assert {p: v["success_rate"] for p, v in a["protocols"].items()} == \
            {p: v["success_rate"] for p, v in b["protocols"].items()}


def test_a_checkpoint_for_another_recipe_is_set_aside_and_the_run_trains_afresh(suite_file, capsys):
    """The suite file changed what a run trains on: its old folder moves to <name>.superseded-<time> (nothing
    is deleted) and the run starts over; a change that only evaluates differently still resumes; nothing
    moves while another process holds the folder's run lock."""
    from ddp.checkpoint import load_checkpoint
    from ddp.cli import main
    from ddp.recipe import load_yaml
    from ddp.run_dir import RunLock
    from ddp.suite import execute_run
    from ddp.suite.superseded import set_aside_if_superseded, superseded

    run = select(load_suite(suite_file), tasks=["near"], methods=["dp3"], seeds=[0]).runs[0]
    run_dir = suite_file.parent / run.recipe["train"]["output_dir"]
    execute_run(run, threads=1)

    def variant(**sections):
        recipe = copy.deepcopy(run.recipe)
        for section, values in sections.items():
            recipe[section].update(values)
        return type(run)(**{**run.__dict__, "recipe": recipe})

    # how it is evaluated: the checkpoint resumes
    for kept in (variant(eval={"episodes": 2}), variant(controller={"safe_lift": 0.05})):
        assert superseded(run_dir, kept.recipe) is None
    execute_run(variant(eval={"episodes": 2}), threads=1)
    assert not list(run_dir.parent.glob("*.superseded-*")) and "cannot continue" not in (run_dir / "log.txt").read_text()
    # another step budget, higher or lower: the schedule would change mid-run, not the recipe's run
    for steps in (1, 3):
        assert superseded(run_dir, variant(train={"max_steps": steps}).recipe) == \
            f"train.max_steps: 2 -> {steps} (another step budget)"

    # what it trains: the checkpoint cannot continue it
    changed = variant(train={"lr": 0.003})
    data = yaml.safe_load(suite_file.read_text())
    data["set"] = ["train.lr=0.003"]
    suite_file.write_text(yaml.safe_dump(data, sort_keys=False))
    assert main(["suite", str(suite_file), "--dry-run", "--tasks", "near", "--methods", "dp3", "--seeds", "0"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"{run.run_id}: to run, trains from scratch (its last.pt cannot continue this recipe: "
                             "train.lr: 0.002 -> 0.003; the folder will be set aside);")
    assert out[-1].startswith("1 runs: 0 done, 1 to run (0 stale, 0 resuming a checkpoint, 1 setting one aside)")

    with RunLock(run_dir):  # another process trains there: nothing moves
        assert set_aside_if_superseded(run_dir, changed.recipe) is None
    assert not list(run_dir.parent.glob("*.superseded-*"))

    first = (run_dir / "last.pt").read_bytes()
    result = execute_run(changed, threads=1)
    old = list(run_dir.parent.glob(f"{run_dir.name}.superseded-*"))
    assert len(old) == 1 and (old[0] / "last.pt").read_bytes() == first  # kept, untouched
    assert load_yaml(load_checkpoint(run_dir / "last.pt")["recipe"])["train"]["lr"] == 0.003  # trained afresh
    assert result["train"]["steps"] == 2
    log = (run_dir / "log.txt").read_text()
    assert "cannot continue this recipe (train.lr: 0.002 -> 0.003)" in log and log.count("started") == 1


def test_reevaluate_updates_the_named_protocols_of_stale_runs_from_their_checkpoints(suite_file, capsys):
    """A change in how runs are evaluated: --reevaluate re-runs only the named protocols from each stale run's
    checkpoint, keeps the others, records what was redone, and refuses a run it cannot bring up to date."""
    from ddp.cli import main
    from ddp.errors import DDPError

    def part():
        return select(load_suite(suite_file), tasks=["near"], methods=["ddp"], seeds=[0])

    def edit(*settings):
        data = yaml.safe_load(suite_file.read_text())
        data["set"] = ["train.lr=0.002", *settings]
        suite_file.write_text(yaml.safe_dump(data, sort_keys=False))

    def stored(run):
        return {k: v for k, v in store._complete(run).items() if k not in ("format", "complete", "recipe_hash")}

    run_suite(part(), progress=False, echo=lambda *_: None)
    store = ResultStore(part().results_dir)
    before = store.load(part().runs[0])
    before["protocols"]["ood_base"]["seconds"] = 1234.5  # a marker: a kept protocol keeps its stored values
    store.save(part().runs[0], {k: v for k, v in before.items() if k not in ("format", "complete", "recipe_hash")})

    edit("controller.safe_lift=0.01")  # evaluated differently: the result is stale
    run = part().runs[0]
    assert store.status(run) == "stale"
    dry = ["suite", str(suite_file), "--dry-run", "--tasks", "near", "--methods", "ddp", "--seeds", "0"]
    assert main([*dry, "--reevaluate", " id"]) == 0
    assert capsys.readouterr().out.startswith(f"{run.run_id}: stale, re-evaluates id from ")
    for bad, message in (("idd", "unknown protocol 'idd'; did you mean 'id'"), (",", "at least one protocol")):
        assert main([*dry, "--reevaluate", bad]) == 2
        assert message in capsys.readouterr().err
    with pytest.raises(DDPError, match="near__ddp__seed0 does not evaluate ood_ddp"):
        run_suite(part(), progress=False, echo=lambda *_: None, reevaluate=["ood_ddp"])

    run_suite(part(), progress=False, echo=lambda *_: None, reevaluate=["id"])
    after = store.load(run)
    assert after is not None and after["recipe_hash"] == run.recipe_hash  # stored under the current recipe
    assert after["protocols"]["ood_base"] == before["protocols"]["ood_base"]  # kept as stored
    assert after["protocols"]["id"]["seconds"] != before["protocols"]["id"]["seconds"]  # evaluated again
    record = after["reevaluated"][-1]
    assert record["protocols"] == ["id"] and "controller.safe_lift" in record["changed_since_training"]
    assert record["previous"] == {"id": before["protocols"]["id"]["success_rate"]}
    assert after["train"] == before["train"]
    log = (suite_file.parent / run.recipe["train"]["output_dir"] / "log.txt").read_text()
    assert log.count("re-evaluating id") == 1 and log.count("started") == 1  # trained once

    edit("controller.safe_lift=0.02")  # a second change: the history grows
    run_suite(part(), progress=False, echo=lambda *_: None, reevaluate=["id", "ood_base"])
    assert [r["protocols"] for r in store.load(part().runs[0])["reevaluated"]] == [["id"], ["id", "ood_base"]]

    result = stored(part().runs[0])  # as if the result came from an earlier checkpoint of this run
    store.save(part().runs[0], {**result, "train": {**result["train"], "steps": 1}})
    edit("controller.safe_lift=0.03")
    with pytest.raises(DDPError, match="at step 2, its stored result at 1: not the model the result came from"):
        run_suite(part(), progress=False, echo=lambda *_: None, reevaluate=["id"])
    for settings, message in ((["train.lr=0.003"], "cannot serve this recipe .train.lr: 0.002 -> 0.003"),
                              (["train.lr=0.002", "train.max_steps=3"], "cannot serve this recipe .train.max_steps changed")):
        data = yaml.safe_load(suite_file.read_text())
        data["set"] = settings
        suite_file.write_text(yaml.safe_dump(data, sort_keys=False))
        with pytest.raises(DDPError, match=message):
            run_suite(part(), progress=False, echo=lambda *_: None, reevaluate=["id"])


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_run_is_reported_and_the_others_finish(suite_file, workers):
    """One run's checkpoint is corrupt: its traceback goes to its log.txt, the suite prints one line,
    finishes the other run and raises SuiteRunsFailed naming the failed one."""
    from ddp.suite import SuiteRunsFailed

    suite = select(load_suite(suite_file), tasks=["near"], methods=["dp3"])
    bad = suite.runs[1]
    run_dir = suite_file.parent / bad.recipe["train"]["output_dir"]
    run_dir.mkdir(parents=True)
    (run_dir / "last.pt").write_bytes(b"not a checkpoint")
    lines = []
    with pytest.raises(SuiteRunsFailed, match=f"1 run.s. failed: {bad.run_id}") as failed:
        run_suite(suite, workers=workers, threads=1, progress=False, echo=lines.append)
    assert list(failed.value.done) == [suite.runs[0].run_id] and list(failed.value.failed) == [bad.run_id]
    assert any(line.startswith(f"failed {bad.run_id}:") for line in lines)
    log = (run_dir / "log.txt").read_text()
    assert "Traceback" in log and log.rstrip().endswith(f"== {bad.run_id} failed")
    assert ResultStore(suite.results_dir).load(suite.runs[0]) is not None


def test_a_stopped_pool_saves_its_runs_and_starts_no_queued_one(suite_file):
    """SIGTERM to `ddp suite --workers 2` alone (as `kill PID` sends): the two runs in training save their
    checkpoints, the queued third never starts, and no worker outlives the suite."""
    import contextlib
    import os
    import signal
    import subprocess
    import sys
    import time

    spec = yaml.safe_load(suite_file.read_text())
    spec["set"] = ["train.lr=0.002", "train.max_steps=100000", "train.epochs=100000"]
    spec["methods"] = {"dp3": spec["methods"]["dp3"]}
    spec["seeds"] = [0, 1]  # near and far: four runs for two workers
    suite_file.write_text(yaml.safe_dump(spec, sort_keys=False))
    runs = [suite_file.parent / "runs/suites/tiny_suite" / f"{t}__dp3__seed{k}" for k in (0, 1) for t in ("near", "far")]
    proc = subprocess.Popen([sys.executable, "-m", "ddp", "suite", str(suite_file), "--workers", "2", "--threads", "1",
                             "--quiet"], cwd=suite_file.parent, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    children: list[str] = []
    try:
        deadline = time.time() + 120
        while not all((r / "logs").exists() for r in runs[:2]) and time.time() < deadline:
            time.sleep(0.5)  # the first two runs are training (their loggers exist)
        assert time.time() < deadline, proc.stdout.read().decode()[-2000:] if proc.poll() is not None else "no start"
        time.sleep(3)
        children = subprocess.run(["pgrep", "-P", str(proc.pid), "-f", "spawn_main"], capture_output=True,
                                  text=True).stdout.split()
        assert len(children) == 2  # the two workers
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=120)[0].decode()
    finally:
        if proc.poll() is None:
            proc.kill()
            for c in children:  # whatever failed, leave no worker behind
                with contextlib.suppress(OSError):
                    os.kill(int(c), signal.SIGKILL)
    assert proc.returncode == 128 + signal.SIGTERM, out[-2000:]
    assert "Traceback" not in out, out[-3000:]  # a clean stop: one line, no thread dying in the pool
    assert all((r / "last.pt").exists() for r in runs[:2]), out[-2000:]
    assert not any((r / "log.txt").exists() for r in runs[2:]), out[-2000:]  # queued: never started
    for _ in range(20):  # workers exit before the suite does; allow for the kernel's bookkeeping
        alive = [c for c in children if os.path.exists(f"/proc/{c}")]
        if not alive:
            break
        time.sleep(0.5)
    assert not alive, f"workers outlived the suite: {alive}"


def _result(task, method, seed, rates, bench="mw", episodes=10):
    return {"task": task, "method": method, "seed": seed, "benchmark": bench,
            "protocols": {p: {"success_rate": r, "successes": round(r * episodes), "episodes": episodes}
                          for p, r in rates.items()}}


def test_aggregation_math(tmp_path):
    results = [
        _result("a", "ddp", 0, {"id": 1.0, "ood": 0.8}), _result("a", "ddp", 1, {"id": 0.9, "ood": 0.6}),
        _result("b", "ddp", 0, {"id": 0.5, "ood": 0.2}), _result("b", "ddp", 1, {"id": 0.7, "ood": 0.4}),
        _result("c", "ddp", 0, {"id": 0.3}, bench="other"),
    ]
    table = aggregate(results)
    assert table["rows"] == [("ddp", "id"), ("ddp", "ood")]
    assert table["benchmarks"] == {"mw": ["a", "b"], "other": ["c"]}
    cell = table["cells"]["ddp|id|a"]
    assert cell["mean"] == pytest.approx(0.95) and cell["std"] == pytest.approx(math.sqrt(0.005))
    assert cell["episodes"] == 20 and cell["successes"] == 19
    avg = table["cells"]["ddp|ood|avg:mw"]
    assert avg["mean"] == pytest.approx(0.5) and avg["per_seed"] == pytest.approx([0.5, 0.5]) and avg["std"] == 0
    one = table["cells"]["ddp|id|c"]
    assert "std" not in one and one["wilson95"] == pytest.approx(list(wilson(3, 10)))
    lo, hi = wilson(3, 10)
    assert lo == pytest.approx(0.1078, abs=1e-4) and hi == pytest.approx(0.6032, abs=1e-4)  # textbook values
    assert "ddp|ood|c" not in table["cells"]
    paths = write_suite_report(results, tmp_path, "t")
    md = (tmp_path / "table.md").read_text()
    # an average: ± std over per-seed averages, then the 95 % interval its 40 episodes allow (two seeds that
    # agree, as on ood, still leave ±15 points); a one-task average's interval is that task's Wilson interval
    assert "| ddp | id | 95 ± 7 (n=20) | 60 ± 14 (n=20) | 30 [11, 60] (n=10) | 78 ± 4 [62, 88] (n=40) | 30 [11, 60] (n=10) |" in md
    assert "| ddp | ood | 70 ± 14 (n=20) | 30 ± 14 (n=20) | - | 50 ± 0 [35, 65] (n=40) | - |" in md
    assert avg["ci95"] == pytest.approx(list(wilson(20, 40)))  # equal episodes per task: the pooled interval
    assert {p.name for p in paths} >= {"table.md", "table.json", "table.csv"}
    rows = (tmp_path / "table.csv").read_text().splitlines()
    assert rows[0].startswith("method,protocol,a_mean,a_std,a_n,a_seeds,a_lo95,a_hi95,b_mean")
    first = rows[1].split(",")
    assert first[2] == "0.95" and float(first[3]) == pytest.approx(math.sqrt(0.005)) and first[4:6] == ["20", "0 1"]
    assert [float(x) for x in first[6:8]] == pytest.approx(list(wilson(19, 20)))


def test_an_average_over_tasks_with_different_seeds_or_missing_tasks_says_so(tmp_path):
    """Task a has seeds 0-2, b seeds 0-1: the average is the mean of the task means, with no std (one over
    the shared seeds would describe other runs than the mean), marked; a method short of a task is marked too."""
    results = [_result("a", "ddp", 0, {"id": 1.0}), _result("a", "ddp", 1, {"id": 0.9}),
               _result("a", "ddp", 2, {"id": 0.2}), _result("b", "ddp", 0, {"id": 0.5}),
               _result("b", "ddp", 1, {"id": 0.6}), _result("a", "dp3", 0, {"id": 0.4}),
               _result("a", "dp3", 1, {"id": 0.6})]
    table = aggregate(results)
    avg = table["cells"]["ddp|id|avg:mw"]
    assert avg["mean"] == pytest.approx((0.7 + 0.55) / 2) and "std" not in avg and avg["uneven_seeds"]
    assert avg["seeds"] == [0, 1] and "missing_tasks" not in avg
    dp3 = table["cells"]["dp3|id|avg:mw"]
    assert dp3["missing_tasks"] == ["b"] and dp3["std"] == pytest.approx(math.sqrt(0.02))
    write_suite_report(results, tmp_path, "t")
    md = (tmp_path / "table.md").read_text()
    assert "| ddp | id | 70 ± 44 (n=30) | 55 ± 7 (n=20) | 63 [48, 75] (n=50) † |" in md
    assert "| dp3 | id | 50 ± 14 (n=20) | - | 50 ± 14 [30, 70] (n=20) (1/2 tasks) |" in md


def test_an_average_over_part_of_the_suites_tasks_is_marked_everywhere(tmp_path):
    """A suite of three tasks with results for two: the average says 2/3 in table.md, table.csv and
    vs_reference.md (it read as the benchmark's average, compared with the paper's as such)."""
    results = [_result("a", "ddp", 0, {"id": 1.0}), _result("b", "ddp", 0, {"id": 0.5})]
    suite_tasks = {"a": "mw", "b": "mw", "c": "mw"}
    table = aggregate(results, suite_tasks)
    assert table["benchmarks"] == {"mw": ["a", "b", "c"]} and table["tasks"] == ["a", "b"]
    assert table["cells"]["ddp|id|avg:mw"]["missing_tasks"] == ["c"]
    ref = {"label": "paper", "tolerance": 10, "values": {"ddp": {"id": {"mw": {"a": 90, "b": 60, "c": 10}}}}}
    write_suite_report(results, tmp_path, "t", reference=ref, tasks_of_suite=suite_tasks)
    assert "| ddp | id | 100 [72, 100] (n=10) | 50 [24, 76] (n=10) | 75 [53, 89] (n=20) (2/3 tasks) |" in (tmp_path / "table.md").read_text()
    assert "| ddp | id | mw (2/3 tasks) | 75.0 | 75 | +0.0 | yes |" in (tmp_path / "vs_reference.md").read_text()
    rows = (tmp_path / "table.csv").read_text().splitlines()
    assert rows[0] == ("method,protocol," + ",".join(f"{c}_{k}" for c in ("a", "b") for k in
                       ("mean", "std", "n", "seeds", "lo95", "hi95")) + ",avg:mw_mean,avg:mw_std,avg:mw_n,avg:mw_seeds,"
                       "avg:mw_lo95,avg:mw_hi95,avg:mw_tasks,avg:mw_uneven_seeds")
    lo, hi = wilson(15, 20)
    assert rows[1].startswith("ddp,id,1.0,,10,0,") and rows[1].endswith(f",0.75,,20,0,{lo},{hi},2/3,False")
    assert "missing_tasks" not in aggregate(results, {"a": "mw", "b": "mw"})["cells"]["ddp|id|avg:mw"]


def test_a_report_removes_the_files_an_earlier_one_wrote_that_it_does_not(tmp_path):
    """vs_reference.md of a suite that no longer names a reference, detection.png when no stored run has
    traces: left behind, they described other results than the table beside them."""
    results = [_result("a", "ddp", 0, {"id": 1.0})]
    (tmp_path / "vs_reference.md").write_text("old gaps")
    (tmp_path / "detection.png").write_bytes(b"old figure")
    paths = write_suite_report(results, tmp_path, "t")
    assert not (tmp_path / "vs_reference.md").exists() and not (tmp_path / "detection.png").exists()
    assert {p.name for p in paths} == {"table.md", "table.json", "table.csv", "cost.md", "table.png"}
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths)  # no temporary files


def test_report_states_what_the_runs_cost(tmp_path):
    results = []
    for seed, (train, wall) in enumerate([(600.0, 900.0), (1200.0, 1500.0), (900.0, 1200.0)]):
        r = _result("a", "ddp", seed, {"id": 1.0, "ood": 0.5})
        r["protocols"]["id"]["seconds"], r["protocols"]["ood"]["seconds"] = 60.0, 120.0
        results.append({**r, "train": {"steps": 3000, "seconds": train}, "wall_seconds": wall})
    results.append({**_result("a", "dp3", 0, {"id": 1.0}), "train": {"steps": 1000, "seconds": 60.0},
                    "wall_seconds": 90.0})
    paths = write_suite_report(results, tmp_path, "t")
    cost = (tmp_path / "cost.md").read_text().splitlines()
    assert tmp_path / "cost.md" in paths
    assert "| ddp | 3 | 3000 | 15.0 [10.0, 20.0] | 3.0 [3.0, 3.0] | 20.0 [15.0, 25.0] | 1.0 |" in cost
    assert "| dp3 | 1 | 1000 | 1.0 [1.0, 1.0] | 0.0 [0.0, 0.0] | 1.5 [1.5, 1.5] | 0.0 |" in cost
    # a resumed run: its wall_seconds cover its last start only (6 min of 76 trained); the earlier attempts'
    # training counts too (the stored assembly / push runs said 6 and 3 minutes for over an hour)
    resumed = {**_result("a", "flow", 0, {"id": 1.0}), "wall_seconds": 360.0,
               "train": {"steps": 9000, "seconds": 4560.0, "attempt_seconds": 240.0}}
    write_suite_report([resumed], tmp_path, "t")
    assert "| flow | 1 | 9000 | 76.0 [76.0, 76.0] | 0.0 [0.0, 0.0] | 78.0 [78.0, 78.0] | 1.3 |" in \
        (tmp_path / "cost.md").read_text()


def test_concurrent_suite_processes_write_the_report_in_turn(suite_file, monkeypatch):
    """Two `ddp suite` processes on one suite (other --tasks) each read the store, then wrote the report: the
    one that read first could write last, leaving the committed report without the other's run. The store is
    read and the report written under one lock, so the last writer read last."""
    from ddp import cli
    from ddp.file_lock import LockBusy, exclusive_lock
    from ddp.suite import report

    suite = load_suite(suite_file)
    store = ResultStore(suite.results_dir)
    for run in suite.runs:
        store.save(run, _result(run.task, run.method, run.seed, {"id": 1.0}, bench=run.benchmark))
    held = []

    def locked() -> bool:
        try:
            with exclusive_lock(suite.results_dir / "report", wait=False):
                return False
        except LockBusy:
            return True

    real_all, real_write = ResultStore.all, report.write_suite_report
    monkeypatch.setattr(ResultStore, "all", lambda self, runs: (held.append(("read", locked())),
                                                                 real_all(self, runs))[1])
    monkeypatch.setattr(report, "write_suite_report", lambda *a, **k: (held.append(("write", locked())),
                                                                        real_write(*a, **k))[1])
    import ddp.suite

    monkeypatch.setattr(ddp.suite, "write_suite_report", report.write_suite_report)
    assert cli.main(["suite", str(suite_file), "--report"]) == 0
    assert held == [("read", True), ("write", True)], held
    with exclusive_lock(suite.results_dir / "report", wait=False):  # released after
        pass


def test_a_run_another_suite_process_is_running_is_refused_in_one_line(suite_file):
    """Overlapping selections (one process started without --tasks) trained or evaluated one run twice into
    one folder; the second process now gets one line and the run is left to the first."""
    from ddp.file_lock import LockBusy, exclusive_lock
    from ddp.suite.runner import execute_run

    run = load_suite(suite_file).runs[0]
    run_dir = Path(run.recipe["train"]["output_dir"])
    with exclusive_lock(run_dir, wait=False):
        with pytest.raises(LockBusy, match=rf"{run_dir}: another ddp suite process is running this run") as err:
            execute_run(run)
    assert "\n" not in str(err.value) and not (run_dir / "log.txt").exists()  # nothing ran


def test_stored_results_keep_the_detector_traces_and_the_report_draws_them(tmp_path):
    """A run's stored result keeps, per protocol with a detector statistic, each episode's statistic per
    chunk, mode and first visible chunk (one line per trace in the JSON); the report draws them."""
    from ddp import results_json
    from ddp.suite.runner import _summary

    nan = float("nan")
    episode = {"seed": 1000, "success": True, "score": [nan, 0.51234, 7.0, 30.0], "mode": [0.0, 0.0, 1.0, 1.0],
               "disturbed": [False, False, True, True], "discrepancy": [nan, 1e-3, 2e-2, 3e-2]}
    protocol = {"success_rate": 1.0, "successes": 1, "episodes": 1, "tau": 3.0, "alpha": 0.05,
                "per_episode": [episode], "detection": {"detected": 1, "per_episode": [{"seed": 1000}]}}
    summary = _summary(protocol)
    assert summary["traces"] == [{"success": True, "first_visible": 2, "score": [None, 0.512, 7.0, 30.0],
                                  "mode": "0011"}]
    assert "per_episode" not in summary["detection"]
    oracle = {**protocol, "per_episode": [{**episode, "score": [nan] * 4}]}  # the oracle schedule: no statistic
    assert "traces" not in _summary(oracle)
    text = results_json.dumps({"protocols": {"ood_ddp": summary}})
    assert '"score": [null, 0.512, 7.0, 30.0]' in text and json.loads(text)["protocols"]["ood_ddp"] == \
        json.loads(json.dumps(results_json.strict(summary)))
    results = [_result("a", "ddp", 0, {"id": 1.0}), _result("a", "dp3", 0, {"id": 0.9})]
    write_suite_report(results, tmp_path / "plain", "t")
    assert (tmp_path / "plain" / "table.png").stat().st_size > 0 and not (tmp_path / "plain" / "detection.png").exists()
    clean = {**episode, "disturbed": [False] * 4, "mode": [0.0] * 4, "score": [nan, 0.4, 0.6, 0.5]}
    results[0]["protocols"]["ood_ddp"] = summary
    results[0]["protocols"]["id_ddp"] = _summary({**protocol, "per_episode": [clean]})
    paths = write_suite_report(results, tmp_path / "traced", "t")
    assert tmp_path / "traced" / "detection.png" in paths and (tmp_path / "traced" / "detection.png").stat().st_size > 0


def test_reference_rows_sit_under_their_rows_and_average_the_same_tasks(tmp_path):
    from ddp.suite.spec import load_reference

    results = [_result("a", "ddp", 0, {"id": 1.0}), _result("b", "ddp", 0, {"id": 0.5}),
               _result("a-x", "ddp", 0, {"id": 0.2}, bench="x"), _result("a", "dp3", 0, {"id": 0.9})]
    ref = load_reference({"label": "paper", "values": {
        "ddp": {"id": {"mw": {"a": 90, "b": 70, "c": 10, "avg": 12.5}, "x": {"a": 40}}}}}, source="s")
    write_suite_report(results, tmp_path, "t", reference=ref)
    md = (tmp_path / "table.md").read_text().splitlines()
    row = md.index("| ddp | id | 100 [72, 100] (n=10) | 50 [24, 76] (n=10) | 20 [6, 51] (n=10) | 75 [53, 89] (n=20) | 20 [6, 51] (n=10) |")
    # the task columns, then the mean of the published numbers over the suite's tasks (not the paper's 12.5)
    assert md[row + 1] == "| ddp | id (paper) | 90 | 70 | 40 | 80 | 40 |"
    assert md[row + 2].startswith("| dp3 | id |") and "(paper)" not in md[row + 2]  # no numbers: no row
    table = json.loads((tmp_path / "table.json").read_text())
    assert table["reference"]["cells"]["ddp|id|avg:mw"] == pytest.approx(0.8)
    # a suite averaging exactly the reference's tasks shows the reference's own average
    exact = load_reference({"values": {"ddp": {"id": {"mw": {"a": 90, "b": 70, "avg": 81}}}}}, source="s")
    write_suite_report(results, tmp_path / "exact", "t", reference=exact)
    assert "| ddp | id (reference) | 90 | 70 | - | 81 | - |" in (tmp_path / "exact" / "table.md").read_text()
    # a mean over part of the reference's tasks reads to a tenth of a point (it printed 0.1429, 22.14)
    for a, b, avg in ((0, 0.2857, "0.1"), (23, 21.29, "22.1")):
        part = load_reference({"values": {"ddp": {"id": {"mw": {"a": a, "b": b, "c": 0}}}}}, source="s")
        write_suite_report(results, tmp_path / f"part{a}", "t", reference=part)
        assert f"| ddp | id (reference) | {a} | {b} | - | {avg} | - |" in (tmp_path / f"part{a}" / "table.md").read_text()
    empty = load_reference({"values": {"ddp": None}}, source="s")  # nothing for a method: no rows, no crash
    write_suite_report(results, tmp_path / "empty", "t", reference=empty)
    for bad, message in (({"values": {"ddp": {"id": {"mw": {"a": 130}}}}}, r"ddp\.id\.mw\.a must be a percentage in \[0, 100\], got 130"),
                         ({"label": "p"}, r"must be \{label, values: method"),
                         ("missing.yaml", "reference file not found: missing.yaml"),
                         ({"values": {"ddp": {"id": {"mw": 90}}}}, r"ddp\.id\.mw must be a mapping .* got 90"),
                         ({"values": {"ddp": ["id"]}}, r"ddp must be a mapping .* got \['id'\]"),
                         ({"values": {}, "tolerance": -1}, r"tolerance must be percentage points in \[0, 100\], got -1")):
        with pytest.raises(RecipeError, match=message):
            load_reference(bad, source="s")


def test_report_lists_the_gaps_to_the_reference_within_its_tolerance(tmp_path):
    """vs_reference.md: each benchmark average against the published one (difference, within the tolerance
    or not) and the task cells outside the tolerance, largest shortfall first; the suite's ``tolerance``."""
    from ddp.suite.spec import load_reference

    results = [_result("a", "ddp", 0, {"id": 1.0}), _result("a", "ddp", 1, {"id": 0.8}),
               _result("b", "ddp", 0, {"id": 0.5}), _result("b", "ddp", 1, {"id": 0.5}),
               _result("c", "ddp", 0, {"id": 0.7})]
    ref = load_reference({"values": {"ddp": {"id": {"mw": {"a": 90, "b": 70, "c": 72, "avg": 79}}}}}, source="s")
    assert ref["tolerance"] == 10
    paths = write_suite_report(results, tmp_path, "t", reference=ref)
    md = (tmp_path / "vs_reference.md").read_text().splitlines()
    assert tmp_path / "vs_reference.md" in paths
    # ours: (0.9 + 0.5 + 0.7) / 3 = 70.0 (no std: c has one seed) against the paper's own 79 (the same tasks)
    assert "| ddp | id | mw | 70.0 | 79 | -9.0 | yes |" in md
    rows = [line for line in md if line.startswith("| ddp | id | ") and "| mw |" not in line]
    assert rows == ["| ddp | id | b | 50.0 ± 0.0 | 70 | -20.0 |"]  # a: 0, c: -2: within 10 points
    strict = load_reference({"tolerance": 1.5, "values": {"ddp": {"id": {"mw": {"a": 90, "b": 70, "c": 72,
                                                                                    "avg": 79}}}}}, source="s")
    write_suite_report(results, tmp_path / "strict", "t", reference=strict)
    md = (tmp_path / "strict" / "vs_reference.md").read_text().splitlines()
    assert "| ddp | id | mw | 70.0 | 79 | -9.0 | no |" in md
    rows = [line.split(" | ")[2] for line in md if line.startswith("| ddp | id | ") and "| mw |" not in line]
    assert rows == ["b", "c"]  # -20 before -2; a (0) stays out
    write_suite_report(results, tmp_path / "none", "t")
    assert not (tmp_path / "none" / "vs_reference.md").exists()
    for bad in (-1, 101, "ten", True):
        with pytest.raises(RecipeError, match="tolerance"):
            load_reference({"tolerance": bad, "values": {}}, source="s")


SHIPPED_SUITES = sorted(p.stem for p in (ROOT / "suites").glob("*.yaml") if "tasks" in yaml.safe_load(p.read_text()))


def test_every_suite_file_is_a_suite_or_the_reference():
    assert {"metaworld_cpu", "metaworld_budget", "franka_budget", "table1"} <= set(SHIPPED_SUITES)
    others = {p.stem for p in (ROOT / "suites").glob("*.yaml")} - set(SHIPPED_SUITES)
    assert others == {"paper_table1"}  # the reference numbers the suites name


@pytest.mark.parametrize("name", SHIPPED_SUITES)
def test_shipped_suites_expand(name, monkeypatch):
    """Every suite file in suites/ loads: its recipes, overlays, overrides and reference all resolve."""
    monkeypatch.chdir(ROOT)  # suite paths are relative to the repository root
    suite = load_suite(ROOT / "suites" / f"{name}.yaml")
    assert name.startswith("franka") or suite.reference["values"]["ddp"]["id"]  # the paper's numbers beside ours
    assert suite.name == name and len(suite.runs) == len(suite.tasks) * len(suite.methods) * len(suite.seeds)


@pytest.mark.parametrize("name, steps", [("metaworld_budget", 9000), ("metaworld_cpu", 3000)])
def test_metaworld_cpu_baselines_compose_as_documented(name, steps, monkeypatch):
    """The shipped suites' DP3 and FlowPolicy runs are the quickstart's parts with the method overlays
    (the README's "baselines against their reference code" table), trained as long as DDP."""
    monkeypatch.chdir(ROOT)  # the suite names its recipes relative to the repository
    suite = load_suite(ROOT / "suites" / f"{name}.yaml")
    runs = {(r.task, r.method): r for r in suite.runs if r.seed == 0}
    ddp, dp3, flow = (runs["push", m].recipe for m in ("ddp", "dp3", "flowpolicy"))
    for r in (ddp, dp3, flow):
        assert r["train"]["max_steps"] == steps and r["train"]["batch_size"] == 32
        assert r["policy"]["denoiser"]["down_dims"] == [64, 128, 256] and r["task"]["num_points"] == 128
        assert r["env"]["visible_sites"] == ["goal"] and r["env"]["crop_min"][2] == 0.005
        assert r["data"]["episodes"] == 50 and r["data"]["path"] == "data/metaworld/{task}_suite50"  # the paper's 50
    assert ddp["world_model"]["enabled"] is not False
    assert dp3["world_model"]["enabled"] is False and dp3["policy"]["scheduler"]["prediction_type"] == "sample"
    assert flow["world_model"]["enabled"] is False
    assert (flow["policy"]["horizon"], flow["policy"]["obs_steps"], flow["policy"]["action_steps"]) == (4, 2, 3)
    assert flow["policy"]["scheduler"]["name"] == "consistency_flow"
    assert flow["policy"]["scheduler"]["num_inference_steps"] == 1


def test_flowpolicy_overlay_trains_and_acts(tmp_path, monkeypatch):
    """recipes/methods/flowpolicy.yaml laid over a tiny recipe by a suite: it trains and returns 3-action chunks."""
    import torch
    from tensordict import TensorDict

    from ddp import build

    monkeypatch.chdir(tmp_path)
    overlay = ROOT / "recipes" / "methods" / "flowpolicy.yaml"
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(copy.deepcopy(TINY)))
    (tmp_path / "suite.yaml").write_text(yaml.safe_dump(
        {"name": "flow", "tasks": {"reach": "tiny.yaml"}, "methods": {"flowpolicy": {"overlay": str(overlay)}},
         "seeds": [0], "protocols": ["id"]}))
    recipe = load_suite(tmp_path / "suite.yaml").runs[0].recipe
    (tmp_path / "flow.yaml").write_text(yaml.safe_dump(recipe))
    model = build(str(tmp_path / "flow.yaml")).model
    assert not model.has_world_model and model.horizon == 4 and model.action_steps == 3
    g = torch.Generator().manual_seed(0)
    P, A, D = TINY["task"]["num_points"], TINY["task"]["action_dim"], TINY["task"]["agent_pos_dim"]
    batch = TensorDict({"point_cloud": torch.randn(8, 5, P, 3, generator=g), "agent_pos": torch.rand(8, 5, D, generator=g),
                        "action": 2 * torch.rand(8, 5, A, generator=g) - 1}, batch_size=[8])
    model.normalizer.fit({"point_cloud": batch["point_cloud"].reshape(-1, 3), "agent_pos": batch["agent_pos"].reshape(-1, D),
                          "action": batch["action"].reshape(-1, A)})
    losses = model.train().loss(batch)
    assert losses["loss_wm"] == 0 and torch.isfinite(losses["loss"]) and losses["loss"] == losses["loss_bc"]
    losses["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    out = model.eval()(TensorDict({"point_cloud": batch["point_cloud"][:2, :2], "agent_pos": batch["agent_pos"][:2, :2]},
                                  batch_size=[2]))
    assert out["action_chunk"].shape == (2, 4, A) and out["action"].shape == (2, 3, A)
    assert torch.isfinite(out["action"]).all()


def test_a_suite_refuses_an_env_that_cannot_judge_success(suite_file, monkeypatch, tmp_path):
    """A real robot's episodes carry no success verdict (None): the suite's tables would crash on them after the
    training, so the run stops before it trains, with one line."""
    from ddp.envs.synthetic_reach import SyntheticReachEnvConfig
    from ddp.errors import DDPError
    from ddp.experiment import build
    from ddp.suite.runner import _check_judged

    run = load_suite(suite_file).runs[0]
    exp = build(run.recipe)
    _check_judged(exp, run)  # a simulator judges
    monkeypatch.setattr(SyntheticReachEnvConfig, "judges_success", lambda self: False, raising=False)
    with pytest.raises(DDPError, match=r"cannot judge success .*evaluate it with `ddp eval`"):
        _check_judged(exp, run)
    monkeypatch.undo()
    # the env the episodes run in decides: eval.env may put a simulated recipe on the robot
    monkeypatch.setattr(SyntheticReachEnvConfig, "judges_success", lambda self: self.table_points != 7,
                        raising=False)
    _check_judged(exp, run)
    exp.recipe.eval.env = {"table_points": 7}  # stands for {backend: real} on a Franka recipe
    with pytest.raises(DDPError, match=r"cannot judge success"):
        _check_judged(exp, run)
    # a stale run re-evaluated (`--reevaluate`) is checked too, before its checkpoint is read (a TypeError on
    # the unjudged success while its result was made, after the evaluation)
    import dataclasses

    import ddp.experiment as experiment_module
    from ddp.suite.runner import _reevaluate_run

    monkeypatch.setattr(experiment_module, "build", lambda recipe: exp)
    again = dataclasses.replace(run, reevaluate=("id",))
    with pytest.raises(DDPError, match=r"cannot judge success"):
        _reevaluate_run(again, tmp_path, 0.0)


def test_an_empty_seed_list_is_an_error_not_every_seed(suite_file, capsys):
    """--seeds "" (a job script's unset $SEED) ran every seed of the suite; --tasks "" already failed."""
    from ddp.cli import main

    assert main(["suite", str(suite_file), "--dry-run", "--seeds", ""]) == 2
    assert "--seeds takes comma-separated integers, got ''" in capsys.readouterr().err


def test_a_suite_whose_every_run_failed_exits_1(suite_file, capsys):
    """README: a failed run exits 1; with nothing stored the error went to the one-line handler's exit 2."""
    from ddp.cli import main

    data = yaml.safe_load(suite_file.read_text())
    data["set"] = ["eval.env={displacement_chunk: 99}"]  # refused when the run builds its env, after it started
    suite_file.write_text(yaml.safe_dump(data, sort_keys=False))
    assert main(["suite", str(suite_file), "--tasks", "near", "--methods", "dp3", "--seeds", "0"]) == 1
    assert "ddp: 1 run(s) failed: near__dp3__seed0" in capsys.readouterr().err


def test_a_result_that_cannot_be_stored_is_one_line(suite_file, monkeypatch):
    """A full disk or a read-only results folder escaped the suite as an OSError traceback."""
    import errno

    from ddp.errors import DDPError
    from ddp.suite import store as store_module

    run = load_suite(suite_file).runs[0]
    store = ResultStore(load_suite(suite_file).results_dir)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(store_module, "atomic_write", full)
    with pytest.raises(DDPError, match=rf"cannot store {run.run_id}'s result \(No space left on device\); its "
                                       "checkpoint stays") as err:
        store.save(run, _result(run.task, run.method, run.seed, {"id": 1.0}))
    assert "\n" not in str(err.value)
