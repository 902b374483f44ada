"""The paper's OOD detector: a real-imagination discrepancy statistic above a threshold tau.

By default the statistic is the paper's D_R-I (the mean squared latent error
between the real and the imagined window) and tau is calibrated from ID
rollouts to a stated false-alarm rate: ``alpha`` is the probability that an
ID episode raises an alarm at all, and the threshold is the split-conformal
quantile of ID episode maxima (``ddp.detectors.scores``), valid for any
number of calibration episodes that allows it. ``dims`` / ``frames`` /
``whiten`` / ``spread`` / ``per_chunk`` / ``cusum`` choose another statistic of the same
residual (see ``ddp.detectors.scores``; ``ddp detect`` compares them on a
checkpoint). ``tau`` fixes the threshold instead (in the statistic's units).
``threshold_on: successful`` (the default) sets tau on the held-out ID episodes
that succeeded only: false alarms are then bounded by ``alpha`` over nominal
(successful) episodes, by ``alpha`` + the ID failure rate over all ID episodes, and a failing ID episode, whose residual can wander far (it leaves
the demonstrations), does not set the threshold for every other one.

Reads the controller's ``("ddp", "latent_real")`` / ``("ddp", "latent_pred")``
windows ([B, M, D]; the forecast is NaN before the first one exists, so no
alarm is possible on an episode's first chunk) and ``chunk_index``; writes
``("ddp", "ood")`` and the statistic as ``("ddp", "score")``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from ddp.config import check_choices

from ddp.detectors.scores import ScoreCalibration, ScoreSpec, fit_calibration, residual_score
from ddp.keys import KeyedModule
from ddp.registry import register


@dataclass
class DiscrepancyConfig:
    tau: float | None = None  # threshold on the statistic; null = calibrate it from ID rollouts for alpha
    # target probability that an ID episode raises a false alarm (calibration); with threshold_on: successful,
    # an ID episode the policy solves (over all ID episodes: at most alpha + the ID failure rate)
    alpha: float = 0.05
    dims: str = "all"  # latent dims scored: all, point (point-cloud features), state
    frames: str = "mean"  # frames of the window: mean, newest, max
    whiten: bool = False  # residuals divided per dim by their ID std (calibrated)
    per_chunk: bool = False  # the score divided by the ID score of the task phase (chunk +- window)
    window: int = 1  # per_chunk: neighbouring chunks pooled on each side
    chunk_quantile: float = 0.5  # per_chunk: the ID quantile of the phase's scores divided by (0.5: median)
    cusum: bool = False  # accumulate evidence over chunks (CUSUM on the normalised score)
    drift: float = 1.0  # cusum: subtracted each chunk, in units of the per-chunk scale (the ID median by default)
    spread: bool = False  # residuals scaled by the forecast samples' spread (controller.forecast_samples > 1)
    fit_fraction: float = 0.5  # calibration: share of ID episodes fitting the score; the rest set tau
    # the held-out ID episodes that set tau: the successful ones (alpha then bounds false alarms over
    # nominal episodes; a failing ID episode's wandering residual no longer sets tau; more episodes are
    # rolled out while fewer than (1 - alpha) / alpha succeeded), or all of them
    threshold_on: Literal["successful", "all"] = "successful"
    # the fitting ID episodes the statistic's reference (per-phase scale, median, whitening) comes from: all,
    # or the successful ones (a failing episode's wandering residual then does not raise a phase's scale)
    fit_on: Literal["all", "successful"] = "all"

    def __post_init__(self):
        check_choices(self)
        if self.tau is not None and not self.tau > 0:
            raise ValueError(f"tau must be > 0 or null; got {self.tau}")
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1); got {self.alpha}")
        if not 0.0 < self.fit_fraction < 1.0:
            raise ValueError(f"fit_fraction must be in (0, 1); got {self.fit_fraction}")
        self.spec  # noqa: B018 - validates dims, frames, window, drift, chunk_quantile

    @property
    def spec(self) -> ScoreSpec:
        return ScoreSpec(self.dims, self.frames, self.whiten, self.per_chunk, self.window, self.cusum, self.drift,
                         self.spread, self.chunk_quantile)


@register("detector", "discrepancy", config=DiscrepancyConfig)
class DiscrepancyDetector(KeyedModule):
    """OOD iff the real-imagination statistic (D_R-I by default) exceeds tau (calibrated to alpha)."""

    default_in_keys = {
        "real": ("ddp", "latent_real"), "pred": ("ddp", "latent_pred"), "point_dims": ("ddp", "point_dims"),
        "chunk_index": "chunk_index", "pred_std": ("ddp", "latent_pred_std"),
    }
    default_out_keys = {"ood": ("ddp", "ood"), "score": ("ddp", "score")}
    sticky = True  # once OOD, stay until recovery and a re-check say otherwise
    needs_discrepancy = True

    def __init__(self, config: DiscrepancyConfig):
        super().__init__()
        self.config = config
        self.spec = config.spec
        self.cal = ScoreCalibration(tau=config.tau)
        self._acc: list[float] = []  # CUSUM accumulators, one per environment

    @property
    def tau(self) -> float | None:
        return self.cal.tau

    @property
    def needs_calibration(self) -> bool:
        """No threshold yet, or a statistic whose ID reference is not fitted: ``ddp eval`` calibrates it."""
        fitted = self.cal.median is not None or not self.spec.normalised
        fitted = fitted and (self.cal.center is not None or not (self.spec.whiten or self.spec.spread))
        return self.cal.tau is None or not fitted

    def calibrate(self, episodes, *, point_dims: int = 0) -> float:
        """Fit the statistic and tau on ID episodes (``latent_real`` / ``latent_pred`` per chunk); return tau."""
        cfg = self.config
        self.cal = fit_calibration(list(episodes), self.spec, alpha=cfg.alpha, point_dims=point_dims,
                                   fit_fraction=cfg.fit_fraction, tau=cfg.tau, threshold_on=cfg.threshold_on,
                                   fit_on=cfg.fit_on)
        return self.cal.tau

    def calibration(self) -> dict:
        """The fitted statistic and threshold (JSON-ready), e.g. to save beside the checkpoint."""
        return self.cal.to_dict()

    def load_calibration(self, calibration: dict) -> None:
        self.cal = ScoreCalibration.from_dict(calibration)

    def reset(self):
        self._acc = []

    def forward(self, td):
        if self.needs_calibration:
            raise RuntimeError(
                "detector 'discrepancy' has no threshold: set controller.detector.tau, "
                "or calibrate it from ID rollouts (ddp eval does this when tau is null)"
            )
        real, pred = td.get(self.key("real")), td.get(self.key("pred"))
        point_dims = td.get(self.key("point_dims"), None)
        pd = int(point_dims.reshape(-1)[0]) if point_dims is not None else 0
        center, scale = self.cal.tensors()
        std = td.get(self.key("pred_std"), None) if self.spec.spread else None
        if self.spec.spread and std is None:
            raise RuntimeError("detector option spread: true needs controller.forecast_samples > 1 "
                               "(no ('ddp', 'latent_pred_std') to scale by)")
        score = residual_score(real, pred, self.spec, point_dims=pd, center=center, scale=scale, std=std).reshape(-1)
        chunks = td.get(self.key("chunk_index")).reshape(-1).tolist()
        if len(self._acc) != score.numel():
            self._acc = [0.0] * score.numel()
        stat = []
        for b, (v, c) in enumerate(zip(score.tolist(), chunks)):
            if c == 0:
                self._acc[b] = 0.0
            if self.spec.normalised and v == v:
                v = v / self.cal.scale_at(int(c))
            if self.spec.cusum and v == v:
                self._acc[b] = max(0.0, self._acc[b] + v - self.spec.drift)
                v = self._acc[b]
            stat.append(v)
        stat = torch.tensor(stat, dtype=torch.float64)
        ood = stat > self.cal.tau  # NaN (no forecast yet) is never above
        for b in torch.nonzero(ood).reshape(-1).tolist():
            # a CUSUM restarts after its alarm with a head start of tau / 2 (the "fast initial response" CUSUM,
            # Lucas & Crosier 1982): a change that persists alarms again on the next chunk's evidence, so the
            # controller's re-check reads OOD (from 0 it read ID almost always); an ID chunk drains it
            self._acc[b] = 0.5 * self.cal.tau
        shape = td.get(self.key("chunk_index")).shape[:-1] if td.batch_dims else ()
        td.set(self.key("score"), stat.float().reshape(shape))
        td.set(self.key("ood"), ood.reshape(shape))
        return td
