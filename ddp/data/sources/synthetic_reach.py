"""A tiny point-cloud pick task generated on the fly: real data for tests and smoke runs.

The scene: a table plane, a 4 cm cube placed at random in an ID region, and
a small gripper. A scripted expert moves above the cube, descends, closes
the gripper (the cube attaches), and lifts. The cube's position is only
visible in the point cloud, so a policy has to look; the gripper's own
motion follows the actions, so a world model has dynamics to learn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict

from ddp.data.episodes import Episodes
from ddp.registry import register

CUBE_HALF = 0.02
ACTION_SCALE = 0.02  # metres per unit action and step


@dataclass
class SyntheticReachConfig:
    episodes: int = 20
    max_steps: int = 60
    cube_x: tuple[float, float] = (-0.1, 0.1)
    cube_y: tuple[float, float] = (0.6, 0.7)
    table_points: int = 256
    cube_points: int = 192
    gripper_points: int = 64

    def __post_init__(self):
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1; got {self.episodes}")
        if self.max_steps < 10:
            raise ValueError(f"max_steps must be >= 10; got {self.max_steps}")


def _box_surface(rng: np.random.Generator, center: np.ndarray, half: np.ndarray, n: int) -> np.ndarray:
    pts = rng.uniform(-1.0, 1.0, size=(n, 3))
    face = rng.integers(0, 3, size=n)
    pts[np.arange(n), face] = np.sign(rng.uniform(-1, 1, size=n))
    return center + pts * half


class SyntheticReach:
    """Scripted pick episodes with DP3-style observations (point_cloud, agent_pos 9-d, action 4-d)."""

    def __init__(self, config: SyntheticReachConfig, *, task, seed: int = 0):
        if task.action_dim != 4 or task.agent_pos_dim != 9 or task.point_dim != 3:
            raise ValueError(
                "synthetic_reach provides action_dim 4, agent_pos_dim 9, point_dim 3; "
                f"the recipe's task says {task.action_dim}, {task.agent_pos_dim}, {task.point_dim}"
            )
        self.cfg = config
        self.num_points = task.num_points
        self.seed = seed

    def _observe(self, rng, ee, grip, cube):
        cfg = self.cfg
        table = np.stack(
            [rng.uniform(-0.3, 0.3, cfg.table_points), rng.uniform(0.4, 0.9, cfg.table_points), np.zeros(cfg.table_points)],
            axis=1,
        )
        cube_pts = _box_surface(rng, cube, np.full(3, CUBE_HALF), cfg.cube_points)
        width = 0.01 + 0.03 * (1.0 - grip)
        gripper = _box_surface(rng, ee + np.array([0, 0, 0.02]), np.array([width, 0.01, 0.02]), cfg.gripper_points)
        cloud = np.concatenate([table, cube_pts, gripper], 0)
        idx = rng.choice(cloud.shape[0], self.num_points, replace=cloud.shape[0] < self.num_points)
        fingers = np.concatenate([ee + np.array([width, 0, 0]), ee - np.array([width, 0, 0])])
        return cloud[idx].astype(np.float32), np.concatenate([ee, fingers]).astype(np.float32)

    @staticmethod
    def expert_action(ee, grip, cube, attached) -> np.ndarray:
        above = cube + np.array([0, 0, 0.08])
        if attached:  # lift straight up
            target, g = np.array([cube[0], cube[1], 0.2]), 1.0
        elif np.linalg.norm((ee - above)[:2]) > 0.01:  # move above the cube
            target, g = above, -1.0
        elif ee[2] > cube[2] + 0.005:  # descend
            target, g = cube, -1.0
        else:  # close the gripper
            target, g = ee, 1.0
        delta = np.clip((target - ee) / ACTION_SCALE, -1.0, 1.0)
        return np.concatenate([delta, [g]]).astype(np.float32)

    def episode(self, index: int) -> tuple[TensorDict, bool]:
        cfg = self.cfg
        rng = np.random.default_rng([self.seed, index])
        cube = np.array([rng.uniform(*cfg.cube_x), rng.uniform(*cfg.cube_y), CUBE_HALF])
        ee = np.array([0.0, 0.5, 0.2]) + rng.normal(0, 0.01, 3)
        grip, attached, success_at = 0.0, False, None
        rows = []
        for t in range(cfg.max_steps):
            pc, pos = self._observe(rng, ee, grip, cube)
            a = self.expert_action(ee, grip, cube, attached)
            rows.append((pc, pos, a))
            ee = ee + ACTION_SCALE * a[:3]
            grip = float(np.clip(grip + 0.5 * a[3], 0.0, 1.0))
            if not attached and grip >= 1.0 and np.linalg.norm(ee - cube) < 0.015:
                attached = True
            if attached:
                cube = ee.copy()
            if success_at is None and attached and cube[2] > 0.12:
                success_at = t
            if success_at is not None and t >= success_at + 5:
                break
        td = TensorDict(
            {
                "point_cloud": torch.from_numpy(np.stack([r[0] for r in rows])),
                "agent_pos": torch.from_numpy(np.stack([r[1] for r in rows])),
                "action": torch.from_numpy(np.stack([r[2] for r in rows])),
            },
            batch_size=[len(rows)],
        )
        return td, success_at is not None

    def load(self) -> Episodes:
        """``episodes`` successful demonstrations (failed ones are skipped)."""
        kept, i = [], 0
        while len(kept) < self.cfg.episodes:
            td, ok = self.episode(i)
            i += 1
            if ok:
                kept.append(td)
            if i > 10 * self.cfg.episodes:
                raise RuntimeError("synthetic_reach expert keeps failing; check cube_x / cube_y")
        return Episodes.from_list(kept)


register("dataset", "synthetic_reach", config=SyntheticReachConfig)(SyntheticReach)
