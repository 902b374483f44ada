"""A battery of bad inputs and faults, as a new user meets them through the CLI.

Each case ends in exactly one ``ddp: error: ...`` line on stderr (exit code 2), no traceback,
and nothing lost: the shared trained run's files are byte-identical afterwards.
"""

from __future__ import annotations

import hashlib
import pickle
import shutil
import warnings
from pathlib import Path

import pytest
import torch
import yaml

from conftest import runnable
from ddp.cli import main


tiny = runnable  # TINY trained for 2 steps, 1 id episode; a mapping updates a section


def write(path: Path, recipe: dict | str) -> str:
    path.write_text(recipe if isinstance(recipe, str) else yaml.safe_dump(recipe))
    return str(path)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny trained run (2 steps): its recipe file, output dir and checkpoint."""
    root = tmp_path_factory.mktemp("trained")
    recipe = write(root / "tiny.yaml", tiny(train={"output_dir": str(root / "run")}))
    torch.set_num_threads(1)
    assert main(["train", recipe, "--quiet"]) == 0
    return {"recipe": recipe, "run": root / "run", "ckpt": root / "run" / "last.pt"}


def digest(directory: Path) -> dict[str, str]:
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob("*")) if p.is_file() and p.name != ".lock"}


def copy_run(trained, tmp: Path, **train) -> tuple[str, Path]:
    """A copy of the trained run in ``tmp``, and a recipe file training into it."""
    run = tmp / "run"
    shutil.copytree(trained["run"], run)
    return write(tmp / "r.yaml", tiny(train={"output_dir": str(run), **train})), run


def own_demos(t: Path, edit) -> dict:
    """The runnable recipe training on its synthetic demos saved as an episodes_dir after ``edit(steps, ends)``
    (which returns the episode ends to save)."""
    from ddp.data.episodes import Episodes
    from ddp.experiment import build

    eps = build(write(t / "src.yaml", tiny())).episodes()
    steps = eps.steps.clone()
    ends = edit(steps, eps.episode_ends.clone())
    Episodes(steps[: int(ends[-1])], ends).save(t / "eps")
    return {**tiny(train={"output_dir": str(t / "o")}), "data": {"name": "episodes_dir", "path": str(t / "eps")}}


def _nan_action(steps, ends):
    steps["action"][int(ends[1]) + 3, 2] = float("nan")  # episode 2, step 3
    return ends


def _short_episodes(steps, ends):
    return torch.arange(4, steps.batch_size[0] + 1, 4)  # 4 steps each; a window needs 16 - 1 - 7 = 8


def fake_checkpoint(path: Path, payload) -> str:
    torch.save(payload, path)
    return str(path)


def ckpt_state(trained) -> dict:
    return torch.load(trained["ckpt"], weights_only=True)


# Each case: (id, builder(tmp, trained) -> argv, fragment expected in the error line)
CASES = [
    # -------- recipe files
    ("missing-file", lambda t, tr: ["recipe", str(t / "nope.yaml")], "recipe file not found"),
    ("directory", lambda t, tr: ["recipe", str(t)], "cannot read recipe"),
    ("binary-file", lambda t, tr: (t.joinpath("b.yaml").write_bytes(b"\xff\xfe\x00\x81name: x"), ["recipe", str(t / "b.yaml")])[1],
     "not a text file"),
    ("malformed-yaml", lambda t, tr: ["recipe", write(t / "r.yaml", "name: [x\n")], "malformed YAML at line"),
    ("duplicate-top-key", lambda t, tr: ["recipe", write(t / "r.yaml", "name: a\ntrain: {lr: 0.1}\ntrain: {epochs: 2}\n")],
     "duplicate key 'train' (first given on line 2)"),
    ("duplicate-nested-key", lambda t, tr: ["recipe", write(t / "r.yaml", "name: a\ntrain:\n  lr: 0.1\n  lr: 0.2\n")],
     "duplicate key 'lr'"),
    ("list-recipe", lambda t, tr: ["recipe", write(t / "r.yaml", "- a\n- b\n")], "a recipe must be a YAML mapping"),
    ("unknown-section", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(trian={}))], "trian: unknown option; did you mean 'train'?"),
    ("unknown-option", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(train={"lrr": 0.1}))], "train.lrr: unknown option"),
    ("wrong-type", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(train={"lr": "fast"}))], "train.lr: expected float"),
    ("nan-lr", lambda t, tr: ["recipe", write(t / "r.yaml", "name: a\ntrain: {lr: .nan}\n")], "train.lr: must be a finite number"),
    ("inf-lr", lambda t, tr: ["recipe", write(t / "r.yaml", "name: a\ntrain: {lr: .inf}\n")], "train.lr: must be a finite number"),
    ("nan-tau", lambda t, tr: ["recipe", write(t / "r.yaml", "name: a\ncontroller: {detector: {name: discrepancy, tau: .nan}}\n")],
     "controller.detector.tau: must be a finite number"),
    ("negative-lambda", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(world_model={"weight": -1.0}))], "weight must be >= 0"),
    ("zero-batch", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(train={"batch_size": 0}))], "batch_size must be >= 1"),
    ("zero-points", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(task={"num_points": 0}))], "num_points must be >= 1"),
    ("zero-eval-episodes", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(eval={"episodes": 0}))], "episodes must be >= 1"),
    ("unknown-scheduler", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(policy={"scheduler": {"name": "dimm"}}))],
     "unknown scheduler 'dimm'; did you mean 'ddim'"),
    ("unknown-encoder", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(encoder={"name": "pointnet++"}))], "unknown encoder"),
    ("section-without-name", lambda t, tr: ["recipe", write(t / "r.yaml", "name: a\ndata: {episodes: 2}\n")],
     "missing required option 'name'"),
    ("missing-base", lambda t, tr: ["recipe", write(t / "r.yaml", "base: nope.yaml\nname: a\n")], "base recipe"),
    ("cyclic-base", lambda t, tr: ["recipe", write(t / "r.yaml", "base: r.yaml\nname: a\n")], "cyclic base"),
    ("unknown-protocol", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(eval={"protocols": ["id", "odd_ddp"]}))],
     "eval.protocols: unknown protocol 'odd_ddp'; did you mean 'ood_ddp'"),
    ("env-points-differ", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(env={"num_points": 32}))],
     "env.num_points: 32 differs from task.num_points (64)"),
    ("short-horizon", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(policy={"horizon": 4}))], "horizon must be >="),
    ("missing-plugin-module", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(plugins=["no_such_plugin_mod"]))],
     "cannot import plugin module 'no_such_plugin_mod'"),
    ("bad-on-nonfinite", lambda t, tr: ["recipe", write(t / "r.yaml", tiny(controller={"on_nonfinite": "maybe"}))],
     "controller.on_nonfinite: must be one of 'raise', 'hold'"),
    ("colour-without-rgb", lambda t, tr: ["summary", write(t / "r.yaml", tiny(encoder={"name": "dp3", "use_color": True}))],
     "set task.point_dim to 6"),
    # -------- --set overrides
    ("set-no-equals", lambda t, tr: ["recipe", tr["recipe"], "--set", "train.lr"], "--set: bad override 'train.lr'"),
    ("set-bad-key", lambda t, tr: ["recipe", tr["recipe"], "--set", "train..lr=1"], "is not a dotted key"),
    ("set-bad-yaml", lambda t, tr: ["recipe", tr["recipe"], "--set", "train.lr=[1"], "the value is not valid YAML"),
    ("set-into-scalar", lambda t, tr: ["recipe", tr["recipe"], "--set", "train.lr.x=1"], "is 0.001, not a mapping"),
    ("set-unknown-option", lambda t, tr: ["recipe", tr["recipe"], "--set", "train.lrr=1"], "--set train.lrr=1: train.lrr: unknown option"),
    ("set-nan", lambda t, tr: ["recipe", tr["recipe"], "--set", "train.lr=.nan"], "--set train.lr=.nan: train.lr: must be a finite"),
    ("set-unknown-section", lambda t, tr: ["recipe", tr["recipe"], "--set", "foo.bar=1"], "--set foo.bar=1: foo: unknown option"),
    # -------- training
    ("train-cuda-on-cpu", lambda t, tr: ["train", write(t / "r.yaml", tiny(train={"device": "cuda", "output_dir": str(t / "o")}))],
     "train.device: 'cuda' but CUDA is not available"),
    ("train-bad-device", lambda t, tr: ["train", write(t / "r.yaml", tiny(train={"device": "gpu0", "output_dir": str(t / "o")}))],
     "train.device: 'gpu0' is not a torch device"),
    ("train-missing-data", lambda t, tr: ["train", write(t / "r.yaml", {**tiny(train={"output_dir": str(t / "o")}),
                                                                         "data": {"name": "episodes_dir", "path": str(t / "none")}})],
     "none does not exist"),
    ("train-nan-in-demos", lambda t, tr: ["train", write(t / "r.yaml", own_demos(t, _nan_action))],
     "the training data's 'action' holds NaN or inf at episode 2, step 3"),
    ("train-episodes-too-short", lambda t, tr: ["train", write(t / "r.yaml", own_demos(t, _short_episodes))],
     "no demonstration episode is long enough to train on: a window needs 8 steps"),
    ("train-micro-batches-beyond-data", lambda t, tr: ["train", write(t / "r.yaml", tiny(
        train={"batch_size": 512, "micro_batches": 512, "output_dir": str(t / "o")}, data={"episodes": 1}))],
     "fewer than train.micro_batches (512)"),
    ("train-without-data", lambda t, tr: ["train", write(t / "r.yaml", {**tiny(train={"output_dir": str(t / "o")}), "data": None})],
     "data: this recipe has no data section"),
    ("resume-changed-lr", lambda t, tr: ["train", copy_run(tr, t)[0], "--set", "train.lr=0.003"],
     "cannot resume: the recipe differs from the run's (train.lr: 0.001 -> 0.003)"),
    ("resume-other-recipe", lambda t, tr: ["train", write(t / "o.yaml", tiny(name="other", train={"output_dir": copy_run(tr, t)[1].as_posix()}))],
     "name: 'tiny' -> 'other'"),
    ("resume-other-architecture", lambda t, tr: ["train", copy_run(tr, t)[0], "--set", "policy.denoiser.down_dims=[8,16]"],
     "policy.denoiser.down_dims"),
    ("resume-truncated", lambda t, tr: (lambda r, run: (run.joinpath("last.pt").write_bytes(run.joinpath("last.pt").read_bytes()[:500]),
                                                       ["train", r])[1])(*copy_run(tr, t)), "not a readable checkpoint"),
    ("resume-random-bytes", lambda t, tr: (lambda r, run: (run.joinpath("last.pt").write_bytes(b"\x00junk" * 99), ["train", r])[1])(*copy_run(tr, t)),
     "not a readable checkpoint"),
    ("resume-no-model", lambda t, tr: (lambda r, run: (fake_checkpoint(run / "last.pt", {k: v for k, v in ckpt_state(tr).items() if k != "model"}),
                                                      ["train", r])[1])(*copy_run(tr, t)), "cannot resume: the checkpoint lacks model"),
    ("resume-pickled-object", lambda t, tr: (lambda r, run: (fake_checkpoint(run / "last.pt", {**ckpt_state(tr), "obj": torch.nn.Linear(1, 1)}),
                                                            ["train", r])[1])(*copy_run(tr, t)),
     "refused to load: it holds Python objects (torch.nn.modules.linear.Linear)"),
    ("resume-raw-pickle", lambda t, tr: (lambda r, run: (run.joinpath("last.pt").write_bytes(pickle.dumps(Path("/"))), ["train", r])[1])(*copy_run(tr, t)),
     "not a readable checkpoint"),
    ("resume-foreign-dict", lambda t, tr: (lambda r, run: (fake_checkpoint(run / "last.pt", {"weights": torch.zeros(2)}), ["train", r])[1])(*copy_run(tr, t)),
     "not a ddp checkpoint"),
    ("resume-stored-recipe-not-a-mapping", lambda t, tr: (lambda r, run: (fake_checkpoint(run / "last.pt", {**ckpt_state(tr), "recipe": "- a\n"}),
                                                                         ["train", r])[1])(*copy_run(tr, t)),
     "the stored recipe is not a mapping"),
    ("checkpoint-is-directory", lambda t, tr: (lambda r, run: ((run / "last.pt").unlink(), (run / "last.pt").mkdir(), ["train", r])[2])(*copy_run(tr, t)),
     "last.pt: is a directory, not a checkpoint file"),
    # -------- evaluation
    ("eval-other-prediction-type", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--set",
                                                 "policy.scheduler.prediction_type=epsilon", "--output-dir", str(t / "e")],
     "trained under other scheduler settings than this recipe's (policy.scheduler.prediction_type: 'sample' -> 'epsilon')"),
    ("eval-other-noise-schedule", lambda t, tr: ["eval", "--checkpoint", str(tr["ckpt"]), "--set",
                                                "world_model.scheduler.beta_schedule=linear", "--output-dir", str(t / "e")],
     "world_model.scheduler.beta_schedule: 'squaredcos_cap_v2' -> 'linear'"),
    ("eval-episodes-negative", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--episodes", "-1",
                                              "--output-dir", str(t)], "--episodes: must be a whole number >= 1; got -1"),
    ("eval-episodes-zero", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--episodes", "0",
                                          "--output-dir", str(t)], "--episodes: must be a whole number >= 1; got 0"),
    ("eval-num-envs-zero", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--num-envs", "0",
                                          "--output-dir", str(t)], "--num-envs: must be a whole number >= 1; got 0"),
    ("eval-unknown-protocol", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--protocols", "id,odd",
                                             "--output-dir", str(t)], "--protocols: unknown protocol 'odd'"),
    ("eval-empty-protocols", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--protocols", ",",
                                            "--output-dir", str(t)], "--protocols: empty; name at least one"),
    ("eval-missing-checkpoint", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(t / "none.pt")], "checkpoint not found"),
    ("eval-other-architecture", lambda t, tr: ["eval", write(t / "r.yaml", tiny(policy={"denoiser": {"name": "unet1d", "down_dims": [8, 16],
                                                                                                      "n_groups": 4}})),
                                               "--checkpoint", str(tr["ckpt"])], "shape mismatches (checkpoint vs model): policy_net"),
    ("eval-other-encoder", lambda t, tr: ["eval", write(t / "r.yaml", tiny(encoder={"name": "state_mlp"})), "--checkpoint", str(tr["ckpt"])],
     "missing: encoder."),
    ("eval-no-model", lambda t, tr: ["eval", tr["recipe"], "--checkpoint",
                                     fake_checkpoint(t / "x.pt", {k: v for k, v in ckpt_state(tr).items() if k not in ("model", "ema")})],
     "holds no model weights"),
    ("eval-nan-weights", lambda t, tr: ["eval", tr["recipe"], "--checkpoint",
                                        fake_checkpoint(t / "x.pt", {**ckpt_state(tr), "ema": {k: v.float() * float("nan") if v.is_floating_point() else v
                                                                                              for k, v in ckpt_state(tr)["ema"].items()}})],
     "weights hold NaN or inf"),
    ("eval-no-recipe-in-checkpoint", lambda t, tr: ["eval", "--checkpoint",
                                                    fake_checkpoint(t / "x.pt", {k: v for k, v in ckpt_state(tr).items() if k != "recipe"})],
     "holds no recipe"),
    ("eval-stored-recipe-not-a-mapping", lambda t, tr: ["eval", "--checkpoint", fake_checkpoint(t / "x.pt", {**ckpt_state(tr), "recipe": "- a\n"})],
     "the stored recipe is not a mapping"),
    ("eval-stored-recipe-not-yaml", lambda t, tr: ["eval", "--checkpoint", fake_checkpoint(t / "x.pt", {**ckpt_state(tr), "recipe": "a: [\n"})],
     "the stored recipe is not readable YAML"),
    ("eval-untrusted-plugin", lambda t, tr: ["eval", "--checkpoint", fake_checkpoint(t / "x.pt", {**ckpt_state(tr), "recipe": yaml.safe_dump(
        tiny(plugins=["evil_plugin_pkg"], controller={"detector": {"name": "evil"}}))})],
     "the recipe's plugin modules were not imported (evil_plugin_pkg)"),
    ("eval-cuda-on-cpu", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--set", "eval.device=cuda",
                                        "--output-dir", str(t)], "eval.device: 'cuda' but CUDA is not available"),
    ("eval-terminate-on-success", lambda t, tr: ["eval", tr["recipe"], "--checkpoint", str(tr["ckpt"]), "--set",
                                                 "env.terminate_on_success=true", "--output-dir", str(t)],
     "env.terminate_on_success: must be false for evaluation"),
    ("eval-without-env", lambda t, tr: ["eval", write(t / "r.yaml", tiny(env=None)), "--checkpoint", str(tr["ckpt"])],
     "evaluation needs an env section"),
    # -------- other commands
    ("bench-zero-repeats", lambda t, tr: ["bench", tr["recipe"], "--repeats", "0"], "--repeats: must be >= 1"),
    ("bench-zero-threads", lambda t, tr: ["bench", tr["recipe"], "--threads", "0"], "--threads: must be >= 1"),
    ("bench-cuda-on-cpu", lambda t, tr: ["bench", tr["recipe"], "--device", "cuda"], "--device: 'cuda' but CUDA is not available"),
    ("demos-zero-episodes", lambda t, tr: ["demos", tr["recipe"], "--episodes", "0"], "--episodes: must be >= 1"),
    ("list-unknown-kind", lambda t, tr: ["list", "detectr"], "unknown plugin kind 'detectr'; did you mean 'detector'?"),
    # -------- detect and suite
    ("detect-alpha-out-of-range", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--alpha", "1.5"],
     "--alpha: must be in (0, 1)"),
    ("detect-unknown-score", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--scores", "point_newst"],
     "--scores: unknown score 'point_newst'; did you mean 'point_newest'"),
    ("detect-bad-env-pair", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--env", "displacement_chunk"],
     "--env: expected KEY=VALUE"),
    ("detect-truncated-rollouts", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--rollouts",
                                                 (t.joinpath("r.npz").write_bytes(b"PK\x03\x04broken"), str(t / "r.npz"))[1]],
     "is not a ddp detect rollouts file"),
    ("eval-weight-not-a-tensor", lambda t, tr: ["eval", tr["recipe"], "--checkpoint",
                                                fake_checkpoint(t / "x.pt", {**ckpt_state(tr), "ema": {
                                                    k: (3 if k.endswith(".weight") else v) for k, v in ckpt_state(tr)["ema"].items()}})],
     "is a int, not a tensor"),
    ("detect-env-not-yaml", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--env", "displacement_delta=[1,"],
     "--env: displacement_delta: not a YAML value"),
    ("detect-unknown-env-key", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--env", "displacment_chunk=2"],
     "--env: env 'synthetic_reach' has no option 'displacment_chunk'; did you mean 'displacement_chunk'"),
    ("detect-missing-rollouts", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--rollouts", str(t / "x.npz")],
     "--rollouts: no such file"),
    # flags that make rollouts were accepted with --rollouts and ignored (the file's values were used)
    ("detect-rollouts-with-making-flags", lambda t, tr: ["detect", "--checkpoint", str(tr["ckpt"]), "--rollouts",
                                                         str(t / "x.npz"), "--episodes", "5", "--seed", "3"],
     "--rollouts scores saved rollouts: --episodes, --seed would change how they are made"),
    ("suite-missing-file", lambda t, tr: ["suite", str(t / "nope.yaml")], "suite file not found"),
    ("suite-unknown-key", lambda t, tr: ["suite", write(t / "s.yaml", {"name": "s", "tasks": {"a": tr["recipe"]},
                                                                           "sedes": [0]})],
     "unknown key 'sedes'; did you mean 'seeds'"),
    ("suite-zero-workers", lambda t, tr: ["suite", write(t / "s.yaml", {"name": "s", "tasks": {"a": tr["recipe"]}}),
                                          "--workers", "0"], "--workers: must be >= 1"),
    ("suite-report-nothing-yet", lambda t, tr: ["suite", write(t / "s.yaml", {"name": "s", "tasks": {"a": tr["recipe"]},
                                                                                  "results_dir": str(t / "res")}),
                                                "--report"], "no finished runs of suite 's'"),
    ("suite-bad-time-limit", lambda t, tr: ["suite", write(t / "s.yaml", {"name": "s", "tasks": {"a": tr["recipe"]}}),
                                            "--time-limit", "2h3"], "--time-limit: cannot read '2h3' as a duration"),
]


@pytest.mark.parametrize("build_argv, expected", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_ends_in_one_line(build_argv, expected, trained, tmp_path, capsys):
    before = digest(trained["run"])
    argv = build_argv(tmp_path, trained)
    capsys.readouterr()
    with warnings.catch_warnings(record=True):  # a warning may come first (e.g. untrusted plugins): not an error line
        try:
            code = main(argv)
        except SystemExit as exit_:  # argparse-level errors (ddp list KIND)
            code = exit_.code
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert "Traceback" not in err
    assert len(lines) == 1 and lines[0].startswith("ddp: error: "), err
    assert expected in lines[0], lines[0]
    assert digest(trained["run"]) == before  # nothing lost


def test_the_battery_is_large_enough():
    assert len(CASES) >= 60 and len({c[0] for c in CASES}) == len(CASES)
