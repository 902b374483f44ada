"""DDIM: Song et al. 2021, "Denoising Diffusion Implicit Models" (eq. 12 and 16).

Trained with the same loss as DDPM; samples in ``num_inference_steps``
strided steps (deterministically when ``eta = 0``). Numerically equal to
``diffusers.DDIMScheduler`` with the same options (no thresholding,
``use_clipped_model_output=False``), except with ``timestep_spacing="trailing"`` and
``num_train_timesteps`` not a multiple of ``num_inference_steps``: each step goes to the next listed
timestep, where diffusers goes to ``k - K // n`` (beside the next one; see ``_previous``); and with
leading spacing and ``steps_offset >= K // n``: the last step here goes to the clean sample
(``final_alpha_cumprod``), where diffusers stops at ``k - K // n``, still a noisy level.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import torch

from ddp.registry import register
from ddp.schedulers.base import DiscreteDiffusionScheduler, StepOutput, check_diffusion_fields, randn


@dataclass
class DDIMConfig:
    """Options of the DDIM scheduler (the noise schedule and step counts follow DP3: 100 train steps,
    squaredcos_cap_v2, 10 inference steps; ``prediction_type`` defaults to the paper's epsilon, where DP3
    and every shipped recipe predict the sample)."""

    num_train_timesteps: int = 100
    beta_start: float = 1e-4
    beta_end: float = 0.02
    beta_schedule: Literal["squaredcos_cap_v2", "linear", "scaled_linear"] = "squaredcos_cap_v2"
    clip_sample: bool = True
    clip_sample_range: float = 1.0
    #: alpha_bar of the step after the last one: 1 (True) or alpha_bar_0 (False)
    set_alpha_to_one: bool = True
    steps_offset: int = 0
    timestep_spacing: Literal["leading", "trailing"] = "leading"
    #: eta = 0: deterministic DDIM; eta = 1: DDPM-like posterior noise (eq. 16)
    eta: float = 0.0
    num_inference_steps: int = 10
    prediction_type: Literal["epsilon", "sample"] = "epsilon"

    #: options a trained model may be sampled with other values of (the rest define what the network learned)
    free_at_inference: ClassVar[frozenset[str]] = frozenset({
        "num_inference_steps", "eta", "timestep_spacing", "clip_sample", "clip_sample_range", "set_alpha_to_one",
        "steps_offset"})

    def __post_init__(self):
        check_diffusion_fields(self)
        K, n = self.num_train_timesteps, self.num_inference_steps
        if not 1 <= n <= K:
            raise ValueError(f"num_inference_steps must be in [1, num_train_timesteps={K}]; got {n}")
        if not 0.0 <= self.eta <= 1.0:  # past 1 the direction's variance 1 - alpha_bar' - sigma^2 goes negative
            raise ValueError(f"eta must be in [0, 1]; got {self.eta}")
        if self.steps_offset < 0:
            raise ValueError(f"steps_offset must be >= 0; got {self.steps_offset}")
        if self.timestep_spacing == "leading" and (n - 1) * (K // n) + self.steps_offset >= K:
            raise ValueError(
                f"steps_offset must keep the first step below num_train_timesteps={K} "
                f"(largest allowed: {K - 1 - (n - 1) * (K // n)}); got {self.steps_offset}"
            )


@register("scheduler", "ddim", config=DDIMConfig)
class DDIMScheduler(DiscreteDiffusionScheduler):
    """DDIM sampling (Song et al. 2021, eq. 12) with optional eta-noise (eq. 16)."""

    def __init__(self, config: DDIMConfig):
        self._init_schedule(config)
        # alpha_bar used after the last step (k_prev < 0)
        self.final_alpha_cumprod = torch.tensor(1.0) if config.set_alpha_to_one else self.alphas_cumprod[0]
        self.set_timesteps(config.num_inference_steps)

    def set_timesteps(self, num_inference_steps: int) -> None:
        """``leading``: k in {(n-1) r, ..., r, 0} + steps_offset with r = K // n;
        ``trailing``: k = round(K - i K / n) - 1 for i = 0..n-1 (Lin et al. 2024, Table 2).
        """
        self._check_num_inference_steps(num_inference_steps)
        K = self.config.num_train_timesteps
        self.num_inference_steps = num_inference_steps
        if self.config.timestep_spacing == "leading":
            ratio = K // num_inference_steps
            ks = [i * ratio + self.config.steps_offset for i in reversed(range(num_inference_steps))]
        else:
            ratio = K / num_inference_steps
            # numpy's round (half to even), as diffusers does, on the float grid K, K - ratio, ...
            # exactly n steps (K / ratio can come out a hair above n, e.g. K = 100, n = 29: diffusers then adds
            # a step at level -1, i.e. alphas_cumprod[-1], the noisiest)
            ks = [max(round(K - i * ratio) - 1, 0) for i in range(num_inference_steps)]
        self.timesteps = torch.tensor(ks, dtype=torch.int64)

    def _previous(self, k: int) -> int:
        """The step after ``k`` in ``timesteps`` (-1 after the last): with trailing spacing and K not a multiple
        of n the steps are not evenly spaced (K=100, n=3: 99, 66, 32), so ``k - K // n`` (diffusers' rule)
        would land beside the next one; a ``k`` off the grid falls back to that rule."""
        ks = self.timesteps.tolist()
        if k in ks:
            i = ks.index(k)
            return ks[i + 1] if i + 1 < len(ks) else -1
        return k - self.config.num_train_timesteps // self.num_inference_steps

    def step(
        self, model_output: torch.Tensor, timestep: int, sample: torch.Tensor, generator: torch.Generator | None = None
    ) -> StepOutput:
        """x_k -> x_{k'} with k' the next of ``timesteps`` (``k - K // n`` for leading spacing; DDIM eq. 12):

        1. alpha_bar_k, alpha_bar_{k'} (final_alpha_cumprod when k' < 0)
        2. x_0 and eps from the network output, x_0 clipped to +-clip_sample_range
           (eps is the network's, or re-derived from the unclipped x_0 for "sample")
        3. sigma_k = eta sqrt((1 - alpha_bar_{k'}) / (1 - alpha_bar_k)) sqrt(1 - alpha_bar_k / alpha_bar_{k'})
           (eq. 16)
        4. x_{k'} = sqrt(alpha_bar_{k'}) x_0 + sqrt(1 - alpha_bar_{k'} - sigma_k^2) eps + sigma_k z
        """
        k = int(timestep)
        k_prev = self._previous(k)
        # 1.
        alpha_bar_t = self.alphas_cumprod[k]
        alpha_bar_prev = self.alphas_cumprod[k_prev] if k_prev >= 0 else self.final_alpha_cumprod
        beta_bar_t = 1 - alpha_bar_t
        beta_bar_prev = 1 - alpha_bar_prev
        # 2.
        if self.config.prediction_type == "epsilon":
            pred_eps = model_output
        else:
            pred_eps = (sample - alpha_bar_t**0.5 * model_output) / beta_bar_t**0.5
        pred_x0 = self._pred_original_sample(model_output, sample, alpha_bar_t)
        # 3.
        eta = self.config.eta
        variance = (beta_bar_prev / beta_bar_t) * (1 - alpha_bar_t / alpha_bar_prev)
        sigma_t = eta * variance**0.5
        # 4.
        # at eta 1 sigma^2 can equal 1 - alpha_bar' and round past it (a negative root: NaN)
        direction = torch.clamp(1 - alpha_bar_prev - sigma_t**2, min=0.0) ** 0.5 * pred_eps
        x_prev = alpha_bar_prev**0.5 * pred_x0 + direction
        if eta > 0:
            z = randn(model_output.shape, generator=generator, device=model_output.device, dtype=model_output.dtype)
            x_prev = x_prev + sigma_t * z
        return StepOutput(x_prev, pred_x0)
