"""Subtask ends when the gripper has closed (the paper's trigger for picking)."""

from __future__ import annotations

from dataclasses import dataclass

from ddp.registry import register


@dataclass
class GripperClosureConfig:
    width_below: float = 0.045  # finger distance (m) under which the gripper counts as closed
    left: tuple[int, int] = (3, 6)  # agent_pos slices of the two finger positions (DP3's 9-d layout)
    right: tuple[int, int] = (6, 9)
    min_chunks: int = 1  # ignore a closed gripper in the subtask's first chunks

    def __post_init__(self):
        if self.width_below <= 0:
            raise ValueError(f"width_below must be > 0; got {self.width_below}")


@register("trigger", "gripper_closure", config=GripperClosureConfig)
class GripperClosureTrigger:
    """Fires when the distance between the finger positions in ``agent_pos`` drops below a width."""

    def __init__(self, config: GripperClosureConfig):
        self.config = config

    def width(self, agent_pos) -> float:
        c = self.config
        return float((agent_pos[..., c.left[0] : c.left[1]] - agent_pos[..., c.right[0] : c.right[1]]).norm(dim=-1))

    def fired(self, obs, chunk_index: int, subtask_chunks: int) -> bool:
        if subtask_chunks < self.config.min_chunks:
            return False
        return self.width(obs["agent_pos"][-1]) < self.config.width_below
