"""Detection statistics on the real-imagination residual, and their calibration to a false-alarm rate.

The paper's score is D_R-I = ||O_real - O_pred||^2, the mean squared latent
error over the M newest frames and all latent dims. :class:`ScoreSpec` names
the variants the discrepancy detector can use instead, all computed from the
same two latent windows (``real``, ``pred``: ``[..., M, D]``):

* ``dims``: ``all`` latent dims, the ``point`` part only (the encoder's
  point-cloud features, the first ``point_dims``) or the ``state`` part;
* ``frames``: the ``mean`` over the M frames, the ``newest`` frame, or the
  ``max`` over frames;
* ``whiten``: residuals centred and divided per latent dim by their ID
  mean / std (from calibration rollouts) before squaring;
* ``spread``: residuals divided per latent dim by the spread of the K
  world-model samples behind the forecast (controller ``forecast_samples``
  K > 1; a diffusion model's own uncertainty) added in quadrature to the median ID
  spread of that dim (sqrt(std^2 + median^2)) so a confident dim cannot blow up;
* ``per_chunk``: the score divided by the ID score typical of the task's
  phase (the median at chunks ``c - window .. c + window``, or another
  ``chunk_quantile``), so a contact phase with large ID errors does not set
  the threshold for an approach with small ones; a high quantile (0.9)
  divides by the phase's ID tail instead of its middle, which evens out
  phases whose ID scores are spread wide around a small median;
* ``cusum``: evidence accumulated over chunks, ``S_t = max(0, S_{t-1} + s_t
  - drift)`` on the normalised score (the ID median is 1); a persistent
  moderate excess then fires as surely as one large one. The online detector
  restarts it at tau / 2 after an alarm (``DiscrepancyDetector``); the offline
  statistic here does not restart, so traces after the first alarm differ
  while the first alarm is the same.

:class:`ScoreCalibration` fits the reference statistics on one part of the ID
calibration episodes (:func:`split_fit`) and sets the threshold on the other
part by the split-conformal rule: with ``n`` held-out episode maxima, the
threshold is the ``ceil((n + 1)(1 - alpha))``-th smallest, so that a new ID
episode (drawn like them) exceeds it with probability at most ``alpha``, for
any score. With ``threshold_on="successful"`` only the held-out episodes that
succeeded count, and the guarantee is over nominal ID episodes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "ScoreSpec", "ScoreCalibration", "residual_score", "conformal_threshold", "episode_scores", "episode_statistic",
    "fit_calibration", "split_fit", "THRESHOLD_ON",
]

DIMS = ("all", "point", "state")
FRAMES = ("mean", "newest", "max")


@dataclass(frozen=True)
class ScoreSpec:
    """Which statistic of the residual a detector thresholds (see the module docstring)."""

    dims: str = "all"
    frames: str = "mean"
    whiten: bool = False
    per_chunk: bool = False
    window: int = 1
    cusum: bool = False
    drift: float = 1.0
    spread: bool = False
    chunk_quantile: float = 0.5

    def __post_init__(self):
        if self.whiten and self.spread:
            raise ValueError("whiten and spread are alternative normalisations of the residual: choose one")
        if self.dims not in DIMS:
            raise ValueError(f"dims must be one of {DIMS}; got {self.dims!r}")
        if self.frames not in FRAMES:
            raise ValueError(f"frames must be one of {FRAMES}; got {self.frames!r}")
        if self.window < 0:
            raise ValueError(f"window must be >= 0; got {self.window}")
        if not self.drift >= 0:
            raise ValueError(f"drift must be >= 0; got {self.drift}")
        if not 0.0 < self.chunk_quantile < 1.0:
            raise ValueError(f"chunk_quantile must be in (0, 1); got {self.chunk_quantile}")

    @property
    def normalised(self) -> bool:
        """The statistic is in units of the ID median (needed to accumulate it)."""
        return self.per_chunk or self.cusum

    @property
    def needs_reference(self) -> bool:
        """Reference statistics must be fitted on ID rollouts before the score means anything."""
        return self.whiten or self.spread or self.normalised

    def label(self) -> str:
        parts = [f"{self.dims} dims", f"{self.frames} frame" if self.frames != "mean" else "mean frames"]
        if self.whiten:
            parts.append("whitened")
        if self.spread:
            parts.append("by sample spread")
        if self.per_chunk:
            q = "" if self.chunk_quantile == 0.5 else f", ID quantile {self.chunk_quantile:g}"
            parts.append(f"per-chunk (window {self.window}{q})")
        if self.cusum:
            parts.append(f"CUSUM (drift {self.drift:g})")
        return ", ".join(parts)


def _dim_slice(dims: str, point_dims: int, total: int) -> slice:
    if dims == "all":
        return slice(0, total)
    if point_dims <= 0 or point_dims >= total:
        raise ValueError(f"dims {dims!r} needs an encoder whose latent has point-cloud and state parts "
                         f"(point_dims {point_dims} of {total})")
    return slice(0, point_dims) if dims == "point" else slice(point_dims, total)


def residual_score(real: torch.Tensor, pred: torch.Tensor, spec: ScoreSpec, *, point_dims: int = 0,
                   center: torch.Tensor | None = None, scale: torch.Tensor | None = None,
                   std: torch.Tensor | None = None) -> torch.Tensor:
    """The instantaneous score of ``real`` against ``pred`` (``[..., M, D]`` each) -> ``[...]``; NaN where
    ``pred`` is NaN (no forecast yet). ``center`` / ``scale`` ([D]) whiten when ``spec.whiten``; with
    ``spec.spread``, ``std`` (``[..., M, D]``, the forecast samples' spread) divides the residual, added in
    quadrature to ``scale`` (the ID median spread per dim)."""
    r = real.double() - pred.double()
    if spec.spread:
        if std is None or scale is None:
            raise ValueError("a spread-scaled score needs the forecast samples' spread (controller.forecast_samples "
                             "> 1) and its ID floor (calibrate the detector)")
        r = r / torch.sqrt(std.double() ** 2 + scale.to(r) ** 2)
    elif spec.whiten:
        if center is None or scale is None:
            raise ValueError("a whitened score needs the ID residual mean and std (calibrate the detector)")
        r = (r - center.to(r)) / scale.to(r)
    r = r[..., _dim_slice(spec.dims, point_dims, r.shape[-1])]
    per_frame = (r**2).mean(-1)
    if spec.frames == "mean":
        return per_frame.mean(-1)
    if spec.frames == "newest":
        return per_frame[..., -1]
    return per_frame.amax(-1)


def conformal_threshold(maxima, alpha: float) -> float:
    """The split-conformal threshold: the ``ceil((n + 1)(1 - alpha))``-th smallest of ``n`` ID episode maxima."""
    x = np.sort(np.asarray(maxima, dtype=np.float64))
    n = x.size
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1); got {alpha}")
    k = math.ceil((n + 1) * (1.0 - alpha))
    if k > n:
        need = math.ceil((1.0 - alpha) / alpha)
        raise ValueError(f"alpha {alpha:g} needs at least {need} held-out ID calibration episodes for its threshold; "
                         f"got {n} (raise eval.calibration_episodes or alpha)")
    return float(x[k - 1])


def episode_statistic(scores: np.ndarray, spec: ScoreSpec, reference) -> np.ndarray:
    """The thresholded statistic over one episode's chunk scores (NaN: no forecast), as the detector
    computes it online: normalised per chunk phase (its ID median or quantile) / by the ID median,
    accumulated by CUSUM."""
    s = np.asarray(scores, dtype=np.float64)
    if spec.normalised:
        s = s / np.array([reference.scale_at(c) for c in range(s.size)])
    if not spec.cusum:
        return s
    out, acc = np.full(s.size, np.nan), 0.0
    for c, v in enumerate(s):
        if np.isnan(v):
            continue
        acc = max(0.0, acc + v - spec.drift)
        out[c] = acc
    return out


@dataclass
class ScoreCalibration:
    """Reference statistics of a score on ID episodes, and its conformal threshold.

    ``center`` / ``scale``: per latent dim residual mean / std (whitening); ``chunk_scale``: the ID
    score per chunk phase (``per_chunk``: its median, or its ``chunk_quantile``), ``chunk_fallback``: the
    same quantile over all chunks (the scale of chunks past the table; None: ``median``), ``median``: the
    median over all chunks; ``tau``: the threshold on the statistic; ``reference``: the statistic per
    chunk of every held-out ID episode (the ID side of AUROC in reports; with ``threshold_on: successful``
    the failing ones too, though only the successful ones set tau).
    """

    alpha: float | None = None
    tau: float | None = None
    center: list[float] | None = None
    scale: list[float] | None = None
    median: float | None = None
    chunk_scale: list[float] | None = None
    chunk_fallback: float | None = None
    fit_episodes: int = 0
    threshold_episodes: int = 0
    threshold_on: str = "all"  # the held-out episodes that set tau: all, or the successful ones
    fit_on: str = "all"  # the fitting episodes the reference came from: all, or the successful ones
    reference: list[list[float]] | None = None

    def scale_at(self, chunk: int) -> float:
        if self.chunk_scale and chunk < len(self.chunk_scale):
            return self.chunk_scale[chunk]
        return self.chunk_fallback if self.chunk_scale and self.chunk_fallback is not None else self.median

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, data: dict) -> "ScoreCalibration":
        known = {k: v for k, v in data.items() if k in cls.__dataclass_fields__}
        if known.get("reference") is not None:  # strict JSON stored NaN (no forecast) as null
            known["reference"] = [[math.nan if v is None else float(v) for v in row] for row in known["reference"]]
        return cls(**known)

    def tensors(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        if self.center is None:
            return None, None
        return torch.tensor(self.center, dtype=torch.float64), torch.tensor(self.scale, dtype=torch.float64)


def _episode_std(ep: dict, spec: ScoreSpec) -> torch.Tensor | None:
    if not spec.spread:
        return None
    if ep.get("latent_pred_std") is None:
        raise ValueError("a spread-scaled score needs rollouts with controller.forecast_samples > 1 "
                         "(the forecast samples' spread is not recorded)")
    return torch.as_tensor(np.asarray(ep["latent_pred_std"], dtype=np.float64))


def episode_scores(ep: dict, spec: ScoreSpec, cal: ScoreCalibration, point_dims: int = 0) -> np.ndarray:
    """The instantaneous score of every chunk of a recorded episode (``latent_real`` / ``latent_pred`` /
    ``latent_pred_std`` arrays [chunks, M, D]), as the detector computes it online."""
    center, scale = cal.tensors()
    real = torch.as_tensor(np.asarray(ep["latent_real"], dtype=np.float64))
    pred = torch.as_tensor(np.asarray(ep["latent_pred"], dtype=np.float64))
    std = _episode_std(ep, spec)
    return residual_score(real, pred, spec, point_dims=point_dims, center=center, scale=scale, std=std).numpy()


def _scores(episodes, spec: ScoreSpec, point_dims: int, cal: ScoreCalibration) -> list[np.ndarray]:
    """Calibration's scores: a non-finite chunk (sensor fault) is no ID evidence and reads NaN."""
    out = []
    for ep in episodes:
        s = episode_scores(ep, spec, cal, point_dims)
        out.append(np.where(np.isfinite(s), s, np.nan))
    return out


THRESHOLD_ON = ("all", "successful")


def split_fit(n: int, fit_fraction: float) -> list[bool]:
    """Which of ``n`` calibration episodes fit the score (True) and which set the threshold: episode
    ``i`` fits iff ``floor((i + 1) f) > floor(i f)``, so a fraction ``f`` of any prefix fits and
    episodes added later never move an earlier one to the other side (0.5: every second one)."""
    return [math.floor((i + 1) * fit_fraction) > math.floor(i * fit_fraction) for i in range(n)]


def _needed(alpha: float) -> int:
    return math.ceil((1.0 - alpha) / alpha)


def _fewest_holding_out(need: int, fit_fraction: float) -> int:
    """The fewest episodes whose split (:func:`split_fit`) holds out at least ``need`` of them."""
    n = need
    while n - sum(split_fit(n, fit_fraction)) < need:
        n += 1
    return n


def _successful(fit: list[dict]) -> list[dict]:
    """The fitting episodes that succeeded (``fit_on: successful``)."""
    if any("success" not in e for e in fit):
        raise ValueError("fit_on: successful needs calibration episodes that record their success")
    if not any(e["success"] for e in fit):
        raise ValueError(f"none of the {len(fit)} fitting ID calibration episodes succeeded (fit_on: "
                         "successful); set controller.detector.fit_on: all")
    return [e for e in fit if e["success"]]


def fit_calibration(episodes: list[dict], spec: ScoreSpec, *, alpha: float | None, point_dims: int = 0,
                    fit_fraction: float = 0.5, tau: float | None = None,
                    threshold_on: str = "all", fit_on: str = "all") -> ScoreCalibration:
    """Fit ``spec``'s reference statistics on a ``fit_fraction`` of the ID ``episodes`` (each with
    ``latent_real`` / ``latent_pred`` arrays ``[chunks, M, D]``, NaN forecasts where none; see
    :func:`split_fit`) and, unless ``tau`` is given, the conformal threshold for ``alpha`` on the rest,
    or (``threshold_on="successful"``) on the rest that succeeded: the threshold then bounds false
    alarms over nominal ID episodes, and failing ones (heavy-tailed residuals) do not set it. Too few
    successful held-out episodes raise :class:`ddp.contracts.NeedMoreEpisodes`. ``fit_on="successful"`` fits
    the reference on the fitting episodes that succeeded only."""
    from ddp.contracts import NeedMoreEpisodes

    if threshold_on not in THRESHOLD_ON:
        raise ValueError(f"threshold_on must be one of {', '.join(THRESHOLD_ON)}; got {threshold_on!r}")
    if fit_on not in THRESHOLD_ON:
        raise ValueError(f"fit_on must be one of {', '.join(THRESHOLD_ON)}; got {fit_on!r}")
    # what selects successful episodes: the threshold when it is calibrated, the reference whenever the
    # statistic has one (tau given too: a per-phase scale fitted on failing episodes is inflated by them)
    unjudged = [on for on, value, selects in (("threshold_on", threshold_on, tau is None),
                                               ("fit_on", fit_on, spec.needs_reference))
                if selects and value == "successful"]
    if unjudged and any("success" in e and e["success"] is None for e in episodes):
        # a real robot's episodes: taken as failures, they asked for ever more episodes, then failed anyway
        raise ValueError(f"the ID calibration episodes' success was not judged (a real robot), so "
                         f"{' and '.join(f'{on}: successful' for on in unjudged)} cannot select successful ones; "
                         f"set controller.detector.{unjudged[0]}: all")
    n = len(episodes)
    if n < 2 and spec.needs_reference and tau is None:
        raise ValueError(f"calibrating this score needs at least 2 ID episodes; got {n}")
    if spec.needs_reference and tau is None:
        fits = split_fit(n, fit_fraction)
        if not any(fits):
            fits[-1] = True
        fit = [e for e, f in zip(episodes, fits) if f]
        held = [e for e, f in zip(episodes, fits) if not f]
        fit = _successful(fit) if fit_on == "successful" else fit
        n_fit = len(fit)
    else:  # tau given: the reference (if any) is fitted on every episode (that succeeded, with fit_on:
        # successful), and every episode is the in-sample ID side
        fit, held = list(episodes), list(episodes)
        if spec.needs_reference and fit_on == "successful":
            fit = _successful(fit)
        n_fit = len(fit) if spec.needs_reference else 0
    if tau is None and not held:
        raise ValueError(f"no ID episodes left for the threshold ({n} episodes, {n_fit} used to fit the score)")
    if tau is None and threshold_on == "successful":
        if any("success" not in e for e in held):
            raise ValueError("threshold_on: successful needs calibration episodes that record their success")
        ok = [e for e in held if e["success"]]
        need = _needed(alpha)
        if not ok and len(held) >= need:
            raise ValueError(f"none of the {len(held)} held-out ID calibration episodes succeeded, so none can set tau "
                             "(threshold_on: successful): the policy does not solve the task in distribution; "
                             "set controller.detector.threshold_on: all to calibrate on failing episodes")
        if len(ok) < need:
            rate = max(len(ok), 1) / (len(held) + 1)  # the held-out success rate, never taken as 0
            share = 1.0 - fit_fraction if spec.needs_reference else 1.0
            raise NeedMoreEpisodes(
                f"alpha {alpha:g} needs {need} successful held-out ID calibration episodes for its threshold "
                f"(threshold_on: successful); {len(ok)} of {len(held)} succeeded",
                more=math.ceil((need - len(ok)) / (share * rate)),
                at_least=_fewest_holding_out(need, fit_fraction) if spec.needs_reference else need)
    reference_eps = held  # every held-out ID episode, failing ones too: the ID side of the reports' AUROC
    if tau is None and threshold_on == "successful":
        held = [e for e in held if e["success"]]
    cal = ScoreCalibration(alpha=alpha, fit_episodes=n_fit, threshold_episodes=len(held) if tau is None else 0,
                           threshold_on=threshold_on, fit_on=fit_on)
    if spec.whiten:
        res = np.concatenate([
            (np.asarray(e["latent_real"], np.float64) - np.asarray(e["latent_pred"], np.float64)).reshape(-1, np.shape(
                e["latent_real"])[-1]) for e in fit
        ])
        res = res[np.isfinite(res).all(1)]  # chunks without a forecast, or with a non-finite latent
        if res.shape[0] < 2:
            raise ValueError("whitening needs ID residuals from at least two forecast chunks")
        cal.center = res.mean(0).tolist()
        std = res.std(0)  # a dim with (almost) no ID variance is floored relative to the others, not at 1e-8,
        cal.scale = np.maximum(std, max(1e-3 * float(np.median(std)), 1e-12)).tolist()  # or noise reads as 1e5 sigma
    if spec.spread:
        stds = np.concatenate([_episode_std(e, spec).numpy().reshape(-1, np.shape(e["latent_real"])[-1]) for e in fit])
        stds = stds[np.isfinite(stds).all(1)]
        if stds.shape[0] == 0:
            raise ValueError("no forecast spread recorded in the ID episodes (no chunk had a forecast)")
        cal.center = [0.0] * stds.shape[1]
        cal.scale = np.maximum(np.median(stds, 0), 1e-8).tolist()  # the floor: median ID spread per dim
    if spec.normalised:
        raw = _scores(fit, spec, point_dims, cal)
        allv = np.concatenate([s[np.isfinite(s)] for s in raw])
        if allv.size == 0:
            raise ValueError("no finite ID scores to normalise by (no chunk had a forecast)")
        cal.median = float(max(np.median(allv), 1e-12))
        if spec.per_chunk:
            chunks = max(s.size for s in raw)
            # past the longest fitting episode (and for a phase with no finite score): the same quantile over all
            cal.chunk_fallback = float(max(np.quantile(allv, spec.chunk_quantile), 1e-12))
            table = []
            for c in range(chunks):
                near = [s[j] for s in raw for j in range(max(0, c - spec.window), min(s.size, c + spec.window + 1))]
                near = np.asarray([v for v in near if np.isfinite(v)])
                table.append(float(max(np.quantile(near, spec.chunk_quantile), 1e-12)) if near.size else cal.chunk_fallback)
            cal.chunk_scale = table
    stats = [episode_statistic(s, spec, cal) for s in _scores(reference_eps, spec, point_dims, cal)]
    cal.reference = [[float(v) for v in s] for s in stats]
    if tau is None:  # tau from the episodes that set it (threshold_on): ids keep the two lists aligned
        setting = {id(e) for e in held}
        maxima = [np.nanmax(s) if np.isfinite(s).any() else 0.0 for e, s in zip(reference_eps, stats)
                  if id(e) in setting]
        cal.tau = conformal_threshold(maxima, alpha)
    else:
        cal.tau = float(tau)
    return cal
