"""Layers shared by the 1D U-Nets: step embedding, conv blocks, FiLM residual blocks.

The policy pi_theta (paper Sec. "Diffusion Policy") and the world model W_phi
(Sec. "Diffusion World Model") are "identically parameterised" 1D conditional
U-Nets. Everything they share lives here; the two plugins only differ in how
they build the U-Net's input (eq. X_in = Repeat(x_obs, N) (+) X_sample for the
world model) and which keys they read.

Tensors inside the U-Net are channel-first: ``[B, C, T]``.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import torch
from torch import Tensor, nn

from ddp.denoisers.conv import Conv1d
from ddp.keys import KeyedModule


def sinusoidal_embedding(timestep: Tensor, dim: int, max_period: float = 10000.0) -> Tensor:
    """Sinusoidal features of a diffusion step k: ``[B] -> [B, dim]`` (sin half, cos half).

    Frequencies are geometric from 1 down to ``1 / max_period``. ``timestep``
    may be integer or float (flow-matching schedulers pass fractional steps).
    """
    half = dim // 2
    exponent = -math.log(max_period) * torch.arange(half, device=timestep.device, dtype=torch.float32) / (half - 1)
    angles = timestep.to(torch.float32)[:, None] * torch.exp(exponent)[None, :]
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


class StepEmbedding(nn.Module):
    """Diffusion step k -> vector: sinusoidal(dim) -> Linear(dim, 4 dim) -> Mish -> Linear(4 dim, dim)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.Mish(), nn.Linear(4 * dim, dim))

    def forward(self, timestep: Tensor) -> Tensor:
        return self.mlp(sinusoidal_embedding(timestep, self.dim))


class Conv1dBlock(nn.Sequential):
    """Conv1d (odd kernel, 'same' padding) -> GroupNorm -> Mish.

    The conv is :class:`ddp.denoisers.conv.Conv1d` (``nn.Conv1d``'s parameters; ``weight_grad``
    chooses its CPU weight-gradient kernel)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, n_groups: int, *,
                 weight_grad: str = "auto") -> None:
        super().__init__(
            Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2, weight_grad=weight_grad),
            nn.GroupNorm(n_groups, out_channels),
            nn.Mish(),
        )


class FiLMResidualBlock(nn.Module):
    """Residual block conditioned by FiLM (Perez et al. 2018), the paper's "FiLM(.)".

    ``h = Conv1dBlock(x)``; ``h = scale(c) * h + bias(c)`` with
    ``[scale, bias] = Linear(Mish(c))``; ``h = Conv1dBlock(h)``;
    ``out = h + residual(x)`` where ``residual`` is a 1x1 conv when the channel
    count changes (identity otherwise). With ``predict_scale=False`` only the
    bias is predicted (``h = h + bias(c)``).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        cond_dim: int,
        *,
        kernel_size: int,
        n_groups: int,
        predict_scale: bool,
        weight_grad: str = "auto",
    ) -> None:
        super().__init__()
        self.out_channels = out_channels
        self.predict_scale = predict_scale
        self.conv1 = Conv1dBlock(in_channels, out_channels, kernel_size, n_groups, weight_grad=weight_grad)
        self.conv2 = Conv1dBlock(out_channels, out_channels, kernel_size, n_groups, weight_grad=weight_grad)
        film_dim = 2 * out_channels if predict_scale else out_channels
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, film_dim))
        self.residual = (
            nn.Conv1d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()
        )

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        h = self.conv1(x)
        film = self.film(cond).unsqueeze(-1)  # [B, film_dim, 1], broadcast over time
        if self.predict_scale:
            scale, bias = film.split(self.out_channels, dim=1)
            h = scale * h + bias
        else:
            h = h + film
        h = self.conv2(h)
        return h + self.residual(x)


class Downsample1d(nn.Conv1d):
    """Halve the time axis: Conv1d(k=3, stride=2, padding=1)."""

    def __init__(self, channels: int) -> None:
        super().__init__(channels, channels, 3, stride=2, padding=1)


class Upsample1d(nn.ConvTranspose1d):
    """Double the time axis: ConvTranspose1d(k=4, stride=2, padding=1)."""

    def __init__(self, channels: int) -> None:
        super().__init__(channels, channels, 4, stride=2, padding=1)


class ConditionalUnet1DBackbone(nn.Module):
    """The FiLM-conditioned 1D U-Net shared by the policy and the world model.

    ``forward(x [B, in_channels, T], timestep [B], global_cond [B, G]) -> [B, out_channels, T]``.

    The FiLM condition of every residual block is ``cat(StepEmbedding(k), global_cond)``.

    Layout, with ``L = len(down_dims)`` and ``c_i = down_dims[i]``:

    * down level i (i = 0..L-1): ``blocks_per_level`` residual blocks
      ``c_{i-1} -> c_i`` (``c_{-1} = in_channels``), output kept as skip i,
      then a stride-2 downsample except after the last level;
    * ``mid_blocks`` residual blocks at ``c_{L-1}``;
    * up level i (i = L-1..1): concatenate skip i (``2 c_i`` channels), one
      residual block ``2 c_i -> c_{i-1}``, ``blocks_per_level - 1`` blocks at
      ``c_{i-1}``, then a transposed-conv upsample;
    * ``Conv1dBlock(c_0, c_0)`` and a 1x1 conv to ``out_channels``.

    The up path has one level fewer than the down path, so skip 0 (full
    resolution) is not concatenated: the same layout (and parameter count)
    as the Diffusion Policy / DP3 U-Net.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        global_cond_dim: int,
        *,
        down_dims: Sequence[int],
        kernel_size: int,
        n_groups: int,
        step_embed_dim: int,
        blocks_per_level: int,
        mid_blocks: int,
        predict_scale: bool,
        weight_grad: str = "auto",
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.global_cond_dim = global_cond_dim
        self.down_dims = tuple(down_dims)
        self.step_embedding = StepEmbedding(step_embed_dim)
        cond_dim = step_embed_dim + global_cond_dim

        def block(c_in: int, c_out: int) -> FiLMResidualBlock:
            return FiLMResidualBlock(
                c_in, c_out, cond_dim, kernel_size=kernel_size, n_groups=n_groups, predict_scale=predict_scale,
                weight_grad=weight_grad,
            )

        widths = [in_channels, *self.down_dims]
        n_levels = len(self.down_dims)

        self.down = nn.ModuleList()
        for i in range(n_levels):
            blocks = [block(widths[i], widths[i + 1])]
            blocks += [block(widths[i + 1], widths[i + 1]) for _ in range(blocks_per_level - 1)]
            level = nn.Module()
            level.blocks = nn.ModuleList(blocks)
            level.sample = Downsample1d(widths[i + 1]) if i < n_levels - 1 else nn.Identity()
            self.down.append(level)

        mid = self.down_dims[-1]
        self.mid = nn.ModuleList([block(mid, mid) for _ in range(mid_blocks)])

        self.up = nn.ModuleList()
        for i in reversed(range(1, n_levels)):
            c_skip, c_out = self.down_dims[i], self.down_dims[i - 1]
            blocks = [block(2 * c_skip, c_out)]
            blocks += [block(c_out, c_out) for _ in range(blocks_per_level - 1)]
            level = nn.Module()
            level.blocks = nn.ModuleList(blocks)
            level.sample = Upsample1d(c_out)
            self.up.append(level)

        self.head = nn.Sequential(
            Conv1dBlock(self.down_dims[0], self.down_dims[0], kernel_size, n_groups, weight_grad=weight_grad),
            nn.Conv1d(self.down_dims[0], out_channels, 1),
        )

    @property
    def time_divisor(self) -> int:
        """The horizon must be a multiple of this (one halving per downsample)."""
        return 2 ** (len(self.down_dims) - 1)

    def forward(self, x: Tensor, timestep: Tensor, global_cond: Tensor) -> Tensor:
        cond = torch.cat([self.step_embedding(timestep).to(x.dtype), global_cond], dim=-1)
        skips = []
        for level in self.down:
            for blk in level.blocks:
                x = blk(x, cond)
            skips.append(x)
            x = level.sample(x)
        for blk in self.mid:
            x = blk(x, cond)
        for level in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            for blk in level.blocks:
                x = blk(x, cond)
            x = level.sample(x)
        return self.head(x)


def check_unet_options(
    down_dims: Sequence[int],
    kernel_size: int,
    n_groups: int,
    diffusion_step_embed_dim: int,
    blocks_per_level: int,
    mid_blocks: int,
) -> None:
    """Config-time checks shared by the U-Net configs; raises ValueError naming the field."""
    if len(down_dims) == 0:
        raise ValueError(f"down_dims must be non-empty; got {list(down_dims)}")
    if any(d <= 0 for d in down_dims):
        raise ValueError(f"down_dims must be positive; got {list(down_dims)}")
    if kernel_size <= 0 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd number (keeps the horizon); got {kernel_size}")
    if n_groups <= 0:
        raise ValueError(f"n_groups must be positive; got {n_groups}")
    bad = [d for d in down_dims if d % n_groups != 0]
    if bad:
        raise ValueError(f"every down_dims entry must be divisible by n_groups={n_groups}; got {list(down_dims)}")
    if diffusion_step_embed_dim < 4 or diffusion_step_embed_dim % 2:
        raise ValueError(f"diffusion_step_embed_dim must be even and >= 4; got {diffusion_step_embed_dim}")
    if blocks_per_level < 1:
        raise ValueError(f"blocks_per_level must be >= 1; got {blocks_per_level}")
    if mid_blocks < 0:
        raise ValueError(f"mid_blocks must be >= 0; got {mid_blocks}")


class UnetDenoiser(KeyedModule):
    """A :class:`ConditionalUnet1DBackbone` behind the one denoiser call signature.

    ``predict(sample [*, T, C], timestep [*], global_cond [*, G], local_cond=None) -> [*, T, C]``
    on any leading batch dims; ``forward(td)`` reads the declared keys and
    writes ``prediction``. Subclasses choose the keys and override
    :meth:`unet_input` to build the U-Net input from ``sample`` and ``local_cond``.
    """

    default_in_keys = {"sample": "sample", "timestep": "timestep", "global_cond": "global_cond"}
    default_out_keys = {"prediction": "prediction"}

    @property
    def length_multiple(self) -> int:
        """Sequence lengths T it takes are multiples of this (the model factory checks the recipe's)."""
        return self.unet.time_divisor

    def __init__(self, config: Any, *, input_dim: int, global_cond_dim: int, local_cond_dim: int = 0) -> None:
        super().__init__()
        for name, value in (("input_dim", input_dim), ("global_cond_dim", global_cond_dim)):
            if value <= 0:
                raise ValueError(f"{name} must be positive; got {value}")
        if local_cond_dim < 0:
            raise ValueError(f"local_cond_dim must be >= 0; got {local_cond_dim}")
        self.config = config
        self.input_dim = input_dim
        self.global_cond_dim = global_cond_dim
        self.local_cond_dim = local_cond_dim
        self.unet = ConditionalUnet1DBackbone(
            input_dim + local_cond_dim,
            input_dim,
            global_cond_dim,
            down_dims=config.down_dims,
            kernel_size=config.kernel_size,
            n_groups=config.n_groups,
            step_embed_dim=config.diffusion_step_embed_dim,
            blocks_per_level=config.blocks_per_level,
            mid_blocks=config.mid_blocks,
            predict_scale=config.cond_predict_scale,
            weight_grad=config.cpu_weight_grad,
        )

    def unet_input(self, sample: Tensor, local_cond: Tensor | None) -> Tensor:
        """The U-Net input ``[*, T, C_in]``; the policy U-Net takes ``sample`` as is."""
        if local_cond is not None:
            raise ValueError(
                f"{type(self).__name__} takes no local_cond; got a tensor of shape {tuple(local_cond.shape)}"
            )
        return sample

    def predict(
        self,
        sample: Tensor,
        timestep: Tensor | int | float,
        global_cond: Tensor,
        local_cond: Tensor | None = None,
    ) -> Tensor:
        """Denoiser output for ``sample`` at diffusion step ``timestep`` (any leading batch dims)."""
        name = type(self).__name__
        if sample.dim() < 2 or sample.shape[-1] != self.input_dim:
            raise ValueError(f"{name}: sample must be [*, T, {self.input_dim}]; got {tuple(sample.shape)}")
        batch_shape, horizon = sample.shape[:-2], sample.shape[-2]
        divisor = self.unet.time_divisor
        if horizon % divisor:
            raise ValueError(
                f"horizon {horizon} must be a multiple of {divisor} for down_dims of length {len(self.unet.down_dims)}"
            )
        if global_cond.shape != (*batch_shape, self.global_cond_dim):
            raise ValueError(
                f"{name}: global_cond must be {[*batch_shape, self.global_cond_dim]} "
                f"(sample's leading dims + global_cond_dim); got {list(global_cond.shape)}"
            )
        timestep = torch.as_tensor(timestep, device=sample.device)
        if timestep.dim() == 0:
            timestep = timestep.expand(batch_shape)
        elif timestep.shape != batch_shape:
            raise ValueError(
                f"{name}: timestep must be a scalar or have the sample's leading dims "
                f"{list(batch_shape)}; got {list(timestep.shape)}"
            )

        x = self.unet_input(sample, local_cond)
        x = x.reshape(-1, horizon, x.shape[-1]).transpose(1, 2)  # [B, C_in, T]
        out = self.unet(x, timestep.reshape(-1), global_cond.reshape(-1, self.global_cond_dim).to(x.dtype))
        return out.transpose(1, 2).reshape(*batch_shape, horizon, self.input_dim)

    def forward(self, td):
        local_cond = td.get(self.key("local_cond")) if "local_cond" in self.default_in_keys else None
        prediction = self.predict(
            td.get(self.key("sample")), td.get(self.key("timestep")), td.get(self.key("global_cond")), local_cond
        )
        td.set(self.key("prediction"), prediction)
        return td
