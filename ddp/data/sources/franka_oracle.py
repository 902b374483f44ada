"""Franka demonstrations from the task's scripted kinematic oracle, generated once and cached on disk.

The paper collects "25 expert demonstrations per task via a scripted
kinematic oracle that injects spatial variance to efficiently mimic human
data distributions". Here the oracle is the task's
:class:`~ddp.envs.franka.tasks.base.WaypointOracle`: it reads the privileged
object poses and the commanded end-effector target of the ``franka`` env
(simulated backend), follows the task's phases (e.g. above, descend, close,
lift, over, lower, release for stack) with per-episode random variations
(grasp and place offsets, heights, speed, hold times), and each step stores
the point cloud and agent_pos seen *before* its action. Only successful
episodes are kept.

The demos use the recipe's ``env`` section (task, cameras, crop, points)
with the evaluation-only options neutralised (displacement, oracle
tracking, occlusion, the tracking camera, chunked rendering, termination at
success). Episodes last at most ``max_steps`` (default: the task's episode
length) and end ``stop_after_success`` steps after the first success.
Caching (hash in ``<path>/generation.json``, atomic writes, reuse of a
larger cache) is :class:`ddp.data.cached_demos.CachedExpertDemos`.

Seeding: attempt ``i`` resets the env with seed ``seed + i`` (the ID layout
and the oracle's variations are drawn from it). ``seed`` defaults to 0, not
to the recipe's seed, so that training seeds share one dataset.
"""

from __future__ import annotations

from dataclasses import dataclass

from ddp.data.cached_demos import CachedDemosConfig, CachedExpertDemos
from ddp.envs.franka.control import ACTION_DIM, AGENT_POS_DIM
from ddp.errors import RecipeError
from ddp.registry import register

__all__ = ["FrankaOracleConfig", "FrankaOracleDemos"]

CACHE_FORMAT = "ddp-franka-oracle"
CACHE_VERSION = 1

#: env options that only matter at evaluation: reset to their defaults for demos (and the cache hash)
_EVAL_ONLY = (
    "obs_every", "obs_history", "chunk_len", "displacement", "displacement_chunks", "displacement_deltas",
    "oracle_tracking", "settle_steps", "occlusion_chunk", "occlusion_chunks", "occlusion_mode",
    "terminate_on_success", "tracking_camera", "tracking_rgb", "tracking_image_height", "tracking_image_width",
)  # fmt: skip


@dataclass
class FrankaOracleConfig(CachedDemosConfig):
    """Options of the ``franka_oracle`` data source.

    Attributes:
        episodes: successful demonstrations to keep (the paper: 25).
        max_steps: steps per episode at most (null: the task's episode length).
        stop_after_success: end an episode this many steps after the first success.
        seed: seed of the first attempt (attempt i uses seed + i); null: the recipe's seed.
        path: cache directory; ``{task}``, ``{episodes}``, ``{seed}`` and ``{num_points}`` are filled in.
        regenerate: ignore a matching cache and generate again.
        max_attempts: give up after this many episodes (null: 2 * episodes + 10).
        variance: randomise the oracle's motions per episode (false: one nominal motion per layout).
    """

    episodes: int = 25
    max_steps: int | None = None
    stop_after_success: int | None = 8
    path: str = "data/franka/{task}_{num_points}"
    variance: bool = True


class FrankaOracleDemos(CachedExpertDemos):
    """Scripted-oracle demos of a Franka task (successful episodes only), cached under data/franka/."""

    name = "franka_oracle"
    env_name = "franka"
    cache_format = CACHE_FORMAT
    cache_version = CACHE_VERSION
    software = ("mujoco", "robosuite")
    eval_only = _EVAL_ONLY
    record_keys = {"point_cloud": "point_cloud", "agent_pos": "agent_pos", "object_pos": ("privileged", "object_pos")}

    def __init__(self, config: FrankaOracleConfig, *, task, seed: int = 0, env=None):
        if env is not None and env.plugin.name == self.env_name:
            if env.config.backend != "sim":
                raise RecipeError(
                    "data 'franka_oracle' needs env.backend: sim (the scripted oracle reads the simulator's "
                    f"object poses); got {env.config.backend!r}",
                    key="env.backend",
                )
        self.variance = config.variance
        super().__init__(config, task=task, seed=seed, env=env)

    def env_horizon(self, env_config) -> int:
        return int(env_config.episode_steps)

    def check_task(self, task) -> None:
        if (task.action_dim, task.agent_pos_dim, task.point_dim) != (ACTION_DIM, AGENT_POS_DIM, 3):
            raise RecipeError(
                f"franka demos have action_dim {ACTION_DIM}, agent_pos_dim {AGENT_POS_DIM}, point_dim 3; the "
                f"recipe's task says {task.action_dim}, {task.agent_pos_dim}, {task.point_dim}",
                key="task",
            )

    def generation_params(self) -> dict:
        oracle = self.env_config.task_spec.oracle_version
        return {**super().generation_params(), "variance": self.variance, "oracle_version": oracle}

    def _matches(self, meta: dict) -> bool:
        want = self.generation_params()
        return super()._matches(meta) and all(meta.get(k) == want[k] for k in ("variance", "oracle_version"))

    def make_expert(self):
        return self.env_config.task_spec.oracle(variance=self.variance)


register("dataset", "franka_oracle", config=FrankaOracleConfig)(FrankaOracleDemos)
