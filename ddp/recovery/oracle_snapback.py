"""The paper's MetaWorld oracle snap-back (Appendix, "Two-Stage Tracking and Recovery")."""

from __future__ import annotations

from dataclasses import dataclass

from ddp.recovery.target_specific import TargetSpecificConfig, TargetSpecificRecovery
from ddp.registry import register


@dataclass
class OracleSnapbackConfig(TargetSpecificConfig):
    chunk: int = 6  # the pre-defined chunk of Stage 2 (6; 8 for coffee-pull)

    def __post_init__(self):
        if self.chunk < 1:
            raise ValueError(f"chunk must be >= 1; got {self.chunk}")


@register("recovery", "oracle_snapback", config=OracleSnapbackConfig)
class OracleSnapbackRecovery(TargetSpecificRecovery):
    """Snap the end-effector back by -Delta p at a hard-coded chunk (the subtask end of the oracle protocol)."""

    def __init__(self, config: OracleSnapbackConfig):
        super().__init__(config)
        self.trigger_chunk = config.chunk
