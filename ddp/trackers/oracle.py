"""Oracle tracker: the simulator's applied displacement of every target object."""

from __future__ import annotations

from dataclasses import dataclass

from ddp.keys import KeyedModule
from ddp.registry import register


@dataclass
class OracleTrackerConfig:
    pass


@register("tracker", "oracle", config=OracleTrackerConfig)
class OracleTracker(KeyedModule):
    """Delta p_Cj = p_Cj - p_Cj^exp read from the privileged simulator state ([*, K, 3])."""

    default_in_keys = {"displacement": ("privileged", "displacement")}
    default_out_keys = {"offsets": ("ddp", "offsets")}

    def __init__(self, config: OracleTrackerConfig):
        super().__init__()
        self.config = config

    def forward(self, td):
        td.set(self.key("offsets"), td.get(self.key("displacement")).clone())
        return td

    def reset(self):
        pass
