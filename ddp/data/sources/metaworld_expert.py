"""MetaWorld demonstrations from the task's scripted expert, generated once and cached on disk.

The paper trains on "a fixed dataset of 50 demonstrations per task"
generated DP3-style: MetaWorld's scripted policy
(``metaworld.policies.ENV_POLICY_MAP``) reads the 39-d simulator state (the
env's ``("privileged", "state")``), episodes of at most ``max_steps`` steps
are kept only when they succeed, and each step stores the point cloud and
agent_pos seen *before* its action. A point cloud is rendered at every step
(all frames are training data), whatever the recipe's ``obs_every`` says.

The demos use the recipe's ``env`` section (task, camera, crop, image size,
number of points, MT1 initial states) with the evaluation-only options
neutralised: no displacement, oracle tracking or occlusion, no termination
at success. Caching (hash in ``<path>/generation.json``, atomic writes,
reuse of larger caches) is :class:`ddp.data.cached_demos.CachedExpertDemos`.

Seeding: attempt ``i`` resets the env with seed ``seed + i``; the MetaWorld
env maps seed ``s`` to MT1 initial state ``start + s % (stop - start)``
of ``env.task_indices = [start, stop)`` (``s % 50`` with the default range). ``seed`` defaults to 0, not to the recipe's seed, so
that training seeds 0, 1, 2 share one dataset as in the paper.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from ddp.data.cached_demos import CachedDemosConfig, CachedExpertDemos
from ddp.data.cached_demos import demo_env_config as _demo_env_config
from ddp.errors import RecipeError
from ddp.registry import register

__all__ = ["MetaWorldExpertConfig", "MetaWorldExpertDemos", "MetaWorldExpert", "demo_env_config", "expert_succeeds"]

CACHE_FORMAT = "ddp-metaworld-expert"
CACHE_VERSION = 1

#: env options that only matter at evaluation: reset to their defaults for demos (and the cache hash)
_EVAL_ONLY = (
    "obs_every", "obs_history", "chunk_len", "displacement", "displacement_chunk", "displacement_delta",
    "oracle_tracking", "settle_steps", "pause_fingers", "occlusion_chunk", "occlusion_chunks", "occlusion_mode",
    "terminate_on_success",
)  # fmt: skip


@dataclass
class MetaWorldExpertConfig(CachedDemosConfig):
    """Options of the ``metaworld_expert`` data source.

    Attributes:
        episodes: successful demonstrations to keep (the paper: 50; DP3: 10).
        max_steps: steps per episode at most (DP3: 200).
        stop_after_success: end an episode this many steps after the first success
            (null: DP3's full ``max_steps`` length).
        seed: seed of the first attempt (attempt i uses seed + i); null: the recipe's seed.
        path: cache directory; ``{task}``, ``{episodes}``, ``{seed}``, ``{num_points}`` and
            ``{image_size}`` are filled in.
        regenerate: ignore a matching cache and generate again.
        max_attempts: give up after this many episodes (null: 2 * episodes + 10).
    """

    path: str = "data/metaworld/{task}"


def demo_env_config(env_config, max_steps: int):
    """The env config used for demos: the recipe's, with evaluation-only options at their defaults."""
    return _demo_env_config(env_config, max_steps, _EVAL_ONLY)


class MetaWorldExpert:
    """MetaWorld's scripted policy as a ``tensordict -> action`` callable (reads ``("privileged", "state")``).

    With ``id_frame=True`` the expert reads the state with the applied displacement and
    end-effector shifts removed (``id_frame_state``): it acts as if nothing had moved, the
    situation the paper's oracle tracking is meant to rescue.
    """

    def __init__(self, task: str, id_frame: bool = False):
        try:
            from metaworld.policies import ENV_POLICY_MAP
        except ImportError as err:
            raise ImportError(f'metaworld demonstrations need metaworld ({err}): pip install "ddp[sim]"') from None
        name = f"{task}-v3"
        if name not in ENV_POLICY_MAP:
            raise ValueError(f"metaworld has no scripted policy for task {task!r}")
        self.policy = ENV_POLICY_MAP[name]()
        self.id_frame = None
        if id_frame:
            from ddp.envs.metaworld_tasks import PAPER_TASKS

            self.id_frame = PAPER_TASKS[task]

    def __call__(self, tensordict) -> np.ndarray:
        state = tensordict.get(("privileged", "state")).detach().cpu().double().numpy()
        if self.id_frame is not None:
            from ddp.envs.metaworld_tasks import id_frame_state

            p = tensordict.get("privileged")
            state = id_frame_state(self.id_frame, state, p["displacement"].numpy(), p["ee_offset"].numpy())
        with warnings.catch_warnings():  # the policies warn that their gains exceed [-1, 1]
            warnings.filterwarnings("ignore", message="Constant")
            action = self.policy.get_action(state)
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def expert_succeeds(env, expert, seed: int) -> bool:
    """Run ``expert`` for one episode of ``env`` from ``seed``; True at the first success."""
    td = env.reset(seed=seed)
    while True:
        td["action"] = torch.as_tensor(expert(td), dtype=torch.float32)
        td = env.step(td)["next"]
        if bool(td["success"]):
            return True
        if bool(td["done"]):
            return False


class MetaWorldExpertDemos(CachedExpertDemos):
    """MetaWorld scripted-expert demos (successful episodes only), cached under data/metaworld/<task>."""

    name = "metaworld_expert"
    env_name = "metaworld"
    cache_format = CACHE_FORMAT
    cache_version = CACHE_VERSION
    software = ("mujoco", "metaworld")
    eval_only = _EVAL_ONLY
    record_keys = {"point_cloud": "point_cloud", "agent_pos": "agent_pos", "full_state": ("privileged", "state")}

    def check_task(self, task) -> None:
        if (task.action_dim, task.agent_pos_dim, task.point_dim) != (4, 9, 3):
            raise RecipeError(
                "metaworld demos have action_dim 4, agent_pos_dim 9, point_dim 3; the recipe's task says "
                f"{task.action_dim}, {task.agent_pos_dim}, {task.point_dim}",
                key="task",
            )

    def make_expert(self) -> MetaWorldExpert:
        return MetaWorldExpert(self.env_config.task)


register("dataset", "metaworld_expert", config=MetaWorldExpertConfig)(MetaWorldExpertDemos)
