"""Subtask ends when a given action chunk has been executed (the paper's hard-coded oracle timing)."""

from __future__ import annotations

from dataclasses import dataclass

from ddp.registry import register


@dataclass
class ChunkIndexConfig:
    chunk: int = 6

    def __post_init__(self):
        if self.chunk < 1:
            raise ValueError(f"chunk must be >= 1; got {self.chunk}")


@register("trigger", "chunk_index", config=ChunkIndexConfig)
class ChunkIndexTrigger:
    """Fires once ``chunk`` chunks have been executed in the episode."""

    def __init__(self, config: ChunkIndexConfig):
        self.config = config

    def fired(self, obs, chunk_index: int, subtask_chunks: int) -> bool:
        return chunk_index >= self.config.chunk
