"""Subtask ends after an allotted number of chunks (the paper's trigger for pouring)."""

from __future__ import annotations

from dataclasses import dataclass

from ddp.registry import register


@dataclass
class TimerConfig:
    chunks: int = 4

    def __post_init__(self):
        if self.chunks < 1:
            raise ValueError(f"chunks must be >= 1; got {self.chunks}")


@register("trigger", "timer", config=TimerConfig)
class TimerTrigger:
    """Fires after ``chunks`` chunks spent in the current subtask."""

    def __init__(self, config: TimerConfig):
        self.config = config

    def fired(self, obs, chunk_index: int, subtask_chunks: int) -> bool:
        return subtask_chunks >= self.config.chunks
