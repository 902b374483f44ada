import os
from pathlib import Path

import pytest
import torch

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


@pytest.fixture
def tiny_recipe():
    import copy

    return copy.deepcopy(TINY)


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)  # tiny models: 1 thread is faster and immune to busy-waiting OpenMP workers
    yield
