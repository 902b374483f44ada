"""What a protocol is (:class:`EvalProtocol`), and the lookups evaluation makes."""

from __future__ import annotations

from dataclasses import dataclass, field

from ddp import registry
from ddp.errors import RecipeError


@dataclass(frozen=True)
class EvalProtocol:
    """An evaluation condition: how the env is set up and how the controller is configured."""

    env: dict = field(default_factory=dict)  # env config overrides (an env without such a field is an error)
    env_if_supported: dict = field(default_factory=dict)  # overrides applied only where the env has the field
    detector: dict | None = None  # a detector section; None: the recipe's
    imagine: bool | None = None  # None: the recipe's; True: the protocol is imagination (needs a world model)
    tracker: bool = True  # False: no tracker and no recovery
    occlusion: bool = False  # blind the camera at eval.occlusion_chunk for eval.occlusion_chunks
    env_tracking: bool = False  # honour eval.env_oracle_tracking (the env's own oracle tracks)
    # the condition is DDP's (its forecasts, D_R-I or imagination): a model without a world model is refused
    # rather than run as another protocol under this name (optional for plugins: absent reads False)
    needs_world_model: bool = False


@dataclass
class NoOptions:
    """Protocols take no options: a recipe names them in ``eval.protocols``."""


def get_protocol(name: str, *, source: str | None = None, key: str | None = None) -> EvalProtocol:
    """The registered protocol ``name`` (one line, with the closest names, when unknown)."""
    from ddp.contracts import check

    plugin = registry.get("protocol", str(name), source=source, key=key)
    protocol = plugin.factory(plugin.config_cls())
    check("protocol", protocol, name=plugin.name, module=plugin.module)
    return protocol


def check_protocols(names, *, source: str | None, key: str | None = None) -> None:
    """One line for the first unknown protocol name."""
    for name in names:
        if not isinstance(name, str) or not name:
            raise RecipeError(f"a protocol name must be a non-empty string; got {name!r}", source=source, key=key)
        registry.get("protocol", name, source=source, key=key)


def check_protocols_for_model(names, *, has_world_model: bool, source: str | None, key: str | None = None) -> None:
    """One line for a protocol named twice, or one the model cannot run: an imagination protocol, or one of
    DDP's conditions (``needs_world_model``), on a model without a world model."""
    names = list(names)
    for name in names:
        if names.count(name) > 1:
            raise RecipeError(f"protocol {name} is named twice", source=source, key=key)
    for name in names:
        protocol = get_protocol(name, source=source, key=key)
        if protocol.imagine and not has_world_model:
            raise RecipeError(f"protocol {name} acts on imagined latents: it needs a world model "
                              "(world_model.enabled is false)", source=source, key=key)
        if getattr(protocol, "needs_world_model", False) and not has_world_model:
            raise RecipeError(f"protocol {name} is DDP's (forecasts, D_R-I, imagination): it needs a world model "
                              "(world_model.enabled is false; the DP3 ablation's tracking is ood_tracking)",
                              source=source, key=key)
