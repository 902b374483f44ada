"""The shared 3D encoder E_psi of DP3 (paper Sec. "Diffusion Policy", "Implementation Details").

E_psi(X) = cat(PointNet(point cloud), MLP(agent_pos)) = O: per observation step a
64-d point-cloud feature and a 64-d proprioception feature give the 128-d
latent that conditions both the policy and the world model.

PointNet (DP3's lightweight variant): per-point Linear 3-64-128-256, each
followed by LayerNorm and ReLU; max-pool over the points (order invariant);
Linear 256-64 + LayerNorm. State MLP: agent_pos_dim-64-ReLU-64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from ddp.config import check_choices
from ddp.keys import KeyedModule
from ddp.registry import register


def mlp(in_dim: int, widths: tuple[int, ...], *, final_activation: bool, layernorm: bool = False) -> nn.Sequential:
    """Linear layers of the given widths, each followed by [LayerNorm] and ReLU (the last one optionally bare)."""
    layers: list[nn.Module] = []
    dims = (in_dim, *widths)
    for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
        layers.append(nn.Linear(d_in, d_out))
        if i < len(widths) - 1 or final_activation:
            if layernorm:
                layers.append(nn.LayerNorm(d_out))
            layers.append(nn.ReLU(inplace=True))  # in place: no input of a ReLU is read again
    return nn.Sequential(*layers)


def _max_pool(features: Tensor) -> Tensor:
    """Max over the points ``[F, P, C] -> [F, C]``; its gradient is split evenly among tied points."""
    return features.amax(dim=-2)


def _max_pool_indexed(features: Tensor) -> Tensor:
    """The same maxima; the backward sends each channel's gradient to one winning point (a scatter)
    instead of amax's comparison of every point with the maximum, a cast and a product (about 13 % of
    the PointNet's forward + backward at 128 points). The parameter gradients are the same within float
    rounding, ties included: tied points have equal activations, so the sum over them does not depend on
    how the gradient is split. Used when only the parameters need gradients; a cloud that needs its own
    gradient keeps amax's even split among duplicated points."""
    return features.max(dim=-2).values


@dataclass
class DP3EncoderConfig:
    """Options of the DP3 point-cloud + proprioception encoder (defaults = DP3 / the paper)."""

    pointnet_channels: tuple[int, ...] = (64, 128, 256)
    out_channels: int = 64  # point-cloud feature size after the final projection
    state_channels: tuple[int, ...] = (64, 64)  # the last entry is the state feature size
    use_layernorm: bool = True  # LayerNorm after each PointNet linear
    final_norm: Literal["layernorm", "none"] = "layernorm"
    use_color: bool = False  # True: points are xyz+rgb (6 channels)
    # On CPU the per-point MLP runs on blocks of about this many points (whole frames) so that its
    # activations stay in the cache: 2-3x faster encoding at equal results (rows are independent; only
    # float rounding differs). 0: all points at once (the plain DP3 forward, always used on GPUs).
    points_per_block: int = 2048
    # Training: only the points that win the max-pool in some channel get a gradient (the per-point MLP
    # is row-independent, every other point's gradient is exactly zero). "winners" first runs the
    # PointNet without gradient on every point, then with gradient on each frame's winners only
    # (rows padded to the batch's most winners): the same latents, and gradients within float rounding,
    # at about a third of the backward's arithmetic once frames have 256+ points. "dense": the plain
    # backward through every point. "auto": winners on a CPU at 256+ points per frame. A point cloud
    # that itself needs a gradient always takes the dense path.
    pool_backward: Literal["auto", "winners", "dense"] = "auto"

    def __post_init__(self) -> None:
        self.pointnet_channels = tuple(self.pointnet_channels)
        self.state_channels = tuple(self.state_channels)
        for name in ("pointnet_channels", "state_channels"):
            widths = getattr(self, name)
            if len(widths) == 0 or any(w <= 0 for w in widths):
                raise ValueError(f"{name} must be a non-empty list of positive widths; got {list(widths)}")
        if self.points_per_block < 0:
            raise ValueError(f"points_per_block must be >= 0 (0: no blocking); got {self.points_per_block}")
        if self.out_channels <= 0:
            raise ValueError(f"out_channels must be positive; got {self.out_channels}")
        check_choices(self)


@register("encoder", "dp3", config=DP3EncoderConfig)
class DP3Encoder(KeyedModule):
    """DP3 encoder: PointNet(point_cloud) (+) MLP(agent_pos) -> latent (128-d by default).

    ``encode(point_cloud [*, P, C], agent_pos [*, D]) -> [*, out_dim]`` on any
    leading dims. ``C`` is 3 (xyz), or 6 (xyz+rgb) with ``use_color``; extra
    channels beyond those are ignored (DP3 keeps xyz only when colour is off).
    Keys: point_cloud, agent_pos -> latent.
    """

    default_in_keys = {"point_cloud": "point_cloud", "agent_pos": "agent_pos"}
    default_out_keys = {"latent": "latent"}

    def __init__(self, config: DP3EncoderConfig, *, agent_pos_dim: int, point_dim: int = 3) -> None:
        super().__init__()
        if agent_pos_dim <= 0:
            raise ValueError(f"agent_pos_dim must be positive; got {agent_pos_dim}")
        if config.use_color and point_dim < 6:
            raise ValueError(f"encoder.use_color reads xyz+rgb points: set task.point_dim to 6 (got {point_dim})")
        self.config = config
        self.agent_pos_dim = agent_pos_dim
        self.point_channels = 6 if config.use_color else 3
        self.pointnet = mlp(
            self.point_channels, config.pointnet_channels, final_activation=True, layernorm=config.use_layernorm
        )
        self.projection = nn.Sequential(
            nn.Linear(config.pointnet_channels[-1], config.out_channels),
            nn.LayerNorm(config.out_channels) if config.final_norm == "layernorm" else nn.Identity(),
        )
        self.state_mlp = mlp(agent_pos_dim, config.state_channels, final_activation=False)

    @property
    def out_dim(self) -> int:
        return self.config.out_channels + self.config.state_channels[-1]

    @property
    def point_dims(self) -> int:
        """The latent's first ``out_channels`` dims are the point-cloud features, the rest proprioception."""
        return self.config.out_channels

    def encode_points(self, point_cloud: Tensor) -> Tensor:
        """PointNet: ``[*, P, C] -> [*, out_channels]`` (max-pool over the P points)."""
        if point_cloud.dim() < 2 or point_cloud.shape[-1] < self.point_channels:
            raise ValueError(
                f"DP3Encoder: point_cloud must be [*, P, {self.point_channels}] "
                f"(use_color={self.config.use_color}); got {tuple(point_cloud.shape)}"
            )
        points = point_cloud[..., : self.point_channels]
        frames = points.reshape(-1, *points.shape[-2:])
        if self._winners_backward(frames):
            frames = self._winners(frames)
        return self.projection(self._pooled(frames)).reshape(*points.shape[:-2], self.config.out_channels)

    def _frame_blocks(self, frames: Tensor) -> list[Tensor] | tuple[Tensor, ...]:
        """Cache blocking: whole frames of about ``points_per_block`` points, each taken through the whole
        MLP and the max-pool at once. It pays on CPU caches; on a GPU it would only split one launch."""
        if self.config.points_per_block == 0 or frames.device.type != "cpu":
            return [frames]
        return frames.split(max(1, self.config.points_per_block // max(1, frames.shape[-2])))

    def _pooled(self, frames: Tensor) -> Tensor:
        """PointNet + max-pool of frames ``[F, P, C] -> [F, pointnet_channels[-1]]``."""
        blocks = self._frame_blocks(frames)
        pool = _max_pool_indexed if torch.is_grad_enabled() and not frames.requires_grad else _max_pool
        if len(blocks) == 1:
            return pool(self.pointnet(frames))
        return torch.cat([pool(self.pointnet(part)) for part in blocks])

    def _winners_backward(self, frames: Tensor) -> bool:
        mode = self.config.pool_backward
        if mode == "dense" or not torch.is_grad_enabled() or frames.requires_grad:  # input gradients: dense
            return False
        if not any(p.requires_grad for p in self.pointnet.parameters()):
            return False
        return mode == "winners" or (frames.device.type == "cpu" and frames.shape[-2] >= 256)

    @torch.no_grad()
    def _winners(self, frames: Tensor) -> Tensor:
        """Each frame's max-pool winners ``[F, K, C]`` (K: the most winners of any frame; a frame with fewer
        is padded with its other points, which cannot change its maxima)."""
        n_points = frames.shape[-2]
        if frames.shape[0] == 0:
            return frames
        won = []
        for part in self._frame_blocks(frames):
            top, where = self.pointnet(part).max(dim=-2)  # [f, channels]
            # a channel whose maximum is 0 (all ReLU-clamped) passes no gradient to any point
            where = torch.where(top > 0, where, n_points)
            hits = torch.zeros(part.shape[0], n_points + 1, device=frames.device)
            won.append(hits.scatter_(1, where, 1.0)[:, :n_points] > 0)
        won = torch.cat(won)
        k = max(1, int(won.sum(1).max()))
        if k >= n_points:
            return frames
        order = torch.argsort(won.to(torch.uint8), dim=1, descending=True, stable=True)[:, :k]
        return frames.gather(1, order.unsqueeze(-1).expand(-1, -1, frames.shape[-1]))

    def encode(self, point_cloud: Tensor, agent_pos: Tensor) -> Tensor:
        """O = cat(PointNet(point_cloud), MLP(agent_pos)): ``[*, P, C], [*, D] -> [*, out_dim]``."""
        if agent_pos.shape[-1:] != (self.agent_pos_dim,) or point_cloud.shape[:-2] != agent_pos.shape[:-1]:
            raise ValueError(
                f"DP3Encoder: agent_pos must be [*, {self.agent_pos_dim}] with the point cloud's leading dims "
                f"{list(point_cloud.shape[:-2])}; got {list(agent_pos.shape)}"
            )
        return torch.cat([self.encode_points(point_cloud), self.state_mlp(agent_pos)], dim=-1)

    def forward(self, td):
        td.set(self.key("latent"), self.encode(td.get(self.key("point_cloud")), td.get(self.key("agent_pos"))))
        return td
