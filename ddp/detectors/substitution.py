"""Imagination substitution: the paper's "World Model Imagination Analysis (ID)"."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ddp.keys import KeyedModule
from ddp.registry import register
from ddp.rng import generator, mix


@dataclass
class SubstitutionConfig:
    p: float = 0.1  # probability of using imagined latents in a cycle (1.0 = open-loop imagination)
    seed: int = 0  # mixed with the controller's per-episode key: a training seed's draws differ from another's

    def __post_init__(self):
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"p must be in [0, 1]; got {self.p}")


@register("detector", "substitution", config=SubstitutionConfig)
class SubstitutionDetector(KeyedModule):
    """After the first chunk, replace the real latents by imagined ones with probability p.

    Decided anew every cycle (not sticky); with p = 1 the policy runs on
    open-loop imagination after the initial observation. No tracking.

    Each draw is a function of ``seed``, the episode's key (``("ddp", "episode_key")``, which the
    controller derives from its own seed and the episode's seed) and the chunk: an episode gets the same
    draws whatever env row or batch size runs it, and another training seed gets other draws. Without
    that key (the detector called outside a controller) the draws come from one stream seeded with ``seed``.
    """

    default_in_keys = {"chunk_index": "chunk_index", "episode_key": ("ddp", "episode_key")}
    default_out_keys = {"ood": ("ddp", "ood")}
    sticky = False
    needs_discrepancy = False
    decides = False  # substitutes by chance, not from observations: no detection metrics

    def __init__(self, config: SubstitutionConfig):
        super().__init__()
        self.config = config
        self.reset()

    def reset(self):
        self._gen = torch.Generator().manual_seed(self.config.seed)

    def forward(self, td):
        chunk = td.get(self.key("chunk_index")).reshape(-1)
        keys = td.get(self.key("episode_key"), None)
        if keys is None:
            u = torch.rand(chunk.shape, generator=self._gen)
        else:
            u = torch.stack([torch.rand((), generator=generator(mix(self.config.seed, int(k), int(c))))
                             for k, c in zip(keys.reshape(-1).tolist(), chunk.tolist())])
        draw = u < self.config.p
        td.set(self.key("ood"), (draw & (chunk >= 1)).reshape(td.get(self.key("chunk_index")).shape[:-1]))
        return td
