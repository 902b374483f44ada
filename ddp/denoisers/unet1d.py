"""The policy's denoiser pi_theta: a 1D conditional U-Net with FiLM (paper Sec. "Diffusion Policy").

pi_theta(a^k_{0..H-1}, k, FiLM(O_{0..M-1})) (eq. L_BC): the noisy action chunk
is the U-Net's input sequence, and cat(step embedding of k, O_{0..M-1}
flattened) modulates every residual block. Layout as in DP3 / Diffusion
Policy; see :class:`ddp.denoisers.blocks.ConditionalUnet1DBackbone`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ddp.config import check_choices
from ddp.denoisers.blocks import UnetDenoiser, check_unet_options
from ddp.registry import register


@dataclass
class ConditionalUnet1DConfig:
    """Options of the FiLM U-Net.

    The paper's simulation size is ``down_dims=(256, 512, 1024)``; "Simple DDP"
    uses ``(128, 256, 384)`` for the policy; DP3 uses ``(512, 1024, 2048)``.
    DP3's "simple" variant is ``blocks_per_level=1, mid_blocks=1``.
    """

    down_dims: tuple[int, ...] = (256, 512, 1024)
    kernel_size: int = 5
    n_groups: int = 8
    diffusion_step_embed_dim: int = 128
    blocks_per_level: int = 2
    mid_blocks: int = 2
    cond_predict_scale: bool = True  # FiLM scale and bias; False = bias only
    condition_type: Literal["film"] = "film"
    # CPU training: the convolutions' weight gradient as one matmul where that is faster ("auto": 4 M+
    # element weights, and 256 K+ element weights on levels of 2 steps; conv.matmul_pays), always
    # ("matmul") or never ("onednn"). Same results within float rounding
    # (ddp/denoisers/conv.py).
    cpu_weight_grad: Literal["auto", "matmul", "onednn"] = "auto"

    def __post_init__(self) -> None:
        self.down_dims = tuple(self.down_dims)
        check_unet_options(
            self.down_dims,
            self.kernel_size,
            self.n_groups,
            self.diffusion_step_embed_dim,
            self.blocks_per_level,
            self.mid_blocks,
        )
        check_choices(self)  # condition_type, cpu_weight_grad (a config built in Python is not checked on load)


@register("denoiser", "unet1d", config=ConditionalUnet1DConfig)
class ConditionalUnet1D(UnetDenoiser):
    """1D conditional U-Net (FiLM global conditioning) for action chunks.

    ``predict(sample [*, T, input_dim], timestep [*], global_cond [*, global_cond_dim]) -> [*, T, input_dim]``;
    ``T`` must be a multiple of ``2 ** (len(down_dims) - 1)``.
    Keys: sample, timestep, global_cond -> prediction.
    """

    def __init__(self, config: ConditionalUnet1DConfig, *, input_dim: int, global_cond_dim: int) -> None:
        super().__init__(config, input_dim=input_dim, global_cond_dim=global_cond_dim)
