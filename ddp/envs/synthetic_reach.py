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
``occluded``; ``occlusion_chunk`` blinds the camera for ``occlusion_chunks``
chunks (``occlusion_mode``: all points at the origin by default). The
episode, observation and occlusion logic is the shared
:class:`ddp.envs.base.PointCloudEnv`; this module is its NumPy adapter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDictBase

from ddp.envs.base import ObservationOptions, PointCloudEnv
from ddp.registry import register
from ddp.safety import DELTAS, require_finite

CUBE_HALF = 0.02
ACTION_SCALE = 0.02  # metres per unit action and step
LIFT_HEIGHT = 0.12
GRASP_RADIUS = 0.015  # the closing fingers capture a cube centred within 1.5 cm
START = np.array([0.0, 0.5, 0.2])


@dataclass
class SyntheticReachEnvConfig(ObservationOptions):
    """Options of the ``synthetic_reach`` env (see the module docstring).

    Attributes:
        num_points: points per cloud (a fresh random sample of the scene every step).
        max_episode_steps: steps before ``truncated``.
        terminate_on_success: end the episode (``terminated``) at the first success.
        render_point_cloud: return the ``point_cloud`` key.
        cube_x, cube_y: the ID region of the cube's centre.
        table_points, cube_points, gripper_points: surface samples per part before sub-sampling.
        chunk_len: actions per chunk; disturbance chunk ``k`` starts at step ``k * chunk_len``.
        displacement, displacement_chunk, displacement_delta: move the cube by the delta at the start
            of the chunk (unless it is grasped).
        occlusion_chunk, occlusion_chunks, occlusion_mode: blind chunks and their cloud.
        crop_min, crop_max: the scene box (where ``noise`` / ``drop`` occlusion draws its points).
    """

    num_points: int = 128
    max_episode_steps: int = 48
    cube_x: tuple[float, float] = (-0.1, 0.1)
    cube_y: tuple[float, float] = (0.6, 0.7)
    table_points: int = 256
    cube_points: int = 192
    gripper_points: int = 64
    displacement: bool = False
    displacement_chunk: int = 1
    displacement_delta: tuple[float, float, float] = (0.2, 0.0, 0.0)
    crop_min: tuple[float, float, float] = (-0.5, 0.4, 0.0)
    crop_max: tuple[float, float, float] = (0.5, 0.9, 0.3)

    def __post_init__(self):
        self.check_observation_options(positive=("table_points", "cube_points", "gripper_points"))
        if self.displacement_chunk < 0:
            raise ValueError(f"displacement_chunk must be >= 0; got {self.displacement_chunk}")
        shown = (self.displacement_chunk + 1) * self.chunk_len  # the first observation showing the move
        if self.displacement and shown >= self.max_episode_steps:  # as MetaWorld's: the move must be acted on
            raise ValueError(f"displacement_chunk {self.displacement_chunk} is first observed at step {shown}: with "
                             f"max_episode_steps {self.max_episode_steps} no chunk acts after the move (it needs "
                             f"max_episode_steps > {shown})")


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
class SyntheticReachEnv(PointCloudEnv):
    """Point-cloud pick task (NumPy physics), seeded: the same seed gives the same episode."""

    env_name = "synthetic_reach env"
    action_dim = 4
    agent_pos_dim = 9
    #: holding still: translations and gripper increments are deltas, all 0
    action_hold = DELTAS

    def __init__(self, config: SyntheticReachEnvConfig | None = None, *, seed: int | None = None, device="cpu"):
        super().__init__(config or SyntheticReachEnvConfig(), seed=seed, device=device)
        self.cube, self.ee = np.array([0.0, 0.65, CUBE_HALF]), START.copy()
        self.grip, self.attached = 0.0, False
        self.displacement, self.ee_offset = np.zeros(3), np.zeros(3)
        self._build_specs()

    # ------------------------------------------------------------- the adapter
    def _privileged_spec(self) -> dict:
        return {
            "object_pos": self._vec_spec(1, 3),
            "displacement": self._vec_spec(1, 3),
            "ee_offset": self._vec_spec(3),
            "attached": self._flag_spec(),
        }

    def _episode_rng(self, seed: int) -> np.random.Generator:
        return np.random.default_rng([abs(seed), 1])

    def _sim_reset(self, seed: int) -> None:
        c = self.config
        init = np.random.default_rng([abs(seed), 0])
        self.cube = np.array([init.uniform(*c.cube_x), init.uniform(*c.cube_y), CUBE_HALF])
        self.ee = START + init.normal(0, 0.01, 3)
        self.grip, self.attached = 0.0, False
        self.displacement = np.zeros(3)
        self.ee_offset = np.zeros(3)

    def _before_action(self, t: int) -> None:
        c = self.config
        if c.displacement and t == c.displacement_chunk * c.chunk_len and not self.attached:
            self.displace_objects(np.asarray(c.displacement_delta))

    def _sim_step(self, a: np.ndarray) -> tuple[float, bool]:
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
        success = self._success or (self.attached and self.cube[2] > LIFT_HEIGHT)  # lifted once is a success
        return float(success), success

    def _render_due(self, t: int) -> bool:
        return True  # a fresh sample every step: skipping one would shift the episode's random stream

    def _render_cloud(self) -> np.ndarray:
        c, rng = self.config, self._rng
        table = np.stack(
            [rng.uniform(-0.5, 0.5, c.table_points), rng.uniform(0.4, 0.9, c.table_points), np.zeros(c.table_points)], 1
        )
        cube = _box_surface(rng, self.cube, np.full(3, CUBE_HALF), c.cube_points)
        width = 0.01 + 0.03 * (1.0 - self.grip)
        grip = _box_surface(rng, self.ee + np.array([0, 0, 0.02]), np.array([width, 0.01, 0.02]), c.gripper_points)
        cloud = np.concatenate([table, cube, grip], 0)
        idx = rng.choice(cloud.shape[0], c.num_points, replace=cloud.shape[0] < c.num_points)
        return cloud[idx].astype(np.float32)

    def _agent_pos(self) -> np.ndarray:
        width = 0.01 + 0.03 * (1.0 - self.grip)
        return np.concatenate([self.ee, self.ee + [width, 0, 0], self.ee - [width, 0, 0]])

    def _privileged(self) -> dict:
        return {
            "object_pos": self._f32(self.cube[None]),
            "displacement": self._f32(self.displacement[None]),
            "ee_offset": self._f32(self.ee_offset),
            "attached": self._flag(self.attached),
        }

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
