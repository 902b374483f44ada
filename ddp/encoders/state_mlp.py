"""State-only encoder (ablation without vision): O = MLP(agent_pos).

Replaces E_psi's PointNet + MLP (paper Sec. "Diffusion Policy") by one MLP on
proprioception, so a recipe can measure what the point cloud contributes.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from ddp.encoders.dp3 import mlp
from ddp.keys import KeyedModule
from ddp.registry import register


@dataclass
class StateMLPEncoderConfig:
    """Options of the state-only encoder: agent_pos_dim -> hidden (ReLU) -> out_dim (no final activation)."""

    hidden: tuple[int, ...] = (64, 64)
    out_dim: int = 128

    def __post_init__(self) -> None:
        self.hidden = tuple(self.hidden)
        if any(w <= 0 for w in self.hidden):
            raise ValueError(f"hidden widths must be positive; got {list(self.hidden)}")
        if self.out_dim <= 0:
            raise ValueError(f"out_dim must be positive; got {self.out_dim}")


@register("encoder", "state_mlp", config=StateMLPEncoderConfig)
class StateMLPEncoder(KeyedModule):
    """State-only encoder: MLP(agent_pos) -> latent; reads no point cloud.

    ``encode(point_cloud, agent_pos [*, D]) -> [*, out_dim]``; ``point_cloud``
    is accepted (and ignored, may be None) so every encoder is called alike.
    Keys: agent_pos -> latent.
    """

    default_in_keys = {"agent_pos": "agent_pos"}
    default_out_keys = {"latent": "latent"}

    def __init__(self, config: StateMLPEncoderConfig, *, agent_pos_dim: int, point_dim: int = 3) -> None:
        super().__init__()
        if agent_pos_dim <= 0:
            raise ValueError(f"agent_pos_dim must be positive; got {agent_pos_dim}")
        self.config = config
        self.agent_pos_dim = agent_pos_dim
        self.mlp = mlp(agent_pos_dim, (*config.hidden, config.out_dim), final_activation=False)

    @property
    def out_dim(self) -> int:
        return self.config.out_dim

    def encode(self, point_cloud: Tensor | None, agent_pos: Tensor) -> Tensor:
        """O = MLP(agent_pos): ``[*, D] -> [*, out_dim]`` (point_cloud is ignored)."""
        if agent_pos.dim() < 1 or agent_pos.shape[-1] != self.agent_pos_dim:
            raise ValueError(
                f"StateMLPEncoder: agent_pos must be [*, {self.agent_pos_dim}]; got {list(agent_pos.shape)}"
            )
        return self.mlp(agent_pos)

    def forward(self, td):
        td.set(self.key("latent"), self.encode(None, td.get(self.key("agent_pos"))))
        return td
