"""Fixed-length windows over episodes with DP3's edge padding.

A window starts up to ``pad_before`` steps before an episode's first step
and ends up to ``pad_after`` steps after its last; the missing steps repeat
the first / last frame. With M observation steps and N executed actions DP3
uses pad_before = M - 1 and pad_after = N - 1.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from ddp.data.episodes import Episodes


def window_indices(episode_ends: torch.Tensor, length: int, pad_before: int, pad_after: int) -> torch.Tensor:
    """Step indices [num_windows, length] of every window, edge-padded by clamping."""
    rows = []
    start = 0
    for end in episode_ends.tolist():
        ep_len = end - start
        first = -pad_before
        last = ep_len - length + pad_after  # inclusive
        if last >= first:
            offsets = torch.arange(first, last + 1).unsqueeze(1) + torch.arange(length).unsqueeze(0)
            rows.append(start + offsets.clamp(0, ep_len - 1))
        start = end
    if not rows:
        raise ValueError(f"no episode is long enough for windows of length {length}")
    return torch.cat(rows, 0)


class SequenceDataset(torch.utils.data.Dataset):
    """Windows of ``length`` steps: observations and actions, unnormalised.

    ``ds[i]`` is a TensorDict with batch size [length]; ``ds.batch(idx)``
    gathers many windows at once (fast path for training).
    """

    def __init__(self, episodes: Episodes, length: int, pad_before: int = 0, pad_after: int = 0, keys=None):
        self.episodes = episodes
        self.keys = list(keys) if keys is not None else list(episodes.steps.keys())
        self.indices = window_indices(episodes.episode_ends, length, pad_before, pad_after)
        self.steps = episodes.steps.select(*self.keys)

    def __len__(self) -> int:
        return self.indices.shape[0]

    def __getitem__(self, i: int) -> TensorDict:
        return _single(self.steps[self.indices[i]])

    def batch(self, idx: torch.Tensor) -> TensorDict:
        flat = self.indices[idx].reshape(-1)
        return _single(self.steps[flat].reshape(idx.shape[0], self.indices.shape[1]))


def _single(windows: TensorDict) -> TensorDict:
    """float64 leaves (numpy's default, e.g. in an episodes_dir) as float32, per window: the data stay
    memory-mapped, and the model's float32 layers refused float64 at the first step."""
    if not any(x.dtype == torch.float64 for x in windows.values(True, True)):
        return windows
    return windows.apply(lambda x: x.float() if x.dtype == torch.float64 else x)
