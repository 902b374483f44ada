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
import torch  # noqa: E402
from tensordict import TensorDict, TensorDictBase  # noqa: E402
from torchrl.data import Bounded, Categorical, Composite, Unbounded  # noqa: E402
from torchrl.envs import EnvBase  # noqa: E402

from ddp.envs.adroit_tasks import ADROIT_TASKS, CROP_MAX, CROP_MIN, HAND_JOINTS, AdroitTask  # noqa: E402
from ddp.envs.cloud_state import CloudStateMixin  # noqa: E402
from ddp.envs.disturbances import OCCLUSION_MODES, Occlusion  # noqa: E402
from ddp.envs.mujoco_render import SceneRenderer, use_egl  # noqa: E402
from ddp.envs.seeding import EpisodeSeeds  # noqa: E402
from ddp.errors import DDPError, suggest  # noqa: E402
from ddp.registry import register  # noqa: E402
from ddp.safety import HoldSpec, require_finite  # noqa: E402

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
class AdroitEnvConfig:
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
    terminate_on_success: bool = False
    render_point_cloud: bool = True
    image_size: int = 84
    camera: str = "fixed"
    camera_pos: tuple[float, float, float] | None = None
    camera_quat: tuple[float, float, float, float] | None = None
    crop_min: tuple[float, float, float] = CROP_MIN
    crop_max: tuple[float, float, float] = CROP_MAX
    num_points: int = 512
    agent_pos: Literal["hand", "arm_hand"] = "hand"
    obs_every: int = 1
    obs_history: int = 1
    chunk_len: int = 8
    occlusion_chunk: int | None = None
    occlusion_chunks: int = 1
    occlusion_mode: Literal["zeros", "drop", "noise"] = "zeros"

    def __post_init__(self):
        if self.task not in ADROIT_TASKS:
            known = ", ".join(ADROIT_TASKS)
            raise ValueError(f"task must be one of {known}; got {self.task!r}{suggest(self.task, ADROIT_TASKS)}")
        if self.max_episode_steps is None:
            self.max_episode_steps = self.task_spec.max_episode_steps
        for name in ("max_episode_steps", "image_size", "num_points", "obs_every", "obs_history", "chunk_len"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1; got {getattr(self, name)}")
        if self.image_size < 8:
            raise ValueError(f"image_size must be >= 8 pixels; got {self.image_size}")
        if self.obs_history > self.obs_every:
            raise ValueError(f"obs_history ({self.obs_history}) must be <= obs_every ({self.obs_every})")
        if self.camera_pos is not None and len(self.camera_pos) != 3:
            raise ValueError(f"camera_pos needs 3 entries; got {self.camera_pos}")
        if self.camera_quat is not None:
            if len(self.camera_quat) != 4:
                raise ValueError(f"camera_quat needs 4 entries (w, x, y, z); got {self.camera_quat}")
            if not np.isclose(np.linalg.norm(self.camera_quat), 1.0, atol=1e-3):
                raise ValueError(f"camera_quat must be a unit quaternion (w, x, y, z); got {self.camera_quat}")
        if len(self.crop_min) != 3 or len(self.crop_max) != 3:
            raise ValueError(f"crop_min and crop_max need 3 entries; got {self.crop_min} and {self.crop_max}")
        if any(lo >= hi for lo, hi in zip(self.crop_min, self.crop_max)):
            raise ValueError(f"crop_min must be below crop_max on every axis; got {self.crop_min} and {self.crop_max}")
        if self.agent_pos not in ("hand", "arm_hand"):
            raise ValueError(f"agent_pos must be 'hand' or 'arm_hand'; got {self.agent_pos!r}")
        if self.occlusion_chunk is not None and self.occlusion_chunk < 0:
            raise ValueError(f"occlusion_chunk must be >= 0; got {self.occlusion_chunk}")
        if self.occlusion_chunks < 1:
            raise ValueError(f"occlusion_chunks must be >= 1; got {self.occlusion_chunks}")
        if self.occlusion_mode not in OCCLUSION_MODES:
            raise ValueError(f"occlusion_mode must be one of {OCCLUSION_MODES}; got {self.occlusion_mode!r}")
        if self.occlusion_chunk is not None and not self.render_point_cloud:
            raise ValueError("occlusion_chunk needs render_point_cloud=True (it corrupts the point cloud)")

    @property
    def task_spec(self) -> AdroitTask:
        return ADROIT_TASKS[self.task]

    @property
    def agent_pos_dim(self) -> int:
        return len(HAND_JOINTS) if self.agent_pos == "hand" else self.task_spec.action_dim

    def occlusion_schedule(self) -> Occlusion | None:
        if self.occlusion_chunk is None:
            return None
        return Occlusion(self.occlusion_chunk, self.occlusion_chunks, self.occlusion_mode)


@register("env", "adroit", config=AdroitEnvConfig)
class AdroitEnv(EpisodeSeeds, CloudStateMixin, EnvBase):
    """An Adroit hand task (door, hammer, pen) with DP3 point clouds and optional occlusion."""

    #: holding still: every dimension is an absolute joint target, repeated (none before the first action)
    action_hold = HoldSpec(absolute="all")

    def __init__(self, config: AdroitEnvConfig | None = None, *, seed: int | None = None, device="cpu"):
        cfg = AdroitEnvConfig() if config is None else config
        adroit_hand, mujoco = _import_sim()
        super().__init__(device=device, batch_size=torch.Size([]))
        self.config = cfg
        self.task: AdroitTask = cfg.task_spec
        self._mj = mujoco
        self._occlusion_plan = cfg.occlusion_schedule()
        self.sim = getattr(adroit_hand, self.task.env_class)()
        model = self.sim.model

        self._renderer = SceneRenderer(model)  # depth for clouds, colour for videos (lazy)
        self._cam = self._renderer.camera_id(cfg.camera)
        model.cam_pos[self._cam] = self.task.camera_pos if cfg.camera_pos is None else cfg.camera_pos
        model.cam_quat[self._cam] = self.task.camera_quat if cfg.camera_quat is None else cfg.camera_quat

        if cfg.agent_pos == "hand":
            joints = [model.joint(name).id for name in HAND_JOINTS]
        else:
            joints = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)]
        self._agent_qpos = np.array([model.jnt_qposadr[j] for j in joints], dtype=np.int64)

        self._init_cloud()

        self._init_seeds(seed)
        self._steps = 0
        self._rng = np.random.default_rng(0)
        self._state = np.zeros(self.task.state_dim)
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        cfg, dev = self.config, self.device
        vec = lambda *shape: Unbounded(shape=shape, dtype=torch.float32, device=dev)  # noqa: E731
        flag = lambda: Categorical(2, shape=(1,), dtype=torch.bool, device=dev)  # noqa: E731
        privileged = Composite(
            state=vec(self.task.state_dim),
            occluded=flag(),
            seed=Unbounded(shape=(1,), dtype=torch.int64, device=dev),
            device=dev,
        )
        obs = {"agent_pos": vec(len(self._agent_qpos)), "success": flag(), "privileged": privileged}
        if cfg.render_point_cloud:
            obs["point_cloud"] = vec(cfg.num_points, 3)
        self.observation_spec = Composite(obs, device=dev)
        self.action_spec = Bounded(-1.0, 1.0, shape=(self.task.action_dim,), dtype=torch.float32, device=dev)
        self.reward_spec = vec(1)
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), device=dev)

    # -------------------------------------------------------------- TorchRL API
    def _reset(self, tensordict: TensorDictBase | None = None, seed: int | None = None, **kwargs) -> TensorDictBase:
        seed = self._episode_seed(seed)
        # gymnasium seeds must be non-negative; keep distinct seeds distinct
        state, _ = self.sim.reset(seed=seed if seed >= 0 else 2**31 + abs(seed))
        self._state = state
        self._rng = np.random.default_rng(abs(seed))
        self._steps = 0
        self._reset_cloud()
        return self._output(reward=None, success=False, terminated=False, truncated=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        cfg = self.config
        action = tensordict.get("action").detach().to("cpu", torch.float64).numpy().reshape(self.task.action_dim)
        require_finite("action", action, "adroit env")
        state, reward, _, _, info = self.sim.step(np.clip(action, -1.0, 1.0))
        self._state = state
        self._steps += 1
        self._update_cloud(self._steps)
        success = bool(info["success"])
        return self._output(
            reward=float(reward),
            success=success,
            terminated=success and cfg.terminate_on_success,
            truncated=self._steps >= cfg.max_episode_steps,
        )

    # ------------------------------------------------------------ public API
    @property
    def steps_done(self) -> int:
        """Actions executed since the last reset."""
        return self._steps

    @property
    def episode_seed(self) -> int:
        """The seed of the current episode's reset."""
        return self._seed

    def shift_end_effector(self, delta, *, safe_lift: float = 0.0):
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

    # ---------------------------------------------------------------- helpers
    def _output(self, *, reward: float | None, success: bool, terminated: bool, truncated: bool) -> TensorDictBase:
        dev = self.device
        f32 = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float32), device=dev)  # noqa: E731
        flag = lambda b: torch.tensor([b], dtype=torch.bool, device=dev)  # noqa: E731
        out = {
            "agent_pos": f32(self.sim.data.qpos[self._agent_qpos]),
            "success": flag(success),
            "privileged": {
                "state": f32(self._state),
                "occluded": flag(self._occluded),
                "seed": torch.tensor([self._seed], dtype=torch.int64, device=dev),
            },
            "done": flag(terminated or truncated),
            "terminated": flag(terminated),
            "truncated": flag(truncated),
        }
        if self.config.render_point_cloud:
            out["point_cloud"] = torch.as_tensor(self._cloud.copy(), device=dev)
        if reward is not None:
            out["reward"] = torch.tensor([reward], dtype=torch.float32, device=dev)
        return TensorDict(out, batch_size=torch.Size([]), device=dev)
