"""Franka Panda: the paper's real-robot tasks (stack, pour, press) in simulation and on hardware.

Importing this package registers the ``franka`` env (``ddp.envs.franka.env``).
Heavy dependencies load only when used: robosuite / MuJoCo when a simulated
backend is built (``ddp.envs.franka.sim``), franky / pyrealsense2 when the
hardware backend is (``ddp.envs.franka.real``).
"""

from ddp._autoload import import_submodules

import_submodules(__name__, __path__)
