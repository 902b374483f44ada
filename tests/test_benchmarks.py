"""Every benchmark script runs (at the smallest sizes) and prints its table: a script reading the envs'
internals broke unnoticed when they changed (benchmarks/metaworld_env.py read a renderer attribute that had
gone). Numbers are not checked: benchmarks print them, tests never time anything. unet_forward.py and
ddp_vs_dp3.py build the paper's sizes only and are left out (the same code paths as train_step.py /
fewer_steps.py and `ddp bench`, which tests/test_training_details.py runs)."""

from __future__ import annotations

import copy
import os
import re
import subprocess
import sys

import pytest
import yaml

from conftest import ROOT, TINY


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("bench") / "tiny.yaml"
    path.write_text(yaml.safe_dump(copy.deepcopy(TINY)))
    return str(path)


CASES = {
    "metaworld_env": (["--repeats", "1", "--image-size", "32", "--num-points", "64"], "metaworld",
                      r"TorchRL step with point cloud +[0-9.]+"),
    "franka_env": (["--steps", "2", "--height", "48", "--width", "64", "--points", "64"], "robosuite",
                   r"per step \(median ms\): step [0-9.]+"),
    "tracker_error": (["--seeds", "1"], "robosuite", r"\| pink \| 1 \| .* \|"),
    "train_step": (["--threads", "1", "--rounds", "1", "--batch", "4", "{tiny}"], None,
                   r"\| \S+tiny\.yaml \| [0-9.]+ ms \| [0-9.]+ ms \| [0-9.]+x"),
    "trainer_steps": (["--threads", "1", "--steps", "2", "--rounds", "1", "t={tiny}"], None,
                      r"t +-?[0-9.]+ ms/step"),  # (a difference of two timings: noise can make 2 steps negative)
    "fewer_steps": (["--recipe", "{tiny}", "--steps", "2,1", "--repeats", "1", "--threads", "1"], None,
                    r"\| 1 \| [0-9.]+ \([0-9.]+x\) \|"),
}


@pytest.mark.parametrize("script", sorted(CASES))
def test_benchmark_script_runs_and_prints_its_table(script, tiny):
    args, needs, expected = CASES[script]
    if needs is not None:
        pytest.importorskip(needs)
    cmd = [sys.executable, str(ROOT / "benchmarks" / f"{script}.py"), *(a.format(tiny=tiny) for a in args)]
    env = {**os.environ, "MUJOCO_GL": "egl", "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.search(expected, done.stdout), done.stdout[-3000:]
