"""The world model W_phi: a 1D conditional U-Net over future latents (paper Sec. "Diffusion World Model").

W_phi(C_wm, k_w, FiLM(a_{M-1..M+N-2})) (eq. L_WM) with the input built by
feature-level integration, eq. X_in = Repeat(x_obs, N) (+) X_sample: the
history latent x_obs (O_{0..M-1} flattened) is repeated over the N future
steps and concatenated channel-wise with the noisy future latents
O^{k_w}_{M..M+N-1}, so every convolution sees the history. The executed
actions, flattened, are the global FiLM condition together with the step
embedding. The output has the latent's channels only (noise or clean
sample of the N future latents). Same U-Net family and options as the
policy (``unet1d``): the paper uses "a separate, identically parameterized"
network.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ddp.denoisers.blocks import UnetDenoiser
from ddp.denoisers.unet1d import ConditionalUnet1DConfig
from ddp.registry import register


@dataclass
class WorldModelUnet1DConfig(ConditionalUnet1DConfig):
    """Options of the world-model U-Net: the same fields as ``unet1d``.

    The paper's simulation size is ``down_dims=(256, 512, 1024)``; "Simple DDP"
    uses ``(128, 256, 512)`` for the world model.
    """


@register("denoiser", "unet1d_wm", config=WorldModelUnet1DConfig)
class WorldModelUnet1D(UnetDenoiser):
    """1D U-Net world model: input = Repeat(history latent, N) (+) noisy future latents.

    ``predict(sample [*, N, input_dim], timestep [*], global_cond [*, N*action_dim],
    local_cond [*, local_cond_dim] or [*, N, local_cond_dim]) -> [*, N, input_dim]``.
    Keys: sample, timestep, global_cond, local_cond -> prediction.
    """

    default_in_keys = {**UnetDenoiser.default_in_keys, "local_cond": "local_cond"}

    def __init__(
        self, config: WorldModelUnet1DConfig, *, input_dim: int, global_cond_dim: int, local_cond_dim: int
    ) -> None:
        if local_cond_dim <= 0:
            raise ValueError(f"local_cond_dim must be positive; got {local_cond_dim}")
        super().__init__(config, input_dim=input_dim, global_cond_dim=global_cond_dim, local_cond_dim=local_cond_dim)

    def unet_input(self, sample: Tensor, local_cond: Tensor | None) -> Tensor:
        """X_in = Repeat(x_obs, N) (+) X_sample: ``[*, N, local_cond_dim + input_dim]``."""
        if local_cond is None:
            raise ValueError("WorldModelUnet1D needs local_cond (the history latent x_obs); got None")
        batch_shape, n_steps = sample.shape[:-2], sample.shape[-2]
        if local_cond.shape == (*batch_shape, self.local_cond_dim):
            local_cond = local_cond.unsqueeze(-2).expand(*batch_shape, n_steps, self.local_cond_dim)
        elif local_cond.shape != (*batch_shape, n_steps, self.local_cond_dim):
            raise ValueError(
                f"WorldModelUnet1D: local_cond must be {[*batch_shape, self.local_cond_dim]} (repeated over the "
                f"{n_steps} steps) or {[*batch_shape, n_steps, self.local_cond_dim]}; got {list(local_cond.shape)}"
            )
        return torch.cat([local_cond.to(sample.dtype), sample], dim=-1)
