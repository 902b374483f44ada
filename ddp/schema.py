"""The recipe schema: top-level sections as config dataclasses.

Sections that name a plugin (``encoder``, ``policy.denoiser``, ...) are
mappings ``{name: <registered name>, <option>: <value>, ...}``; their options
are validated against that plugin's own config dataclass by
:func:`resolve_part`.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

from ddp import registry
from ddp.config import from_dict, to_dict
from ddp.errors import RecipeError


@dataclass
class TaskConfig:
    """Shapes of the task's data: what the environment / data set provides."""

    action_dim: int = 4
    agent_pos_dim: int = 9
    num_points: int = 512
    point_dim: int = 3

    def __post_init__(self):
        for name in ("action_dim", "agent_pos_dim", "num_points", "point_dim"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1; got {getattr(self, name)}")


@dataclass
class PolicyConfig:
    """The diffusion policy head: H-step action chunks from M latent steps."""

    horizon: int = 16  # H
    obs_steps: int = 2  # M
    action_steps: int = 8  # N (executed per call; also the world model's horizon)
    denoiser: dict = field(default_factory=lambda: {"name": "unet1d"})
    scheduler: dict = field(default_factory=lambda: {"name": "ddim"})

    def __post_init__(self):
        if self.obs_steps < 1:
            raise ValueError(f"obs_steps must be >= 1; got {self.obs_steps}")
        if self.action_steps < 1:
            raise ValueError(f"action_steps must be >= 1; got {self.action_steps}")
        if self.action_steps < self.obs_steps:
            raise ValueError(
                f"action_steps must be >= obs_steps = {self.obs_steps} (the env stacks the last obs_steps frames of "
                f"each executed chunk, and the world model's last obs_steps forecast latents are the next "
                f"cycle's history); got {self.action_steps}"
            )
        if self.horizon < self.obs_steps + self.action_steps - 1:
            raise ValueError(
                f"horizon must be >= obs_steps + action_steps - 1 = {self.obs_steps + self.action_steps - 1} "
                f"(the executed chunk is actions[obs_steps-1 : obs_steps-1+action_steps]); got {self.horizon}"
            )


@dataclass
class WorldModelConfig:
    """The diffusion world model head: N future latents from M latents + N actions."""

    enabled: bool = True
    weight: float = 1.0  # lambda in L = L_BC + lambda * L_WM
    # Algorithm 1 encodes the future targets with gradients (true); false encodes them without
    # gradient (cheaper; the encoder then learns from L_WM only through the history latents)
    target_gradient: bool = True
    # beyond the paper (1.0: every sample): L_WM on the batch's first ceil(fraction * B) samples only (a
    # random subset of a shuffled batch; with train.micro_batches, of each micro-batch), so only their future
    # frames are encoded and denoised; L_BC keeps all
    batch_fraction: float = 1.0
    # beyond the paper (0: off, the targets are encoded with every batch): with target_gradient false, the
    # future targets are looked up in a table of every training frame's latent, re-encoded by the current
    # encoder every `target_refresh_every` optimiser steps (targets at most that many steps old); each
    # step then skips encoding its B x N future frames
    target_refresh_every: int = 0
    denoiser: dict = field(default_factory=lambda: {"name": "unet1d_wm"})
    scheduler: dict = field(default_factory=lambda: {"name": "ddim", "clip_sample": False})

    def __post_init__(self):
        if self.weight < 0:
            raise ValueError(f"weight must be >= 0; got {self.weight}")
        if not 0.0 < self.batch_fraction <= 1.0:
            raise ValueError(f"batch_fraction must be in (0, 1]; got {self.batch_fraction}")
        if self.target_refresh_every < 0:
            raise ValueError(f"target_refresh_every must be >= 0 (0: off); got {self.target_refresh_every}")
        if self.target_refresh_every and self.target_gradient:
            raise ValueError("target_refresh_every needs target_gradient: false (a table of latents carries no "
                             "gradient back to the encoder)")


@dataclass
class EMAConfig:
    """Diffusion-Policy-style EMA: decay = 1 - (1 + step / inv_gamma) ** -power, clamped."""

    enabled: bool = True
    power: float = 0.75
    max_value: float = 0.9999
    min_value: float = 0.0
    inv_gamma: float = 1.0
    update_after_step: int = 0

    def __post_init__(self):
        if not 0.0 <= self.min_value <= self.max_value <= 1.0:
            raise ValueError(f"need 0 <= min_value <= max_value <= 1; got {self.min_value}, {self.max_value}")
        if not self.inv_gamma > 0:  # it divides the step count in the decay's power warm-up
            raise ValueError(f"inv_gamma must be > 0; got {self.inv_gamma}")


def check_output_dir(path: str) -> None:
    """An output folder may name the recipe as ``{name}``, nothing else (a typo such as ``{nam}`` was a
    KeyError traceback when the run started)."""
    try:
        path.format(name="x")
    except (KeyError, IndexError, ValueError, AttributeError) as err:
        raise ValueError(f"output_dir {path!r}: only {{name}} (the recipe's name) may be filled in "
                         f"({type(err).__name__}: {err}); write a literal brace as {{{{ or }}}}") from None


@dataclass
class TrainConfig:
    """Optimisation (DP3's defaults: AdamW 1e-4, betas (0.95, 0.999), wd 1e-6, batch 128, 500 warm-up)."""

    batch_size: int = 128
    lr: float = 1e-4
    betas: tuple[float, float] = (0.95, 0.999)
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    epochs: int = 500
    max_steps: int | None = None  # stop early after this many optimiser steps (at most epochs x batches)
    lr_schedule: Literal["cosine", "constant"] = "cosine"
    grad_clip_norm: float | None = None
    checkpoint_every_epochs: int = 50
    log_every_steps: int = 20
    output_dir: str = "runs/{name}"
    device: str = "auto"
    num_threads: int | None = None
    logger: Literal["csv", "tensorboard", "wandb", "none"] = "csv"  # torchrl.record.loggers backends
    autocast_bf16: bool = False  # bf16 autocast of the forward passes (CUDA or CPU)
    compile: bool = False  # torch.compile the loss computation
    # the global batch is split into this many equal micro-batches, each with its own noise stream
    # (gradient accumulation); under torchrun the ranks share them out (ddp.distributed)
    micro_batches: int = 1

    def __post_init__(self):
        check_output_dir(self.output_dir)
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1; got {self.batch_size}")
        if self.micro_batches < 1 or self.batch_size % self.micro_batches:
            raise ValueError(f"micro_batches must be >= 1 and divide batch_size ({self.batch_size}); "
                             f"got {self.micro_batches}")
        if self.lr <= 0:
            raise ValueError(f"lr must be > 0; got {self.lr}")
        if self.epochs < 1:
            raise ValueError(f"epochs must be >= 1; got {self.epochs}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 or null; got {self.max_steps}")
        if self.checkpoint_every_epochs < 1:
            raise ValueError(f"checkpoint_every_epochs must be >= 1; got {self.checkpoint_every_epochs}")
        if self.log_every_steps < 1:
            raise ValueError(f"log_every_steps must be >= 1; got {self.log_every_steps}")
        if self.num_threads is not None and self.num_threads < 1:
            raise ValueError(f"num_threads must be >= 1 or null; got {self.num_threads}")


@dataclass
class SubtaskSpec:
    """A subtask S_j: its target object C_j (index into the env's object list) and completion trigger."""

    target: int | None = 0
    trigger: dict | None = None  # a trigger plugin section; null = the subtask lasts until the episode ends


@dataclass
class ControllerConfig:
    """The inference controller (paper Algorithm 2): which detector, tracker and recovery to use."""

    detector: dict = field(default_factory=lambda: {"name": "discrepancy"})
    tracker: dict | None = field(default_factory=lambda: {"name": "oracle"})
    recovery: dict = field(default_factory=lambda: {"name": "target_specific"})
    subtasks: list[SubtaskSpec] = field(default_factory=lambda: [SubtaskSpec()])
    imagine: bool = True  # act from imagined latents in OOD mode (false: the tracking-only DP3 ablation)
    track: bool = True  # execute the tracking shift a^track on an OOD event
    safe_lift: float = 0.0  # lift (m) before an end-effector shift, to avoid dragging through the table
    forecast_every_cycle: bool = False  # always run the world model (D_R-I diagnostics with any detector)
    forecast_samples: int = 1  # world-model samples per forecast: K > 1 forecasts their mean, and their spread
    # where every cycle needs a forecast (a D_R-I detector, forecast_every_cycle), make it in a background
    # thread while the chunk executes: the robot waits for encode + detect + policy only; the results are
    # those of the inline forecast exactly (the world model has its own noise stream)
    async_forecast: bool = True
    # (("ddp", "latent_pred_std")) lets a detector with spread: true scale residuals by the model's own uncertainty
    # an environment whose observation is not finite and that cannot act from imagination, or whose
    # sampled actions are not finite: "raise" a one-line error, or "hold" (the env's hold action:
    # zero motion, gripper command unchanged). A non-finite action is never emitted either way.
    on_nonfinite: Literal["raise", "hold"] = "raise"
    # beyond the paper, off by default: back to the real stream once every displaced subtask target has been
    # recovered, though D_R-I stays high (a displaced object no subtask targets, e.g. coffee-pull's machine)
    resume_after_recovery: bool = False
    # beyond the paper, off by default: re-check D_R-I on every observation after a failed re-check, while no
    # displaced object awaits its recovery (the paper re-checks once: a blind camera can end in imagination)
    recheck_until_id: bool = False


@dataclass
class EvalConfig:
    """Evaluation protocols and their budget (``ddp eval``)."""

    protocols: list[str] = field(default_factory=lambda: ["id", "ood_tracking", "ood_ddp"])
    episodes: int = 20
    seed: int = 1000  # first environment seed; episode i uses seed + i
    num_envs: int = 1
    max_steps: int | None = None  # env steps per episode (default: the env's own limit)
    calibration_episodes: int = 40  # ID episodes calibrating a detector (half fit its statistic, half set tau)
    # a detector that sets tau on successful ID episodes only, short of them after calibration_episodes:
    # further ID episodes are rolled out, up to this many in all (then a one-line error)
    max_calibration_episodes: int = 160
    occlusion_chunk: int = 3
    occlusion_chunks: int = 2
    parallel: bool = False  # num_envs > 1: one worker process per env (torchrl ParallelEnv) instead of SerialEnv
    device: str = "auto"  # where the controller's networks run: auto (cuda when available), cpu, cuda, cuda:1
    video: bool = False  # record rollout videos labelled with the controller's mode
    video_episodes: int = 2  # recorded episodes per env and protocol
    video_size: int = 256  # pixels (square)
    video_fps: int = 20
    video_camera: str | None = None  # the env's camera name (None: its default)
    output_dir: str = "runs/{name}/eval"
    env: dict = field(default_factory=dict)  # env config overrides for evaluation (e.g. held-out initial states)
    # env config overrides for a detector's calibration rollouts, on top of the id protocol's env; None: the
    # env's own held-out initial states (MetaWorld: the next MT1 draw), so no calibration episode replays an
    # evaluated one; {}: the evaluation's env, on seeds eval.seed + 100000 on
    calibration_env: dict | None = None
    env_oracle_tracking: bool = False  # OOD protocols with tracking: the env's oracle tracks and snaps back

    def __post_init__(self):
        check_output_dir(self.output_dir)
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1; got {self.episodes}")
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1; got {self.num_envs}")
        if self.max_calibration_episodes < self.calibration_episodes:
            raise ValueError(f"max_calibration_episodes must be >= calibration_episodes ({self.calibration_episodes}); "
                             f"got {self.max_calibration_episodes}")
        if self.video_episodes < 0:
            raise ValueError(f"video_episodes must be >= 0; got {self.video_episodes}")
        if self.video_size < 16 or self.video_fps < 1:
            raise ValueError(f"video_size must be >= 16 and video_fps >= 1; got {self.video_size}, {self.video_fps}")


@dataclass
class Recipe:
    """A whole experiment. ``ddp.build(path)`` validates a YAML file into this."""

    name: str
    seed: int = 0
    plugins: list[str] = field(default_factory=list)
    task: TaskConfig = field(default_factory=TaskConfig)
    encoder: dict = field(default_factory=lambda: {"name": "dp3"})
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    ema: EMAConfig = field(default_factory=EMAConfig)
    data: dict | None = None  # the demonstrations' source plugin; training without one is an error
    train: TrainConfig = field(default_factory=TrainConfig)
    env: dict | None = None  # the environment plugin (evaluation, demo generation)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


#: recipe sections holding one plugin each: dotted key -> kind
PART_SECTIONS: dict[str, str] = {
    "encoder": "encoder",
    "policy.denoiser": "denoiser",
    "policy.scheduler": "scheduler",
    "world_model.denoiser": "denoiser",
    "world_model.scheduler": "scheduler",
    "data": "dataset",
    "env": "env",
    "controller.detector": "detector",
    "controller.tracker": "tracker",
    "controller.recovery": "recovery",
}

#: plugin sections that may be null
OPTIONAL_SECTIONS = {"env", "data", "controller.tracker"}


@dataclass
class Part:
    """A resolved plugin section: the registry entry and its validated config."""

    plugin: registry.Plugin
    config: Any

    def build(self, **context):
        """The part, checked against its kind's contract (a factory function is only checkable here)."""
        from ddp.contracts import check

        part = self.plugin.factory(self.config, **context)
        try:
            check(self.plugin.kind, part, name=self.plugin.name, module=self.plugin.module)
        except Exception:
            close = getattr(part, "close", None)  # an env holds a renderer or a robot connection
            if callable(close):
                try:
                    close()
                except Exception:  # noqa: BLE001 - the contract error is the one to report
                    pass
            raise
        return part

    def as_dict(self) -> dict:
        return {"name": self.plugin.name, **to_dict(self.config)}


def resolve_part(kind: str, section: Any, *, key: str, source: str | None) -> Part:
    """Validate a ``{name: ..., **options}`` section against its plugin's config."""
    if isinstance(section, str):
        section = {"name": section}
    if not isinstance(section, dict):
        raise RecipeError(f"expected a mapping with a 'name' key, got {section!r}", source=source, key=key)
    if "name" not in section:
        raise RecipeError(
            f"missing required option 'name' (one of: {', '.join(registry.list_plugins(kind))})",
            source=source,
            key=f"{key}.name",
        )
    name = section["name"]
    if not isinstance(name, str):
        raise RecipeError(f"expected a plugin name, got {name!r}", source=source, key=f"{key}.name")
    plugin = registry.get(kind, name, source=source, key=f"{key}.name")
    options = {k: v for k, v in section.items() if k != "name"}
    return Part(plugin, from_dict(plugin.config_cls, options, key=key, source=source))


def _get(data: dict, dotted: str):
    node = data
    for part in dotted.split("."):
        node = node[part]
    return node


def _set(data: dict, dotted: str, value) -> None:
    *head, last = dotted.split(".")
    node = data
    for part in head:
        node = node[part]
    node[last] = value


def _env_follows_task(part: Part, section, task: TaskConfig) -> Part:
    """An env section that leaves ``num_points`` / ``point_dim`` unset renders what ``task`` says."""
    import dataclasses

    names = {f.name for f in dataclasses.fields(part.config)}
    given = section if isinstance(section, dict) else {}
    fill = {n: getattr(task, n) for n in ("num_points", "point_dim") if n in names and n not in given}
    return Part(part.plugin, dataclasses.replace(part.config, **fill)) if fill else part


def _world_model_unclipped(part: Part, section) -> Part:
    """A world-model scheduler section that leaves ``clip_sample`` unset does not clip: latents are not in
    [-1, 1] (the default section says ``clip_sample: false``; a section of one's own replaces it whole)."""
    names = {f.name for f in dataclasses.fields(part.config)} if dataclasses.is_dataclass(part.config) else set()
    given = section if isinstance(section, dict) else {}
    if "clip_sample" in names and "clip_sample" not in given:
        return Part(part.plugin, dataclasses.replace(part.config, clip_sample=False))
    return part


def _check_cross_section(recipe: Recipe, parts: dict[str, Part], source: str | None) -> None:
    """Rules that span sections: protocol names, and the env's shapes against ``task``."""
    from ddp.protocols.base import check_protocols

    check_protocols(recipe.eval.protocols, source=source, key="eval.protocols")
    env = parts.get("env")
    if env is not None:
        for name in ("num_points", "point_dim"):
            value = getattr(env.config, name, None)
            if value is not None and value != getattr(recipe.task, name):
                raise RecipeError(f"{value} differs from task.{name} ({getattr(recipe.task, name)}): the env would "
                                  f"feed the model clouds it was not built for", source=source, key=f"env.{name}")


def _refuse_code_paths(part: Part, key: str, source: str | None) -> None:
    """An untrusted recipe (read from a checkpoint) may not move a part's options that name code to import
    (config fields with ``metadata={"imports_code": True}``, e.g. foundationpose's repo and module) off
    their defaults: importing them would run that code."""
    config = part.config
    if not dataclasses.is_dataclass(config):
        return
    for f in dataclasses.fields(config):
        if f.metadata.get("imports_code") and getattr(config, f.name) != _default(f):
            raise RecipeError(f"names code to import ({getattr(config, f.name)!r}); a recipe read from a checkpoint "
                              "may set it only when trusted: pass trust_plugins=True (--trust-plugins)",
                              source=source, key=f"{key}.{f.name}")


def _default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else dataclasses.MISSING


def _named_sections(data: dict, source: str | None) -> dict:
    """``data`` with each plugin section that names no plugin (``--set policy.scheduler.num_inference_steps=5``
    on a recipe that leaves the scheduler at its default) started from the default section: its plugin and
    options under the ones given. A section without a default plugin keeps asking for a name."""
    defaults, out = None, data
    for dotted in PART_SECTIONS:
        node = data
        for part in dotted.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or "name" in node:
            continue
        if defaults is None:
            defaults = to_dict(from_dict(Recipe, {"name": "defaults"}, source=source))
        default = _get(defaults, dotted)
        if not isinstance(default, dict) or "name" not in default:
            continue
        if out is data:
            out = copy.deepcopy(data)
        _set(out, dotted, {**default, **node})
    return out


def validate(data: dict, source: str | None, *, import_plugins: bool = True) -> tuple[Recipe, dict[str, Part], dict]:
    """Recipe dataclass, resolved parts, and the fully resolved (defaults filled) dict.

    The modules under ``plugins:`` are imported (that runs their code, like any Python import)
    unless ``import_plugins`` is false, as for a recipe read from a checkpoint nobody vouched for.
    """
    modules = data.get("plugins") or []
    if import_plugins and isinstance(modules, list):
        registry.import_plugin_modules([str(m) for m in modules], source=source)
    data = _named_sections(data, source)
    recipe = from_dict(Recipe, data, source=source)
    resolved = to_dict(recipe)
    parts: dict[str, Part] = {}
    skipped = [] if import_plugins else list(recipe.plugins)
    for dotted, kind in PART_SECTIONS.items():
        if dotted in OPTIONAL_SECTIONS and _get(resolved, dotted) is None:
            continue
        try:
            part = resolve_part(kind, _get(resolved, dotted), key=dotted, source=source)
        except RecipeError as err:
            if skipped and err.reason.startswith("unknown "):
                raise RecipeError(f"{err.reason}; the recipe's plugin modules were not imported "
                                  f"({', '.join(skipped)}): pass trust_plugins=True (--trust-plugins) "
                                  "if you trust their code", source=err.source, key=err.key) from None
            raise
        if dotted == "env":
            part = _env_follows_task(part, _get(resolved, dotted), recipe.task)
        elif dotted == "world_model.scheduler":
            part = _world_model_unclipped(part, _get(resolved, dotted))
        if not import_plugins:
            _refuse_code_paths(part, dotted, source)
        parts[dotted] = part
        _set(resolved, dotted, part.as_dict())
    _check_cross_section(recipe, parts, source)
    for i, sub in enumerate(resolved["controller"]["subtasks"]):
        if sub["trigger"] is not None:
            key = f"controller.subtasks[{i}].trigger"
            part = resolve_part("trigger", sub["trigger"], key=key, source=source)
            parts[key] = part
            sub["trigger"] = part.as_dict()
    return recipe, parts, resolved
