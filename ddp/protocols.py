"""Evaluation protocols: the paper's Table 1 conditions, each an env condition plus a controller setting.

==================  ==========================  ==============================================
protocol            environment                 controller
==================  ==========================  ==============================================
id                  in distribution             base policy (detector ``never``)
ood_base            displacement                base policy, no tracking
ood_tracking        displacement                oracle detector + tracking/recovery, real latents
                                                (the paper's "DP3 (Ablation)")
ood_ddp             displacement                the recipe's controller: detect, track, imagine
imagination_10/50/  in distribution             real latents replaced by imagined ones with
100                                             probability 0.1 / 0.5 / 1 after the first chunk
occlusion           camera blind for some       the recipe's detector; imagination through it
                    chunks
==================  ==========================  ==============================================

This module is light (no simulator, no torchrl): recipes are checked against it at build time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ddp.errors import RecipeError, suggest


@dataclass(frozen=True)
class Protocol:
    env: dict = field(default_factory=dict)  # env config overrides
    env_if_supported: dict = field(default_factory=dict)  # overrides applied only where the env has the field
    detector: dict | None = None  # None: the recipe's detector
    imagine: bool | None = None  # None: the recipe's
    tracker: bool = True
    occlusion: bool = False
    env_tracking: bool = False  # honour eval.env_oracle_tracking


PROTOCOLS: dict[str, Protocol] = {
    "id": Protocol(detector={"name": "never"}, tracker=False),
    "ood_base": Protocol(env={"displacement": True}, env_if_supported={"oracle_tracking": False},
                         detector={"name": "never"}, tracker=False),
    "ood_tracking": Protocol(env={"displacement": True}, detector={"name": "oracle"}, imagine=False, env_tracking=True),
    "ood_ddp": Protocol(env={"displacement": True}, env_tracking=True),
    "imagination_10": Protocol(detector={"name": "substitution", "p": 0.1}, tracker=False),
    "imagination_50": Protocol(detector={"name": "substitution", "p": 0.5}, tracker=False),
    "imagination_100": Protocol(detector={"name": "substitution", "p": 1.0}, tracker=False),
    "occlusion": Protocol(occlusion=True, tracker=False),
}


def check_protocols(names, *, source: str | None, key: str | None = None) -> None:
    """One line for the first unknown protocol name, with the closest known one."""
    for name in names:
        if name not in PROTOCOLS:
            raise RecipeError(
                f"unknown protocol {name!r}{suggest(str(name), PROTOCOLS)} (known: {', '.join(PROTOCOLS)})",
                source=source, key=key,
            )
