"""What every scheduler offers, and the pieces DDPM and DDIM share.

A scheduler is a small, config-driven object (not an ``nn.Module``; it holds
no parameters) that owns one generative process:

- ``loss(model_fn, x0, *, generator=None)``: the scalar training loss for a
  batch of clean samples ``x0`` of shape ``[B, ...]``;
- ``sample(model_fn, noise, *, generator=None)``: the whole reverse process
  from ``noise`` (the output's shape) to a clean sample.

``model_fn(x_t, t)`` is the denoiser closure (it captures the condition):
``x_t`` has the sample's shape ``[B, ...]`` and ``t`` is a float tensor of
shape ``[B]`` holding the value the network embeds (the integer step ``k``
for DDPM/DDIM, ``t * time_scale`` for consistency flow).

Random draws go through a ``torch.Generator`` when one is given, or a
sequence of them, one per batch row (each row keeps its own stream: the
controller's per-episode noise, :mod:`ddp.rng`). They are made on the
generator's device and then moved to the sample's device, the way diffusers'
``randn_tensor`` does, so seeded runs match it.
"""

from __future__ import annotations

import abc
import math
from typing import Callable, NamedTuple

import torch

from ddp.config import check_choices
from ddp.rng import per_row

#: ``model_fn(x_t, t) -> prediction`` with ``x_t: [B, ...]`` and ``t: [B]`` (float).
ModelFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class StepOutput(NamedTuple):
    """Result of one reverse step: ``x_{k_prev}`` and the predicted ``x_0``."""

    prev_sample: torch.Tensor
    pred_original_sample: torch.Tensor


class Scheduler(abc.ABC):
    """A diffusion or flow process: a training loss and a sampling loop."""

    config: object

    def _configured_inference_steps(self) -> int | None:
        """The step count :meth:`sample` takes: the config's ``num_inference_steps`` (a subclass whose config
        may leave it unset returns its default); None where the config has none."""
        return getattr(self.config, "num_inference_steps", None)

    @property
    def inference_steps(self) -> int | None:
        """How many denoising steps :meth:`sample` takes (None where the config names none)."""
        steps = self._configured_inference_steps()
        return None if steps is None else int(steps)

    @abc.abstractmethod
    def loss(self, model_fn: ModelFn, x0: torch.Tensor, *, generator: torch.Generator | None = None) -> torch.Tensor:
        """Scalar training loss (a mean squared error over all elements)."""

    @abc.abstractmethod
    def sample(
        self, model_fn: ModelFn, noise: torch.Tensor, *, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Run the reverse process from ``noise``; returns a tensor of ``noise``'s shape."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config})"


# ---------------------------------------------------------------- random draws


def _draw(fn, shape, generator, device, **kwargs) -> torch.Tensor:
    """``fn(shape)`` drawn on the generator's device then moved; a sequence of generators draws row ``i``
    of the leading dim from generator ``i`` (a batch whose rows each keep their own stream)."""
    if generator is None:
        return fn(shape, device=device, **kwargs)
    if isinstance(generator, torch.Generator):
        return fn(shape, generator=generator, device=generator.device, **kwargs).to(device)
    shape = tuple(shape)
    rows = per_row(generator, shape[0])
    return torch.stack([fn(shape[1:], generator=g, device=g.device, **kwargs).to(device) for g in rows])


def randn(shape, *, generator, device, dtype) -> torch.Tensor:
    """Standard normal noise from ``generator`` (one, one per row of ``shape[0]``, or None)."""
    return _draw(torch.randn, shape, generator, device, dtype=dtype)


def rand(shape, *, generator, device, dtype) -> torch.Tensor:
    """Uniform noise in [0, 1) from ``generator`` (one, one per row of ``shape[0]``, or None)."""
    return _draw(torch.rand, shape, generator, device, dtype=dtype)


def randint(high: int, shape, *, generator, device) -> torch.Tensor:
    """Integers in [0, high) from ``generator`` (one, one per row of ``shape[0]``, or None)."""
    return _draw(lambda sh, **kw: torch.randint(0, high, sh, **kw), shape, generator, device)


def full_precision(dtype: torch.dtype) -> torch.dtype:
    """``dtype``, or float32 for a narrower float (bf16 / fp16 under autocast): the dtype schedule arithmetic
    runs in (float32 and float64 pass unchanged)."""
    return torch.promote_types(dtype, torch.float32)


def expand_as_batch(values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Reshape per-sample values ``[B]`` to ``[B, 1, ..., 1]`` to broadcast against ``like``."""
    return values.reshape(values.shape[0], *([1] * (like.dim() - 1)))


# ------------------------------------------------------------- noise schedules


def betas_for_schedule(
    beta_schedule: str, num_train_timesteps: int, beta_start: float, beta_end: float
) -> torch.Tensor:
    """The forward-process variances beta_1..beta_K (float32), as diffusers builds them.

    - ``linear``: beta_k evenly spaced from ``beta_start`` to ``beta_end`` (DDPM, Ho et al. 2020);
    - ``scaled_linear``: sqrt(beta_k) evenly spaced (latent diffusion);
    - ``squaredcos_cap_v2``: the cosine schedule of Nichol & Dhariwal 2021, eq. (17):
      alpha_bar(s) = cos^2((s + 0.008) / 1.008 * pi / 2) and
      beta_k = min(1 - alpha_bar(k / K) / alpha_bar((k - 1) / K), 0.999),
      computed in float64 Python arithmetic and stored as float32.
    """
    if beta_schedule == "linear":
        return torch.linspace(beta_start, beta_end, num_train_timesteps, dtype=torch.float32)
    if beta_schedule == "scaled_linear":
        return torch.linspace(beta_start**0.5, beta_end**0.5, num_train_timesteps, dtype=torch.float32) ** 2
    if beta_schedule == "squaredcos_cap_v2":

        def alpha_bar(s: float) -> float:
            return math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2

        betas = [
            min(1.0 - alpha_bar((k + 1) / num_train_timesteps) / alpha_bar(k / num_train_timesteps), 0.999)
            for k in range(num_train_timesteps)
        ]
        return torch.tensor(betas, dtype=torch.float32)
    raise ValueError(
        f"beta_schedule must be one of 'linear', 'scaled_linear', 'squaredcos_cap_v2'; got {beta_schedule!r}"
    )


def check_diffusion_fields(cfg) -> None:
    """Validate the fields DDPM and DDIM configs share (raise ValueError naming the field), and every choice
    field (a config built in Python is not checked by the recipe loader)."""
    check_choices(cfg)
    if cfg.num_train_timesteps < 1:
        raise ValueError(f"num_train_timesteps must be >= 1; got {cfg.num_train_timesteps}")
    if cfg.beta_schedule != "squaredcos_cap_v2":
        if not 0.0 < cfg.beta_start < 1.0:
            raise ValueError(f"beta_start must be in (0, 1); got {cfg.beta_start}")
        if not cfg.beta_start <= cfg.beta_end < 1.0:
            raise ValueError(f"beta_end must be in [beta_start, 1) = [{cfg.beta_start}, 1); got {cfg.beta_end}")
    if cfg.clip_sample_range <= 0.0:
        raise ValueError(f"clip_sample_range must be > 0; got {cfg.clip_sample_range}")


class DiscreteDiffusionScheduler(Scheduler):
    """Shared by DDPM and DDIM: the forward process q(x_k | x_0), the loss and the loop.

    Subclasses build ``self.betas`` (via :func:`betas_for_schedule`), and
    implement ``set_timesteps(n)`` and ``step(model_output, timestep, sample, generator)``.
    Schedule tensors stay float32 on the CPU; they are indexed with Python
    ints in ``step`` (0-dim tensors, valid against tensors on any device).
    """

    def _init_schedule(self, cfg) -> None:
        self.config = cfg
        # beta_k, alpha_k = 1 - beta_k, alpha_bar_k = prod_{i<=k} alpha_i   (DDPM eq. 4)
        self.betas = betas_for_schedule(cfg.beta_schedule, cfg.num_train_timesteps, cfg.beta_start, cfg.beta_end)
        self.alphas = 1.0 - self.betas
        self.alphas_cumprod = torch.cumprod(self.alphas, dim=0)
        self.timesteps = torch.arange(cfg.num_train_timesteps - 1, -1, -1, dtype=torch.int64)
        self.num_inference_steps: int | None = None

    @property
    def num_train_timesteps(self) -> int:
        return self.config.num_train_timesteps

    def _check_num_inference_steps(self, n: int) -> None:
        if not 1 <= n <= self.config.num_train_timesteps:
            raise ValueError(
                f"num_inference_steps must be in [1, num_train_timesteps={self.config.num_train_timesteps}]; got {n}"
            )

    # -- forward process -----------------------------------------------------

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """x_k = sqrt(alpha_bar_k) x_0 + sqrt(1 - alpha_bar_k) eps   (DDPM eq. 4); ``timesteps``: int ``[B]``."""
        work = full_precision(x0.dtype)  # in bf16, 1 - alpha_bar is 0 at k = 0, 1 and k = 2, 3 are one level
        alpha_bar = self.alphas_cumprod.to(device=x0.device, dtype=work)[timesteps.to(x0.device)]
        sqrt_alpha_bar = expand_as_batch(alpha_bar**0.5, x0)
        sqrt_one_minus_alpha_bar = expand_as_batch((1 - alpha_bar) ** 0.5, x0)
        return (sqrt_alpha_bar * x0.to(work) + sqrt_one_minus_alpha_bar * noise.to(work)).to(x0.dtype)

    def loss(self, model_fn: ModelFn, x0: torch.Tensor, *, generator: torch.Generator | None = None) -> torch.Tensor:
        """Simplified DDPM objective (Ho et al. 2020, eq. 14).

        eps ~ N(0, I), k ~ U{0, ..., K-1}, x_k = add_noise(x_0, eps, k);
        loss = mean ||target - model_fn(x_k, k)||^2 with target = eps
        (``prediction_type="epsilon"``) or x_0 (``"sample"``, as in DP3).
        """
        x0 = x0.to(full_precision(x0.dtype))  # bf16 targets (autocast): noise levels and steps kept exact
        noise = randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
        timesteps = randint(self.config.num_train_timesteps, (x0.shape[0],), generator=generator, device=x0.device)
        x_k = self.add_noise(x0, noise, timesteps)
        prediction = model_fn(x_k, timesteps.to(x0.dtype))
        target = noise if self.config.prediction_type == "epsilon" else x0
        return torch.nn.functional.mse_loss(prediction, target)

    # -- reverse process -----------------------------------------------------

    def _pred_original_sample(self, model_output: torch.Tensor, sample: torch.Tensor, alpha_bar_t: torch.Tensor):
        """x_0 predicted from the network output (DDPM eq. 15 / DDIM eq. 12), clipped if configured."""
        if self.config.prediction_type == "epsilon":
            pred_x0 = (sample - (1 - alpha_bar_t) ** 0.5 * model_output) / alpha_bar_t**0.5
        else:
            pred_x0 = model_output
        if self.config.clip_sample:
            pred_x0 = pred_x0.clamp(-self.config.clip_sample_range, self.config.clip_sample_range)
        return pred_x0

    @abc.abstractmethod
    def set_timesteps(self, num_inference_steps: int) -> None:
        """Choose the descending steps the reverse process visits."""

    @abc.abstractmethod
    def step(
        self, model_output: torch.Tensor, timestep: int, sample: torch.Tensor, generator: torch.Generator | None = None
    ) -> StepOutput:
        """One reverse step x_k -> x_{k_prev}."""

    @torch.no_grad()
    def sample(
        self, model_fn: ModelFn, noise: torch.Tensor, *, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """x_K = noise; for each k of ``set_timesteps(config.num_inference_steps)``: x <- step(model_fn(x, k), k, x).

        Runs without autograd. Resets the timesteps to the configured count.
        """
        self.set_timesteps(self._configured_inference_steps())
        x = noise
        for k in self.timesteps.tolist():
            k_batch = torch.full((x.shape[0],), float(k), device=x.device, dtype=x.dtype)
            x = self.step(model_fn(x, k_batch), k, x, generator=generator).prev_sample
        return x
