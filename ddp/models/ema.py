"""Exponential moving average of model weights (Diffusion Policy's warm-up schedule)."""

from __future__ import annotations

import copy

import torch
from torch import nn

from ddp.schema import EMAConfig


def ema_decay(step: int, cfg: EMAConfig) -> float:
    """decay = 1 - (1 + step / inv_gamma) ** -power, clamped to [min_value, max_value].

    ``step`` is the number of EMA updates made before this one (DP3's and
    Diffusion Policy's ``optimization_step``); decay is 0 for the first two
    updates after ``update_after_step`` (the average starts as a copy of the
    weights).
    """
    step = step - cfg.update_after_step - 1
    if step <= 0:
        return 0.0
    value = 1.0 - (1.0 + step / cfg.inv_gamma) ** -cfg.power
    return float(min(max(value, cfg.min_value), cfg.max_value))


class EMA(nn.Module):
    """Holds ``module``, an averaged copy of a model, evaluated instead of the raw weights."""

    def __init__(self, model: nn.Module, cfg: EMAConfig):
        super().__init__()
        self.cfg = cfg
        self.module = copy.deepcopy(model).eval().requires_grad_(False)
        self.register_buffer("optimization_step", torch.zeros((), dtype=torch.long))
        self.decay = 0.0

    @torch.no_grad()
    def update(self, model: nn.Module) -> float:
        self.decay = ema_decay(int(self.optimization_step), self.cfg)  # from the updates made before this one
        self.optimization_step += 1
        d = self.decay
        averaged, frozen = ([], []), ([], [])  # (ema, model) tensors, updated in one foreach call each
        for ema_p, p in zip(self.module.parameters(), model.parameters()):
            pair = averaged if p.requires_grad else frozen
            pair[0].append(ema_p)
            pair[1].append(p.detach())
        for ema_b, b in zip(self.module.buffers(), model.buffers()):
            frozen[0].append(ema_b)
            frozen[1].append(b)
        if averaged[0]:
            torch._foreach_lerp_(averaged[0], averaged[1], 1.0 - d)  # ema <- d * ema + (1 - d) * p
        if frozen[0]:
            torch._foreach_copy_(frozen[0], frozen[1])
        return d
