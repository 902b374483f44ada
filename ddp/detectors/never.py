"""Never OOD: the plain base policy (DP3 / DDP without imagination)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ddp.keys import KeyedModule
from ddp.registry import register


@dataclass
class NeverConfig:
    pass


@register("detector", "never", config=NeverConfig)
class NeverDetector(KeyedModule):
    """Always in distribution: the policy always acts from real observations."""

    default_in_keys = {"chunk_index": "chunk_index"}
    default_out_keys = {"ood": ("ddp", "ood")}
    sticky = True
    needs_discrepancy = False
    decides = False  # decides nothing from observations: its protocols get no detection metrics

    def __init__(self, config: NeverConfig):
        super().__init__()
        self.config = config

    def forward(self, td):
        td.set(self.key("ood"), torch.zeros(td.get(self.key("chunk_index")).shape[:-1], dtype=torch.bool))
        return td

    def reset(self):
        pass
