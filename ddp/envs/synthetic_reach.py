"""A tiny point-cloud pick task with the paper's OOD disturbances, in pure NumPy.

The scene: a table plane, a 4 cm cube placed at random in an ID region, and
a gripper. Actions are 4-d: an end-effector displacement (2 cm per unit) and
a gripper command (> 0 closes). Closing around the cube grasps it; success
is the cube lifted above 12 cm. The cube is only visible in the point cloud.

It exists so that the whole pipeline -- demos, joint training, the DDP
controller, evaluation protocols -- can be exercised in seconds on a CPU,
with the same interface as the MuJoCo suites: ``displacement`` moves the cube
out of the ID region at the start of chunk ``displacement_chunk``;
``shift_end_effector`` is the tracking action; ``("privileged", ...)``
holds ``object_pos`` / ``displacement`` [1, 3], ``ee_offset`` and
``occluded``; ``occlusion_chunk`` blinds the camera (all points at the
origin) for ``occlusion_chunks`` chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from ddp.registry import register
from ddp.safety import DELTAS, require_finite

CUBE_HALF = 0.02
ACTION_SCALE = 0.02  # metres per unit action and step
LIFT_HEIGHT = 0.12
GRASP_RADIUS = 0.015  # the closing fingers capture a cube centred within 1.5 cm
START = np.array([0.0, 0.5, 0.2])


@dataclass
class SyntheticReachEnvConfig:
    num_points: int = 128
    max_episode_steps: int = 48
    cube_x: tuple[float, float] = (-0.1, 0.1)
    cube_y: tuple[float, float] = (0.6, 0.7)
    table_points: int = 256
    cube_points: int = 192
    gripper_points: int = 64
    chunk_len: int = 8
    displacement: bool = False
    displacement_chunk: int = 1
    displacement_delta: tuple[float, float, float] = (0.2, 0.0, 0.0)
    occlusion_chunk: int | None = None
    occlusion_chunks: int = 1

    def __post_init__(self):
        if self.num_points < 1:
            raise ValueError(f"num_points must be >= 1; got {self.num_points}")
        if self.max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1; got {self.max_episode_steps}")
        if self.displacement_chunk < 0:
            raise ValueError(f"displacement_chunk must be >= 0; got {self.displacement_chunk}")


def _box_surface(rng: np.random.Generator, center: np.ndarray, half: np.ndarray, n: int) -> np.ndarray:
    pts = rng.uniform(-1.0, 1.0, size=(n, 3))
    face = rng.integers(0, 3, size=n)
    pts[np.arange(n), face] = np.sign(rng.uniform(-1, 1, size=n))
    return center + pts * half


def expert_action(ee: np.ndarray, cube: np.ndarray, attached: bool) -> np.ndarray:
    """The scripted expert: above the cube, down, close, lift."""
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


@register("env", "synthetic_reach", config=SyntheticReachEnvConfig)
class SyntheticReachEnv(EnvBase):
    """Point-cloud pick task (NumPy physics), seeded: the same seed gives the same episode."""

    #: holding still: translations and gripper increments are deltas, all 0
    action_hold = DELTAS

    def __init__(self, config: SyntheticReachEnvConfig | None = None, *, seed: int | None = None, device="cpu"):
        super().__init__(device=device, batch_size=torch.Size([]))
        self.config = config or SyntheticReachEnvConfig()
        self._next_seed = 0 if seed is None else int(seed)
        vec = lambda *s: Unbounded(shape=s, dtype=torch.float32, device=device)  # noqa: E731
        flag = lambda: Categorical(2, shape=(1,), dtype=torch.bool, device=device)  # noqa: E731
        self.observation_spec = Composite(
            point_cloud=vec(self.config.num_points, 3),
            agent_pos=vec(9),
            success=flag(),
            privileged=Composite(
                object_pos=vec(1, 3), displacement=vec(1, 3), ee_offset=vec(3), occluded=flag(),
                attached=flag(), device=device,
            ),
            device=device,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(4,), dtype=torch.float32, device=device)
        self.reward_spec = vec(1)
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), device=device)

    # -------------------------------------------------------------- scene
    def _occluded(self) -> bool:
        c = self.config
        if c.occlusion_chunk is None:
            return False
        chunk = self._steps // c.chunk_len
        return c.occlusion_chunk <= chunk < c.occlusion_chunk + c.occlusion_chunks

    def _cloud(self) -> np.ndarray:
        c, rng = self.config, self._rng
        if self._occluded():
            return np.zeros((c.num_points, 3), dtype=np.float32)
        table = np.stack(
            [rng.uniform(-0.5, 0.5, c.table_points), rng.uniform(0.4, 0.9, c.table_points), np.zeros(c.table_points)], 1
        )
        cube = _box_surface(rng, self.cube, np.full(3, CUBE_HALF), c.cube_points)
        width = 0.01 + 0.03 * (1.0 - self.grip)
        grip = _box_surface(rng, self.ee + np.array([0, 0, 0.02]), np.array([width, 0.01, 0.02]), c.gripper_points)
        cloud = np.concatenate([table, cube, grip], 0)
        idx = rng.choice(cloud.shape[0], c.num_points, replace=cloud.shape[0] < c.num_points)
        return cloud[idx].astype(np.float32)

    def _output(self, reward=None, done=False, truncated=False) -> TensorDictBase:
        width = 0.01 + 0.03 * (1.0 - self.grip)
        fingers = np.concatenate([self.ee + [width, 0, 0], self.ee - [width, 0, 0]])
        f32 = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float32), device=self.device)  # noqa: E731
        flag = lambda b: torch.tensor([bool(b)], device=self.device)  # noqa: E731
        out = {
            "point_cloud": torch.from_numpy(self._cloud()).to(self.device),
            "agent_pos": f32(np.concatenate([self.ee, fingers])),
            "success": flag(self.success),
            "privileged": {
                "object_pos": f32(self.cube[None]),
                "displacement": f32(self.displacement[None]),
                "ee_offset": f32(self.ee_offset),
                "occluded": flag(self._occluded()),
                "attached": flag(self.attached),
            },
            "done": flag(done), "terminated": flag(False), "truncated": flag(truncated),
        }
        if reward is not None:
            out["reward"] = torch.tensor([reward], dtype=torch.float32, device=self.device)
        return TensorDict(out, batch_size=[], device=self.device)

    # -------------------------------------------------------------- TorchRL API
    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._next_seed = int(seed)

    def _reset(self, tensordict=None, **kwargs) -> TensorDictBase:
        seed = self._next_seed
        self._next_seed += 1
        c = self.config
        init = np.random.default_rng([seed, 0])
        self.cube = np.array([init.uniform(*c.cube_x), init.uniform(*c.cube_y), CUBE_HALF])
        self.ee = START + init.normal(0, 0.01, 3)
        self._rng = np.random.default_rng([seed, 1])
        self.grip, self.attached, self.success = 0.0, False, False
        self.displacement = np.zeros(3)
        self.ee_offset = np.zeros(3)
        self._steps = 0
        return self._output()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        c = self.config
        if c.displacement and self._steps == c.displacement_chunk * c.chunk_len and not self.attached:
            self.displace_objects(np.asarray(c.displacement_delta))
        a = tensordict.get("action").detach().cpu().numpy().astype(np.float64)
        require_finite("action", a, "synthetic_reach env")
        self.ee = self.ee + ACTION_SCALE * np.clip(a[:3], -1, 1)
        self.ee[2] = max(self.ee[2], 0.0)
        self.grip = float(np.clip(self.grip + 0.5 * np.clip(a[3], -1, 1), 0.0, 1.0))
        if not self.attached and self.grip >= 1.0 and np.linalg.norm(self.ee - self.cube) < GRASP_RADIUS:
            self.attached = True
        if self.attached and self.grip < 0.5:
            self.attached = False
            self.cube = np.array([self.cube[0], self.cube[1], CUBE_HALF])
        if self.attached:
            self.cube = self.ee.copy()
        self.success = self.success or (self.attached and self.cube[2] > LIFT_HEIGHT)
        self._steps += 1
        truncated = self._steps >= c.max_episode_steps
        return self._output(reward=float(self.success), done=truncated, truncated=truncated)

    # -------------------------------------------------------------- disturbances and tracking
    def displace_objects(self, delta) -> None:
        """Move the cube by ``delta`` now (a sudden OOD displacement)."""
        self.cube = self.cube + np.asarray(delta, dtype=np.float64)
        self.displacement = self.displacement + np.asarray(delta, dtype=np.float64)

    def shift_end_effector(self, delta, *, safe_lift: float = 0.0) -> np.ndarray:
        """Move the end-effector (and a grasped cube) by ``delta``; returns the applied shift."""
        delta = np.asarray(delta, dtype=np.float64).reshape(3)
        require_finite("end-effector shift", delta, "synthetic_reach env")
        self.ee = self.ee + delta
        self.ee_offset = self.ee_offset + delta
        if self.attached:
            self.cube = self.ee.copy()
            self.displacement = self.displacement + delta
        return delta

    def render_rgb(self, width: int = 256, height: int = 256, camera: str | None = None) -> np.ndarray:
        """A top-down colour frame ``[height, width, 3]`` uint8 (videos): table grey, cube red, gripper blue,
        its height shown by the marker size. ``camera`` must be None or ``"top"``."""
        if camera not in (None, "top"):
            raise ValueError(f"the synthetic_reach env has one video camera, 'top'; got {camera!r}")
        image = np.full((height, width, 3), 225, dtype=np.uint8)
        x0, x1, y0, y1 = -0.5, 0.5, 0.4, 0.9  # the table

        def pixel(p):
            u = int(np.clip((p[0] - x0) / (x1 - x0), 0, 1) * (width - 1))
            v = int(np.clip((y1 - p[1]) / (y1 - y0), 0, 1) * (height - 1))
            return u, v

        def disc(p, radius, colour):
            u, v = pixel(p)
            yy, xx = np.ogrid[:height, :width]
            image[(xx - u) ** 2 + (yy - v) ** 2 <= radius**2] = colour

        disc(self.cube, max(2, int(CUBE_HALF / (x1 - x0) * width) + 1), (200, 40, 40))
        disc(self.ee, max(2, int(3 + 20 * self.ee[2])), (40, 70, 200) if self.grip < 0.5 else (20, 20, 90))
        return image

    def expert(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The scripted expert's action for the current state (reads the simulator, not the observation)."""
        return torch.from_numpy(expert_action(self.ee, self.cube, self.attached))
