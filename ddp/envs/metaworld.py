"""MetaWorld v3 as a TorchRL env: DP3 point clouds and the paper's OOD protocol.

Observations (root keys, float32 unless noted), as in DP3, which the paper
follows for MetaWorld (Sec. 4, Appendix "Details of Simulation OOD
Experiments"):

* ``"point_cloud"`` ``[num_points, 3]``: depth from camera ``corner2``
  re-posed at DP3's ``[0.6, 0.295, 0.8]``, back-projected to the world
  frame, cropped to a workspace box and farthest-point-sampled (sites such
  as the goal marker are hidden unless named in ``visible_sites``). Absent
  when ``render_point_cloud=False``.
* ``"agent_pos"`` ``[9]``: hand position + ``rightEndEffector`` +
  ``leftEndEffector`` site positions.
* ``"success"`` (bool ``[1]``): MetaWorld's success flag at this step.
* ``("privileged", ...)``: simulator truth for oracles, experts and logging:
  ``"state"`` ``[39]`` (MetaWorld's state observation, goal not clipped),
  ``"goal"`` ``[3]`` (the success target ``_target_pos``), ``"ee_offset"``
  ``[3]`` (end-effector shift applied by the oracle so far), ``"task_index"``
  (int64 ``[1]``, which of the 50 MT1 initial states), ``"occluded"`` (bool
  ``[1]``, the cloud is the occlusion's blind one) and, for the paper's
  ten tasks, ``"object_pos"`` ``[K, 3]`` and ``"displacement"`` ``[K, 3]``
  (world position of, and displacement currently applied to, each
  displaceable body in ``MetaWorldTask.bodies`` order).

Plus ``"reward"``, ``"done"``, ``"terminated"`` (MetaWorld never terminates:
True only at a success with ``terminate_on_success``) and ``"truncated"``
(after ``max_episode_steps``).

Rendering only what is consumed: a policy that executes chunks of ``N``
actions and reads the last ``M`` observations of each chunk needs clouds at
those steps only. ``obs_every=N, obs_history=M`` renders the cloud after
``t`` actions iff ``t % N == 0`` or ``t % N > N - M`` (and at reset); the
other steps return the previous cloud unchanged. This keeps the env a plain
one-action-per-step TorchRL env, so it composes with ``MultiAction`` and
``CatFrames`` (append ``CatFrames`` before ``MultiAction`` so it sees every
step).

Seeding: ``reset(seed=s)`` (or ``set_seed(s)`` then ``reset()``) selects MT1
train task ``task_indices[0] + s % (stop - start)``; seeds 0..49 visit the 50
ID initial states once each. Resets without a seed continue from the last
seed + 1 (starting at the constructor's ``seed``, default 0). The same seed
gives the same initial state, the same point clouds and, with the same
actions, the same trajectory.

Disturbances (``ddp.envs.disturbances``): with ``displacement=True`` the
task's row of the paper's table is applied at the start of its chunk:
free-joint bodies move through ``qpos`` (velocity zeroed), fixed bodies
through ``model.body_pos``, and the success target moves where the goal is
attached to the moved body. Every model edit is undone at the next reset.
With ``oracle_tracking=True`` the env also runs the paper's oracle protocol:
the end-effector follows the object at the displacement chunk (with a 5 cm
"safe lift" for pick-place) and, on two-stage tasks, snaps back by
``-delta`` at the snap-back chunk; the carried object's recorded
displacement is then cleared. Each oracle move pauses the episode for
``settle_steps`` simulated steps so the hand reaches its new target
(``pause_fingers=True``: with the fingers held where they are).
``occlusion_chunk`` blinds the camera for ``occlusion_chunks`` chunks.

Public methods for oracle tracker / recovery plugins:
``shift_end_effector(delta, safe_lift=0.0, settle_steps=None)`` (returns the
applied shift), ``displace_objects(delta)``; properties ``steps_done``,
``task_index``, ``task`` (the ``MetaWorldTask`` or None) and ``sim`` (the raw
MetaWorld env).
"""

from __future__ import annotations

import functools
import os

# MuJoCo picks its OpenGL backend when it is first imported (torchrl imports
# it too): render headless through EGL unless the user chose a backend.
os.environ.setdefault("MUJOCO_GL", "egl")

from dataclasses import dataclass  # noqa: E402
from typing import ClassVar  # noqa: E402

import numpy as np  # noqa: E402

from ddp.envs.base import ObservationOptions  # noqa: E402
from ddp.envs.disturbances import Displacement  # noqa: E402
from ddp.envs.metaworld_tasks import METAWORLD_V3_TASKS, PAPER_TASKS, MetaWorldTask, env_name  # noqa: E402
from ddp.envs.mujoco_render import CloudCamera, MujocoCloudEnv, SceneRenderer, use_egl  # noqa: E402
from ddp.errors import suggest  # noqa: E402
from ddp.registry import register  # noqa: E402
from ddp.safety import HoldSpec, require_finite  # noqa: E402

__all__ = ["MetaWorldEnvConfig", "MetaWorldEnv"]

NUM_TRAIN_TASKS = 50  # MT1 builds 50 fixed initial states per task
#: MT1 draws of evaluation seeds past the first 50 are this far apart (calibration uses the draws right after)
EVALUATION_DRAW_STRIDE = 1000
#: MT1 draws of demo attempts past the first 50 (an expert that failed on some states) are this far apart
DEMO_DRAW_STRIDE = 500


def _import_sim():
    """Import metaworld and mujoco; make MuJoCo's renderer use EGL when MUJOCO_GL=egl.

    If mujoco was imported before MUJOCO_GL was set (e.g. by ``import
    torchrl`` ahead of ``ddp``), it chose GLFW, which needs a display; its
    context class is then swapped for the EGL one.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import metaworld
        import mujoco
    except ImportError as err:
        raise ImportError(f'the MetaWorld env needs metaworld and mujoco ({err}): pip install "ddp[sim]"') from None
    use_egl()
    return metaworld, mujoco


@functools.lru_cache(maxsize=None)
def _train_tasks(task: str, seed: int) -> tuple:
    """The 50 MT1 train tasks (initial states) of a task; cached, building them costs ~1 s."""
    metaworld, _ = _import_sim()
    return tuple(metaworld.MT1(env_name(task), seed=seed).train_tasks)


@dataclass
class MetaWorldEnvConfig(ObservationOptions):
    """Options of the ``metaworld`` env (see the module docstring).

    Attributes:
        task: MetaWorld v3 task name without "-v3", e.g. ``"button-press"``.
        seed_tasks: seed of ``metaworld.MT1`` (which 50 initial states exist). The recipes train on draw 0,
            evaluate on draw 1 (``eval.env``) and calibrate detectors on draw 2
            (:meth:`held_out_initial_states`).
        task_indices: ``[start, stop)`` range of MT1 train tasks that resets draw from.
        max_episode_steps: steps before ``truncated``.
        terminate_on_success: end the episode (``terminated``) at the first success.
        render_point_cloud: render the ``point_cloud`` key (False: state-only, fast).
        image_size: depth image height = width in pixels (DP3 uses 128; 84 is faster).
        camera: MuJoCo camera name.
        camera_pos: world position the camera is moved to (None: keep the model's).
        crop_min, crop_max: world-frame workspace box kept in the cloud.
        visible_sites: sites drawn into the depth frames, hence the cloud (default none). ``[goal]``
            shows the goal marker: the only sign of the target in push and pick-place, whose goal
            changes with the initial state (as in soccer and sweep; DP3's renderer draws every site).
            The named sites move to site group 5 of this env's model for good.
        num_points: points after farthest point sampling.
        obs_every, obs_history: render the cloud after ``t`` actions iff
            ``t % obs_every == 0`` or ``t % obs_every > obs_every - obs_history``.
        chunk_len: actions per chunk; disturbance chunk ``k`` starts at step ``k * chunk_len``.
        displacement: apply the paper's displacement for ``task``.
        displacement_chunk, displacement_delta: override its chunk / vector.
        oracle_tracking: apply the paper's oracle end-effector tracking (and snap-back).
        settle_steps: MetaWorld steps simulated (not counted) after each oracle end-effector
            move so the hand reaches it (per phase of a safe-lift move; 0 = bare mocap write).
        pause_fingers: hold the two finger joints where they are during those settle steps (the
            paper pauses the environment while the end-effector moves); False lets the last gripper
            command keep acting, so fingers that had begun to close go on closing on the way.
        occlusion_chunk: first blind chunk (None: no occlusion).
        occlusion_chunks: number of blind chunks.
        occlusion_mode: the blind cloud: ``"zeros"``, ``"drop"`` or ``"noise"``.
    """

    #: options that leave the demo-cache hash alone at this value (added after caches existed)
    cache_neutral_defaults: ClassVar[dict] = {"visible_sites": [], "pause_fingers": False}

    task: str = "button-press"
    seed_tasks: int = 0
    task_indices: tuple[int, int] = (0, NUM_TRAIN_TASKS)
    image_size: int = 84
    camera: str = "corner2"
    camera_pos: tuple[float, float, float] | None = (0.6, 0.295, 0.8)
    crop_min: tuple[float, float, float] = (-0.6, 0.3, -0.01)
    crop_max: tuple[float, float, float] = (0.6, 1.1, 0.7)
    visible_sites: tuple[str, ...] = ()
    obs_every: int = 1
    obs_history: int = 1
    displacement: bool = False
    displacement_chunk: int | None = None
    displacement_delta: tuple[float, float, float] | None = None
    oracle_tracking: bool = False
    settle_steps: int = 10
    pause_fingers: bool = False

    def __post_init__(self):
        self.visible_sites = tuple(self.visible_sites)
        if self.task.endswith("-v3"):
            self.task = self.task[: -len("-v3")]
        if self.task not in METAWORLD_V3_TASKS:
            raise ValueError(
                f"task must be one of the MetaWorld v3 tasks; got {self.task!r}{suggest(self.task, METAWORLD_V3_TASKS)}"
            )
        if len(self.task_indices) != 2:
            raise ValueError(f"task_indices needs 2 entries [start, stop); got {list(self.task_indices)}")
        if self.camera_pos is not None and len(self.camera_pos) != 3:
            raise ValueError(f"camera_pos needs 3 entries; got {list(self.camera_pos)}")
        start, stop = self.task_indices
        if not 0 <= start < stop <= NUM_TRAIN_TASKS:
            raise ValueError(f"task_indices must satisfy 0 <= start < stop <= 50; got {tuple(self.task_indices)}")
        self.check_observation_options(positive=("image_size",))
        if self.image_size < 8:
            raise ValueError(f"image_size must be >= 8 pixels; got {self.image_size}")
        if self.settle_steps < 0:
            raise ValueError(f"settle_steps must be >= 0; got {self.settle_steps}")
        overrides = self.displacement_chunk is not None or self.displacement_delta is not None
        if (self.displacement or self.oracle_tracking or overrides) and self.task not in PAPER_TASKS:
            raise ValueError(
                f"displacement and oracle_tracking need one of the paper's tasks ({', '.join(PAPER_TASKS)}); "
                f"got task {self.task!r}"
            )
        if overrides and not self.displacement:
            raise ValueError("displacement_chunk / displacement_delta are set but displacement is False")
        if self.oracle_tracking and not self.displacement:
            raise ValueError("oracle_tracking=True needs displacement=True (it tracks the displaced object)")
        if self.displacement_chunk is not None and self.displacement_chunk < 0:
            raise ValueError(f"displacement_chunk must be >= 0; got {self.displacement_chunk}")
        if self.displacement_delta is not None and len(self.displacement_delta) != 3:
            raise ValueError(f"displacement_delta needs 3 entries; got {self.displacement_delta}")
        plan = self.displacement_schedule()
        if plan is not None and self.max_episode_steps is not None:
            # a move (or the oracle's snap-back) the episode never reaches would leave an "OOD" protocol
            # measuring an undisturbed episode
            last, move = self.max_episode_steps - 1, plan.step(self.chunk_len)
            if not plan.acted_on(self.chunk_len, self.max_episode_steps):
                raise ValueError(f"displacement_chunk {plan.chunk} starts at step {move} ({self.chunk_len} actions per "
                                 f"chunk): with max_episode_steps {self.max_episode_steps} no chunk acts after the "
                                 f"move is observed (it needs max_episode_steps > {move + self.chunk_len})")
            if self.oracle_tracking and not plan.snaps_back_in(self.chunk_len, self.max_episode_steps):
                raise ValueError(f"the oracle's snap-back chunk {plan.snap_back_chunk} starts at step "
                                 f"{plan.snap_back_step(self.chunk_len)}, past the episode's last step {last} "
                                 f"(max_episode_steps {self.max_episode_steps})")

    def held_out_initial_states(self, block: int = 0) -> dict:
        """Overrides under which no reset draws an initial state that this config's resets draw: a later
        MT1 draw (``seed_tasks + 1 + block``). A reset here picks state ``seed % 50`` of one draw (of the
        ``task_indices`` range), so seeds 50 apart repeat a layout; the detector's calibration rollouts
        (``ddp eval``, ``ddp detect``) use these, else their seeds (the evaluation's + 100000) would replay
        the evaluated layouts, and go to the next ``block`` every :attr:`initial_states_per_draw` seeds, so
        that none of them replays another's."""
        if block < 0:
            raise ValueError(f"block must be >= 0; got {block}")
        return {"seed_tasks": self.seed_tasks + 1 + block}

    def more_initial_states(self, block: int) -> dict:
        """Overrides for evaluation seeds past this config's ``initial_states_per_draw`` (block 1, 2, ...): a
        draw far from the calibration's (``seed_tasks + 1 + block``), so that 100 evaluated episodes start from
        100 initial states (seeds 50 apart would replay one) and none is a calibration episode's."""
        if block < 1:
            raise ValueError(f"block must be >= 1; got {block}")
        return {"seed_tasks": self.seed_tasks + EVALUATION_DRAW_STRIDE * block}

    def demo_initial_states(self, block: int) -> dict:
        """Overrides for demo attempts past this config's ``initial_states_per_draw`` (block 1, 2, ...; an
        expert that failed on some states needs more attempts than there are states): another MT1 draw
        (``seed_tasks + 500 * block``), apart from the evaluation's and the calibration's, so that no two
        demos start from one state (attempt 50 replayed state 0: the same demo twice)."""
        if block < 1:
            raise ValueError(f"block must be >= 1; got {block}")
        return {"seed_tasks": self.seed_tasks + DEMO_DRAW_STRIDE * block}

    @property
    def initial_states_per_draw(self) -> int:
        """How many consecutive seeds reset to distinct initial states (then they repeat)."""
        start, stop = self.task_indices
        return stop - start

    @property
    def task_spec(self) -> MetaWorldTask | None:
        """The task's row of the paper's table (None outside the ten tasks)."""
        return PAPER_TASKS.get(self.task)

    def displacement_schedule(self) -> Displacement | None:
        if not self.displacement:
            return None
        return self.task_spec.displacement.replace(chunk=self.displacement_chunk, delta=self.displacement_delta)


@register("env", "metaworld", config=MetaWorldEnvConfig)
class MetaWorldEnv(MujocoCloudEnv):
    """A MetaWorld v3 task with DP3 point clouds and the paper's OOD disturbances."""

    env_name = "metaworld env"
    action_dim = 4
    agent_pos_dim = 9
    #: holding still: xyz deltas at 0, the gripper (an absolute effort, -1 open after reset) unchanged
    action_hold = HoldSpec(absolute=(3,), reset={3: -1.0})

    def __init__(self, config: MetaWorldEnvConfig | None = None, *, seed: int | None = None, device="cpu"):
        cfg = MetaWorldEnvConfig() if config is None else config
        metaworld, mujoco = _import_sim()
        super().__init__(cfg, seed=seed, device=device)
        self._mj = mujoco
        self.task: MetaWorldTask | None = cfg.task_spec
        self._displacement_plan = cfg.displacement_schedule()

        self._train_tasks = _train_tasks(cfg.task, cfg.seed_tasks)
        self.sim = metaworld.env_dict.ALL_V3_ENVIRONMENTS[env_name(cfg.task)]()
        self.sim.set_task(self._train_tasks[cfg.task_indices[0]])
        self.sim.max_path_length = max(self.sim.max_path_length, cfg.max_episode_steps)
        self._widen_goal_space()
        model = self.sim.model

        # depth for clouds, colour for videos (lazy)
        self._renderer = SceneRenderer(model, visible_sites=cfg.visible_sites)
        cam = self._renderer.camera_id(cfg.camera)
        if cfg.camera_pos is not None:
            model.cam_pos[cam] = cfg.camera_pos
        self._camera = CloudCamera(self._renderer, cam, cfg) if cfg.render_point_cloud else None
        bodies = self.task.bodies if self.task is not None else ()
        self._body_ids = np.array([model.body(b).id for b in bodies], dtype=np.int64)
        self._hand = model.body("hand").id
        self._fingers = (model.site("rightEndEffector").id, model.site("leftEndEffector").id)
        self._mocap = int(model.body_mocapid[model.body("mocap").id])
        finger_joints = [model.joint(name) for name in ("r_close", "l_close")]
        self._finger_qpos = np.array([int(j.qposadr[0]) for j in finger_joints])
        self._finger_qvel = np.array([int(j.dofadr[0]) for j in finger_joints])
        # model state that disturbances edit; restored at every reset
        self._body_pos0 = model.body_pos.copy()
        self._site_pos0 = model.site_pos.copy()

        self._task_index = cfg.task_indices[0]
        self._state = np.zeros(39)
        self._displacement = np.zeros((len(bodies), 3))
        self._ee_offset = np.zeros(3)
        self._tracked = np.zeros(3)
        self._build_specs()

    # ------------------------------------------------------------- the adapter
    def _privileged_spec(self) -> dict:
        spec = {
            "state": self._vec_spec(39),
            "goal": self._vec_spec(3),
            "ee_offset": self._vec_spec(3),
            "task_index": self._int_spec(1),
        }
        if len(self._body_ids):
            spec["object_pos"] = self._vec_spec(len(self._body_ids), 3)
            spec["displacement"] = self._vec_spec(len(self._body_ids), 3)
        return spec

    def _sim_reset(self, seed: int) -> None:
        start, stop = self.config.task_indices
        self._task_index = start + seed % (stop - start)
        self.sim.set_task(self._train_tasks[self._task_index])
        self._widen_goal_space()
        model = self.sim.model
        model.body_pos[:] = self._body_pos0  # undo last episode's displacements
        model.site_pos[:] = self._site_pos0
        self._state, _ = self.sim.reset()
        self._displacement[:] = 0.0
        self._ee_offset[:] = 0.0
        self._tracked[:] = 0.0

    def _before_action(self, t: int) -> None:
        plan, cfg = self._displacement_plan, self.config
        if plan is not None:
            if t == plan.step(cfg.chunk_len):
                self._apply_displacement(plan)
            if cfg.oracle_tracking and t == plan.snap_back_step(cfg.chunk_len):
                self._snap_back()

    def _sim_step(self, action: np.ndarray) -> tuple[float, bool]:
        self._state, reward, _, _, info = self.sim.step(np.clip(action, -1.0, 1.0))
        return float(reward), bool(info["success"])

    def _agent_pos(self) -> np.ndarray:
        data = self.sim.data
        right, left = self._fingers
        return np.concatenate([data.xpos[self._hand], data.site_xpos[right], data.site_xpos[left]])

    def _privileged(self) -> dict:
        privileged = {
            "state": self._f32(self._state),
            "goal": self._f32(self.sim._target_pos),
            "ee_offset": self._f32(self._ee_offset),
            "task_index": self._int(self._task_index),
        }
        if len(self._body_ids):
            privileged["object_pos"] = self._f32(self.sim.data.xpos[self._body_ids])
            privileged["displacement"] = self._f32(self._displacement)
        return privileged

    # ------------------------------------------------------- oracle interface
    @property
    def task_index(self) -> int:
        """Index of the current MT1 train task (initial state)."""
        return self._task_index

    def shift_end_effector(self, delta, *, safe_lift: float = 0.0, settle_steps: int | None = None) -> np.ndarray:
        """Oracle tracking: move the end-effector target (mocap) by ``delta``.

        Paper, Appendix "Oracle State Transitions": the offset is added to
        ``data.mocap_pos`` while "the environment execution is temporarily
        paused". The hand follows the mocap through its weld, so the pause
        simulates ``settle_steps`` MetaWorld steps (default
        ``config.settle_steps``; about 10 bring a 25 cm jump within ~1 cm)
        with the gripper command unchanged (``config.pause_fingers``: the finger
        joints held where they were); they do not count as env steps.
        ``settle_steps=0`` only writes the mocap (the hand then catches up
        during the next actions). The target is clipped to MetaWorld's mocap
        bounds, as the next action would do. With ``safe_lift > 0`` (the
        pick-place "Safe Lift") the move has three settled phases: up by
        ``safe_lift``, across by ``delta``, down again.

        Returns the shift actually applied (after clipping); it is added to
        ``("privileged", "ee_offset")``.
        """
        delta = np.asarray(delta, dtype=np.float64).reshape(3)
        require_finite("end-effector shift", delta, "metaworld env")
        data = self.sim.data
        low, high = self.sim.mocap_low, self.sim.mocap_high
        start = data.mocap_pos[self._mocap].copy()
        target = np.clip(start + delta, low, high)
        n = self.config.settle_steps if settle_steps is None else settle_steps
        if n < 0:
            raise ValueError(f"settle_steps must be >= 0; got {n}")
        if safe_lift > 0.0 and n == 0:  # the three waypoints would collapse into the last one
            raise ValueError("safe_lift needs settle_steps >= 1: with 0 only the last waypoint is written and the "
                             "hand is dragged across the table to it")
        waypoints = [target]
        if safe_lift > 0.0:
            lift = np.array([0.0, 0.0, safe_lift])
            waypoints = [start + lift, target + lift, target]
        for waypoint in waypoints:
            self._settle(np.clip(waypoint, low, high), n)
        self._mj.mj_forward(self.sim.model, data)
        applied = target - start
        self._ee_offset += applied
        return applied

    def displace_objects(self, delta) -> None:
        """Move the task's displaceable bodies by ``delta`` now (and the goal where attached).

        Free-joint bodies move through their joint's ``qpos`` (velocity set to
        zero); other bodies through ``model.body_pos`` (undone at reset). The
        success target ``_target_pos`` moves by ``delta * task.goal_mask``, and so
        does a site that marked it and is not attached to a moved body (soccer's
        ``goal`` site, which MetaWorld keeps at ``_target_pos``): a visible goal
        marker stays on the moved net instead of showing the old place.
        """
        if self.task is None:
            raise ValueError(f"task {self.config.task!r} has no displaceable bodies (not one of the paper's tasks)")
        delta = np.asarray(delta, dtype=np.float64).reshape(3)
        model, data = self.sim.model, self.sim.data
        free = self._mj.mjtJoint.mjJNT_FREE
        for bid in self._body_ids:
            jnt = model.body_jntadr[bid]
            if model.body_jntnum[bid] > 0 and model.jnt_type[jnt] == free:
                qadr, vadr = model.jnt_qposadr[jnt], model.jnt_dofadr[jnt]
                data.qpos[qadr : qadr + 3] += delta
                data.qvel[vadr : vadr + 6] = 0.0
            else:
                parent_rot = data.xmat[model.body_parentid[bid]].reshape(3, 3)
                model.body_pos[bid] += parent_rot.T @ delta
        self._displacement += delta
        old_target = np.asarray(self.sim._target_pos, dtype=np.float64).copy()
        shift = delta * np.asarray(self.task.goal_mask)
        self.sim._target_pos = old_target + shift
        self._mj.mj_forward(model, data)
        if np.any(shift):  # sites still at the old target (not carried by a moved body) mark it: they follow
            for sid in np.flatnonzero(np.linalg.norm(data.site_xpos - old_target, axis=1) < 1e-6):
                parent_rot = data.xmat[model.site_bodyid[sid]].reshape(3, 3)
                model.site_pos[sid] += parent_rot.T @ shift
            self._mj.mj_forward(model, data)

    # ---------------------------------------------------------------- helpers
    def _apply_displacement(self, plan: Displacement) -> None:
        delta = np.asarray(plan.delta, dtype=np.float64)
        self.displace_objects(delta)
        if self.config.oracle_tracking:
            self._tracked = self.shift_end_effector(delta, safe_lift=plan.safe_lift)

    def _snap_back(self) -> None:
        """Two-stage Stage 2: the end-effector (with the grasped object) returns by -delta."""
        self.shift_end_effector(-self._tracked)
        self._tracked = np.zeros(3)
        for k, body in enumerate(self.task.bodies):
            if body in self.task.carried:
                self._displacement[k] = 0.0

    def _settle(self, mocap_pos: np.ndarray, steps: int) -> None:
        data = self.sim.data
        data.mocap_pos[self._mocap] = mocap_pos
        data.mocap_quat[self._mocap] = np.array([1.0, 0.0, 1.0, 0.0])
        nstep = steps * self.sim.frame_skip
        if nstep == 0:
            return
        if not self.config.pause_fingers:
            self._mj.mj_step(self.sim.model, data, nstep=nstep)
            return
        # the arm moves, the fingers stay put: what they hold is still squeezed (the actuators keep
        # their command against it), fingers closing on air stop where they are
        qpos = data.qpos[self._finger_qpos].copy()
        for _ in range(nstep):
            self._mj.mj_step(self.sim.model, data)
            data.qpos[self._finger_qpos] = qpos
            data.qvel[self._finger_qvel] = 0.0

    def _widen_goal_space(self) -> None:
        """Let a displaced goal leave MetaWorld's ID goal box unclipped in the state."""
        from gymnasium.spaces import Box

        if not np.all(np.isinf(self.sim.goal_space.high)):
            self.sim.goal_space = Box(-np.inf, np.inf, shape=(3,), dtype=np.float64)
            self.sim.__dict__.pop("sawyer_observation_space", None)  # a cached_property

    def render_rgb(self, width: int = 256, height: int = 256, camera: str | None = None) -> np.ndarray:
        """A colour frame ``[height, width, 3]`` uint8 of the current state (videos); ``camera``
        defaults to the point-cloud camera. MetaWorld's corner cameras are mounted upside down (their
        images come out with the table on top): a camera whose image-up direction points down gives its
        frame turned 180 degrees (the gripper cameras are upright)."""
        cam = self._renderer.camera_id(camera or self.config.camera, what="video camera")
        upside_down = float(self.sim.data.cam_xmat[cam].reshape(3, 3)[2, 1]) <= 0.0  # image up (camera y): world z
        return self._renderer.rgb(self.sim.data, cam, width, height, upside_down=upside_down)
