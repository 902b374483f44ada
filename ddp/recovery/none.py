"""No recovery: tracking shifts are never undone (ablation)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ddp.registry import register


@dataclass
class NoRecoveryConfig:
    pass


@register("recovery", "none", config=NoRecoveryConfig)
class NoRecovery:
    """Never shifts back and never marks an object recovered."""

    trigger_chunk: int | None = None

    def __init__(self, config: NoRecoveryConfig):
        self.config = config

    def recover(self, offsets: torch.Tensor, displaced: torch.Tensor, target: int):
        return torch.zeros(3, dtype=offsets.dtype), torch.zeros_like(displaced)

    def reset(self):
        pass
