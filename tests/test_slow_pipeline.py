"""End-to-end learnability on MetaWorld (slow, about 3 min: `bash scripts/test.sh --slow`)."""

import pytest

from ddp import build
from conftest import RECIPES

pytestmark = pytest.mark.slow


def test_dp3_learns_metaworld_button_press(tmp_path):
    pytest.importorskip("metaworld")
    exp = build(RECIPES / "metaworld/quickstart_dp3.yaml", [
        "env.task=button-press", "data.episodes=10", f"data.path={tmp_path}/demos",
        f"train.output_dir={tmp_path}/run", "train.max_steps=700", "train.batch_size=64",
    ])
    res = exp.train(progress=False)
    exp.load_checkpoint(res.checkpoint)
    rep = exp.evaluate(["id"], episodes=5, output_dir=tmp_path / "eval", progress=False)
    assert rep["protocols"]["id"]["success_rate"] >= 0.8, rep["protocols"]["id"]
