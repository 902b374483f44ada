"""Imagination substitution: the paper's "World Model Imagination Analysis (ID)"."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ddp.keys import KeyedModule
from ddp.registry import register


@dataclass
class SubstitutionConfig:
    p: float = 0.1  # probability of using imagined latents in a cycle (1.0 = open-loop imagination)
    seed: int = 0

    def __post_init__(self):
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"p must be in [0, 1]; got {self.p}")


@register("detector", "substitution", config=SubstitutionConfig)
class SubstitutionDetector(KeyedModule):
    """After the first chunk, replace the real latents by imagined ones with probability p.

    Decided anew every cycle (not sticky); with p = 1 the policy runs on
    open-loop imagination after the initial observation. No tracking.
    """

    default_in_keys = {"chunk_index": "chunk_index"}
    default_out_keys = {"ood": ("ddp", "ood")}
    sticky = False
    needs_discrepancy = False

    def __init__(self, config: SubstitutionConfig):
        super().__init__()
        self.config = config
        self.reset()

    def reset(self):
        self._gen = torch.Generator().manual_seed(self.config.seed)

    def forward(self, td):
        chunk = td.get(self.key("chunk_index")).reshape(-1)
        draw = torch.rand(chunk.shape, generator=self._gen) < self.config.p
        td.set(self.key("ood"), (draw & (chunk >= 1)).reshape(td.get(self.key("chunk_index")).shape[:-1]))
        return td
