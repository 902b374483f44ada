import subprocess
import sys

import pytest

from ddp.cli import main
from conftest import RECIPES


def test_help_for_every_command(capsys):
    for cmd in ([], ["list"], ["recipe"], ["summary"], ["train"]):
        with pytest.raises(SystemExit) as info:
            main([*cmd, "--help"])
        assert info.value.code == 0
        assert "usage: ddp" in capsys.readouterr().out


def test_list_shows_kinds_and_plugins(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for line in ("encoder:", "  dp3", "scheduler:", "  consistency_flow", "dataset:", "  synthetic_reach"):
        assert line in out
    assert main(["list", "scheduler", "--pattern", "dd*"]) == 0
    out = capsys.readouterr().out
    assert "ddim" in out and "consistency_flow" not in out


def test_summary_prints_parameter_counts(capsys):
    assert main(["summary", str(RECIPES / "base/simple_ddp.yaml")]) == 0
    out = capsys.readouterr().out
    assert "encoder" in out and "policy" in out and "world_model" in out and "total" in out


def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"base: {RECIPES / 'quickstart.yaml'}\nworld_model:\n  scheduler:\n    name: ddmp\n")
    assert main(["recipe", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "world_model.scheduler.name: unknown scheduler 'ddmp'" in err


def test_recipe_with_set_prints_resolved_yaml(capsys):
    assert main(["recipe", str(RECIPES / "quickstart.yaml"), "--set", "policy.scheduler.num_inference_steps=5"]) == 0
    out = capsys.readouterr().out
    assert "num_inference_steps: 5" in out


def test_console_script_entry_point_runs():
    out = subprocess.run([sys.executable, "-m", "ddp.cli", "list", "encoder"], capture_output=True, text=True, check=True)
    assert "dp3" in out.stdout


def test_python_dash_m_runs_the_cli():
    out = subprocess.run([sys.executable, "-m", "ddp", "list", "scheduler"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "ddim" in out.stdout and "consistency_flow" in out.stdout


def test_a_closed_pipe_ends_quietly():
    """`ddp list | head -1`: the reader leaves early; no BrokenPipeError traceback."""
    out = subprocess.run(f"{sys.executable} -m ddp list | head -1", shell=True, capture_output=True, text=True,
                         timeout=120)
    assert out.stdout.startswith("encoder:") and "Traceback" not in out.stderr, out.stderr


@pytest.mark.parametrize("command", ["eval", "run"])
def test_sigterm_ends_an_evaluation_through_its_clean_up(tmp_path, command):
    """ddp eval (or ddp run, in its evaluation) stopped by SIGTERM (a scheduler, a robot's supervisor) unwinds
    like Ctrl-C: its envs close (a real robot's backend stops) and it exits 128 + 15 with one line, instead of
    dying mid-motion."""
    import signal
    import threading
    import time

    import torch
    import yaml

    from conftest import runnable
    from ddp.cli import main

    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump(runnable(train={"output_dir": str(tmp_path / "run")},
                                              eval={"episodes": 400, "protocols": ["id"], "max_steps": 48})))
    torch.set_num_threads(1)
    assert main(["train", str(recipe), "--quiet"]) == 0
    argv = (["eval", str(recipe), "--checkpoint", str(tmp_path / "run" / "last.pt"), "--output-dir",
             str(tmp_path / "eval")] if command == "eval" else ["run", str(recipe)])  # run: trained, resumes
    proc = subprocess.Popen([sys.executable, "-m", "ddp", *argv], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    seen = []
    reader = threading.Thread(target=lambda: seen.extend(iter(lambda: proc.stderr.read(1), "")), daemon=True)
    reader.start()
    deadline = time.time() + 180
    while "1/400" not in "".join(seen) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.5)  # until the first id episode is done: envs are open
    assert proc.poll() is None, "".join(seen)[-2000:]
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=60)
    reader.join(timeout=10)
    err = "".join(seen)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "ddp: stopped by SIGTERM" in err and "Traceback" not in err


def test_flags_are_checked_before_any_work(capsys, tmp_path, suite_file):
    """From a read-only review of the CLI: an empty list flag is an error (it meant "all"), ddp run checks its
    protocols and episode count before it trains, detect refuses --num-envs 0, the suite's executor flags are
    alternatives, and list says when nothing matches a pattern."""
    recipe = str(RECIPES / "quickstart.yaml")
    cases = [
        (["run", recipe, "--protocols", "id,ood_dpp", "--set", f"train.output_dir={tmp_path}/r"], "ood_dpp"),
        (["run", recipe, "--episodes", "0", "--set", f"train.output_dir={tmp_path}/r"], "--episodes: must be >= 1"),
        (["run", recipe, "--protocols", "", "--set", f"train.output_dir={tmp_path}/r"], "--protocols: empty"),
        # the DP3 baseline beside DDP with one of DDP's protocols: found before DDP trains (it was after)
        (["run", str(RECIPES / "synthetic" / "ddp.yaml"), str(RECIPES / "synthetic" / "dp3.yaml"), "--protocols",
          "id,ood_ddp", "--set",
          f"train.output_dir={tmp_path}/r"], "protocol ood_ddp"),
        (["run", str(RECIPES / "synthetic" / "ddp.yaml"), str(tmp_path / "typo.yaml"), "--set",
          f"train.output_dir={tmp_path}/r"], "typo.yaml"),
        (["run", str(RECIPES / "synthetic" / "ddp.yaml"), str(RECIPES / "synthetic" / "dp3.yaml"), "--jobs", "2",
          "--protocols", "id,ood_ddp", "--set", f"train.output_dir={tmp_path}/r"], "protocol ood_ddp"),
        (["eval", recipe, "--checkpoint", str(tmp_path / "none.pt"), "--protocols", " , "], "--protocols: empty"),
        (["suite", str(suite_file), "--tasks", ""], "--tasks: empty"),
        (["suite", str(suite_file), "--workers", "2", "--ray"], "--workers and --ray are alternatives"),
        (["suite", str(suite_file), "--gpus-per-run", "1"], "--gpus-per-run 1.0 needs --ray"),
        (["detect", recipe, "--checkpoint", str(tmp_path / "none.pt"), "--num-envs", "0"], "--num-envs: must be >= 1"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert message in err and err.count("\n") == 0, (argv, err)
    assert not (tmp_path / "r").exists()  # nothing trained
    assert main(["list", "scheduler", "--pattern", "zzz*"]) == 0
    assert "(none matching 'zzz*')" in capsys.readouterr().out


def test_version_flag_prints_the_package_version(capsys):
    import ddp
    from ddp.cli import main

    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.strip() == f"ddp {ddp.__version__}"
