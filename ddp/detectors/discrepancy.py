"""The paper's OOD detector: real-imagination discrepancy D_R-I above a threshold tau.

tau is the recipe's, or calibrated from ID rollouts (``tau: null``): a margin
times a high percentile of the D_R-I values seen. With ``per_chunk: true`` the
calibration keeps one threshold per chunk index instead (the percentile of the
values at chunks ``c - window .. c + window``), since the world model's ID
forecast error depends on the task's phase: small while the arm approaches,
larger around contacts. A displacement early in an episode can then be seen
before the late, noisier chunks would have set a single tau (chunks past the
calibrated ones use the global tau). This extends the paper, whose tau is one
number per task.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ddp.keys import KeyedModule
from ddp.registry import register


@dataclass
class DiscrepancyConfig:
    tau: float | None = None  # tau_diff; null = calibrate from ID rollouts
    percentile: float = 99.0  # calibration: tau = margin * percentile of ID D_R-I values
    margin: float = 1.5
    per_chunk: bool = False  # calibration: one threshold per chunk index (see the module docstring)
    window: int = 1  # per_chunk: neighbouring chunks pooled on each side

    def __post_init__(self):
        if self.tau is not None and self.tau <= 0:
            raise ValueError(f"tau must be > 0 or null; got {self.tau}")
        if not 0 < self.percentile <= 100:
            raise ValueError(f"percentile must be in (0, 100]; got {self.percentile}")
        if self.window < 0:
            raise ValueError(f"window must be >= 0; got {self.window}")
        if self.per_chunk and self.tau is not None:
            raise ValueError("per_chunk thresholds are calibrated from ID rollouts: set tau to null")


@register("detector", "discrepancy", config=DiscrepancyConfig)
class DiscrepancyDetector(KeyedModule):
    """OOD iff D_R-I(t) = ||O_real^t - O_pred^t||^2 > tau (paper eq. for D_R-I)."""

    default_in_keys = {"discrepancy": ("ddp", "discrepancy"), "chunk_index": "chunk_index"}
    default_out_keys = {"ood": ("ddp", "ood")}
    sticky = True  # once OOD, stay until recovery and a re-check say otherwise
    needs_discrepancy = True

    def __init__(self, config: DiscrepancyConfig):
        super().__init__()
        self.config = config
        self.tau = config.tau
        self.tau_per_chunk: list[float] | None = None  # set by a per_chunk calibration

    @property
    def needs_calibration(self) -> bool:
        """No threshold yet (``tau: null``): ``ddp eval`` calibrates it from ID rollouts."""
        return self.tau is None

    def calibrate(self, values, chunks=None) -> float:
        """Set tau from D_R-I values observed in ID rollouts; return the global tau.

        ``chunks``: the chunk index of each value; with ``per_chunk`` it also sets ``tau_per_chunk``.
        """
        cfg = self.config
        values = np.asarray(values, dtype=np.float64)
        if values.size == 0:
            raise ValueError("cannot calibrate tau from zero D_R-I values")
        self.tau = float(cfg.margin * np.percentile(values, cfg.percentile))
        self.tau_per_chunk = None
        if cfg.per_chunk:
            if chunks is None or len(chunks) != values.size:
                raise ValueError("per_chunk calibration needs the chunk index of every D_R-I value")
            chunks = np.asarray(chunks, dtype=np.int64)
            taus = []
            for c in range(int(chunks.max()) + 1):
                near = values[np.abs(chunks - c) <= cfg.window]
                taus.append(float(cfg.margin * np.percentile(near, cfg.percentile)) if near.size else self.tau)
            self.tau_per_chunk = taus
        return self.tau

    def calibration(self) -> dict:
        """The thresholds in force (``tau``, and ``tau_per_chunk`` or None), e.g. to hand to another detector."""
        return {"tau": self.tau, "tau_per_chunk": self.tau_per_chunk}

    def load_calibration(self, calibration: dict) -> None:
        self.tau = calibration["tau"]
        self.tau_per_chunk = calibration.get("tau_per_chunk")

    def threshold(self, chunk_index: torch.Tensor | None) -> torch.Tensor | float:
        """tau for each environment's chunk (the global tau past the calibrated chunks)."""
        if self.tau_per_chunk is None or chunk_index is None:
            return self.tau
        table = torch.tensor([*self.tau_per_chunk, self.tau], dtype=torch.float32)
        idx = chunk_index.reshape(-1).long().clamp(0, len(self.tau_per_chunk))
        return table[idx]

    def forward(self, td):
        if self.tau is None:
            raise RuntimeError(
                "detector 'discrepancy' has no threshold: set controller.detector.tau, "
                "or calibrate it from ID rollouts (ddp eval does this when tau is null)"
            )
        discrepancy = td.get(self.key("discrepancy"))
        chunk_index = td.get(self.key("chunk_index"), None)
        threshold = self.threshold(chunk_index)
        if isinstance(threshold, torch.Tensor):
            threshold = threshold.to(discrepancy.device).reshape(discrepancy.shape)
        td.set(self.key("ood"), discrepancy > threshold)
        return td

    def reset(self):
        pass
