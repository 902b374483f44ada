"""The ``franka`` env: the paper's three real-robot tasks as a TorchRL env, simulated or on hardware.

One control loop for every backend (:mod:`ddp.envs.franka.control`): the
7-d action (base-frame translation in metres, rotation vector in radians,
gripper ``> 0`` closes) becomes a clipped absolute end-effector target for
``backend.move_to`` / ``set_gripper``; observations are built from what the
backend returns. ``backend: sim`` is robosuite's Panda
(:mod:`ddp.envs.franka.sim`); ``backend: real`` calls
``ddp.envs.franka.real.make_real_backend(config)`` (imported only then).

Observations (root keys; float32 unless noted), mirroring the MetaWorld env
so that ``ChunkedEnv``, the DDP controller and the evaluation protocols work
unchanged:

* ``"point_cloud"`` ``[num_points, 3]``: the policy camera's depth,
  back-projected to the robot base frame, cropped to ``crop_min..crop_max``
  (the table top, ``z = 0``, is dropped by ``crop_min[2] > 0``; the box ends
  25 cm above the table, so the hand and the objects it works on are kept but
  the upper arm, which would take most of the points and drown a moved
  object's change in the latent, is not), randomly pre-sampled to
  ``presample`` points and farthest-point-sampled to ``num_points`` (the
  paper: 10,000 then 2,048).
* ``"agent_pos"`` ``[15]``: end-effector position, left and right fingertip
  positions (DP3's 9-d layout; the fingertips are ``ee -/+ width/2`` along
  the end-effector y axis, so the ``gripper_closure`` trigger reads the
  finger distance), then the 6-d rotation (first two columns of the
  end-effector rotation matrix). Computed from ``backend.ee_pose()`` and
  ``backend.gripper_width()`` for every backend.
* ``"success"`` (bool ``[1]``): the task's success definition at this step
  (simulation; always False on hardware). ``"failed"`` (bool ``[1]``): the
  task failed for good this episode (press: over-pressed), which revokes an
  earlier success (``ChunkedEnv``).
* ``("privileged", ...)``: ``"object_pos"`` ``[K, 3]`` and ``"object_quat"``
  ``[K, 4]`` (objects in ``task.object_names`` order; zeros where the backend
  does not know them), ``"displacement"`` ``[K, 3]`` (OOD displacement
  currently applied to each object; an end-effector shift made while an object
  is held moves its entry with it, so carrying a displaced object back clears
  it), ``"ee_offset"`` ``[3]`` (sum of end-effector shifts), ``"ee_target"``
  ``[3]`` / ``"ee_target_quat"`` ``[4]`` (the commanded end-effector target),
  ``"occluded"`` (bool ``[1]``), ``"seed"`` and ``"step"`` (int64 ``[1]``).
* ``("tracking", ...)`` with ``tracking_camera: true``: the second camera's
  ``"depth"`` ``[H, W]``, ``"intrinsics"`` ``[3, 3]``, ``"cam_to_world"``
  ``[4, 4]`` (OpenCV axes, base frame) and ``"segmentation"`` ``[H, W]`` int32
  (object index per pixel, -1 elsewhere; all -1 on hardware), with
  ``tracking_rgb: true`` also ``"rgb"`` ``[H, W, 3]`` uint8, rendered at the
  same steps as the point cloud.

Rendering only what is consumed (as the MetaWorld env): with
``obs_every=N, obs_history=M`` the cameras render after ``t`` actions iff
``t % N == 0`` or ``t % N > N - M`` (and at reset).

Disturbances: with ``displacement: true`` the task's schedule
(``FrankaTask.displacements``, e.g. both blocks for stack) moves objects at
the start of their chunks, fully outside their ID zones;
``oracle_tracking: true`` also shifts the end-effector by the same vector
(and back at a two-stage row's snap-back chunk), the MetaWorld oracle
protocol. ``occlusion_chunk`` blinds the policy camera for
``occlusion_chunks`` chunks. Model edits are undone at the next reset.

Public methods as the MetaWorld env: ``shift_end_effector(delta,
safe_lift=0.0, settle_steps=None)`` (moves the arm through the backend,
not counted as env steps; returns the applied shift), ``displace_objects(delta)``
(the task's displaced objects), properties ``steps_done`` and ``task``.

Seeding: ``reset(seed=s)`` samples the ID layout from ``s``; resets
without a seed continue from the last seed + 1. The same seed and actions
give the same trajectory and point clouds.
"""

from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from dataclasses import dataclass, field  # noqa: E402
from typing import ClassVar, Literal  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torchrl.data import Bounded, Composite, Unbounded  # noqa: E402

from ddp.envs.base import ObservationOptions, PointCloudEnv  # noqa: E402
from ddp.envs.franka.backend import RobotMotionError  # noqa: E402
from ddp.envs.disturbances import Displacement  # noqa: E402
from ddp.envs.franka.control import ACTION_DIM, AGENT_POS_DIM, FrankaControl, agent_pos, mat_to_quat  # noqa: E402
from ddp.envs.franka.pointcloud import FrameToCloud  # noqa: E402
from ddp.envs.franka.tasks import TASKS, FrankaTask  # noqa: E402
from ddp.envs.franka.tasks.base import CameraSpec  # noqa: E402
from ddp.errors import suggest  # noqa: E402
from ddp.registry import register  # noqa: E402
from ddp.safety import HoldSpec  # noqa: E402

__all__ = ["FrankaEnvConfig", "FrankaEnv"]

Vec3 = tuple[float, float, float]


@dataclass
class FrankaEnvConfig(ObservationOptions):
    """Options of the ``franka`` env (see the module docstring).

    Attributes:
        task: ``stack``, ``pour`` or ``press``.
        backend: ``sim`` (robosuite Panda) or ``real`` (``ddp.envs.franka.real``).
        max_episode_steps: steps before ``truncated`` (null: the task's, filled in: stack 160, pour 240,
            press 96).
        terminate_on_success: end the episode (``terminated``) at the first success.
        render_point_cloud: render the ``point_cloud`` key (False: proprioception only).
        num_points: points after farthest point sampling (paper: 2048).
        presample: random pre-sample size before FPS (paper: 10,000; 0: none).
        image_height, image_width: policy camera resolution.
        camera_pos, camera_lookat, camera_fovy: policy camera pose (null: the task's, filled in).
        crop_min, crop_max: base-frame box kept in the cloud (null: the task's, filled in: x 0.2..0.85,
            y -0.45..0.45, z 0.004..0.25 -- above the table top, below most of the arm).
        tracking_camera: also return the tracking camera's frames under ``"tracking"``.
        tracking_rgb: include its colour image (``("tracking", "rgb")``, for FoundationPose).
        tracking_image_height, tracking_image_width: its resolution.
        obs_every, obs_history: render after ``t`` actions iff ``t % obs_every == 0`` or
            ``t % obs_every > obs_every - obs_history``.
        chunk_len: actions per chunk; a disturbance at chunk ``k`` happens at step ``k * chunk_len``.
        displacement: apply the task's OOD displacement schedule.
        displacement_chunks, displacement_deltas: override the chunk / vector of each scheduled row.
        oracle_tracking: the env also shifts the end-effector with each displacement (MetaWorld protocol).
        settle_steps: control periods at most per phase of an end-effector shift.
        occlusion_chunk: first blind chunk of the policy camera (null: none).
        occlusion_chunks: number of blind chunks.
        occlusion_mode: the blind cloud: ``zeros``, ``drop`` or ``noise``.
        control_period: seconds per action (16 Hz: the paper's 8-action chunks at 2 Hz).
        max_translation: metres per action and axis.
        max_rotation: radians per action and axis.
        max_lead: metres the commanded target may lead the measured end-effector.
        max_tilt: radians the commanded orientation may turn away from the home pose's (the reset's).
        workspace_min, workspace_max: base-frame box of end-effector targets.
        kp: OSC stiffness of the simulated arm.
        real: options of the hardware backend (read by ``make_real_backend``).
    """

    task: str = "stack"
    backend: Literal["sim", "real"] = "sim"
    max_episode_steps: int | None = None
    num_points: int = 2048
    presample: int = 10000
    image_height: int = 240
    image_width: int = 320
    camera_pos: Vec3 | None = None
    camera_lookat: Vec3 | None = None
    camera_fovy: float | None = None
    crop_min: Vec3 | None = None
    crop_max: Vec3 | None = None
    tracking_camera: bool = False
    tracking_rgb: bool = False
    tracking_image_height: int = 120
    tracking_image_width: int = 160
    obs_every: int = 1
    obs_history: int = 1
    displacement: bool = False
    displacement_chunks: list[int] | None = None
    displacement_deltas: list[Vec3] | None = None
    oracle_tracking: bool = False
    settle_steps: int = 30
    control_period: float = 0.0625
    max_translation: float = 0.02
    max_rotation: float = 0.1
    max_lead: float = 0.03
    max_tilt: float = 2.4
    workspace_min: Vec3 = (0.2, -0.45, 0.0)
    workspace_max: Vec3 = (0.8, 0.45, 0.5)
    kp: float = 300.0
    real: dict = field(default_factory=dict)
    #: options added after demos were cached: at these values a cache's key is as before (ddp.data.cached_demos)
    cache_neutral_defaults: ClassVar[dict] = {"max_tilt": 2.4}

    def judges_success(self) -> bool:
        """Whether the env can tell a success (the task's check on the simulator's state); on a real robot
        (franky-sim included, which shares its code path) a person judges, and evaluations report none."""
        return self.backend == "sim"

    def simulator_truth(self) -> bool:
        """Whether the env knows the objects' true poses and displacements (robosuite, or franky-sim's scene);
        on hardware the privileged keys read zero, so parts that read them are refused at build."""
        return self.backend == "sim" or bool((self.real or {}).get("franky_sim_info"))

    def __post_init__(self):
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {', '.join(TASKS)}; got {self.task!r}{suggest(self.task, TASKS)}")
        if self.real:  # checked with the recipe, not first when the robot backend is built
            from dataclasses import fields as dataclass_fields

            from ddp.envs.franka.real import RealBackendConfig

            names = [f.name for f in dataclass_fields(RealBackendConfig)]
            if not isinstance(self.real, dict):
                raise ValueError(f"real must be a mapping of the real backend's options; got {self.real!r}")
            for key in self.real:
                if key not in names:
                    raise ValueError(f"real: unknown option {key!r}{suggest(str(key), names)}")
        # task defaults are filled in, so that a dumped recipe (and a demo cache key) holds the values used
        task = TASKS[self.task]
        if self.max_episode_steps is None:
            self.max_episode_steps = task.max_episode_steps
        if self.crop_min is None:
            self.crop_min = tuple(task.crop_low)
        if self.crop_max is None:
            self.crop_max = tuple(task.crop_high)
        if self.camera_pos is None:
            self.camera_pos = tuple(task.policy_camera.pos)
        if self.camera_lookat is None:
            self.camera_lookat = tuple(task.policy_camera.lookat)
        if self.camera_fovy is None:
            self.camera_fovy = float(task.policy_camera.fovy)
        self.check_observation_options(
            positive=("image_height", "image_width", "tracking_image_height", "tracking_image_width", "settle_steps")
        )
        if self.presample < 0:
            raise ValueError(f"presample must be >= 0; got {self.presample}")
        if min(self.image_height, self.image_width) < 8:
            raise ValueError(
                f"image_height and image_width must be >= 8 pixels; got {self.image_height}x{self.image_width}"
            )
        for name in ("camera_pos", "camera_lookat", "workspace_min", "workspace_max"):
            value = getattr(self, name)
            if value is not None and len(value) != 3:
                raise ValueError(f"{name} needs 3 entries (x, y, z); got {list(value)}")
        if not all(math.isfinite(v) for v in (*self.workspace_min, *self.workspace_max)):
            raise ValueError(f"workspace_min and workspace_max must be finite; got {list(self.workspace_min)} and "
                             f"{list(self.workspace_max)}")
        if any(a >= b for a, b in zip(self.workspace_min, self.workspace_max)):
            raise ValueError(
                f"workspace_min must be below workspace_max on every axis; got {list(self.workspace_min)} and "
                f"{list(self.workspace_max)}"
            )
        if self.camera_fovy is not None and not 0.0 < self.camera_fovy < 180.0:
            raise ValueError(f"camera_fovy must be in (0, 180) degrees; got {self.camera_fovy}")
        if not (math.isfinite(self.control_period) and self.control_period > 0):  # NaN fails every comparison
            raise ValueError(f"control_period must be a finite number > 0; got {self.control_period} (seconds)")
        for name in ("max_translation", "max_rotation", "max_lead", "kp"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0; got {value}")
        if not (math.isfinite(self.max_tilt) and 0 < self.max_tilt <= math.pi):
            raise ValueError(f"max_tilt must be in (0, pi] radians; got {self.max_tilt}")
        rows = len(TASKS[self.task].displacements)
        for name in ("displacement_chunks", "displacement_deltas"):
            value = getattr(self, name)
            if value is None:
                continue
            if not self.displacement:
                raise ValueError(f"{name} is set but displacement is False")
            if len(value) != rows:
                raise ValueError(
                    f"{name} needs one entry per scheduled displacement of task {self.task!r} ({rows}); "
                    f"got {len(value)}"
                )
        if self.displacement_chunks is not None and any(c < 0 for c in self.displacement_chunks):
            raise ValueError(f"displacement_chunks must be >= 0; got {self.displacement_chunks}")
        if self.displacement_deltas is not None and any(len(d) != 3 for d in self.displacement_deltas):
            raise ValueError(f"displacement_deltas entries need 3 values (dx, dy, dz); got {self.displacement_deltas}")
        for row in self.displacement_schedule():  # as MetaWorld's: a move no chunk acts on measures nothing
            step = row.step(self.chunk_len)
            if not row.acted_on(self.chunk_len, self.max_episode_steps):
                raise ValueError(f"the displacement of {', '.join(row.bodies)} at step {step} is first observed at "
                                 f"step {step + self.chunk_len} ({self.chunk_len} actions per chunk): with "
                                 f"max_episode_steps {self.max_episode_steps} no chunk acts on it (displacement_chunks)")
            if self.oracle_tracking and not row.snaps_back_in(self.chunk_len, self.max_episode_steps):
                raise ValueError(f"the oracle's snap-back of {', '.join(row.bodies)} starts at step "
                                 f"{row.snap_back_step(self.chunk_len)}, past the episode's last step "
                                 f"{self.max_episode_steps - 1} (displacement_chunks)")  # only the oracle snaps back
        if self.oracle_tracking and not self.displacement:
            raise ValueError("oracle_tracking=True needs displacement=True (it tracks the displaced objects)")
        if self.backend == "real" and self.displacement:
            raise ValueError("displacement needs backend 'sim': on the real robot, move the objects by hand")
        if self.tracking_rgb and not self.tracking_camera:
            raise ValueError("tracking_rgb needs tracking_camera=True")

    # ------------------------------------------------------------- resolved
    @property
    def task_spec(self) -> FrankaTask:
        return TASKS[self.task]

    @property
    def episode_steps(self) -> int:
        return int(self.max_episode_steps)

    @property
    def crop_box(self) -> tuple[Vec3, Vec3]:
        return tuple(self.crop_min), tuple(self.crop_max)

    @property
    def policy_camera(self) -> CameraSpec:
        return CameraSpec(tuple(self.camera_pos), tuple(self.camera_lookat), float(self.camera_fovy))

    def displacement_schedule(self) -> tuple[Displacement, ...]:
        if not self.displacement:
            return ()
        rows = TASKS[self.task].displacements
        chunks = self.displacement_chunks or [None] * len(rows)
        deltas = self.displacement_deltas or [None] * len(rows)
        return tuple(r.replace(chunk=c, delta=d) for r, c, d in zip(rows, chunks, deltas))


def make_sim_backend(config: FrankaEnvConfig):
    """The robosuite backend with the config's policy and tracking cameras."""
    from ddp.envs.franka.sim import SimCamera, SimFrankaBackend

    task = config.task_spec
    cameras = {"policy": SimCamera(config.policy_camera, config.image_height, config.image_width)}
    if config.tracking_camera:
        cameras["tracking"] = SimCamera(
            task.tracking_camera, config.tracking_image_height, config.tracking_image_width, segmentation=True,
            rgb=config.tracking_rgb,
        )
    return SimFrankaBackend(task, cameras, control_period=config.control_period, kp=config.kp)


@register("env", "franka", config=FrankaEnvConfig)
class FrankaEnv(PointCloudEnv):
    """Franka Panda tasks (stack, pour, press) with point clouds and the paper's OOD disturbances.

    ``backend``: an already built :class:`FrankaBackend` to use instead of building one from the
    config (its cameras must match the config's image sizes); the caller then closes it.
    """

    env_name = "franka env"
    action_dim = ACTION_DIM
    agent_pos_dim = AGENT_POS_DIM
    #: holding still: translation and rotation deltas at 0, the binary gripper command unchanged (open at reset)
    action_hold = HoldSpec(absolute=(6,), reset={6: -1.0})

    def __init__(self, config: FrankaEnvConfig | None = None, *, seed: int | None = None, device="cpu", backend=None):
        cfg = FrankaEnvConfig() if config is None else config
        super().__init__(cfg, seed=seed, device=device)
        self._task: FrankaTask = cfg.task_spec
        self._owns_backend = backend is None  # a backend passed in is closed by the caller
        if backend is None:
            if cfg.backend == "real":
                from ddp.envs.franka.real import make_real_backend

                backend = make_real_backend(cfg)
            else:
                backend = make_sim_backend(cfg)
        self.backend = backend
        self._is_sim = hasattr(backend, "touching_gripper")
        # a backend with its own safety box (the real robot's) clips inside it: the commanded targets, the
        # shifts' applied amounts and ee_offset are computed in the intersection, so they are what it executes
        low, high = np.asarray(cfg.workspace_min, float), np.asarray(cfg.workspace_max, float)
        box = getattr(getattr(backend, "config", None), "workspace_low", None), \
            getattr(getattr(backend, "config", None), "workspace_high", None)
        if box[0] is not None and box[1] is not None:
            low, high = np.maximum(low, box[0]), np.minimum(high, box[1])
            if np.any(low >= high):
                raise ValueError(f"env workspace {list(cfg.workspace_min)}..{list(cfg.workspace_max)} and the "
                                 f"backend's {list(box[0])}..{list(box[1])} do not overlap")
        self.control = FrankaControl(
            backend, workspace_low=low, workspace_high=high,
            max_translation=cfg.max_translation, max_rotation=cfg.max_rotation, max_lead=cfg.max_lead,
            max_tilt=cfg.max_tilt,
        )  # fmt: skip
        self._plan = cfg.displacement_schedule()
        lo, hi = cfg.crop_box
        self._cloud_fn = FrameToCloud(cfg.num_points, cfg.presample, lo, hi,
                                      on_empty="centre" if self._is_sim else "raise")
        k = len(self._task.object_names)
        self._tracking: dict[str, np.ndarray] | None = None
        self._displacement = np.zeros((k, 3))
        self._tracked = np.zeros((len(self._plan), 3))
        self._ee_offset = np.zeros(3)
        self._task_state: dict = {}
        self._failed = False  # the task failed for good this episode (press: over-pressed)
        self._halted = False  # a robot's reflex stopped a motion: no more motion commands this episode
        self._build_specs()

    # ------------------------------------------------------------- the adapter
    def _privileged_spec(self) -> dict:
        k = len(self._task.object_names)
        vec = self._vec_spec
        spec = dict(
            object_pos=vec(k, 3), object_quat=vec(k, 4), displacement=vec(k, 3), ee_offset=vec(3),
            ee_target=vec(3), ee_target_quat=vec(4), seed=self._int_spec(1), step=self._int_spec(1),
        )  # fmt: skip
        if self._info_keys:  # the task's diagnostics (NaN on hardware), for the evaluation's per-episode report
            spec["task_info"] = Composite({name: vec(1) for name in self._info_keys}, device=self.device)
        return spec

    @property
    def _info_keys(self) -> tuple[str, ...]:
        """The task's diagnostics, and on a robot ``motion_stopped`` (1: a reflex ended the episode's motion)."""
        return tuple(self._task.info_keys) + (() if self._is_sim else ("motion_stopped",))

    def _extra_spec(self) -> dict:
        cfg, dev = self.config, self.device
        failed = {"failed": self._flag_spec()}  # the task failed for good (press: over-pressed)
        if not cfg.tracking_camera:
            return failed
        h, w = cfg.tracking_image_height, cfg.tracking_image_width
        vec = self._vec_spec
        tracking = dict(
            depth=vec(h, w), intrinsics=vec(3, 3), cam_to_world=vec(4, 4),
            segmentation=Unbounded(shape=(h, w), dtype=torch.int32, device=dev),
        )  # fmt: skip
        if cfg.tracking_rgb:
            tracking["rgb"] = Bounded(0, 255, shape=(h, w, 3), dtype=torch.uint8, device=dev)
        return {**failed, "tracking": Composite(tracking, device=dev)}

    def _action_bounds(self):
        low = torch.as_tensor(self.control.action_low, dtype=torch.float32)
        return low, -low

    def _episode_rng(self, seed: int) -> np.random.Generator:
        return np.random.default_rng([abs(seed), 1])

    def _sim_reset(self, seed: int) -> None:
        layout = self._task.sample_layout(np.random.default_rng([abs(seed), 0]))
        self.backend.reset(object_positions=layout, home=True)
        self.control.reset()
        self._displacement[:] = 0.0
        self._tracked[:] = 0.0
        self._ee_offset[:] = 0.0
        self._task_state = self._task.new_state()
        self._failed = False
        self._halted = False

    def _before_action(self, t: int) -> None:
        cfg = self.config
        for i, row in enumerate(self._plan):
            if t == row.step(cfg.chunk_len):
                self._apply_displacement(i, row)
            if cfg.oracle_tracking and t == row.snap_back_step(cfg.chunk_len):
                self.shift_end_effector(-self._tracked[i])
                self._tracked[i] = 0.0

    def _halt(self, err: RobotMotionError) -> None:
        """A reflex (collision, limit) stopped the arm: it holds still for the rest of the episode (no more
        motion commands; the evaluation goes on with the next episode), reported as task_info motion_stopped."""
        import warnings

        self._halted = True
        warnings.warn(f"franka: {err}; the arm holds still for the rest of episode {self._seed}", RuntimeWarning,
                      stacklevel=3)

    def _sim_step(self, action: np.ndarray) -> tuple[float, bool]:
        if not self._halted:
            try:
                self.control.step(action)
            except RobotMotionError as err:
                self._halt(err)
        success = False  # on hardware, success is judged by a person
        if self._is_sim:
            self._task.update(self.backend, self._task_state)
            success = bool(self._task.success(self.backend, self._task_state))
            self._failed = self._failed or bool(self._task.failed(self.backend, self._task_state))
        return float(success), success

    def _agent_pos(self) -> np.ndarray:
        pos, quat = self.backend.ee_pose()
        return agent_pos(pos, quat, self.backend.gripper_width())

    def _privileged(self) -> dict:
        k = len(self._task.object_names)
        positions = self.backend.object_positions()
        quats = getattr(self.backend, "object_quaternions", lambda: None)()
        return {
            "object_pos": self._f32(np.zeros((k, 3)) if positions is None else positions),
            "object_quat": self._f32(np.tile([1.0, 0, 0, 0], (k, 1)) if quats is None else quats),
            "displacement": self._f32(self._displacement),
            "ee_offset": self._f32(self._ee_offset),
            "ee_target": self._f32(self.control.target_pos),
            "ee_target_quat": self._f32(mat_to_quat(self.control.target_rot)),
            "seed": self._int(self._seed),
            "step": self._int(self._steps),
            **self._task_info_output(),
        }

    def _task_info_output(self) -> dict:
        keys = self._info_keys
        if not keys:
            return {}
        info = {**self.task_info(), **({} if self._is_sim else {"motion_stopped": float(self._halted)})}
        return {"task_info": {name: self._f32([info.get(name, float("nan"))]) for name in keys}}

    def _render_cloud(self) -> np.ndarray:
        return self._cloud_fn(self.backend.render("policy"), self._rng)

    def _render_extras(self) -> None:
        if not self.config.tracking_camera:
            return
        frame = self.backend.render("tracking")
        seg = frame.segmentation
        if seg is None:
            seg = np.full(frame.depth.shape, -1, dtype=np.int32)
        self._tracking = {
            "depth": np.asarray(frame.depth, dtype=np.float32),
            "intrinsics": np.asarray(frame.intrinsics, dtype=np.float32),
            "cam_to_world": np.asarray(frame.cam_to_world, dtype=np.float32),
            "segmentation": np.asarray(seg, dtype=np.int32),
        }
        if self.config.tracking_rgb:
            rgb = frame.rgb if frame.rgb is not None else np.zeros((*frame.depth.shape, 3), dtype=np.uint8)
            self._tracking["rgb"] = np.asarray(rgb, dtype=np.uint8)

    def _extra_output(self) -> dict:
        failed = {"failed": self._flag(self._failed)}
        if not self.config.tracking_camera:
            return failed
        return {**failed,
                "tracking": {key: torch.as_tensor(v.copy(), device=self.device) for key, v in self._tracking.items()}}

    def _close_sim(self) -> None:
        """Release the backend (simulator and renderers, or the robot connection) unless the caller owns it."""
        backend = self.__dict__.get("backend")
        if backend is not None and self.__dict__.get("_owns_backend", True):
            backend.close()
        self.__dict__["backend"] = None

    # ------------------------------------------------------- oracle interface
    @property
    def task(self) -> FrankaTask:
        """The task (objects, ID lines, displacement schedule, oracle)."""
        return self._task

    @property
    def task_state(self) -> dict:
        """The task's per-episode bookkeeping (simulation)."""
        return self._task_state

    def task_info(self) -> dict[str, float]:
        """The task's diagnostics now (e.g. balls in the cup, press depth); empty on hardware."""
        return self._task.info(self.backend, self._task_state) if self._is_sim else {}

    def shift_end_effector(self, delta, *, safe_lift: float = 0.0, settle_steps: int | None = None) -> np.ndarray:
        """Move the end-effector by ``delta`` (base frame) with the arm, outside the episode's step count.

        The tracking / recovery action of the paper (``a^track = Delta p``,
        ``a^rec = -Delta p``): the commanded target moves by ``delta`` (clipped to
        the workspace), through ``safe_lift`` metres above if > 0, and the arm is
        driven there for at most ``settle_steps`` control periods per phase
        (default ``config.settle_steps``). Objects held by the gripper move
        with it, and so does their recorded displacement. Returns the applied shift.
        """
        steps = self.config.settle_steps if settle_steps is None else int(settle_steps)
        if steps < 1:
            raise ValueError(f"settle_steps must be >= 1; got {steps}")
        if self._halted:
            return np.zeros(3)
        held = self.backend.grasped() if self._is_sim else np.zeros(len(self._task.object_names), dtype=bool)
        try:
            applied = self.control.shift(delta, safe_lift=safe_lift, max_steps=steps)
        except RobotMotionError as err:  # stopped part-way: what the arm did is unknown, the target is not moved
            self._halt(err)
            return np.zeros(3)
        self._ee_offset += applied
        for k in np.flatnonzero(held):
            self._displacement[k] += applied
            if np.linalg.norm(self._displacement[k]) < 2e-3:  # carried back: no longer displaced
                self._displacement[k] = 0.0
        return applied

    def displace_objects(self, delta) -> None:
        """Move the objects of the task's first scheduled displacement by ``delta`` now."""
        if not self._task.displacements:
            raise ValueError(f"task {self._task.name!r} has no displaceable objects")
        self._displace(self._task.displacements[0].bodies, np.asarray(delta, dtype=np.float64).reshape(3))

    # ---------------------------------------------------------------- helpers
    def _displace(self, names, delta: np.ndarray) -> None:
        deltas = np.zeros((len(self._task.object_names), 3))
        for name in names:
            deltas[self._task.object_names.index(name)] = delta
        self.backend.displace_objects(deltas)
        self._displacement += deltas

    def _apply_displacement(self, i: int, row: Displacement) -> None:
        delta = np.asarray(row.delta, dtype=np.float64)
        self._displace(row.bodies, delta)
        if self.config.oracle_tracking:
            self._tracked[i] = self.shift_end_effector(delta, safe_lift=row.safe_lift)

    def render_rgb(self, width: int = 256, height: int = 256, camera: str | None = None) -> np.ndarray:
        """A colour frame for videos (simulation): ``[height, width, 3]`` uint8 from ``camera`` (default policy)."""
        fn = getattr(self.backend, "render_rgb", None)
        if fn is None:
            raise ValueError(f"{type(self.backend).__name__} cannot render colour frames")
        return fn(camera or "policy", width, height)
