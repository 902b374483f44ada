"""Scripted demonstrations of the ``synthetic_reach`` env, generated on the fly (seconds on a CPU)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from tensordict import TensorDict

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

    def episode(self, index: int) -> tuple[TensorDict, bool]:
        env = SyntheticReachEnv(self.env_config, seed=self.seed * 100_003 + index)
        td = env.reset()
        rows, success_at = [], None
        for t in range(self.env_config.max_episode_steps):
            action = env.expert(td)
            rows.append(TensorDict({"point_cloud": td["point_cloud"], "agent_pos": td["agent_pos"], "action": action}, []))
            td = env.step(td.set("action", action))["next"]
            if success_at is None and bool(td["success"]):
                success_at = t
            if success_at is not None and t >= success_at + self.cfg.stop_after_success:
                break
        return torch.stack(rows), success_at is not None

    def load(self) -> Episodes:
        kept, i = [], 0
        while len(kept) < self.cfg.episodes:
            td, ok = self.episode(i)
            i += 1
            if ok:
                kept.append(td)
            if i > 10 * self.cfg.episodes:
                raise RuntimeError("synthetic_reach expert keeps failing; check the env's cube_x / cube_y")
        return Episodes.from_list(kept)


register("dataset", "synthetic_reach", config=SyntheticReachDataConfig)(SyntheticReach)
