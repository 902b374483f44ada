"""The paper's three real-robot tasks, modelled for simulation: stack, pour, press.

``TASKS`` maps a task name to its :class:`~ddp.envs.franka.tasks.base.FrankaTask`.
"""

from ddp.envs.franka.tasks.base import FrankaTask
from ddp.envs.franka.tasks.pour import PourTask
from ddp.envs.franka.tasks.press import PressTask
from ddp.envs.franka.tasks.stack import StackTask

__all__ = ["FrankaTask", "TASKS"]

TASKS: dict[str, FrankaTask] = {"stack": StackTask(), "pour": PourTask(), "press": PressTask()}
