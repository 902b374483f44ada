"""What the Franka env needs from a robot: the backend interface shared by simulation and hardware.

The ``franka`` env (``ddp.envs.franka.env``) runs one control loop for every
backend: it turns the policy's 7-d action (end-effector translation and
rotation deltas, binary gripper) into an absolute end-effector target, clips
it to the workspace and step limits, and hands it to the backend; it builds
the observation (point cloud, ``agent_pos``) from what the backend returns.
What is tested in simulation is therefore what runs on the robot; only this
interface differs.

Frames and units: positions in metres in the robot BASE frame (the world
frame of the simulated scene is chosen to coincide with it), orientations as
unit quaternions ``[w, x, y, z]``, depth in metres. Camera poses use the
OpenCV convention (x right, y down, z forward), as RealSense and
FoundationPose do; MuJoCo cameras (x right, y up, looking along -z) are
converted by the simulated backend.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

__all__ = ["CameraFrame", "FrankaBackend"]


@dataclass
class CameraFrame:
    """One depth image with its geometry.

    Attributes:
        depth: ``[H, W]`` float32 metric depth along the optical axis; 0 where there is no return.
        intrinsics: ``[3, 3]`` pinhole matrix K (fx, fy, cx, cy in pixels).
        cam_to_world: ``[4, 4]`` pose of the camera in the robot base frame, OpenCV axes.
        segmentation: ``[H, W]`` int32 object index per pixel (the env's object order, -1 elsewhere)
            where the backend knows it (simulation); None on hardware.
        rgb: ``[H, W, 3]`` uint8 colour image where rendered/captured (FoundationPose needs it), else None.
    """

    depth: np.ndarray
    intrinsics: np.ndarray
    cam_to_world: np.ndarray
    segmentation: np.ndarray | None = None
    rgb: np.ndarray | None = None


class RobotMotionError(RuntimeError):
    """The robot stopped a motion (reflex, limit, planner); errors were recovered, the episode should end."""


class FrankaBackend(abc.ABC):
    """A Franka arm + hand, its cameras and (where known) the objects' true poses."""

    #: seconds of robot time per env step (one action); the paper runs 8-action chunks at 2 Hz
    control_period: float = 0.0625
    #: object names in the env's order (target objects first, as the task defines them)
    object_names: tuple[str, ...] = ()

    @abc.abstractmethod
    def reset(self, object_positions: dict[str, np.ndarray] | None = None, home: bool = True) -> None:
        """Open the gripper, send the arm to its home pose (``home``) and place the objects.

        ``object_positions``: base-frame positions for objects a simulator places; a hardware
        backend ignores it (the operator places the objects) or checks them against its tracker.
        """

    @abc.abstractmethod
    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """End-effector (between the fingertips) position ``[3]`` and quaternion ``[4]`` (wxyz)."""

    @abc.abstractmethod
    def gripper_width(self) -> float:
        """Distance between the fingers in metres."""

    @abc.abstractmethod
    def move_to(self, position: np.ndarray, quaternion: np.ndarray) -> None:
        """Drive the end-effector toward an absolute target for one ``control_period`` (blocking)."""

    @abc.abstractmethod
    def set_gripper(self, close: bool) -> None:
        """Command the gripper closed (grasp) or open; returns without waiting for the fingers."""

    @abc.abstractmethod
    def render(self, camera: str) -> CameraFrame:
        """The latest frame of a named camera (``"policy"``: the point-cloud camera; ``"tracking"``)."""

    def reachable(self, position: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
        """Where the backend would hold the end-effector for a target at ``position`` (with orientation
        ``quaternion``): ``position`` itself, unless the backend pulls targets back (a real arm's reach);
        a tracking shift counts what this gives as executed."""
        return np.asarray(position, dtype=np.float64)

    def object_positions(self) -> np.ndarray | None:
        """True object positions ``[K, 3]`` in ``object_names`` order where known (simulation), else None."""
        return None

    def displace_objects(self, deltas: np.ndarray) -> None:
        """Move objects by ``deltas`` ``[K, 3]`` now (the OOD disturbance); simulation only."""
        raise NotImplementedError(f"{type(self).__name__} cannot move objects: do it by hand on a real robot")

    def close(self) -> None:
        """Release the robot connection, renderers and processes."""
