"""The README's minimal plugin per kind: these very blocks register, build, train and evaluate together."""

from __future__ import annotations

import math
import re

import pytest
import torch

from conftest import ROOT
from ddp import build, registry
from ddp.contracts import CONTRACTS

EXAMPLES = {  # kind -> registered name, as in the README
    "detector": "fixed_tau", "tracker": "scaled_truth", "recovery": "undo_target_accept_rest", "trigger": "after_chunks",
    "encoder": "mean_point", "denoiser": "mlp_denoiser", "scheduler": "one_step", "dataset": "random_walk",
    "env": "drift", "protocol": "short_id",
}


def readme_blocks() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("<!-- plugin-examples -->")[1].split("<!-- /plugin-examples -->")[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


@pytest.fixture(scope="module")
def examples():
    import sys
    import types

    module = types.ModuleType("readme_plugin_examples")  # dataclasses need their module in sys.modules
    sys.modules[module.__name__] = module
    try:
        for block in readme_blocks():
            exec(compile(block, "README.md", "exec"), module.__dict__)  # noqa: S102 - our own README
        yield module
    finally:
        sys.modules.pop(module.__name__, None)
        for kind, name in EXAMPLES.items():
            registry.unregister(kind, name)


def test_one_example_per_kind(examples):
    assert set(EXAMPLES) == set(CONTRACTS)
    for kind, name in EXAMPLES.items():
        assert name in registry.list_plugins(kind), (kind, name)


def test_a_model_made_of_the_examples_trains_and_evaluates(examples, tmp_path):
    recipe = {
        "name": "readme_plugins",
        "task": {"action_dim": 4, "agent_pos_dim": 9, "num_points": 64},
        "encoder": {"name": "mean_point"},
        "policy": {"horizon": 8, "obs_steps": 2, "action_steps": 4,
                   "denoiser": {"name": "mlp_denoiser"}, "scheduler": {"name": "one_step"}},
        "world_model": {"denoiser": {"name": "mlp_denoiser"}, "scheduler": {"name": "one_step"}},
        "data": {"name": "random_walk"},
        "env": {"name": "drift"},
        "controller": {"detector": {"name": "fixed_tau", "tau": 1e-9}, "tracker": {"name": "scaled_truth"},
                       "recovery": {"name": "undo_target_accept_rest"},
                       "subtasks": [{"target": None, "trigger": {"name": "after_chunks", "chunks": 2}}]},
        "train": {"batch_size": 8, "max_steps": 3, "warmup_steps": 1, "output_dir": str(tmp_path / "run")},
        "eval": {"episodes": 2, "protocols": ["id", "imagination_50", "short_id"], "calibration_episodes": 1},
    }
    exp = build(recipe)
    res = exp.train(progress=False)
    assert res.steps == 3 and math.isfinite(res.loss)
    report = exp.evaluate(output_dir=tmp_path / "eval", progress=False)
    assert list(report["protocols"]) == ["id", "imagination_50", "short_id"]
    assert all(p["episodes"] == 2 for p in report["protocols"].values())
    assert all(ep["chunks"] == 2 for ep in report["protocols"]["short_id"]["per_episode"])  # 8 steps, N = 4
    assert all(ep["chunks"] == 4 for ep in report["protocols"]["id"]["per_episode"])
    # the controller drives the example env through episodes: D_R-I from the example detector (tau
    # tiny: OOD from the first forecast on) and the example trigger ending the subtask after 2 chunks
    from tensordict import TensorDict

    from ddp.evaluate import make_chunked_env

    ctrl = exp.make_controller(tracker=False)
    env = make_chunked_env(exp, seed=0)
    r = env.rollout(4, ctrl, break_when_any_done=False)
    assert r["ddp", "mode"].tolist() == [0, 1, 1, 1] and torch.isfinite(r["action"]).all()
    assert r["ddp", "subtask"].tolist() == [0, 0, 1, 1]
    # the example tracker and recovery on a displaced object (the drift env has none)
    tracker, recovery = exp.make_controller().tracker, exp.parts["controller.recovery"].build()
    td = TensorDict({("privileged", "displacement"): torch.tensor([[[0.1, 0.0, 0.0], [0.0, 0.2, 0.0]]])}, [1])
    offsets = tracker(td)["ddp", "offsets"][0]
    shift, recovered = recovery.recover(offsets, torch.tensor([True, False]), target=0)
    assert torch.allclose(shift, torch.tensor([-0.1, 0.0, 0.0])) and recovered.tolist() == [True, False]
