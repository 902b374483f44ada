"""Target-specific recovery: the inverse shift a^rec_j = -Delta p_Cj after subtask S_j."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ddp.errors import RecipeError
from ddp.registry import register


@dataclass
class TargetSpecificConfig:
    also_recovers: list[int] = field(default_factory=list)  # objects moved back with the target (held by it)

    def __post_init__(self):
        bad = [k for k in self.also_recovers if isinstance(k, bool) or not isinstance(k, int) or k < 0]
        if bad:
            raise ValueError(f"also_recovers must list object indices >= 0; got {list(self.also_recovers)}")


@register("recovery", "target_specific", config=TargetSpecificConfig)
class TargetSpecificRecovery:
    """At the end of a subtask whose target was displaced: shift the end-effector by -Delta p and
    remove the target (and the objects it carries) from the displaced set (paper, Target-Specific Recovery)."""

    trigger_chunk: int | None = None  # use the subtask's own trigger

    def __init__(self, config: TargetSpecificConfig):
        self.config = config

    def recover(self, offsets: torch.Tensor, displaced: torch.Tensor, target: int):
        """offsets [K, 3], displaced [K] bool -> (end-effector shift [3], recovered [K] bool)."""
        recovered = torch.zeros_like(displaced)
        if target is None or not bool(displaced[target]):
            return torch.zeros(3, dtype=offsets.dtype), recovered
        recovered[target] = True
        for k in self.config.also_recovers:
            if k >= displaced.shape[0]:
                raise RecipeError(f"object {k} is not one of the {displaced.shape[0]} object(s) the tracker "
                                  f"follows (0..{displaced.shape[0] - 1})", key="controller.recovery.also_recovers")
            recovered[k] = True
        return -offsets[target], recovered

    def reset(self):
        pass
