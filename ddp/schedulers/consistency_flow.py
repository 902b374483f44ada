"""Consistency flow matching, as FlowPolicy uses it (one-step action generation).

References: Yang et al. 2024, "Consistency Flow Matching: Defining Straight
Flows with Velocity Consistency" (multi-segment objective, eq. 6-7), and
Zhang et al., AAAI 2025, "FlowPolicy: Enabling Fast and Robust 3D Flow-based
Policy via Consistency Flow Matching" (its training loss and one-step sampler,
re-implemented here from their description and public code's behaviour).

Time runs from noise (t = 0) to data (t = 1): x_t = t a_1 + (1 - t) a_0 with
a_0 ~ N(0, I) and a_1 the clean sample. The network predicts a velocity
v(x_t, t * time_scale). [0, 1] is cut into ``num_segments`` equal segments;
s(t) is the end of t's segment (t on a segment end belongs to the segment it
ends), and f(x_t, t) = x_t + (s(t) - t) v(x_t, t) extrapolates to it.

Training (one pair t < r per sample):

1. t ~ U[eps, 1], r = min(t + delta, 1)
2. x_t, x_r on the straight path of the same (a_0, a_1); x_s its point at s = s(t)
3. f_t = x_t + (s - t) v_t
   f_r = x_r + (s - r) v_r  where r < boundary, else the ground-truth x_s
4. loss = mean |f_t - f_r|^2 + alpha * mean(m |v_t - v_r|^2),
   m = [t < boundary] * [(s - t) > 1.01 delta]   (r still inside t's segment)

Choices (all but the last follow FlowPolicy's public code):

- ``boundary`` is a time threshold, not a segment index: with the default
  ``boundary = 1`` only r = 1 (t >= 1 - delta) uses the ground-truth end
  point. When r crosses an inner segment end (t < s < r), f_r is still
  x_r + (s - r) v_r, a short Euler step backwards to s. ``boundary = 0``
  makes every f_r the ground-truth x_s and switches the velocity term off.
- v_r comes from the same network as v_t (no EMA target), with gradients
  flowing through it (FlowPolicy does not detach it). ``stop_grad_r=True``
  evaluates v_r under ``torch.no_grad`` instead (a stop-gradient target, as
  in consistency models); on a toy problem it learns far slower, because the
  ground truth then reaches the network only through the r = 1 pairs.
  Non-finite values of v_r are zeroed (FlowPolicy's ``nan_to_num`` zeroes NaN but maps +/-inf to
  +/-float max, so a diverging network's loss blows up there; here it stays finite).
- The mean runs over every element; velocity terms outside the mask count
  as zeros in it (FlowPolicy's per-sample mean then batch mean, which is the
  same number).
- Sampling is Euler over [eps, 1] starting at z ~ N(0, I) taken as the
  point at t = eps: t_i = eps + i h, h = (1 - eps) / n,
  z <- z + h v(z, t_i * time_scale); one step is a = z + (1 - eps) v(z, eps * time_scale).
  For straight paths this lands exactly on the data (a_1 = x_eps + (1 - eps)(a_1 - a_0)).
  FlowPolicy's code uses the same times but a step of 1 / n, i.e. it
  overshoots by eps * v (1 % of the velocity at the defaults).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from ddp.registry import register
from ddp.schedulers.base import ModelFn, Scheduler, expand_as_batch, full_precision, rand, randn


@dataclass
class ConsistencyFlowConfig:
    """Options of consistency flow matching (defaults are FlowPolicy's)."""

    #: smallest training time and first inference time
    eps: float = 1e-2
    #: gap between the paired times t and r = t + delta
    delta: float = 1e-2
    #: equal segments of [0, 1], each with its own end point s
    num_segments: int = 2
    #: r at or past this time uses the ground-truth point at s (see the module docstring)
    boundary: float = 1.0
    #: weight of the velocity-consistency term
    alpha: float = 1e-5
    #: Euler steps at sampling time (FlowPolicy: 1)
    num_inference_steps: int = 1
    #: the network sees t * time_scale (FlowPolicy: 99)
    time_scale: float = 99.0
    #: evaluate v_r without gradient (FlowPolicy: False)
    stop_grad_r: bool = False

    #: options a trained model may be sampled with other values of (the loss's segments, pairing and weights
    #: shaped training only; eps and time_scale define the times the network saw)
    free_at_inference: ClassVar[frozenset[str]] = frozenset({
        "num_inference_steps", "alpha", "stop_grad_r", "delta", "num_segments", "boundary"})

    def __post_init__(self):
        if not 0.0 <= self.eps < 1.0:
            raise ValueError(f"eps must be in [0, 1); got {self.eps}")
        if not 0.0 < self.delta < 1.0:
            raise ValueError(f"delta must be in (0, 1); got {self.delta}")
        if self.num_segments < 1:
            raise ValueError(f"num_segments must be >= 1; got {self.num_segments}")
        if not 0.0 <= self.boundary <= 1.0:
            raise ValueError(f"boundary must be in [0, 1]; got {self.boundary}")
        if self.alpha < 0.0:
            raise ValueError(f"alpha must be >= 0; got {self.alpha}")
        if self.num_inference_steps < 1:
            raise ValueError(f"num_inference_steps must be >= 1; got {self.num_inference_steps}")
        if self.time_scale <= 0.0:
            raise ValueError(f"time_scale must be > 0; got {self.time_scale}")


@register("scheduler", "consistency_flow", config=ConsistencyFlowConfig)
class ConsistencyFlowScheduler(Scheduler):
    """Consistency flow matching with a velocity network (FlowPolicy): one-step sampling."""

    def __init__(self, config: ConsistencyFlowConfig):
        self.config = config

    def interpolate(self, a0: torch.Tensor, a1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """x_t = t a_1 + (1 - t) a_0 for per-sample times ``t: [B]``."""
        t_ = expand_as_batch(t, a1)
        return t_ * a1 + (1 - t_) * a0

    def segment_ends(self, t: torch.Tensor) -> torch.Tensor:
        """s(t): the end of the segment holding t; a time on a segment end maps to that end."""
        ends = torch.linspace(0, 1, self.config.num_segments + 1, device=t.device, dtype=t.dtype)
        return ends[torch.searchsorted(ends, t, side="left").clamp(min=1)]

    def loss(self, model_fn: ModelFn, x0: torch.Tensor, *, generator: torch.Generator | None = None) -> torch.Tensor:
        """The consistency flow matching loss (module docstring, steps 1-4); calls ``model_fn`` twice."""
        cfg = self.config
        a1 = x0 = x0.to(full_precision(x0.dtype))  # bf16 targets (autocast): t + delta and segment ends kept exact
        a0 = randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
        # 1. paired times
        t = rand((x0.shape[0],), generator=generator, device=x0.device, dtype=x0.dtype) * (1 - cfg.eps) + cfg.eps
        r = torch.clamp(t + cfg.delta, max=1.0)
        # 2. points on the straight path, and its point at t's segment end
        x_t = self.interpolate(a0, a1, t)
        x_r = self.interpolate(a0, a1, r)
        s = self.segment_ends(t)
        x_s = self.interpolate(a0, a1, s)
        # 3. extrapolations to s
        v_t = model_fn(x_t, t * cfg.time_scale)
        with torch.set_grad_enabled(torch.is_grad_enabled() and not cfg.stop_grad_r):
            v_r = model_fn(x_r, r * cfg.time_scale)
        v_r = torch.nan_to_num(v_r, nan=0.0, posinf=0.0, neginf=0.0)
        t_, r_, s_ = (expand_as_batch(u, x0) for u in (t, r, s))
        f_t = x_t + (s_ - t_) * v_t
        f_r = torch.where(r_ < cfg.boundary, x_r + (s_ - r_) * v_r, x_s)
        # 4. endpoint consistency + masked velocity consistency
        loss_f = torch.mean((f_t - f_r) ** 2)
        same_segment = (t < cfg.boundary) & ((s - t) > 1.01 * cfg.delta)
        loss_v = torch.mean(expand_as_batch(same_segment.to(x0.dtype), x0) * (v_t - v_r) ** 2)
        return loss_f + cfg.alpha * loss_v

    @torch.no_grad()
    def sample(
        self, model_fn: ModelFn, noise: torch.Tensor, *, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Euler over [eps, 1] from z = noise: z <- z + h v(z, t_i * time_scale), t_i = eps + i h, h = (1 - eps) / n.

        Deterministic (``generator`` is unused); runs without autograd.
        """
        cfg = self.config
        n = cfg.num_inference_steps
        h = (1 - cfg.eps) / n
        z = noise
        for i in range(n):
            t_i = cfg.eps + i * h
            t_batch = torch.full((z.shape[0],), t_i * cfg.time_scale, device=z.device, dtype=z.dtype)
            z = z + h * model_fn(z, t_batch)
        return z
