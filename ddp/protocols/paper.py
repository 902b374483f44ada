"""The paper's Table 1 conditions.

==================  ==========================  ==============================================
protocol            environment                 controller
==================  ==========================  ==============================================
id                  in distribution             base policy (detector ``never``)
id_ddp              in distribution             the recipe's controller (its false alarms)
ood_base            displacement                base policy, no tracking
ood_tracking        displacement                oracle detector + tracking/recovery, real latents
                                                (the paper's "DP3 (Ablation)")
ood_ddp             displacement                the recipe's controller: its detector decides
                                                when to track, imagine and recover; nothing in
                                                the env tracks for it
ood_ddp_oracle      displacement                the paper's simulation protocol: oracle
                                                detector, imagination, and the env's oracle
                                                tracking where ``eval.env_oracle_tracking``
imagination_10/50/  in distribution             real latents replaced by imagined ones with
100                                             probability 0.1 / 0.5 / 1 after the first chunk
                                                (whatever controller.imagine)
occlusion           camera blind for some       the recipe's detector; imagination through it
                    chunks
occlusion_oracle    camera blind for some       oracle detector (knows when the camera is
                    chunks                      blind); imagination through it
==================  ==========================  ==============================================

id_ddp, ood_ddp, ood_ddp_oracle and imagination_* refuse a model without a world model (they would
run another condition under DDP's name: ood_ddp_oracle without one is ood_tracking); occlusion and
occlusion_oracle run it on the blind observations (the base policy under occlusion).

Where the env's own oracle tracks (``env_tracking`` and ``eval.env_oracle_tracking``), the
controller runs without its tracker and recovery, so nothing moves the end-effector twice.
"""

from __future__ import annotations

from ddp.protocols.base import EvalProtocol, NoOptions
from ddp.registry import register


def _protocol(name: str, summary: str, **fields):
    def factory(config: NoOptions) -> EvalProtocol:
        return EvalProtocol(**fields)

    factory.__doc__ = summary
    factory.__name__ = factory.__qualname__ = name
    register("protocol", name, config=NoOptions)(factory)


_protocol("id", "in distribution, the base policy (detector never, no tracking)",
          detector={"name": "never"}, tracker=False)
_protocol("ood_base", "displaced objects, the base policy without tracking",
          env={"displacement": True}, env_if_supported={"oracle_tracking": False}, detector={"name": "never"},
          tracker=False)
_protocol("ood_tracking", "displaced objects, oracle detector + tracking and recovery on real latents (DP3 ablation)",
          env={"displacement": True}, detector={"name": "oracle"}, imagine=False, env_tracking=True)
_protocol("id_ddp", "in distribution, the recipe's controller (its detector's false alarms and their cost)",
          needs_world_model=True)
_protocol("ood_ddp", "displaced objects, the recipe's controller: its detector decides when to track, imagine, recover",
          env={"displacement": True}, env_if_supported={"oracle_tracking": False}, needs_world_model=True)
_protocol("ood_ddp_oracle", "displaced objects, the paper's simulation protocol: oracle detector (and the env's "
          "oracle tracking where eval.env_oracle_tracking)", env={"displacement": True}, detector={"name": "oracle"},
          env_tracking=True, needs_world_model=True)
for _p in (10, 50, 100):
    _protocol(f"imagination_{_p}", f"in distribution, real latents replaced by imagined ones with probability "
                                   f"{_p / 100:g} after the first chunk",
              detector={"name": "substitution", "p": _p / 100}, imagine=True, tracker=False)
_protocol("occlusion", "the camera is blind for eval.occlusion_chunks chunks; the recipe's detector",
          occlusion=True, tracker=False)
_protocol("occlusion_oracle", "the camera is blind for eval.occlusion_chunks chunks; the oracle detector",
          occlusion=True, tracker=False, detector={"name": "oracle"})
