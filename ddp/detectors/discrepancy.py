"""The paper's OOD detector: real-imagination discrepancy D_R-I above a threshold tau."""

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

    def __post_init__(self):
        if self.tau is not None and self.tau <= 0:
            raise ValueError(f"tau must be > 0 or null; got {self.tau}")
        if not 0 < self.percentile <= 100:
            raise ValueError(f"percentile must be in (0, 100]; got {self.percentile}")


@register("detector", "discrepancy", config=DiscrepancyConfig)
class DiscrepancyDetector(KeyedModule):
    """OOD iff D_R-I(t) = ||O_real^t - O_pred^t||^2 > tau (paper eq. for D_R-I)."""

    default_in_keys = {"discrepancy": ("ddp", "discrepancy")}
    default_out_keys = {"ood": ("ddp", "ood")}
    sticky = True  # once OOD, stay until recovery and a re-check say otherwise
    needs_discrepancy = True

    def __init__(self, config: DiscrepancyConfig):
        super().__init__()
        self.config = config
        self.tau = config.tau

    def calibrate(self, values) -> float:
        """Set tau from D_R-I values observed in ID rollouts."""
        values = np.asarray(values, dtype=np.float64)
        if values.size == 0:
            raise ValueError("cannot calibrate tau from zero D_R-I values")
        self.tau = float(self.config.margin * np.percentile(values, self.config.percentile))
        return self.tau

    def forward(self, td):
        if self.tau is None:
            raise RuntimeError(
                "detector 'discrepancy' has no threshold: set controller.detector.tau, "
                "or calibrate it from ID rollouts (ddp eval does this when tau is null)"
            )
        td.set(self.key("ood"), td.get(self.key("discrepancy")) > self.tau)
        return td

    def reset(self):
        pass
