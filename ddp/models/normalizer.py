"""Per-dimension min-max normalisation to [-1, 1], fitted on data, saved as buffers."""

from __future__ import annotations

from typing import Mapping

import torch
from torch import nn

RANGE_EPS = 1e-4


class MinMaxNormalizer(nn.Module):
    """Maps each field's last-dim features to [-1, 1] with statistics in the state dict.

    Dimensions whose training range is below ``1e-4`` are centred (shifted so
    their minimum maps to 0) instead of scaled, as in DP3.
    """

    def __init__(self, dims: Mapping[str, int]):
        super().__init__()
        self.fields = tuple(dims)
        for name, dim in dims.items():
            self.register_buffer(f"{name}_scale", torch.ones(dim))
            self.register_buffer(f"{name}_offset", torch.zeros(dim))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))

    def _check(self, name: str) -> None:
        if name not in self.fields:
            raise KeyError(f"normalizer has no field '{name}' (fields: {', '.join(self.fields)})")

    @torch.no_grad()
    def fit(self, data: Mapping[str, torch.Tensor]) -> "MinMaxNormalizer":
        """Fit every field from samples shaped [..., dim]."""
        for name in self.fields:
            dim = getattr(self, f"{name}_scale").shape[0]
            x = torch.as_tensor(data[name], dtype=torch.float32)
            if x.shape[-1] < dim:
                raise ValueError(f"normalizer field '{name}' has {dim} features but the data have {x.shape[-1]}")
            x = x.reshape(-1, x.shape[-1])[:, :dim]  # e.g. xyz of xyz+rgb clouds when point_dim is 3
            if not bool(torch.isfinite(x).all()):  # NaN would make every normalised value NaN, inf a scale of 0
                raise ValueError(f"normalizer field '{name}': the data hold NaN or inf")
            lo, hi = x.min(0).values, x.max(0).values
            rng = hi - lo
            degenerate = rng < RANGE_EPS
            scale = torch.where(degenerate, torch.ones_like(rng), 2.0 / rng.clamp_min(RANGE_EPS))
            offset = torch.where(degenerate, -lo, -1.0 - scale * lo)
            getattr(self, f"{name}_scale").copy_(scale)
            getattr(self, f"{name}_offset").copy_(offset)
        self.fitted.fill_(True)
        return self

    def normalize(self, name: str, x: torch.Tensor) -> torch.Tensor:
        self._check(name)
        dim = getattr(self, f"{name}_scale").shape[0]
        scale, offset = getattr(self, f"{name}_scale"), getattr(self, f"{name}_offset")
        if x.shape[-1] > dim:  # e.g. xyz+rgb point clouds: normalise xyz only
            head = x[..., :dim] * scale + offset
            return torch.cat([head, x[..., dim:]], dim=-1)
        return x * scale + offset

    def unnormalize(self, name: str, x: torch.Tensor) -> torch.Tensor:
        self._check(name)
        scale, offset = getattr(self, f"{name}_scale"), getattr(self, f"{name}_offset")
        return (x - offset) / scale
