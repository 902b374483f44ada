"""DDPM: ancestral sampling of Ho et al. 2020, "Denoising Diffusion Probabilistic Models".

Numerically equal to ``diffusers.DDPMScheduler`` with the same options
(``timestep_spacing="leading"``, ``steps_offset=0``, no thresholding).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import torch

from ddp.registry import register
from ddp.schedulers.base import DiscreteDiffusionScheduler, StepOutput, check_diffusion_fields, randn


@dataclass
class DDPMConfig:
    """Options of the DDPM scheduler (defaults follow DP3: 100 steps, cosine betas, clipping)."""

    num_train_timesteps: int = 100
    beta_start: float = 1e-4
    beta_end: float = 0.02
    beta_schedule: Literal["squaredcos_cap_v2", "linear", "scaled_linear"] = "squaredcos_cap_v2"
    variance_type: Literal["fixed_small", "fixed_small_log"] = "fixed_small"
    clip_sample: bool = True
    clip_sample_range: float = 1.0
    prediction_type: Literal["epsilon", "sample"] = "epsilon"
    #: reverse steps used by ``sample``; ``None`` means all ``num_train_timesteps``
    num_inference_steps: int | None = None

    #: options a trained model may be sampled with other values of (the rest define what the network learned)
    free_at_inference: ClassVar[frozenset[str]] = frozenset({
        "num_inference_steps", "variance_type", "clip_sample", "clip_sample_range"})

    def __post_init__(self):
        check_diffusion_fields(self)
        n = self.num_inference_steps
        if n is not None and not 1 <= n <= self.num_train_timesteps:
            raise ValueError(
                f"num_inference_steps must be in [1, num_train_timesteps={self.num_train_timesteps}]; got {n}"
            )


@register("scheduler", "ddpm", config=DDPMConfig)
class DDPMScheduler(DiscreteDiffusionScheduler):
    """DDPM ancestral sampling (Ho et al. 2020, Algorithm 2 with the posterior of eq. 6-7)."""

    def __init__(self, config: DDPMConfig):
        self._init_schedule(config)
        self.set_timesteps(self._configured_inference_steps())

    def _configured_inference_steps(self) -> int:
        n = self.config.num_inference_steps
        return self.config.num_train_timesteps if n is None else n

    def set_timesteps(self, num_inference_steps: int) -> None:
        """Leading spacing: k in {(n-1) r, ..., r, 0} with r = K // n."""
        self._check_num_inference_steps(num_inference_steps)
        self.num_inference_steps = num_inference_steps
        self.step_ratio = self.config.num_train_timesteps // num_inference_steps
        self.timesteps = torch.arange(num_inference_steps - 1, -1, -1, dtype=torch.int64) * self.step_ratio

    def step(
        self, model_output: torch.Tensor, timestep: int, sample: torch.Tensor, generator: torch.Generator | None = None
    ) -> StepOutput:
        """x_k -> x_{k'} with k' = k - K // n the next visited step (x_0 when k' < 0).

        1. alpha_bar_k, alpha_bar_{k'} (= 1 past the end), alpha_k = alpha_bar_k / alpha_bar_{k'}, beta_k = 1 - alpha_k
        2. x_0 from the network output (eq. 15), clipped to +-clip_sample_range
        3. posterior mean (eq. 7): mu = sqrt(alpha_bar_{k'}) beta_k / (1 - alpha_bar_k) x_0
                                     + sqrt(alpha_k) (1 - alpha_bar_{k'}) / (1 - alpha_bar_k) x_k
        4. for k > 0: x_{k'} = mu + sigma_k z with z ~ N(0, I) and
           sigma_k^2 = (1 - alpha_bar_{k'}) / (1 - alpha_bar_k) beta_k  ("fixed_small")
        """
        k = int(timestep)
        k_prev = k - self.step_ratio
        # 1.
        alpha_bar_t = self.alphas_cumprod[k]
        alpha_bar_prev = self.alphas_cumprod[k_prev] if k_prev >= 0 else torch.tensor(1.0)
        beta_bar_t = 1 - alpha_bar_t
        beta_bar_prev = 1 - alpha_bar_prev
        alpha_t = alpha_bar_t / alpha_bar_prev
        beta_t = 1 - alpha_t
        # 2.
        pred_x0 = self._pred_original_sample(model_output, sample, alpha_bar_t)
        # 3.
        pred_x0_coeff = (alpha_bar_prev**0.5 * beta_t) / beta_bar_t
        sample_coeff = alpha_t**0.5 * beta_bar_prev / beta_bar_t
        mu = pred_x0_coeff * pred_x0 + sample_coeff * sample
        # 4.
        if k > 0:
            z = randn(model_output.shape, generator=generator, device=model_output.device, dtype=model_output.dtype)
            variance = torch.clamp(beta_bar_prev / beta_bar_t * beta_t, min=1e-20)
            if self.config.variance_type == "fixed_small_log":
                sigma_t = torch.exp(0.5 * torch.log(variance))
            else:
                sigma_t = variance**0.5
            mu = mu + sigma_t * z
        return StepOutput(mu, pred_x0)
