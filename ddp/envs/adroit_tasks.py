"""Per-task facts for the Adroit hand tasks (door, hammer, pen) as DP3 and the paper use them.

The simulator is gymnasium-robotics' ``AdroitHand{Door,Hammer,Pen}-v1``
(the DAPG tasks of Rajeswaran et al., RSS 2018, rebuilt on the ``mujoco``
bindings). What DP3 (Ze et al., RSS 2024, ``diffusion_policy_3d``) does on
top of it, and what this table keeps:

* Camera. DP3 renders Adroit door and hammer from a ``top`` camera that
  exists only in its own copy of the models (``DAPG_door.xml``: ``pos="0 0
  1.5" euler="0 0 3.14"``; ``DAPG_hammer.xml``: ``pos="0 0 1.1"``, same
  orientation; default fovy 45), and pen from ``vil_camera``, which its
  ``DAPG_pen.xml`` places at ``0 -0.8 0.8`` (gymnasium-robotics: ``0 -1.2
  1.2``) looking down 45 degrees. The gymnasium-robotics models lack ``top``,
  so the env re-poses their ``fixed`` camera (fovy 45, like DP3's) to
  ``camera_pos`` / ``camera_quat`` below. 84 x 84 depth, 512 points (FPS).
* Crop. DP3 builds its cloud in a camera-relative frame and keeps points
  above a per-task height; worked back to the world frame all three keep
  exactly what lies above the table top (z > ~0.001 m; the table surface is
  z = 0, the floor z = -1). The env crops in the world frame with the same
  effect (``CROP_MIN`` / ``CROP_MAX``).
* Proprioception. DP3's ``agent_pos`` is the 24 joint angles of the hand
  (2 wrist + 22 finger joints, ``qpos[4:-2]`` door, ``qpos[2:-7]`` hammer,
  ``qpos[:-6]`` pen), without the arm joints. ``qpos_hand`` names them.
* Horizon. DP3's Adroit env repeats every action twice (``num_repeats=2``)
  under the original 200 / 200 / 100 simulator-step limits. The packaged
  DAPG experts were trained without repeats, so this env executes each
  action once and keeps the original limits: door and hammer 200 steps,
  pen 100.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ADROIT_TASKS", "AdroitTask", "CROP_MIN", "CROP_MAX", "HAND_JOINTS"]

#: The 24 joints of the Shadow-style hand, in qpos order (DP3's agent_pos).
HAND_JOINTS: tuple[str, ...] = (
    "WRJ1", "WRJ0",
    "FFJ3", "FFJ2", "FFJ1", "FFJ0",
    "MFJ3", "MFJ2", "MFJ1", "MFJ0",
    "RFJ3", "RFJ2", "RFJ1", "RFJ0",
    "LFJ4", "LFJ3", "LFJ2", "LFJ1", "LFJ0",
    "THJ4", "THJ3", "THJ2", "THJ1", "THJ0",
)  # fmt: skip

#: World-frame workspace box: everything above the table top (DP3's crop, see the module docstring).
CROP_MIN: tuple[float, float, float] = (-1.0, -1.0, 0.001)
CROP_MAX: tuple[float, float, float] = (1.0, 1.0, 1.0)

_TOP_QUAT = (0.0, 0.0, 0.0, 1.0)  # DP3's euler="0 0 3.14": looking straight down, rotated 180 deg about z
_VIL_QUAT = (0.92388, 0.382683, 0.0, 0.0)  # 45 deg about x (the models' fixed / vil_camera orientation)


@dataclass(frozen=True)
class AdroitTask:
    """One Adroit task.

    Attributes:
        name: short name (``"door"``).
        env_class: gymnasium-robotics class in ``gymnasium_robotics.envs.adroit_hand``.
        gym_id: the registered gymnasium id.
        state_dim: length of the gymnasium observation (``("privileged", "state")``).
        action_dim: actuators (arm + hand), actions in [-1, 1].
        max_episode_steps: the original benchmark's horizon.
        camera_pos, camera_quat: DP3's camera pose for this task (``fixed`` is moved there).
        expert: file name of the packaged DAPG expert in ``ddp/assets/adroit``.
    """

    name: str
    env_class: str
    gym_id: str
    state_dim: int
    action_dim: int
    max_episode_steps: int
    camera_pos: tuple[float, float, float]
    camera_quat: tuple[float, float, float, float]
    expert: str


ADROIT_TASKS: dict[str, AdroitTask] = {
    "door": AdroitTask("door", "AdroitHandDoorEnv", "AdroitHandDoor-v1", 39, 28, 200,
                       (0.0, 0.0, 1.5), _TOP_QUAT, "door_expert.npz"),
    "hammer": AdroitTask("hammer", "AdroitHandHammerEnv", "AdroitHandHammer-v1", 46, 26, 200,
                         (0.0, 0.0, 1.1), _TOP_QUAT, "hammer_expert.npz"),
    "pen": AdroitTask("pen", "AdroitHandPenEnv", "AdroitHandPen-v1", 45, 24, 100,
                      (0.0, -0.8, 0.8), _VIL_QUAT, "pen_expert.npz"),
}  # fmt: skip
