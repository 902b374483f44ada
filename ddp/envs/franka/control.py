"""The Franka control loop shared by every backend: 7-d relative action -> clipped absolute end-effector target.

The policy's action (paper, "Real World Experiments": "7-DoF relative commands
(dx, dy, dz, roll, pitch, yaw) ... plus a binary gripper state") is

* ``action[0:3]``: translation of the end-effector in the robot base frame (metres);
* ``action[3:6]``: rotation of the end-effector as a rotation vector in the base
  frame (radians; for the small per-step angles this is roll, pitch, yaw about the
  base axes), applied on the left: ``R_target = exp([action[3:6]]) @ R``;
* ``action[6]``: gripper, ``> 0`` closes (grasp), ``<= 0`` opens.

:class:`FrankaControl` clips the translation and rotation per step
(``max_translation`` per axis, ``max_rotation`` per axis), adds them to the
previous *commanded* target (so that repeated small steps are not lost to
tracking lag, as a blocking real robot would also reach them), keeps that
target within ``max_lead`` metres / ``max_rotation_lead`` radians of the
measured pose (so that pushing against an obstacle cannot wind the target up
without bound: the contact force stays bounded), clips the position to the
workspace box, keeps the orientation within ``max_tilt`` radians of the one at
reset (the home pose: per-step limits alone let a small bias wind the wrist past
its joint limits or tilt the hand into the table over a few chunks) and sends the
absolute target to ``backend.move_to``. The gripper
command goes to ``backend.set_gripper`` only when it changes.

Quaternions are ``[w, x, y, z]``; rotation matrices act on column vectors.
"""

from __future__ import annotations

import numpy as np

from ddp.envs.franka.backend import FrankaBackend
from ddp.safety import require_finite

__all__ = [
    "FrankaControl",
    "agent_pos",
    "fingertips",
    "mat_to_quat",
    "quat_to_mat",
    "rotvec_to_mat",
    "mat_to_rotvec",
    "rotation_6d",
    "ACTION_DIM",
    "AGENT_POS_DIM",
]

ACTION_DIM = 7
LIFT_SLACK = 0.02  # metres: a shift's lift that stops farther below its height cancels the move across
AGENT_POS_DIM = 15  # ee (3), left fingertip (3), right fingertip (3), 6-d rotation (6)


# --------------------------------------------------------------------------------------- rotations
def quat_to_mat(q) -> np.ndarray:
    """``[w, x, y, z]`` -> 3x3 rotation matrix (the quaternion is normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def mat_to_quat(m) -> np.ndarray:
    """3x3 rotation matrix -> ``[w, x, y, z]`` with ``w >= 0``."""
    m = np.asarray(m, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def rotvec_to_mat(v) -> np.ndarray:
    """Rotation vector (axis * angle) -> 3x3 matrix (Rodrigues)."""
    v = np.asarray(v, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.eye(3)
    k = v / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)


def mat_to_rotvec(m) -> np.ndarray:
    """3x3 rotation matrix -> rotation vector (angle in [0, pi])."""
    q = mat_to_quat(m)
    s = np.linalg.norm(q[1:])
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * np.arctan2(s, q[0])
    return q[1:] / s * angle


def rotation_angle(a, b) -> float:
    """Angle (radians) of the rotation taking matrix ``a`` to matrix ``b``."""
    c = (np.trace(np.asarray(a).T @ np.asarray(b)) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def rotation_6d(quat) -> np.ndarray:
    """The first two columns of the rotation matrix, ``[r00, r10, r20, r01, r11, r21]``."""
    m = quat_to_mat(quat)
    return np.concatenate([m[:, 0], m[:, 1]])


# ------------------------------------------------------------------------------------ agent_pos
def fingertips(position, quaternion, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Left and right fingertip positions: ``ee -/+ width/2`` along the end-effector's y axis.

    The Franka Hand's fingers slide along the end-effector (TCP) frame's y axis;
    deriving the fingertips from the pose and the measured width makes
    ``agent_pos`` identical in meaning for every backend.
    """
    y = quat_to_mat(quaternion)[:, 1]
    p = np.asarray(position, dtype=np.float64)
    return p + 0.5 * width * y, p - 0.5 * width * y


def agent_pos(position, quaternion, width: float) -> np.ndarray:
    """The 15-d proprioception: ee (3), left fingertip (3), right fingertip (3), 6-d rotation (6).

    The first 9 entries follow DP3's layout (end-effector + two finger
    positions), so the ``gripper_closure`` trigger reads the finger distance
    with its default slices ``[3:6]`` and ``[6:9]``.
    """
    left, right = fingertips(position, quaternion, width)
    return np.concatenate([np.asarray(position, dtype=np.float64), left, right, rotation_6d(quaternion)])


# --------------------------------------------------------------------------------------- control
class FrankaControl:
    """Turns relative actions into clipped absolute targets for a :class:`FrankaBackend`.

    Args:
        backend: the robot.
        workspace_low, workspace_high: base-frame box the position target is clipped to.
        max_translation: metres per step and axis (the action's translation is clipped to it).
        max_rotation: radians per step and axis.
        max_lead: metres the commanded target may lead the measured end-effector position.
        max_rotation_lead: radians the commanded orientation may lead the measured one.
        max_tilt: radians the commanded orientation may turn away from the one at :meth:`reset` (the
            oracle demos turn at most 121 degrees, pouring; the default allows 137.5).
    """

    def __init__(
        self,
        backend: FrankaBackend,
        *,
        workspace_low,
        workspace_high,
        max_translation: float = 0.02,
        max_rotation: float = 0.1,
        max_lead: float = 0.03,
        max_rotation_lead: float = 0.3,
        max_tilt: float = 2.4,
    ):
        self.backend = backend
        self.low = np.asarray(workspace_low, dtype=np.float64)
        self.high = np.asarray(workspace_high, dtype=np.float64)
        if (self.low.shape != (3,) or self.high.shape != (3,) or not np.isfinite([*self.low, *self.high]).all()
                or np.any(self.low >= self.high)):
            raise ValueError(
                f"workspace_low must be below workspace_high on x, y, z; got {workspace_low}, {workspace_high}"
            )
        for name, value in (("max_translation", max_translation), ("max_rotation", max_rotation),
                            ("max_lead", max_lead), ("max_rotation_lead", max_rotation_lead),
                            ("max_tilt", max_tilt)):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0; got {value}")
        if max_tilt > np.pi:
            raise ValueError(f"max_tilt must be at most pi (no bound beyond it); got {max_tilt}")
        self.max_tilt = float(max_tilt)
        self.max_translation = float(max_translation)
        self.max_rotation = float(max_rotation)
        self.max_lead = float(max_lead)
        self.max_rotation_lead = float(max_rotation_lead)
        self.action_low = np.array([-max_translation] * 3 + [-max_rotation] * 3 + [-1.0])
        self.action_high = -self.action_low
        self.target_pos = np.zeros(3)
        self.target_rot = np.eye(3)
        self.home_rot = np.eye(3)  # the orientation at reset, which max_tilt is measured from
        self.gripper_closed: bool | None = None

    def reset(self) -> None:
        """Re-anchor the commanded target at the measured pose (call after ``backend.reset``)."""
        pos, quat = self.backend.ee_pose()
        self.target_pos = np.asarray(pos, dtype=np.float64).copy()
        self.target_rot = quat_to_mat(quat)
        self.home_rot = self.target_rot.copy()
        self.gripper_closed = False

    def clip_action(self, action) -> np.ndarray:
        """The action as executed: translation / rotation clipped per axis, gripper in [-1, 1]."""
        a = np.asarray(action, dtype=np.float64).reshape(ACTION_DIM)
        require_finite("action", a, "franka control")  # a NaN gripper command would read as "open"
        return np.clip(a, self.action_low, self.action_high)

    def _targets(self, dpos: np.ndarray, drot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos, quat = self.backend.ee_pose()
        pos = np.asarray(pos, dtype=np.float64)
        rot = quat_to_mat(quat)
        target = self.target_pos + dpos
        lead = target - pos
        dist = float(np.linalg.norm(lead))
        if dist > self.max_lead:  # bounded wind-up against obstacles
            target = pos + lead * (self.max_lead / dist)
        target = np.clip(target, self.low, self.high)
        delta = rotvec_to_mat(drot)
        target_rot = delta @ self.target_rot
        if rotation_angle(rot, target_rot) > self.max_rotation_lead:
            target_rot = delta @ rot
        return target, self._within_tilt(target_rot)

    def _within_tilt(self, target_rot: np.ndarray) -> np.ndarray:
        """``target_rot``, or the rotation on the way to it from the home orientation at ``max_tilt``."""
        away = mat_to_rotvec(target_rot @ self.home_rot.T)  # base frame, as the actions' rotations
        angle = float(np.linalg.norm(away))
        if angle <= self.max_tilt:
            return target_rot
        return rotvec_to_mat(away * (self.max_tilt / angle)) @ self.home_rot

    def step(self, action) -> np.ndarray:
        """Execute one action (one ``control_period``); returns the executed (clipped) action."""
        a = self.clip_action(action)
        close = bool(a[6] > 0.0)
        if close != self.gripper_closed:
            self.backend.set_gripper(close)
            self.gripper_closed = close
        target_pos, target_rot = self._targets(a[:3], a[3:6])
        quat = mat_to_quat(target_rot)
        require_finite("target", np.concatenate([target_pos, quat]), "franka control")  # defence in depth
        self.target_pos, self.target_rot = target_pos, target_rot
        self.backend.move_to(self.target_pos.copy(), quat)
        return a

    def _approach(self, waypoint: np.ndarray, quat: np.ndarray, max_steps: int, tolerance: float) -> None:
        """Up to ``max_steps`` control periods toward ``waypoint``, in bounded increments (so that the arm, and
        what it holds, moves smoothly), fewer once within ``tolerance``."""
        for _ in range(max_steps):
            pos, _ = self.backend.ee_pose()
            step = waypoint - np.asarray(pos)
            dist = float(np.linalg.norm(step))
            if dist < tolerance:
                break
            command = np.clip(pos + step * min(1.0, self.max_lead / max(dist, 1e-9)), self.low, self.high)
            require_finite("shift target", command, "franka control")
            self.backend.move_to(command, quat)

    def shift(self, delta, *, safe_lift: float = 0.0, max_steps: int = 40, tolerance: float = 0.005) -> np.ndarray:
        """Move the end-effector by ``delta`` (base frame) with the orientation and gripper unchanged.

        The commanded target moves by ``delta`` (clipped to the workspace); with
        ``safe_lift > 0`` the move goes up by ``safe_lift``, across, and down
        again. Each phase sends the backend up to ``max_steps`` control periods
        toward its waypoint (fewer once within ``tolerance``). A lift that does not
        get within ``LIFT_SLACK`` of its height (blocked, or too slow) cancels the
        move across, which would drag the hand low through what is on the table: the
        hand goes back down and the shift is not applied (a warning says so). Returns
        the shift of the commanded target actually applied (after clipping to the
        workspace and to what the backend can reach: ``backend.reachable``).
        """
        delta = np.asarray(delta, dtype=np.float64).reshape(3)
        require_finite("end-effector shift", delta, "franka control")
        start = self.target_pos.copy()
        quat = mat_to_quat(self.target_rot)
        reach = getattr(self.backend, "reachable", None)

        def held(point: np.ndarray) -> np.ndarray:  # where the arm would hold a target at ``point``
            point = np.clip(point, self.low, self.high)
            return np.clip(np.asarray(reach(point, quat), dtype=np.float64), self.low, self.high) if reach else point

        goal = held(start + delta)
        waypoints = [goal]
        if safe_lift > 0.0:
            lift = np.array([0.0, 0.0, safe_lift])
            waypoints = [held(start + lift), held(goal + lift), goal]
        for i, waypoint in enumerate(waypoints):
            self._approach(waypoint, quat, max_steps, tolerance)
            if i == 0 and len(waypoints) > 1:
                short = float(waypoint[2] - np.asarray(self.backend.ee_pose()[0])[2])
                if short > LIFT_SLACK:  # not up: moving across now would drag the hand through the scene
                    import warnings

                    warnings.warn(f"franka control: the shift's {safe_lift:.3f} m lift stopped {short:.3f} m short "
                                  "of its height; the shift is not applied", RuntimeWarning, stacklevel=2)
                    goal = start
                    self._approach(goal, quat, max_steps, tolerance)
                    break
        self.target_pos = goal
        self.backend.move_to(goal.copy(), quat)
        return goal - start
