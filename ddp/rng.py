"""Per-episode random streams: noise that depends on which episode runs, not on how episodes are batched.

An episode evaluated alone (``--num-envs 1``) and the same episode in a batch of ten must draw the same
sampling noise and the same substitution draws; two training seeds must draw different ones. The
controller keys each environment's streams by ``mix(controller seed, episode seed, purpose)``: a hash of
integers (SplitMix64's finaliser, chained) into a 63-bit seed that ``torch.Generator.manual_seed`` and an
int64 tensor both take. Samplers take one generator per batch row (:func:`ddp.schedulers.base.randn`), as
diffusers' ``randn_tensor`` takes a list of generators.
"""

from __future__ import annotations

from typing import Sequence

import torch

__all__ = ["ACTIONS", "FORECASTS", "mix", "generator", "per_row"]

#: purposes: the policy's sampling noise and the world model's forecast noise of one episode
ACTIONS, FORECASTS = 0, 1

_MASK = (1 << 64) - 1


def _splitmix64(x: int) -> int:
    x = (x + 0x9E3779B97F4A7C15) & _MASK
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK
    return x ^ (x >> 31)


def mix(*values: int) -> int:
    """A 63-bit seed from integers (negative ones too); changing any of them changes the seed."""
    h = len(values)
    for v in values:
        h = _splitmix64(h ^ (int(v) & _MASK))
    return h >> 1


def generator(seed: int, device: torch.device | str = "cpu") -> torch.Generator:
    """A generator on ``device`` seeded with ``seed``."""
    return torch.Generator(device=device).manual_seed(int(seed))


def per_row(generators: Sequence[torch.Generator], rows: int) -> list[torch.Generator]:
    """``generators`` checked to have one entry per batch row."""
    generators = list(generators)
    if len(generators) != rows:
        raise ValueError(f"{len(generators)} generators for a batch of {rows} rows (one per row, or a single one)")
    return generators
