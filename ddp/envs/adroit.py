"""Adroit hand tasks (door, hammer, pen) as a TorchRL env with DP3 point clouds.

The paper evaluates DDP on DP3's Adroit tasks in distribution only (its
"World Model Imagination Analysis": ``id`` and the ``imagination_*``
substitution protocols); there is no displacement protocol on Adroit, so
this env has none. The simulator is gymnasium-robotics'
``AdroitHand{Door,Hammer,Pen}-v1``; ``ddp.envs.adroit_tasks`` records what
DP3 does on top of it and where this env follows it.

Observations (root keys, float32 unless noted), mirroring the ``metaworld`` env:

* ``"point_cloud"`` ``[num_points, 3]``: depth from camera ``camera``
  (default ``fixed``, re-posed to DP3's camera for the task: its ``top``
  camera for door and hammer, its ``vil_camera`` pose for pen),
  back-projected to the world frame, cropped to the box above the table and
  farthest-point-sampled. Sites are hidden. Absent with
  ``render_point_cloud=False``.
* ``"agent_pos"``: with ``agent_pos="hand"`` (default, DP3's choice) the 24
  joint angles of the hand (wrist + fingers, ``adroit_tasks.HAND_JOINTS``);
  with ``"arm_hand"`` every actuated joint (arm first: door 28, hammer 26,
  pen 24, the action's size and order).
* ``"success"`` (bool ``[1]``): the task's ``info["success"]`` at this step
  (door: hinge >= 1.35 rad; hammer: nail within 1 cm of its goal; pen:
  position within 7.5 cm and orientation cosine > 0.95). Pen success is
  not sticky: the pen can leave the goal again.
* ``("privileged", ...)``: ``"state"`` (the gymnasium observation the
  experts read: door 39, hammer 46, pen 45), ``"occluded"`` (bool ``[1]``,
  the cloud is the occlusion's blind one) and ``"seed"`` (int64 ``[1]``,
  the seed of the episode's reset).

Plus ``"reward"`` (gymnasium-robotics' dense reward; not used by ddp),
``"done"``, ``"terminated"`` (True only at a success with
``terminate_on_success``) and ``"truncated"`` (after ``max_episode_steps``;
default the task's original horizon: door and hammer 200, pen 100).

Rendering only what is consumed: ``obs_every=N, obs_history=M`` renders the
cloud after ``t`` actions iff ``t % N == 0`` or ``t % N > N - M`` (and at
reset), as in the ``metaworld`` env; ``ChunkedEnv`` sets them.

Seeding: ``reset(seed=s)`` resets the simulator with ``seed=s`` (the door's
position, the nail board's height, the pen's goal orientation are drawn from
it). Resets without a seed continue from the last seed + 1 (starting at the
constructor's ``seed``, default 0). The same seed gives the same initial
state, the same point clouds and, with the same actions, the same
trajectory.

Disturbances: only the camera occlusion (``occlusion_chunk``, see
``ddp.envs.disturbances.Occlusion``). There is no end-effector shift:
``shift_end_effector`` raises.
"""

from __future__ import annotations

import contextlib
import io
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is first imported (see ddp.envs.metaworld)

from dataclasses import dataclass  # noqa: E402
from typing import Literal  # noqa: E402

import numpy as np  # noqa: E402

from ddp.config import check_choices  # noqa: E402
from ddp.envs.adroit_tasks import ADROIT_TASKS, CROP_MAX, CROP_MIN, HAND_JOINTS, AdroitTask  # noqa: E402
from ddp.envs.base import ObservationOptions  # noqa: E402
from ddp.envs.mujoco_render import CloudCamera, MujocoCloudEnv, SceneRenderer, use_egl  # noqa: E402
from ddp.errors import DDPError  # noqa: E402
from ddp.registry import register  # noqa: E402
from ddp.safety import HoldSpec  # noqa: E402

__all__ = ["AdroitEnvConfig", "AdroitEnv"]


def _import_sim():
    """Import gymnasium-robotics' Adroit envs and mujoco; render through EGL when MUJOCO_GL=egl.

    gymnasium-robotics 1.4.2 prints a notice at import about the *dense
    rewards* of its v1 Adroit envs having changed in 1.2.1; ddp never uses
    those rewards (success is the metric), so the notice is swallowed.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import mujoco

        with contextlib.redirect_stderr(io.StringIO()):
            from gymnasium_robotics.envs import adroit_hand
    except ImportError as err:
        raise ImportError(
            f'the Adroit env needs gymnasium-robotics and mujoco ({err}): pip install "ddp[sim]"'
        ) from None
    use_egl()
    return adroit_hand, mujoco


@dataclass
class AdroitEnvConfig(ObservationOptions):
    """Options of the ``adroit`` env (see the module docstring).

    Attributes:
        task: ``"door"``, ``"hammer"`` or ``"pen"``.
        max_episode_steps: steps before ``truncated`` (null: the task's horizon, 200 / 200 / 100).
        terminate_on_success: end the episode (``terminated``) at the first success.
        render_point_cloud: render the ``point_cloud`` key (False: state only, fast).
        image_size: depth image height = width in pixels (DP3: 84).
        camera: MuJoCo camera name.
        camera_pos, camera_quat: world pose the camera is moved to (w, x, y, z quaternion);
            null: DP3's pose for the task (``adroit_tasks.ADROIT_TASKS``).
        crop_min, crop_max: world-frame box kept in the cloud (default: above the table top).
        num_points: points after farthest point sampling (DP3: 512).
        agent_pos: ``"hand"`` (DP3: the 24 hand joint angles) or ``"arm_hand"`` (every actuated joint).
        obs_every, obs_history: render the cloud after ``t`` actions iff
            ``t % obs_every == 0`` or ``t % obs_every > obs_every - obs_history``.
        chunk_len: actions per chunk; occlusion chunk ``k`` starts at step ``k * chunk_len``.
        occlusion_chunk: first blind chunk (None: no occlusion).
        occlusion_chunks: number of blind chunks.
        occlusion_mode: the blind cloud: ``"zeros"``, ``"drop"`` or ``"noise"``.
    """

    task: Literal["door", "hammer", "pen"] = "door"
    max_episode_steps: int | None = None
    image_size: int = 84
    camera: str = "fixed"
    camera_pos: tuple[float, float, float] | None = None
    camera_quat: tuple[float, float, float, float] | None = None
    crop_min: tuple[float, float, float] = CROP_MIN
    crop_max: tuple[float, float, float] = CROP_MAX
    agent_pos: Literal["hand", "arm_hand"] = "hand"
    obs_every: int = 1
    obs_history: int = 1

    def __post_init__(self):
        check_choices(self)  # before task_spec reads the task (check_observation_options checks them too, later)
        if self.max_episode_steps is None:
            self.max_episode_steps = self.task_spec.max_episode_steps
        self.check_observation_options(positive=("image_size",))
        if self.image_size < 8:
            raise ValueError(f"image_size must be >= 8 pixels; got {self.image_size}")
        if self.camera_pos is not None and len(self.camera_pos) != 3:
            raise ValueError(f"camera_pos needs 3 entries; got {self.camera_pos}")
        if self.camera_quat is not None:
            if len(self.camera_quat) != 4:
                raise ValueError(f"camera_quat needs 4 entries (w, x, y, z); got {self.camera_quat}")
            if not np.isclose(np.linalg.norm(self.camera_quat), 1.0, atol=1e-3):
                raise ValueError(f"camera_quat must be a unit quaternion (w, x, y, z); got {self.camera_quat}")

    @property
    def task_spec(self) -> AdroitTask:
        return ADROIT_TASKS[self.task]

    @property
    def agent_pos_dim(self) -> int:
        return len(HAND_JOINTS) if self.agent_pos == "hand" else self.task_spec.action_dim


@register("env", "adroit", config=AdroitEnvConfig)
class AdroitEnv(MujocoCloudEnv):
    """An Adroit hand task (door, hammer, pen) with DP3 point clouds and optional occlusion."""

    env_name = "adroit env"
    #: holding still: every dimension is an absolute joint target, repeated (none before the first action)
    action_hold = HoldSpec(absolute="all")

    def __init__(self, config: AdroitEnvConfig | None = None, *, seed: int | None = None, device="cpu"):
        cfg = AdroitEnvConfig() if config is None else config
        adroit_hand, mujoco = _import_sim()
        super().__init__(cfg, seed=seed, device=device)
        self.task: AdroitTask = cfg.task_spec
        self._mj = mujoco
        self.sim = getattr(adroit_hand, self.task.env_class)()
        model = self.sim.model

        self._renderer = SceneRenderer(model)  # depth for clouds, colour for videos (lazy)
        cam = self._renderer.camera_id(cfg.camera)
        model.cam_pos[cam] = self.task.camera_pos if cfg.camera_pos is None else cfg.camera_pos
        model.cam_quat[cam] = self.task.camera_quat if cfg.camera_quat is None else cfg.camera_quat
        self._camera = CloudCamera(self._renderer, cam, cfg) if cfg.render_point_cloud else None

        if cfg.agent_pos == "hand":
            joints = [model.joint(name).id for name in HAND_JOINTS]
        else:
            joints = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)]
        self._agent_qpos = np.array([model.jnt_qposadr[j] for j in joints], dtype=np.int64)
        self.action_dim = self.task.action_dim
        self.agent_pos_dim = len(self._agent_qpos)
        self._state = np.zeros(self.task.state_dim)
        self._build_specs()

    # ------------------------------------------------------------- the adapter
    def _privileged_spec(self) -> dict:
        return {"state": self._vec_spec(self.task.state_dim), "seed": self._int_spec(1)}

    def _episode_rng(self, seed: int) -> np.random.Generator:
        # not default_rng(seed): gymnasium's np_random, which draws the layout, is that very stream (occlusion
        # noise drawn from it was a function of the door's or the board's placement)
        return np.random.default_rng([seed, 1])

    def _sim_reset(self, seed: int) -> None:
        # gymnasium seeds must be non-negative; keep distinct seeds distinct
        self._state, _ = self.sim.reset(seed=seed if seed >= 0 else 2**31 + abs(seed))

    def _sim_step(self, action: np.ndarray) -> tuple[float, bool]:
        self._state, reward, _, _, info = self.sim.step(np.clip(action, -1.0, 1.0))
        return float(reward), bool(info["success"])

    def _agent_pos(self) -> np.ndarray:
        return self.sim.data.qpos[self._agent_qpos]

    def _privileged(self) -> dict:
        return {"state": self._f32(self._state), "seed": self._int(self._seed)}

    # ------------------------------------------------------------ public API
    def shift_end_effector(self, delta, *, safe_lift: float = 0.0, settle_steps: int | None = None):
        """Not supported: Adroit has no displacement protocol (the paper evaluates it in distribution)."""
        raise DDPError(
            "the adroit env has no end-effector shift (Adroit has no displacement protocol); "
            "use a controller without a tracker (controller.tracker: null)"
        )

    def render_rgb(self, width: int = 256, height: int = 256, camera: str | None = None) -> np.ndarray:
        """A colour frame ``[height, width, 3]`` uint8 of the current state (videos); ``camera``
        defaults to ``vil_camera`` (the models' 45-degree overview; the point-cloud camera
        looks straight down on door and hammer)."""
        cam = self._renderer.camera_id(camera or "vil_camera", what="video camera")
        return self._renderer.rgb(self.sim.data, cam, width, height)
