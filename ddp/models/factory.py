"""Assemble a DreamDiffusionPolicy from a validated recipe's parts."""

from __future__ import annotations

from ddp.models.ddp_policy import DreamDiffusionPolicy
from ddp.errors import RecipeError
from ddp.schema import Part, Recipe


def build_model(recipe: Recipe, parts: dict[str, Part]) -> DreamDiffusionPolicy:
    task, pol, wm = recipe.task, recipe.policy, recipe.world_model
    import inspect

    context = {"agent_pos_dim": task.agent_pos_dim, "point_dim": task.point_dim}
    try:
        params = inspect.signature(parts["encoder"].plugin.factory).parameters
        if "point_dim" not in params and not any(p.kind is p.VAR_KEYWORD for p in params.values()):
            context.pop("point_dim")  # an encoder written before point_dim was passed
    except (TypeError, ValueError):
        pass
    try:
        encoder = parts["encoder"].build(**context)
    except (ValueError, TypeError) as err:
        raise RecipeError(str(err).splitlines()[0], key="encoder") from None
    latent = encoder.out_dim
    policy_net = parts["policy.denoiser"].build(input_dim=task.action_dim, global_cond_dim=pol.obs_steps * latent)
    wm_net = wm_sched = None
    if wm.enabled:
        wm_net = parts["world_model.denoiser"].build(
            input_dim=latent,
            global_cond_dim=pol.action_steps * task.action_dim,
            local_cond_dim=pol.obs_steps * latent,
        )
        wm_sched = parts["world_model.scheduler"].build()
    # a U-Net halves T at each level: a length it cannot take fails here, not at the first training step
    for net, length, key, what in ((policy_net, pol.horizon, "policy.horizon", "policy.denoiser"),
                                   (wm_net, pol.action_steps, "policy.action_steps",
                                    "world_model.denoiser (it denoises action_steps future latents)")):
        multiple = getattr(net, "length_multiple", 1) if net is not None else 1
        if length % multiple:
            raise RecipeError(f"{length} is not a multiple of {multiple}, which {what} needs (one halving per "
                              f"down_dims level after the first)", key=key)
    return DreamDiffusionPolicy(
        encoder=encoder,
        policy_net=policy_net,
        policy_scheduler=parts["policy.scheduler"].build(),
        world_model_net=wm_net,
        world_model_scheduler=wm_sched,
        action_dim=task.action_dim,
        agent_pos_dim=task.agent_pos_dim,
        point_dim=task.point_dim,
        horizon=pol.horizon,
        obs_steps=pol.obs_steps,
        action_steps=pol.action_steps,
        world_model_weight=wm.weight,
        world_model_target_gradient=wm.target_gradient,
        world_model_batch_fraction=wm.batch_fraction,
        world_model_target_refresh_every=wm.target_refresh_every,
    )
