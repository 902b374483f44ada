import copy
import os
from pathlib import Path

import pytest
import torch
import yaml

os.environ.setdefault("MUJOCO_GL", "egl")
ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "recipes"

#: a CPU-sized DDP recipe on synthetic data, shared by the model tests
TINY = {
    "name": "tiny",
    "seed": 0,
    "task": {"action_dim": 4, "agent_pos_dim": 9, "num_points": 64},
    "encoder": {"name": "dp3"},
    "policy": {
        "horizon": 16,
        "obs_steps": 2,
        "action_steps": 8,
        "denoiser": {"name": "unet1d", "down_dims": [16, 32], "n_groups": 4, "diffusion_step_embed_dim": 16,
                     "blocks_per_level": 1, "mid_blocks": 1},
        "scheduler": {"name": "ddim", "num_inference_steps": 4, "prediction_type": "sample"},
    },
    "world_model": {
        "enabled": True,
        "weight": 1.0,
        "denoiser": {"name": "unet1d_wm", "down_dims": [16, 32], "n_groups": 4, "diffusion_step_embed_dim": 16,
                     "blocks_per_level": 1, "mid_blocks": 1},
        "scheduler": {"name": "ddim", "num_inference_steps": 4, "clip_sample": False, "prediction_type": "sample"},
    },
    "data": {"name": "synthetic_reach", "episodes": 4},
    "env": {"name": "synthetic_reach", "num_points": 64, "table_points": 64, "cube_points": 48, "gripper_points": 16},
    "train": {"batch_size": 16, "lr": 1e-3, "warmup_steps": 5, "epochs": 3, "checkpoint_every_epochs": 1,
              "log_every_steps": 5},
}


def fit_normalizer(exp):
    """Fit the model's normaliser on the recipe's demonstrations (as training does first); returns ``exp``."""
    eps = exp.episodes()
    exp.model.normalizer.fit({k: eps.steps[k] for k in ("action", "agent_pos", "point_cloud")})
    return exp


DELTA = [0.2, 0.0, 0.0]  # the synthetic cube's displacement at the start of chunk 1 (seen at cycle 2)


def displaced_exp(recipe: dict, **controller):
    """``recipe`` on the synthetic env displaced by DELTA at chunk 1 (8 chunks of 8 steps), with the oracle
    detector and tracker, target-specific recovery at chunk 4 (``controller`` updates that), normaliser fitted."""
    from ddp import build

    recipe["env"].update(displacement=True, displacement_chunk=1, displacement_delta=DELTA, max_episode_steps=64)
    recipe["controller"] = {
        "detector": {"name": "oracle"},
        "tracker": {"name": "oracle"},
        "recovery": {"name": "target_specific"},
        "subtasks": [{"target": 0, "trigger": {"name": "chunk_index", "chunk": 4}}, {"target": None}],
        **controller,
    }
    return fit_normalizer(build(recipe))


def runnable(**sections) -> dict:
    """TINY that trains and evaluates in seconds: 2 steps, 1 id episode of 16 steps, the base controller.

    A mapping in ``sections`` updates that section; anything else replaces it.
    """
    r = copy.deepcopy(TINY)
    r["train"].update(max_steps=2, epochs=1)
    r["eval"] = {"episodes": 1, "protocols": ["id"], "max_steps": 16}
    r["controller"] = {"detector": {"name": "never"}, "tracker": None, "recovery": {"name": "none"}}
    for k, v in sections.items():
        if isinstance(v, dict) and isinstance(r.get(k), dict):
            r[k].update(v)
        else:
            r[k] = v
    return r


@pytest.fixture
def tiny_recipe():
    return copy.deepcopy(TINY)


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)  # tiny models: 1 thread is faster and immune to busy-waiting OpenMP workers
    yield


@pytest.fixture
def suite_file(tmp_path, monkeypatch):
    """A tiny suite: 2 tasks x 2 methods (DDP, DP3 by overlay) x 2 seeds, 2 training steps, 1 short episode."""
    monkeypatch.chdir(tmp_path)
    recipe = copy.deepcopy(TINY)
    recipe["env"].update(displacement_chunk=0, displacement_delta=[0.2, 0.0, 0.0])
    recipe["train"].update(max_steps=2, epochs=1)
    recipe["eval"] = {"episodes": 1, "max_steps": 16}
    recipe["controller"] = {"detector": {"name": "oracle"}, "tracker": {"name": "oracle"},
                            "recovery": {"name": "target_specific"}}
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(recipe))
    (tmp_path / "dp3.yaml").write_text("base: ignored.yaml\nname: ignored\nworld_model: {enabled: false}\n")
    suite = {
        "name": "tiny_suite",
        "tasks": {"near": "tiny.yaml", "far": {"recipe": "tiny.yaml", "set": ["env.displacement_delta=[0.3, 0, 0]"],
                                              "benchmark": "synthetic"}},
        "methods": {"ddp": {}, "dp3": {"overlay": "dp3.yaml", "protocols": ["id", "ood_tracking"]}},
        "seeds": [0, 1],
        "protocols": ["id", "ood_base"],
        "set": ["train.lr=0.002"],
    }
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(suite, sort_keys=False))
    return path
