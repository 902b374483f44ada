"""The simulated Franka backend: robosuite's Panda under OSC_POSE with a task scene and fast depth cameras.

``SimFrankaBackend`` implements :class:`~ddp.envs.franka.backend.FrankaBackend`
on robosuite 1.5 (MuJoCo):

* **Robot**: robosuite's Panda with its Franka Hand, operational-space control
  (``OSC_POSE``) with *absolute* targets in the robot base frame
  (``input_type="absolute"``, ``input_ref_frame="base"``), ``kp`` 300. One
  ``move_to`` = one robosuite step of ``control_period`` seconds (16 Hz: the
  paper's 8-action chunks at 2 Hz). The robot's base sits at the table's
  edge at table height, so the table top is ``z = 0`` of the base frame, and
  the base frame is the world frame translated by the base position.
* **End-effector frame**: robosuite's ``grip_site`` (between the finger pads)
  rotated 90 degrees about its z axis, so that its axes are those of the real
  Franka's TCP frame (x forward, y along the finger motion, z along the
  approach; "straight down" is 180 degrees about the base x axis).
* **Scene**: the task's MJCF bodies (``FrankaTask.mjcf``) are appended to
  robosuite's table arena; free bodies are placed through their joint, fixed
  bodies through ``model.body_pos``; ``hard_reset=False`` (a reset restores
  the initial MuJoCo state, ~1 ms, instead of rebuilding the model).
* **Cameras**: robosuite's camera pipeline is off (it costs ~50 ms per step
  here: shadows, reflections, multisampling); each named camera is a MuJoCo
  camera added to the model and rendered on demand by a depth-only
  ``mujoco.Renderer`` (no shadows, no multisampling, sites hidden; the
  robot and table as their collision geoms, ~12x fewer triangles than the
  visual meshes, which only colour frames for videos use). ``render`` returns a :class:`CameraFrame` with OpenCV-axes
  ``cam_to_world`` in the base frame and, for cameras with segmentation on,
  MuJoCo's segmentation pass mapped to object indices (-1 elsewhere).

robosuite and MuJoCo are imported when the backend is built, never at import
time of this module.
"""

from __future__ import annotations

import atexit
import os
import weakref
import xml.etree.ElementTree as ET
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ddp.envs.franka.backend import CameraFrame, FrankaBackend
from ddp.envs.franka.control import mat_to_quat, mat_to_rotvec, quat_to_mat
from ddp.envs.franka.tasks.base import DOWN, CameraSpec, FrankaTask
from ddp.errors import suggest

__all__ = ["SimCamera", "SimFrankaBackend", "EE_FROM_SITE"]

#: rotation from robosuite's grip_site frame to the Franka TCP frame (90 degrees about z)
EE_FROM_SITE = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
TABLE_SIZE = (0.8, 1.0, 0.05)  # full x, y extent and thickness of robosuite's table arena
TABLE_TOP = 0.8  # world z of the table top
BASE_WORLD = np.array([-0.56, 0.0, TABLE_TOP])  # robot base in world coordinates
MOUNT_HEIGHT = np.array([0.0, 0.0, 0.912])  # robosuite puts the Panda's base this far above the position it is given
FAR = 4.0  # metres: depth beyond this is "no return" (0)
TASK_GROUP = 3  # geom group of the task's objects
GRIPPER_GEOMS = ("finger1_collision", "finger1_pad_collision", "finger2_collision", "finger2_pad_collision")


@dataclass(frozen=True)
class SimCamera:
    """A simulated depth camera: pose, image size, and whether to render segmentation / colour."""

    spec: CameraSpec
    height: int = 120
    width: int = 160
    segmentation: bool = False
    rgb: bool = False


def _import_sim():
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import mujoco
        import robosuite  # noqa: F401  (checked here: the install hint names both)
    except ImportError as err:
        raise ImportError(
            f'the simulated Franka backend needs robosuite and mujoco ({err}): pip install "ddp[sim]"'
        ) from None
    if os.environ["MUJOCO_GL"].lower() == "egl":
        from mujoco import gl_context

        if getattr(gl_context, "GLContext", None) is None or gl_context.GLContext.__module__ != "mujoco.egl":
            from mujoco.egl import GLContext

            gl_context.GLContext = GLContext
    return mujoco


_OPEN: weakref.WeakSet = weakref.WeakSet()
_exit_hook = False


def _close_all() -> None:
    for backend in list(_OPEN):
        backend.close()


def _track(backend) -> None:
    """Close backends nobody closed before EGL shuts down at exit (no EGL errors at exit).

    ``atexit`` runs hooks last-in first-out and MuJoCo registers EGL's termination
    when its first context is created, so a hook registered after that runs first.
    """
    global _exit_hook
    if not _exit_hook:
        atexit.register(_close_all)
        _exit_hook = True
    _OPEN.add(backend)


def _look_at_xyaxes(pos, lookat, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo camera x and y axes (world) for a camera at ``pos`` looking at ``lookat``."""
    f = np.asarray(lookat, dtype=np.float64) - np.asarray(pos, dtype=np.float64)
    f /= np.linalg.norm(f)
    x = np.cross(f, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-6:  # looking straight down: pick the base x axis as image "up"
        x = np.cross(f, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(x, f)
    return x, y


def _make_scene_class():
    """robosuite env holding the Panda, the table and the task's bodies (built lazily)."""
    from robosuite.environments.manipulation.manipulation_env import ManipulationEnv
    from robosuite.models.arenas import TableArena
    from robosuite.models.tasks import ManipulationTask

    class FrankaScene(ManipulationEnv):
        def __init__(self, task: FrankaTask, cameras: dict[str, SimCamera], **kwargs):
            self.task = task
            self.ddp_cameras = cameras
            super().__init__(**kwargs)

        def _load_model(self):
            super()._load_model()
            self.robots[0].robot_model.set_base_xpos(BASE_WORLD - MOUNT_HEIGHT)
            arena = TableArena(
                table_full_size=TABLE_SIZE, table_offset=(0.0, 0.0, TABLE_TOP), table_friction=(1.0, 5e-3, 1e-4)
            )
            arena.set_origin([0, 0, 0])
            self.model = ManipulationTask(mujoco_arena=arena, mujoco_robots=[r.robot_model for r in self.robots])
            assets, bodies = self.task.mjcf()
            for el in ET.fromstring(f"<w>{assets}</w>"):
                self.model.asset.append(el)
            for el in ET.fromstring(f"<w>{bodies}</w>"):  # bodies, and <exclude> contact pairs
                (self.model.contact if el.tag == "exclude" else self.model.worldbody).append(el)
            for name, cam in self.ddp_cameras.items():
                pos = BASE_WORLD + np.asarray(cam.spec.pos)
                x, y = _look_at_xyaxes(pos, BASE_WORLD + np.asarray(cam.spec.lookat))
                el = ET.Element("camera", name=f"ddp_{name}", mode="fixed", fovy=f"{cam.spec.fovy:g}",
                                pos=" ".join(f"{v:.6f}" for v in pos),
                                xyaxes=" ".join(f"{v:.6f}" for v in (*x, *y)))  # fmt: skip
                self.model.worldbody.append(el)

        def _setup_observables(self):
            return OrderedDict()  # the env builds its own observations (cheaper steps)

        def reward(self, action=None):
            return 0.0

        def _check_success(self):
            return False

    return FrankaScene


class SimFrankaBackend(FrankaBackend):
    """robosuite Panda + a task scene + on-demand depth cameras (see the module docstring).

    Args:
        task: the task (objects, scene).
        cameras: camera name -> :class:`SimCamera` (the env uses ``"policy"`` and ``"tracking"``).
        control_period: seconds per ``move_to`` (robosuite's control frequency is its inverse).
        kp: OSC stiffness.
    """

    def __init__(self, task: FrankaTask, cameras: dict[str, SimCamera], *, control_period: float = 0.0625,
                 kp: float = 300.0):
        mujoco = _import_sim()
        from robosuite.controllers import load_composite_controller_config

        self._mj = mujoco
        self.task = task
        self.object_names = tuple(task.object_names)
        self.control_period = float(control_period)
        self.cameras = dict(cameras)
        config = load_composite_controller_config(robot="Panda")
        arm = config["body_parts"]["right"]
        arm.update(input_type="absolute", input_ref_frame="base", kp=kp)
        import logging

        logging.getLogger("robosuite").setLevel(logging.ERROR)
        scene_cls = _make_scene_class()
        self.env = scene_cls(
            task, self.cameras, robots="Panda", controller_configs=config, initialization_noise=None,
            has_renderer=False, has_offscreen_renderer=False, use_camera_obs=False,
            control_freq=1.0 / self.control_period, hard_reset=False, ignore_done=True, horizon=10**9,
            renderer="mujoco", lite_physics=True,
        )  # fmt: skip
        self.model = self.env.sim.model._model
        self.data = self.env.sim.data._data
        self.robot = self.env.robots[0]
        m = self.model
        base = self.data.xpos[m.body("robot0_base").id]
        if not np.allclose(base, BASE_WORLD, atol=1e-6):
            raise RuntimeError(f"robosuite placed the Panda's base at {base.tolist()}, expected {BASE_WORLD.tolist()}")
        self._site = m.site("gripper0_right_grip_site").id
        self._fingers = (m.joint("gripper0_right_finger_joint1").id, m.joint("gripper0_right_finger_joint2").id)
        self._finger_qadr = [int(m.jnt_qposadr[j]) for j in self._fingers]
        self._gripper_geoms = {m.geom(f"gripper0_right_{g}").id for g in GRIPPER_GEOMS}
        self._body_ids = np.array([m.body(f"ddp_{n}").id for n in self.object_names], dtype=np.int64)
        self._cam_ids = {name: m.camera(f"ddp_{name}").id for name in self.cameras}
        # geom -> object index (the task's object order), -1 for the robot, table and extras
        root_of = {int(b): k for k, b in enumerate(self._body_ids)}
        self._geom_object = np.full(m.ngeom + 1, -1, dtype=np.int32)  # last entry: background (-1)
        body_object = np.full(m.nbody, -1, dtype=np.int32)
        for b in range(m.nbody):
            node = b
            while node > 0 and node not in root_of:
                node = int(m.body_parentid[node])
            body_object[b] = root_of.get(node, -1)
        self._body_object = body_object
        self._geom_object[: m.ngeom] = body_object[m.geom_bodyid]
        self._body_pos0 = m.body_pos.copy()
        self._renderers: dict[tuple[int, int], object] = {}
        # depth and segmentation: collision geoms (group 0; the Panda's visual meshes, group 1, have
        # 12x the triangles and cost ~15 ms more per frame in software rendering) + the task's (group 3)
        self._scene_option = mujoco.MjvOption()
        self._scene_option.sitegroup[:] = 0
        self._scene_option.geomgroup[:] = 0
        self._scene_option.geomgroup[0] = self._scene_option.geomgroup[TASK_GROUP] = 1
        self._rgb_option = mujoco.MjvOption()  # colour: visual meshes + the task's geoms
        self._rgb_option.sitegroup[:] = 0
        self._rgb_option.geomgroup[:] = 0
        self._rgb_option.geomgroup[1] = self._rgb_option.geomgroup[TASK_GROUP] = 1
        m.vis.quality.shadowsize = 0
        m.vis.quality.offsamples = 0
        self._grip = -1.0
        self._home_qpos: np.ndarray | None = None
        self._compute_home()

    # ----------------------------------------------------------------- frames
    @staticmethod
    def to_world(p) -> np.ndarray:
        return np.asarray(p, dtype=np.float64) + BASE_WORLD

    @staticmethod
    def to_base(p) -> np.ndarray:
        return np.asarray(p, dtype=np.float64) - BASE_WORLD

    # ------------------------------------------------------------------- reset
    def _compute_home(self) -> None:
        """Drive the arm once to the task's home pose and keep its joint angles as robosuite's init_qpos."""
        self.env.reset()
        home = np.asarray(self.task.home, dtype=np.float64)
        quat = mat_to_quat(DOWN)
        self._grip = -1.0
        for _ in range(80):
            self.move_to(home, quat)
        arm = self.robot._ref_joint_pos_indexes
        self._home_qpos = self.data.qpos[arm].copy()
        self.robot.init_qpos = self._home_qpos.copy()

    def reset(self, object_positions: dict[str, np.ndarray] | None = None, home: bool = True) -> None:
        mj, m, d = self._mj, self.model, self.data
        self.env.reset()  # MuJoCo state back to the initial one, arm at the home joint angles
        m.body_pos[:] = self._body_pos0
        self._grip = -1.0
        d.qpos[self._finger_qadr[0]] = 0.04
        d.qpos[self._finger_qadr[1]] = -0.04
        mj.mj_forward(m, d)
        layout = object_positions if object_positions is not None else {}
        self.task.place(self, layout, np.random.default_rng(0))
        d.qvel[:] = 0.0
        mj.mj_forward(m, d)
        pos, quat = self.ee_pose()
        for _ in range(3):  # let the objects settle with the arm holding still
            self.move_to(pos, quat)

    # ------------------------------------------------------------------ state
    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.data
        pos = self.to_base(d.site_xpos[self._site])
        rot = d.site_xmat[self._site].reshape(3, 3) @ EE_FROM_SITE
        return pos, mat_to_quat(rot)

    def gripper_width(self) -> float:
        q = self.data.qpos
        return float(q[self._finger_qadr[0]] - q[self._finger_qadr[1]])

    def move_to(self, position: np.ndarray, quaternion: np.ndarray) -> None:
        rot_site = quat_to_mat(quaternion) @ EE_FROM_SITE.T
        action = np.concatenate([np.asarray(position, dtype=np.float64), mat_to_rotvec(rot_site), [self._grip]])
        self.env.step(action)

    def set_gripper(self, close: bool) -> None:
        self._grip = 1.0 if close else -1.0

    def object_positions(self) -> np.ndarray:
        return self.to_base(self.data.xpos[self._body_ids])

    def object_quaternions(self) -> np.ndarray:
        """Object orientations ``[K, 4]`` (wxyz) in ``object_names`` order."""
        return self.data.xquat[self._body_ids].copy()

    def displace_objects(self, deltas: np.ndarray) -> None:
        deltas = np.asarray(deltas, dtype=np.float64).reshape(len(self.object_names), 3)
        for name, delta in zip(self.object_names, deltas):
            if np.any(delta != 0.0):
                self.shift_body(f"ddp_{name}", delta)
        self._mj.mj_forward(self.model, self.data)

    # --------------------------------------------------------- scene helpers
    def _free_joint(self, body_id: int) -> int | None:
        m = self.model
        if m.body_jntnum[body_id] > 0:
            j = int(m.body_jntadr[body_id])
            if m.jnt_type[j] == self._mj.mjtJoint.mjJNT_FREE:
                return j
        return None

    def set_body_pose(self, body: str, position, quaternion=(1.0, 0.0, 0.0, 0.0)) -> None:
        """Place a body (base frame): free bodies through their joint (at rest), fixed ones via body_pos."""
        m, d = self.model, self.data
        bid = m.body(body).id
        j = self._free_joint(bid)
        world = self.to_world(position)
        if j is not None:
            qa, va = int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])
            d.qpos[qa : qa + 3] = world
            d.qpos[qa + 3 : qa + 7] = quaternion
            d.qvel[va : va + 6] = 0.0
        else:
            parent = int(m.body_parentid[bid])
            m.body_pos[bid] = world - (d.xpos[parent] if parent > 0 else 0.0)

    def shift_body(self, body: str, delta) -> None:
        """Move a body by ``delta`` now (velocity zeroed); edits of fixed bodies are undone at reset."""
        m, d = self.model, self.data
        bid = m.body(body).id
        delta = np.asarray(delta, dtype=np.float64)
        j = self._free_joint(bid)
        if j is not None:
            qa, va = int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])
            d.qpos[qa : qa + 3] += delta
            d.qvel[va : va + 6] = 0.0
        else:
            parent = int(m.body_parentid[bid])
            m.body_pos[bid] += d.xmat[parent].reshape(3, 3).T @ delta if parent > 0 else delta

    def body_position(self, body: str) -> np.ndarray:
        return self.to_base(self.data.xpos[self.model.body(body).id])

    def body_rotation(self, body: str) -> np.ndarray:
        return self.data.xmat[self.model.body(body).id].reshape(3, 3).copy()

    def body_velocity(self, body: str) -> np.ndarray:
        """Linear velocity (world axes) of a body's frame."""
        import mujoco

        res = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_BODY, self.model.body(body).id, res, 0)
        return res[3:].copy()

    def joint_qpos(self, joint: str) -> float:
        m = self.model
        return float(self.data.qpos[m.jnt_qposadr[m.joint(joint).id]])

    def touching_gripper(self, index: int) -> tuple[bool, bool]:
        """Whether object ``index`` touches the left / right finger."""
        d, m = self.data, self.model
        left = right = False
        for c in d.contact[: d.ncon]:
            g1, g2 = int(c.geom1), int(c.geom2)
            for mine, other in ((g1, g2), (g2, g1)):
                if self._geom_object[mine] == index and other in self._gripper_geoms:
                    name = m.geom(other).name
                    if "finger1" in name:
                        left = True
                    else:
                        right = True
        return left, right

    def grasped(self) -> np.ndarray:
        """[K] bool: the object touches both fingers (it moves with the hand)."""
        return np.array([all(self.touching_gripper(k)) for k in range(len(self.object_names))])

    # ----------------------------------------------------------------- render
    def _renderer(self, height: int, width: int):
        key = (height, width)
        r = self._renderers.get(key)
        if r is None:
            vis = self.model.vis.global_
            vis.offwidth = max(vis.offwidth, width)
            vis.offheight = max(vis.offheight, height)
            r = self._mj.Renderer(self.model, height, width)
            self._renderers[key] = r
            _track(self)
        return r

    def camera_geometry(self, camera: str) -> tuple[np.ndarray, np.ndarray]:
        """``(intrinsics [3,3], cam_to_world [4,4] OpenCV axes, base frame)`` of a named camera."""
        cam = self.cameras[camera]
        h, w = cam.height, cam.width
        f = 0.5 * h / np.tan(0.5 * np.radians(cam.spec.fovy))
        k = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        cid = self._cam_ids[camera]
        rot = self.data.cam_xmat[cid].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])  # MuJoCo -> OpenCV axes
        pose = np.eye(4)
        pose[:3, :3] = rot
        pose[:3, 3] = self.to_base(self.data.cam_xpos[cid])
        return k, pose

    def render(self, camera: str) -> CameraFrame:
        if camera not in self.cameras:
            raise ValueError(f"unknown camera {camera!r}; this backend has {sorted(self.cameras)}")
        cam = self.cameras[camera]
        r = self._renderer(cam.height, cam.width)
        cid = self._cam_ids[camera]
        r.update_scene(self.data, camera=cid, scene_option=self._scene_option)
        r.enable_depth_rendering()
        depth = r.render().astype(np.float32)
        r.disable_depth_rendering()
        depth[depth > FAR] = 0.0
        seg = rgb = None
        if cam.segmentation:
            r.enable_segmentation_rendering()
            raw = r.render()
            r.disable_segmentation_rendering()
            ids = raw[..., 0].astype(np.int64)
            is_geom = raw[..., 1] == int(self._mj.mjtObj.mjOBJ_GEOM)
            ids = np.where(is_geom & (ids >= 0), ids, self.model.ngeom)
            seg = self._geom_object[ids].astype(np.int32)
        if cam.rgb:
            r.update_scene(self.data, camera=cid, scene_option=self._rgb_option)
            rgb = r.render().copy()
        k, pose = self.camera_geometry(camera)
        return CameraFrame(depth=depth, intrinsics=k, cam_to_world=pose, segmentation=seg, rgb=rgb)

    def render_rgb(self, camera: str, width: int, height: int) -> np.ndarray:
        """A colour image of a named camera (videos); ``[H, W, 3]`` uint8."""
        if camera not in self._cam_ids:
            names = list(self._cam_ids)
            raise ValueError(f"video camera must be one of {names}; got {camera!r}{suggest(camera, names)}")
        r = self._renderer(height, width)
        r.update_scene(self.data, camera=self._cam_ids[camera], scene_option=self._rgb_option)
        return r.render().copy()

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers = {}
        env = self.__dict__.pop("env", None)
        if env is not None:
            env.close()
