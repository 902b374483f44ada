"""End-to-end learnability on the synthetic pick task (slow: `bash scripts/test.sh --slow`)."""

import pytest

from ddp import build
from conftest import RECIPES

pytestmark = pytest.mark.slow


def test_synthetic_dp3_learns_the_pick_task(tmp_path):
    exp = build(RECIPES / "synthetic/dp3.yaml", [f"train.output_dir={tmp_path}", "train.max_steps=1000"])
    res = exp.train(progress=False)
    exp.load_checkpoint(res.checkpoint)
    rep = exp.evaluate(["id"], episodes=10, output_dir=tmp_path / "eval", progress=False)
    assert rep["protocols"]["id"]["success_rate"] >= 0.8, rep["protocols"]["id"]
