"""Franka Panda: the paper's real-robot tasks (stack, pour, press) in simulation and on hardware.

Importing this package registers the ``franka`` env (``ddp.envs.franka.env``); the
hardware backend and the franky-sim server are not imported with it.
Heavy dependencies load only when used: robosuite / MuJoCo when a simulated
backend is built (``ddp.envs.franka.sim``), franky / pyrealsense2 when the
hardware backend is (``ddp.envs.franka.real``).
"""

from ddp.envs.franka import env  # noqa: F401  (registers the franka env)
