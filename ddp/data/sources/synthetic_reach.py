"""Scripted demonstrations of the ``synthetic_reach`` env, generated on the fly (seconds on a CPU)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ddp.data.demos import generate_demos
from ddp.data.episodes import Episodes
from ddp.envs.synthetic_reach import SyntheticReachEnv, SyntheticReachEnvConfig
from ddp.registry import register


@dataclass
class SyntheticReachDataConfig:
    episodes: int = 20
    stop_after_success: int = 5  # keep this many steps after the first success, then cut

    def __post_init__(self):
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1; got {self.episodes}")


class SyntheticReach:
    """``episodes`` successful expert episodes (point_cloud, agent_pos 9-d, action 4-d)."""

    def __init__(self, config: SyntheticReachDataConfig, *, task, seed: int = 0, env=None):
        if task.action_dim != 4 or task.agent_pos_dim != 9 or task.point_dim != 3:
            raise ValueError(
                "synthetic_reach provides action_dim 4, agent_pos_dim 9, point_dim 3; "
                f"the recipe's task says {task.action_dim}, {task.agent_pos_dim}, {task.point_dim}"
            )
        if env is not None and env.plugin.name == "synthetic_reach":
            env_cfg = env.config
        else:
            env_cfg = SyntheticReachEnvConfig(num_points=task.num_points)
        # demonstrations are always in distribution
        self.env_config = dataclasses.replace(env_cfg, num_points=task.num_points, displacement=False, occlusion_chunk=None)
        self.cfg = config
        self.seed = seed

    def load(self) -> Episodes:
        """Successful expert episodes; attempt ``i`` is the env's episode with seed ``seed * 100003 + i``."""
        env = SyntheticReachEnv(self.env_config)  # one env; generate_demos seeds every attempt
        demos, _ = generate_demos(
            lambda: env,
            env.expert,  # the scripted expert reads the simulator state, not the observation
            episodes=self.cfg.episodes,
            seed=self.seed * 100_003,
            max_steps=self.env_config.max_episode_steps,
            stop_after_success=self.cfg.stop_after_success,
            max_attempts=10 * self.cfg.episodes,
            progress=False,
            desc="synthetic_reach demos",
        )
        return demos


register("dataset", "synthetic_reach", config=SyntheticReachDataConfig)(SyntheticReach)
