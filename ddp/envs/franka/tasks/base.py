"""What a Franka task defines: objects, ID layout, OOD schedule, success, scripted oracle.

Every task is a :class:`FrankaTask` subclass registered in :data:`TASKS` (see
``ddp.envs.franka.tasks``). Geometry is in the robot base frame, metres, with
the table top at ``z = 0`` (the simulated robot stands on the table's edge,
as on the real bench).

* **Objects** (``object_names``): the env's object order, OOD targets first;
  ``("privileged", "object_pos" | "displacement")`` and the controller's
  ``subtasks[*].target`` index into it.
* **ID layout** (paper, "Real Robot Benchmark": "initial target positions are
  uniformly randomized along a 10 cm linear range"): each object in
  ``id_lines`` is placed uniformly on its segment ``(start, end)``; objects in
  ``fixed`` sit at their position. ``id_zone(name)`` is the segment grown by
  the object's footprint: a displacement is "fully outside the ID zone" when
  the displaced footprint does not overlap it.
* **OOD schedule** (``displacements``): :class:`~ddp.envs.disturbances.Displacement`
  rows (``bodies`` are object names), applied by the env at the start of
  their chunk.
* **Simulation** (``mjcf``, ``place``, ``update``, ``success``): the scene's
  MJCF bodies (root body ``ddp_<name>`` per object, geoms in group 3), how
  to put them in place, per-step bookkeeping and the success check; they
  read the MuJoCo state through the simulated backend.
* **Scripted oracle** (``oracle``): a kinematic waypoint follower that reads
  the privileged object poses and the commanded end-effector target, with
  per-episode random variations ("a scripted kinematic oracle that injects
  spatial variance"): offsets, heights, speed, hold times, and the wrist
  turned (yaw) and tilted (roll, pitch) in free-space phases, so that every
  action dimension varies in the demos (a dimension that never varies would
  be normalised with scale 1 and the policy's error on it would pass
  through unscaled: the rotation deltas accumulate over the steps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ddp.envs.disturbances import Displacement
from ddp.envs.franka.control import mat_to_rotvec, quat_to_mat, rotvec_to_mat

__all__ = [
    "CameraSpec",
    "FrankaTask",
    "Obs",
    "Waypoint",
    "WaypointOracle",
    "DOWN",
    "inertial",
    "down",
    "rot_x",
    "rot_y",
    "rot_z",
]

#: end-effector orientation pointing straight down, fingers along the base y axis
#: (the Franka TCP frame at the usual home pose: 180 degrees about x)
DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def inertial(mass: float, half_size, pos=(0.0, 0.0, 0.0)) -> str:
    """An ``<inertial>`` element of a solid box (robosuite computes inertia from group-0 geoms
    only, and the task geoms are in group 3, so every task body declares its own)."""
    x, y, z = (2.0 * float(v) for v in half_size)
    diag = (mass * (y * y + z * z) / 12.0, mass * (x * x + z * z) / 12.0, mass * (x * x + y * y) / 12.0)
    p = " ".join(f"{v:g}" for v in pos)
    return f'<inertial pos="{p}" mass="{mass:g}" diaginertia="{diag[0]:.3e} {diag[1]:.3e} {diag[2]:.3e}"/>'


def rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def down(yaw: float = 0.0, roll: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    """The pointing-down orientation turned by ``yaw`` about the base z axis and tilted by ``roll`` / ``pitch``."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll) @ DOWN


@dataclass(frozen=True)
class CameraSpec:
    """A fixed depth camera: position, look-at point (base frame), vertical field of view (degrees)."""

    pos: tuple[float, float, float]
    lookat: tuple[float, float, float]
    fovy: float = 55.0


class FrankaTask:
    """Base class of the Franka tasks (see the module docstring)."""

    name: str = ""
    object_names: tuple[str, ...] = ()
    #: object -> (start, end) of its 10 cm ID segment (base frame, z = rest height of the root body)
    id_lines: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {}
    #: object -> fixed base-frame position of objects not randomised
    fixed: dict[str, tuple[float, float, float]] = {}
    #: object -> half extent of its footprint in x and y (for the ID zone)
    footprint: dict[str, float] = {}
    displacements: tuple[Displacement, ...] = ()
    max_episode_steps: int = 200
    #: policy camera (the paper's static L515) and tracking camera (the D455)
    policy_camera = CameraSpec((1.15, 0.0, 0.6), (0.45, 0.0, 0.05), 55.0)
    tracking_camera = CameraSpec((0.5, -0.85, 0.55), (0.5, 0.0, 0.05), 58.0)
    #: base-frame crop box of the point cloud (z above the table top: the table is dropped; below 25 cm:
    #: the hand and the objects, not the upper arm, which would otherwise take most of the points)
    crop_low: tuple[float, float, float] = (0.2, -0.45, 0.004)
    crop_high: tuple[float, float, float] = (0.85, 0.45, 0.25)
    #: end-effector position at reset (orientation: DOWN)
    home: tuple[float, float, float] = (0.4, 0.0, 0.3)
    #: short description of the subtasks and their triggers (for docs and error messages)
    subtasks: tuple[str, ...] = ()
    #: bumped whenever the scripted oracle changes (part of the demo cache's key)
    oracle_version: int = 1
    #: the names :meth:`info` returns, in order (the env's ``("privileged", "task_info")`` keys)
    info_keys: tuple[str, ...] = ()

    # ------------------------------------------------------------------ layout
    def sample_layout(self, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """Base-frame positions of every object: uniform on its ID line, or fixed."""
        layout = {}
        for name in self.object_names:
            if name in self.id_lines:
                start, end = (np.asarray(p, dtype=np.float64) for p in self.id_lines[name])
                layout[name] = start + rng.uniform() * (end - start)
            else:
                layout[name] = np.asarray(self.fixed[name], dtype=np.float64).copy()
        return layout

    def id_zone(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """The xy box an object occupies somewhere in distribution: its ID line grown by its footprint."""
        half = self.footprint.get(name, 0.0)
        if name in self.id_lines:
            pts = np.asarray(self.id_lines[name], dtype=np.float64)[:, :2]
        else:
            pts = np.asarray(self.fixed[name], dtype=np.float64)[None, :2]
        return pts.min(0) - half, pts.max(0) + half

    def outside_id_zone(self, name: str, position) -> bool:
        """Whether an object's footprint at ``position`` does not overlap its ID zone at all."""
        lo, hi = self.id_zone(name)
        half = self.footprint.get(name, 0.0)
        p = np.asarray(position, dtype=np.float64)[:2]
        return bool(np.any(p + half < lo) or np.any(p - half > hi))

    # ------------------------------------------------------------- simulation
    def mjcf(self) -> tuple[str, str]:
        """``(asset XML, worldbody XML)`` of the task's objects (root bodies named ``ddp_<name>``).

        ``<exclude body1=... body2=.../>`` elements in the worldbody string go to the
        model's ``<contact>`` section.
        """
        raise NotImplementedError

    def place(self, sim, layout: dict[str, np.ndarray], rng: np.random.Generator) -> None:
        """Put the objects at ``layout`` (default: each root body, upright, at rest)."""
        for name, pos in layout.items():
            sim.set_body_pose(f"ddp_{name}", pos)

    def new_state(self) -> dict:
        """Per-episode bookkeeping updated by :meth:`update` (latches, counters)."""
        return {}

    def update(self, sim, state: dict) -> None:
        """Called after every simulated step."""

    def success(self, sim, state: dict) -> bool:
        """The paper's success definition, checked on the simulator state."""
        raise NotImplementedError

    def failed(self, sim, state: dict) -> bool:
        """Whether the episode has failed for good (press: an over-press), so that an earlier success no longer
        counts (the env's ``"failed"`` key; ``ChunkedEnv`` revokes the episode's success)."""
        return False

    def info(self, sim, state: dict) -> dict[str, float]:
        """Diagnostics for reports (e.g. balls in the cup, press depth): one float per name in ``info_keys``."""
        return {}

    # ------------------------------------------------------------------ oracle
    def oracle(self, *, id_frame: bool = False, variance: bool = True) -> "WaypointOracle":
        """The scripted oracle (``tensordict -> action``). ``id_frame``: ignore displacements."""
        raise NotImplementedError


# ------------------------------------------------------------------------------------------ oracle
@dataclass
class Obs:
    """What the oracles read from an observation TensorDict (numpy, base frame)."""

    ee: np.ndarray  # measured end-effector position
    rot: np.ndarray  # measured end-effector rotation matrix
    width: float  # finger distance
    cmd: np.ndarray  # commanded end-effector target position
    cmd_rot: np.ndarray  # commanded end-effector rotation
    objects: np.ndarray  # [K, 3] object positions (ID frame for an id_frame oracle)
    quats: np.ndarray  # [K, 4]
    seed: int
    step: int
    anchor: np.ndarray | None = None  # commanded position when the current phase began

    @classmethod
    def from_tensordict(cls, td, id_frame: bool = False) -> "Obs":
        p = td.get("privileged")
        a = td.get("agent_pos").detach().cpu().double().numpy()
        objects = p.get("object_pos").detach().cpu().double().numpy()
        cmd = p.get("ee_target").detach().cpu().double().numpy()
        ee = a[0:3]
        if id_frame:  # the scene as if nothing had moved: what an imagining policy believes
            objects = objects - p.get("displacement").detach().cpu().double().numpy()
            offset = p.get("ee_offset").detach().cpu().double().numpy()
            ee, cmd = ee - offset, cmd - offset
        col0, col1 = a[9:12], a[12:15]
        rot = np.stack([col0, col1, np.cross(col0, col1)], axis=1)
        return cls(
            ee=ee,
            rot=rot,
            width=float(np.linalg.norm(a[3:6] - a[6:9])),
            cmd=cmd,
            cmd_rot=quat_to_mat(p.get("ee_target_quat").detach().cpu().double().numpy()),
            objects=objects,
            quats=p.get("object_quat").detach().cpu().double().numpy(),
            seed=int(p.get("seed").reshape(-1)[0]),
            step=int(p.get("step").reshape(-1)[0]),
        )


@dataclass
class Waypoint:
    """One phase of a scripted motion.

    ``pos(obs)`` / ``rot(obs)`` give the target pose (None: keep the commanded one); the
    phase ends once the command has reached it and the measured end-effector is within
    ``tol``, then ``hold`` more steps; or after ``timeout`` steps.
    """

    pos: Callable[[Obs], np.ndarray] | None
    grip: float  # +1 close, -1 open
    rot: Callable[[Obs], np.ndarray] | None = None
    speed: float | None = None  # metres per step (None: the oracle's speed)
    tol: float = 0.01
    hold: int = 0
    timeout: int = 60
    name: str = ""
    #: ``path(obs, next_rot) -> position``: a position that follows the rotation commanded this step
    #: (e.g. tilting about a point other than the end-effector); replaces ``pos``
    path: Callable[[Obs, np.ndarray], np.ndarray] | None = None


class WaypointOracle:
    """Follows a list of :class:`Waypoint` phases built per episode by ``plan(obs, rng)``.

    Actions move the *commanded* target (``("privileged", "ee_target")``) toward the
    phase's target by at most ``speed`` metres and ``rot_speed`` radians per step, which
    the control loop adds to its command: a kinematic plan the arm tracks.
    """

    def __init__(
        self,
        plan: Callable[[Obs, np.random.Generator], list[Waypoint]],
        *,
        id_frame: bool = False,
        variance: bool = True,
        speed: tuple[float, float] = (0.012, 0.018),
        rot_speed: float = 0.08,
        seed_offset: int = 7919,
    ):
        self.plan_fn = plan
        self.id_frame = id_frame
        self.variance = variance
        self.speed_range = speed
        self.rot_speed = rot_speed
        self.seed_offset = seed_offset
        self.reset()

    def reset(self) -> None:
        self.plan: list[Waypoint] | None = None
        self.phase = 0
        self.phase_steps = 0
        self.held = 0
        self.rng: np.random.Generator | None = None
        self.history: list[tuple[str, int]] = []  # (phase name, env step at which it began)

    @property
    def finished(self) -> bool:
        return self.plan is not None and self.phase >= len(self.plan)

    def __call__(self, td) -> np.ndarray:
        obs = Obs.from_tensordict(td, id_frame=self.id_frame)
        if self.plan is None or obs.step == 0 and self.phase_steps > 0:
            self.reset()
            self.rng = np.random.default_rng([obs.seed, self.seed_offset])
            lo, hi = self.speed_range
            self.speed = float(self.rng.uniform(lo, hi)) if self.variance else 0.5 * (lo + hi)
            self.plan = self.plan_fn(obs, self.rng if self.variance else None)
        if self.finished:
            return np.array([0, 0, 0, 0, 0, 0, self.plan[-1].grip], dtype=np.float32)
        wp = self.plan[self.phase]
        if self.phase_steps == 0:
            self.anchor = obs.cmd.copy()
            self.history.append((wp.name, obs.step))
        obs.anchor = self.anchor
        target_rot = obs.cmd_rot if wp.rot is None else wp.rot(obs)
        drot = mat_to_rotvec(target_rot @ obs.cmd_rot.T)
        angle = float(np.linalg.norm(drot))
        if angle > self.rot_speed:
            drot *= self.rot_speed / angle
        if wp.path is not None:
            target = np.asarray(wp.path(obs, rotvec_to_mat(drot) @ obs.cmd_rot), dtype=np.float64)
        else:
            target = obs.cmd if wp.pos is None else np.asarray(wp.pos(obs), dtype=np.float64)
        speed = self.speed if wp.speed is None else wp.speed
        dpos = target - obs.cmd
        dist = float(np.linalg.norm(dpos))
        if dist > speed:
            dpos *= speed / dist
        self.phase_steps += 1
        reached = (
            dist <= speed
            and angle <= self.rot_speed
            and float(np.linalg.norm(target - obs.ee)) < wp.tol
        )
        if reached:
            self.held += 1
        if (reached and self.held > wp.hold) or self.phase_steps >= wp.timeout:
            self.phase += 1
            self.phase_steps = 0
            self.held = 0
        return np.concatenate([dpos, drot, [wp.grip]]).astype(np.float32)


def jitter(rng: np.random.Generator | None, scale, size=None):
    """Uniform noise in [-scale, scale] (zero without an rng: the oracle without variance)."""
    if rng is None:
        return np.zeros(size) if size is not None else 0.0
    return rng.uniform(-1.0, 1.0, size=size) * np.asarray(scale)


def uniform(rng: np.random.Generator | None, lo: float, hi: float) -> float:
    return 0.5 * (lo + hi) if rng is None else float(rng.uniform(lo, hi))


__all__ += ["jitter", "uniform"]
