"""The real Franka backend: franky for the arm and the hand, RealSense cameras, hard safety limits.

``env.backend: real`` makes the ``franka`` env call :func:`make_real_backend` with its config. The
same code drives a physical Franka (FCI at ``robot_host``) and franky-sim, a simulator that speaks
the libfranka protocol on loopback (``franky_sim_info``: the server's info file; see
:mod:`ddp.envs.franka.franky_sim_server`), so the control loop tested against the simulator is the
one that runs on the robot.

Motion: the env's control loop hands :meth:`FrankyBackend.move_to` an absolute end-effector target
in the robot BASE frame (it composes the policy's relative action with the current pose there).
franky's own relative motions are expressed in the END-EFFECTOR frame (the hand points down, so
y and z flip), which is why relative deltas are never sent as ``ReferenceType.Relative``:
:meth:`FrankyBackend.move_relative` composes a base-frame delta with the measured pose and moves in
absolute reference. Each target passes the safety limits first (:func:`limit_target`): it is
clipped into the workspace box and the arm's reach (``max_reach``: wrist centre from the
shoulder), then shortened to at most ``max_step_translation`` metres and
``max_step_rotation`` radians from the MEASURED pose. franky's Ruckig planner scales velocity,
acceleration and jerk by ``dynamics_factor``; collision reflexes use ``collision_torque`` /
``collision_force``.

Timing: ``motion_wait="period"`` (default) starts the motion asynchronously and returns one
``control_period`` after the call began, so consecutive targets blend into one continuous motion at
the chunk rate (the paper's 8 actions per 0.5 s); a target the arm cannot reach in one period is
taken over by the next. ``"reached"`` blocks until the target is reached (at least one period).

Config fields read from the env config (``getattr``; the same names may instead sit in a ``real``
mapping on it): ``robot_host``, ``franky_sim_info``, ``cameras``, ``calibration``,
``control_period``, ``motion_wait``, ``dynamics_factor``, ``workspace_low``, ``workspace_high``,
``max_step_translation``, ``max_step_rotation``, ``max_reach``, ``home_joints``,
``home_position``, ``home_quaternion``, ``gripper_speed``,
``gripper_force``, ``gripper_open_width``, ``collision_torque``, ``collision_force``,
``realtime``, ``object_names`` (see :class:`RealBackendConfig`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field, fields
from typing import Any, Literal, Mapping

import numpy as np

from ddp.config import check_choices
from ddp.envs.franka.backend import CameraFrame, FrankaBackend, RobotMotionError
from ddp.safety import require_finite

__all__ = [
    "RealBackendConfig",
    "FrankyBackend",
    "make_real_backend",
    "franky_sim_scene",
    "limit_target",
    "RobotMotionError",
]

log = logging.getLogger(__name__)
INSTALL_HINT = "pip install 'ddp[real]'"

#: FR3 / Panda joints with the Franka Hand's TCP at (0.4, 0, 0.3) pointing down: the tasks' home
#: (``FrankaTask.home``), so the Cartesian move after the joint motion is short
DEFAULT_HOME = (0.0, -0.4165, 0.0, -2.5796, 0.0, 2.1639, 0.7854)
#: the Panda's joint limits (radians; Franka's datasheet), which home_joints must lie within
JOINT_LIMITS = ((-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698), (-2.8973, 2.8973),
                (-0.0175, 3.7525), (-2.8973, 2.8973))
#: the shoulder (joints 2) in the base frame, and the wrist centre's distance behind the Franka Hand's
#: TCP (0.1034 m flange to TCP + 0.107 m wrist to flange)
SHOULDER = np.array([0.0, 0.0, 0.333])
WRIST_OFFSET = 0.2104


def _import_franky():
    try:
        import franky
    except ImportError as exc:
        raise ImportError(f"the real Franka backend needs franky: {INSTALL_HINT} ({exc})") from None
    return franky


# ----------------------------------------------------------------------------------------------
# config
# ----------------------------------------------------------------------------------------------


@dataclass
class RealBackendConfig:
    """Everything the real backend reads; validated on construction (errors name the key)."""

    #: the robot's FCI address; ignored when ``franky_sim_info`` is set (the server says where it listens)
    robot_host: str = "172.16.0.2"
    #: path of a franky-sim server's info file: connect to that simulator and its scene socket
    franky_sim_info: str | None = None
    #: seconds to wait for the info file to appear
    franky_sim_wait: float = 10.0
    #: camera name -> source: ``{type: realsense, serial, width, height, fps, align_to, recording}`` or
    #: ``{type: franky_sim, server_camera, rgb, segmentation}``; a missing ``type`` is franky_sim with
    #: ``franky_sim_info``, else realsense. None: "policy", plus "tracking" unless the env has
    #: ``tracking_camera: false`` (a RealSense's serial may come from the calibration file)
    cameras: dict[str, dict] | None = None
    #: YAML/JSON with each camera's ``cam_to_base`` (see :func:`ddp.envs.franka.cameras.load_calibration`)
    calibration: str | None = None
    control_period: float = 0.0625
    motion_wait: Literal["period", "reached"] = "period"
    #: franky's relative dynamics factor (velocity, acceleration and jerk scale), in (0, 1]
    dynamics_factor: float = 0.15
    workspace_low: tuple[float, float, float] = (0.25, -0.45, 0.005)
    workspace_high: tuple[float, float, float] = (0.70, 0.45, 0.50)
    max_step_translation: float = 0.05
    max_step_rotation: float = 0.35
    #: largest wrist-centre distance from the shoulder (the arm's links reach about 0.8 m; stretched
    #: out, the arm is near a singularity); None: no reach limit
    max_reach: float | None = 0.72
    home_joints: tuple[float, ...] = DEFAULT_HOME
    #: after the joint motion, the TCP moves here (base frame; None: stay at ``home_joints``); from the
    #: env: its task's ``home``
    home_position: tuple[float, float, float] | None = None
    #: orientation there, ``[w, x, y, z]`` (default: pointing down, fingers along the base y axis)
    home_quaternion: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 0.0)
    gripper_speed: float = 0.1
    gripper_force: float = 20.0
    #: None: the hand's maximum width
    gripper_open_width: float | None = None
    collision_torque: float = 20.0
    collision_force: float = 30.0
    #: require a realtime kernel; None: on hardware yes, with franky-sim no
    realtime: bool | None = None
    #: the env's object order (privileged positions from franky-sim); empty: the server's order
    object_names: tuple[str, ...] = ()
    #: metres the hand rises straight up (inside the box) at a reset before the joint motion home, so that
    #: the way home does not sweep through what is on the table
    reset_lift: float = 0.08
    #: on hardware (no franky-sim scene), every reset waits for the operator (Enter on the terminal) before
    #: the gripper opens: take what the hand holds, set the scene up for the next episode
    operator_reset: bool = True

    def __post_init__(self):
        p = "env.real"
        check_choices(self, f"{p}.")
        if not 0.0 < float(self.dynamics_factor) <= 1.0:
            raise ValueError(f"{p}.dynamics_factor must be in (0, 1]; got {self.dynamics_factor}")
        low, high = np.asarray(self.workspace_low, float), np.asarray(self.workspace_high, float)
        if low.shape != (3,) or high.shape != (3,) or not np.all(np.isfinite([*low, *high])) or not np.all(low < high):
            raise ValueError(
                f"{p}.workspace_low/high must be 3 finite numbers each with low < high; got {list(self.workspace_low)}, "
                f"{list(self.workspace_high)}"
            )
        # inf would switch a limit off (a step of any size, an endless sleep), NaN every comparison
        for key in ("control_period", "max_step_translation", "max_step_rotation", "gripper_speed", "gripper_force",
                    "collision_torque", "collision_force", "franky_sim_wait"):
            value = float(getattr(self, key))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{p}.{key} must be a finite number > 0; got {getattr(self, key)}")
        if not (math.isfinite(float(self.reset_lift)) and float(self.reset_lift) >= 0.0):
            raise ValueError(f"{p}.reset_lift must be a finite number >= 0 (metres); got {self.reset_lift}")
        if self.max_reach is not None and not (math.isfinite(float(self.max_reach)) and 0.0 < float(self.max_reach) <= 0.855):
            raise ValueError(f"{p}.max_reach must be in (0, 0.855] metres (the Panda's reach) or null; got {self.max_reach}")
        if self.gripper_open_width is not None and not (math.isfinite(float(self.gripper_open_width))
                                                        and 0.0 < float(self.gripper_open_width) <= 0.08):
            raise ValueError(f"{p}.gripper_open_width must be in (0, 0.08] metres or null; got {self.gripper_open_width}")
        if self.home_position is not None:
            home = np.asarray(self.home_position, dtype=float)
            if home.shape != (3,) or not np.all(np.isfinite(home)) or np.any(home < low) or np.any(home > high):
                raise ValueError(f"{p}.home_position must be 3 numbers inside the workspace box; got {self.home_position}")
            self.home_position = tuple(home.tolist())
        if len(tuple(self.home_quaternion)) != 4:
            raise ValueError(f"{p}.home_quaternion must be [w, x, y, z]; got {self.home_quaternion}")
        self.home_quaternion = tuple(_qnormalize(np.asarray(self.home_quaternion)).tolist())
        if len(tuple(self.home_joints)) != 7:
            raise ValueError(f"{p}.home_joints must have 7 joint angles; got {len(tuple(self.home_joints))}")
        for i, (q, (lo, hi)) in enumerate(zip(self.home_joints, JOINT_LIMITS)):
            if not (math.isfinite(float(q)) and lo <= float(q) <= hi):
                raise ValueError(f"{p}.home_joints[{i}] must be within the joint's limits [{lo}, {hi}] rad; got {q}")
        if self.cameras is not None and not isinstance(self.cameras, Mapping):
            raise ValueError(f"{p}.cameras must map camera names to sources; got {type(self.cameras).__name__}")
        self.workspace_low, self.workspace_high = tuple(low.tolist()), tuple(high.tolist())
        self.home_joints = tuple(float(v) for v in self.home_joints)
        self.object_names = tuple(self.object_names)

    @classmethod
    def from_env_config(cls, config: Any) -> "RealBackendConfig":
        """Collect the fields from an env config: its ``real`` mapping if any, else same-named attributes."""
        if isinstance(config, cls):
            return config
        names = {f.name for f in fields(cls)}
        nested = getattr(config, "real", None) if not isinstance(config, Mapping) else config.get("real")
        if isinstance(nested, cls):
            return nested
        values: dict[str, Any] = {}
        for name in names:
            if isinstance(config, Mapping):
                if name in config and config[name] is not None:
                    values[name] = config[name]
            elif getattr(config, name, None) is not None:
                values[name] = getattr(config, name)
        if isinstance(nested, Mapping):
            unknown = set(nested) - names
            if unknown:
                raise ValueError(f"env.real: unknown keys {sorted(unknown)}; valid: {sorted(names)}")
            values.update({k: v for k, v in nested.items() if v is not None})
        return cls(**values)


# ----------------------------------------------------------------------------------------------
# quaternions (wxyz) and the safety limits
# ----------------------------------------------------------------------------------------------


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _qconj(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


def _qrotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector ``v`` by quaternion ``q`` (wxyz)."""
    return _qmul(_qmul(q, np.concatenate([[0.0], v])), _qconj(q))[1:]


def _qnormalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"quaternion must be finite and non-zero; got {q.tolist()}")
    return q / n


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """``[w, x, y, z]`` of a rotation vector (axis * angle, radians)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    axis = rotvec / angle
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def quat_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (radians, in [0, pi]) of the rotation between two orientations."""
    d = abs(float(np.dot(_qnormalize(a), _qnormalize(b))))
    return 2.0 * math.acos(min(1.0, d))


def _slerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    a, b = _qnormalize(a), _qnormalize(b)
    d = float(np.dot(a, b))
    if d < 0.0:
        b, d = -b, -d
    if d > 0.9995:
        return _qnormalize(a + t * (b - a))
    theta = math.acos(d)
    return (math.sin((1 - t) * theta) * a + math.sin(t * theta) * b) / math.sin(theta)


def limit_target(
    current_position: np.ndarray,
    current_quaternion: np.ndarray,
    target_position: np.ndarray,
    target_quaternion: np.ndarray,
    workspace_low,
    workspace_high,
    max_translation: float,
    max_rotation: float,
    max_reach: float | None = None,
    wrist_offset: float = WRIST_OFFSET,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The safe version of a target: inside the box and the arm's reach, at most one step from the measured pose.
    The box wins: a target pulled back into reach, or a step, that would leave the box is clipped to it.

    ``max_reach``: largest distance of the wrist centre (``wrist_offset`` metres behind the TCP along
    the target's approach axis) from the shoulder at ``SHOULDER``; farther targets are pulled back
    toward the shoulder (a stretched arm is near its singularity). Returns ``(position, quaternion,
    limited)``; ``limited`` is True when anything was changed.
    """
    cur = np.asarray(current_position, dtype=np.float64)
    tgt = np.asarray(target_position, dtype=np.float64)
    if cur.shape != (3,) or not np.all(np.isfinite(cur)):  # NaN would pass every step limit below
        raise ValueError(f"measured position must be 3 finite numbers; got {np.asarray(current_position).tolist()}")
    if tgt.shape != (3,) or not np.all(np.isfinite(tgt)):
        raise ValueError(f"target position must be 3 finite numbers; got {np.asarray(target_position).tolist()}")
    q_cur, q_tgt = _qnormalize(current_quaternion), _qnormalize(target_quaternion)
    pos = np.clip(tgt, workspace_low, workspace_high)
    if max_reach is not None:
        approach = _qrotate(q_tgt, np.array([0.0, 0.0, 1.0]))
        wrist = pos - wrist_offset * approach - SHOULDER
        reach = float(np.linalg.norm(wrist))
        if reach > max_reach:  # pulled toward the shoulder, which may leave the box: clipped again
            pos = np.clip(pos - wrist * (1.0 - max_reach / reach), workspace_low, workspace_high)
    limited = not np.allclose(pos, tgt)
    step = pos - cur
    dist = float(np.linalg.norm(step))
    if dist > max_translation:  # a step from a measured pose outside the box may end outside it: clipped
        pos = np.clip(cur + step * (max_translation / dist), workspace_low, workspace_high)
        limited = True
    angle = quat_angle(q_cur, q_tgt)
    quat = q_tgt
    if angle > max_rotation:
        quat = _slerp(q_cur, q_tgt, max_rotation / angle)
        limited = True
    return pos, _qnormalize(quat), limited


# ----------------------------------------------------------------------------------------------
# the backend
# ----------------------------------------------------------------------------------------------


class FrankyBackend(FrankaBackend):
    """A Franka arm + hand driven by franky; cameras are :class:`ddp.envs.franka.cameras.CameraSource`.

    ``scene`` (a :class:`ddp.envs.franka.cameras.FrankySimScene`) is the simulator's truth about
    the objects: object positions, placement at reset, displacement. None on hardware.
    """

    def __init__(self, config: RealBackendConfig, cameras: Mapping[str, Any], scene=None, robot_host: str | None = None):
        franky = _import_franky()
        self.franky = franky
        self.config = config
        self.control_period = float(config.control_period)
        self.cameras = dict(cameras)
        self.scene = scene
        host = robot_host or config.robot_host
        realtime = config.realtime if config.realtime is not None else scene is None
        rt = franky.RealtimeConfig.Enforce if realtime else franky.RealtimeConfig.Ignore
        try:
            self.robot = franky.Robot(host, realtime_config=rt)
            self.gripper = franky.Gripper(host)
        except Exception as exc:  # franky raises its own exception types
            raise ConnectionError(f"cannot connect to the Franka at {host}: {type(exc).__name__}: {exc}") from None
        self.robot.relative_dynamics_factor = float(config.dynamics_factor)
        self.robot.set_collision_behavior(float(config.collision_torque), float(config.collision_force))
        self._open_width = float(config.gripper_open_width or self.gripper.max_width)
        self._gripper_closed: bool | None = None
        self._gripper_futures: list = []
        self._low = np.asarray(config.workspace_low)
        self._high = np.asarray(config.workspace_high)
        self.limited_steps = 0  # how many targets the safety limits changed (a diagnostic)
        if scene is not None:
            server_names = tuple(scene.object_names)
            names = config.object_names or server_names
            missing = [n for n in names if n not in server_names]
            if missing:
                raise ValueError(
                    f"env.real.object_names {list(missing)} are not objects of the franky-sim scene {list(server_names)}"
                )
            self.object_names = tuple(names)
            self._object_index = np.array([server_names.index(n) for n in names], dtype=int)
        else:
            self.object_names = tuple(config.object_names)

    # ---- state ----
    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        pose = self.robot.current_cartesian_state.pose.end_effector_pose
        x, y, z, w = np.asarray(pose.quaternion, dtype=np.float64).reshape(4)
        return np.asarray(pose.translation, dtype=np.float64).reshape(3), np.array([w, x, y, z])

    def gripper_width(self) -> float:
        return float(self.gripper.width)

    def joint_positions(self) -> np.ndarray:
        return np.asarray(self.robot.current_joint_positions, dtype=np.float64).reshape(7)

    # ---- motion ----
    def _affine(self, position: np.ndarray, quaternion: np.ndarray):
        w, x, y, z = quaternion
        return self.franky.Affine(np.asarray(position, dtype=np.float64), np.array([x, y, z, w]))

    def _raise_motion_error(self, exc: BaseException) -> None:
        try:
            self.robot.recover_from_errors()
        except Exception:  # recovery itself failed: report the original error
            pass
        raise RobotMotionError(f"the robot stopped the motion: {type(exc).__name__}: {exc}") from exc

    def move_to(self, position: np.ndarray, quaternion: np.ndarray) -> None:
        t0 = time.monotonic()
        cfg = self.config
        try:
            self.robot.poll_motion()  # raises what an asynchronous motion ran into
        except Exception as exc:
            self._raise_motion_error(exc)
        cur_p, cur_q = self.ee_pose()
        # the step limits are measured from this pose: a NaN reading would pass them all (NaN > x is False)
        require_finite("measured end-effector pose", np.concatenate([np.ravel(cur_p), np.ravel(cur_q)]),
                       "franky backend")
        pos, quat, limited = limit_target(
            cur_p, cur_q, position, quaternion, self._low, self._high,
            cfg.max_step_translation, cfg.max_step_rotation, cfg.max_reach,
        )  # fmt: skip
        self.limited_steps += int(limited)
        motion = self.franky.CartesianMotion(self._affine(pos, quat), self.franky.ReferenceType.Absolute)
        try:
            self.robot.move(motion, asynchronous=cfg.motion_wait == "period")
        except Exception as exc:
            self._raise_motion_error(exc)
        remaining = self.control_period - (time.monotonic() - t0)
        if remaining > 0:
            time.sleep(remaining)

    def reachable(self, position: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
        """``position`` inside this backend's box and the arm's reach, as :meth:`move_to` would hold it."""
        pos, _, _ = limit_target(position, quaternion, position, quaternion, self._low, self._high,
                                 np.inf, np.inf, self.config.max_reach)
        return pos

    def move_relative(self, delta_position: np.ndarray, delta_rotation: np.ndarray | None = None) -> None:
        """Move by a BASE-frame delta (metres; rotation vector in radians, applied in the base frame)."""
        cur_p, cur_q = self.ee_pose()
        quat = cur_q if delta_rotation is None else _qmul(quat_from_rotvec(delta_rotation), cur_q)
        self.move_to(cur_p + np.asarray(delta_position, dtype=np.float64), quat)

    def wait_until_still(self, timeout: float = 5.0) -> bool:
        """Block until the current motion has finished (True) or ``timeout`` passed (False)."""
        try:
            return bool(self.robot.join_motion(timeout))
        except Exception as exc:
            self._raise_motion_error(exc)
            return False

    def set_gripper(self, close: bool) -> None:
        close = bool(close)
        if close == self._gripper_closed:
            return
        cfg = self.config
        if close:
            # width 0 with a wide outer tolerance: squeeze whatever is between the fingers
            future = self.gripper.grasp_async(0.0, cfg.gripper_speed, cfg.gripper_force, 0.0, self._open_width)
        else:
            future = self.gripper.move_async(self._open_width, cfg.gripper_speed)
        # keep every pending command's future: franky crashes if the Gripper goes while one runs
        self._gripper_futures = [f for f in self._gripper_futures if not f.wait(0.0)] + [future]
        self._gripper_closed = close

    def _wait_gripper(self, timeout: float = 5.0) -> None:
        deadline = time.monotonic() + timeout
        for future in self._gripper_futures:
            future.wait(max(0.0, deadline - time.monotonic()))
        self._gripper_futures = [f for f in self._gripper_futures if not f.wait(0.0)]

    # ---- episode ----
    def reset(self, object_positions: dict[str, np.ndarray] | None = None, home: bool = True) -> None:
        """Lift the hand straight up (``reset_lift``, inside the box), on hardware wait for the operator
        (``operator_reset``), open the gripper, then the joint motion home."""
        franky = self.franky
        cfg = self.config
        try:
            self.robot.join_motion(5.0)
        except Exception:
            pass
        if self.robot.has_errors:
            self.robot.recover_from_errors()
        if home and cfg.reset_lift > 0.0:  # clear of the table before the joint motion sweeps the arm home
            pos, quat = self.ee_pose()
            require_finite("measured end-effector pose", np.concatenate([np.ravel(pos), np.ravel(quat)]),
                           "franky backend (reset lift)")  # max(nan, x) is nan: the lift's target would be too
            up = pos.copy()  # straight up (a hand outside the box's x-y is not dragged into it sideways), to
            up[2] = max(pos[2], min(pos[2] + cfg.reset_lift, self._high[2]))  # the box's top at most, never down
            try:
                self.robot.move(franky.CartesianMotion(self._affine(up, quat), franky.ReferenceType.Absolute))
            except Exception as exc:
                self._raise_motion_error(exc)
        if self.scene is None and cfg.operator_reset:  # every reset: an evaluation builds a new env (and
            # backend) per protocol and calibration block, so "not the first" cannot be counted here
            self.confirm("reset: take what the gripper holds and set up the scene for the next episode; the "
                         "gripper then opens and the arm goes home. Press Enter to go on")
        self._gripper_closed = None
        self.set_gripper(False)
        self._wait_gripper()
        if home:
            try:
                self.robot.move(franky.JointMotion(list(cfg.home_joints)))
                if cfg.home_position is not None:
                    target = self._affine(np.asarray(cfg.home_position), np.asarray(cfg.home_quaternion))
                    self.robot.move(franky.CartesianMotion(target, franky.ReferenceType.Absolute))
            except Exception as exc:
                self._raise_motion_error(exc)
        if self.scene is not None:
            positions = np.asarray(self.scene.object_positions(), dtype=np.float64)  # objects not given stay
            given = dict(object_positions or {})
            unknown = set(given) - set(self.object_names)
            if unknown:
                raise ValueError(f"reset: unknown objects {sorted(unknown)}; this scene has {list(self.object_names)}")
            for name, pos in given.items():
                positions[self._object_index[self.object_names.index(name)]] = np.asarray(pos, dtype=np.float64)
            self.scene.place(positions)
        elif object_positions:
            log.info("real robot: place the objects by hand; object_positions ignored")

    @staticmethod
    def confirm(message: str) -> None:
        """Wait for the operator: ``message`` and Enter on the terminal (a process without one gets a one-line
        error naming ``env.real.operator_reset``)."""
        try:
            input(f"{message}: ")
        except EOFError:
            raise RuntimeError("the real robot waits for the operator between episodes, but this process has no "
                               "terminal to read Enter from; set env.real.operator_reset=false to reset "
                               "unattended") from None

    def render(self, camera: str) -> CameraFrame:
        if camera not in self.cameras:
            raise KeyError(f"unknown camera {camera!r}; this backend has {sorted(self.cameras)}")
        return self.cameras[camera].read()

    def object_positions(self) -> np.ndarray | None:
        if self.scene is None:
            return None
        return np.asarray(self.scene.object_positions(), dtype=np.float64)[self._object_index]

    def object_quaternions(self) -> np.ndarray | None:
        """True object orientations ``[K, 4]`` (wxyz) where known (franky-sim), else None."""
        if self.scene is None:
            return None
        return np.asarray(self.scene.object_quaternions(), dtype=np.float64)[self._object_index]

    def displace_objects(self, deltas: np.ndarray) -> None:
        if self.scene is None:
            return super().displace_objects(deltas)
        deltas = np.asarray(deltas, dtype=np.float64)
        if deltas.shape != (len(self.object_names), 3):
            raise ValueError(f"displace_objects: deltas must be [{len(self.object_names)}, 3]; got {list(deltas.shape)}")
        full = np.zeros((len(self.scene.object_names), 3))
        full[self._object_index] = deltas
        self.scene.displace(full)

    def close(self) -> None:
        for cam in self.cameras.values():
            try:
                cam.close()
            except Exception:
                pass
        if getattr(self, "robot", None) is not None:
            try:
                if not self.robot.join_motion(5.0):  # still moving after 5 s: stop it rather than leave it running
                    self.robot.stop()
            except Exception:
                pass
            self._wait_gripper(10.0)
            if self._gripper_futures:
                log.warning("a gripper command is still running; the connection stays open until it ends")
                return
        if self.scene is not None:
            self.scene.close()
            self.scene = None
        self.robot = None
        self.gripper = None


def make_real_backend(config: Any) -> FrankyBackend:
    """Build the real backend from the ``franka`` env's config (see the module docstring for the fields)."""
    from ddp.envs.franka.cameras import FrankySimScene, load_calibration, make_camera, read_server_info

    cfg = RealBackendConfig.from_env_config(config)
    task = getattr(config, "task_spec", None)  # the franka env's task: object order and home pose
    if task is not None:
        updates = {}
        if not cfg.object_names:
            updates["object_names"] = tuple(task.object_names)
        if cfg.home_position is None and getattr(task, "home", None) is not None:
            updates["home_position"] = tuple(task.home)
        if updates:
            cfg = dataclasses.replace(cfg, **updates)
    _import_franky()  # fail early with the install hint, before touching cameras
    calibration = load_calibration(cfg.calibration) if cfg.calibration else None
    scene, host = None, cfg.robot_host
    if cfg.franky_sim_info:
        info = read_server_info(cfg.franky_sim_info, wait=cfg.franky_sim_wait)
        host = info["robot_host"]
        scene = FrankySimScene(info["scene_host"], info["scene_port"])
    default_type = "franky_sim" if scene is not None else "realsense"
    if cfg.cameras is not None:
        specs = cfg.cameras
    else:  # the env's cameras: the policy camera, and the tracking camera where the env uses it
        specs = {"policy": {}}
        if scene is not None or getattr(config, "tracking_camera", True):
            specs["tracking"] = {}
    cameras = {}
    try:
        for name, spec in specs.items():
            spec = dict(spec or {})
            spec.setdefault("type", default_type)
            cameras[name] = make_camera(name, spec, calibration, scene)
        return FrankyBackend(cfg, cameras, scene=scene, robot_host=host)
    except BaseException:
        for cam in cameras.values():
            cam.close()
        if scene is not None:
            scene.close()
        raise


def franky_sim_scene(config: Any, seed: int = 0) -> dict:
    """The ``--scene`` of a franky-sim server matching a ``franka`` env config (or a task).

    The task's MJCF and object order, its ID layout for ``seed`` as initial positions, and the
    cameras: "policy" from the config's camera pose and image size, "tracking" from the task's
    tracking camera and the config's tracking image size (so the frames have the env's shapes).
    Write it as JSON and pass the file to ``franky_sim_server.py --scene``.
    """
    task = getattr(config, "task_spec", config)
    policy = getattr(config, "policy_camera", task.policy_camera)
    asset, worldbody = task.mjcf()
    layout = task.sample_layout(np.random.default_rng([abs(int(seed)), 0]))

    def camera(spec, height, width):
        return {"pos": list(spec.pos), "lookat": list(spec.lookat), "fovy": float(spec.fovy),
                "width": int(width), "height": int(height)}  # fmt: skip

    return {
        "asset": asset,
        "worldbody": worldbody,
        "objects": list(task.object_names),
        "positions": {name: np.asarray(pos, dtype=float).tolist() for name, pos in layout.items()},
        "cameras": {
            "policy": camera(policy, getattr(config, "image_height", 120), getattr(config, "image_width", 160)),
            "tracking": camera(
                task.tracking_camera,
                getattr(config, "tracking_image_height", 120),
                getattr(config, "tracking_image_width", 160),
            ),
        },
    }
