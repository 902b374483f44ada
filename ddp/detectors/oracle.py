"""Oracle detector: knows the disturbance schedule (the paper's simulation protocol)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ddp.keys import KeyedModule
from ddp.registry import register


@dataclass
class OracleDetectorConfig:
    min_displacement: float = 1e-6  # metres; a smaller applied displacement counts as none


@register("detector", "oracle", config=OracleDetectorConfig)
class OracleDetector(KeyedModule):
    """OOD iff the simulator reports a displaced object that has not been recovered yet, or occlusion.

    The paper's MetaWorld evaluation bypasses D_R-I with exactly this oracle
    (Appendix, "Oracle State Transitions"); it reads the privileged keys.
    """

    default_in_keys = {
        "displacement": ("privileged", "displacement"),
        "recovered": ("ddp", "recovered"),
    }
    default_out_keys = {"ood": ("ddp", "ood")}
    sticky = False  # ground truth: re-read every cycle, so in-env oracle snap-backs end OOD mode too
    needs_discrepancy = False

    def __init__(self, config: OracleDetectorConfig):
        super().__init__()
        self.config = config

    def forward(self, td):
        disp = td.get(self.key("displacement"))
        moved = disp.norm(dim=-1) > self.config.min_displacement
        recovered = td.get(self.key("recovered"), torch.zeros_like(moved))
        ood = (moved & ~recovered).any(-1)
        occluded = td.get(("privileged", "occluded"), None)
        if occluded is not None:
            ood = ood | occluded.reshape(ood.shape)
        td.set(self.key("ood"), ood)
        return td

    def reset(self):
        pass
