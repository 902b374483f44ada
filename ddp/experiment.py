"""``build(recipe)``: a validated recipe turned into an experiment you can train and inspect."""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Iterable

import torch

from ddp.checkpoint import load_checkpoint
from ddp.errors import CheckpointError, DDPError, RecipeError, suggest
from ddp.recipe import dump_yaml, load_recipe
from ddp.schema import Part, validate


class Experiment:
    """What :func:`build` returns.

    Attributes: ``recipe`` (the validated dataclass tree), ``resolved`` (the
    recipe as a plain dict with every default filled in: dump it with
    :meth:`to_yaml` and ``build`` it again to get the same experiment),
    ``parts`` (each plugin section's registry entry and config), ``model``.
    """

    def __init__(self, data: dict, source: str, *, trust_plugins: bool = True):
        self.source = source
        self.recipe, self.parts, self.resolved = validate(data, source, import_plugins=trust_plugins)
        #: the plugin modules imported for this recipe (evaluation workers import the same ones)
        self.plugin_modules: tuple[str, ...] = tuple(self.recipe.plugins) if trust_plugins else ()
        torch.manual_seed(self.recipe.seed)
        from ddp.models.factory import build_model

        try:
            self.model = build_model(self.recipe, self.parts)
        except RecipeError as err:
            raise RecipeError(err.reason, source=err.source or source, key=err.key) from None
        self._episodes = None
        self.checkpoint_path: Path | None = None  # set by load_checkpoint
        self.checkpoint_weights: str | None = None  # "ema" or "raw", set by load_checkpoint

    def __repr__(self) -> str:
        return f"Experiment({self.recipe.name!r}, source={self.source!r})"

    def to_yaml(self) -> str:
        return dump_yaml(self.resolved)

    def save_recipe(self, path: str | os.PathLike) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.to_yaml())
        return path

    def dataset(self):
        """The recipe's data source plugin (``data.name``)."""
        if self.parts.get("data") is None:
            raise RecipeError("this recipe has no data section: name the demonstrations' source, e.g. "
                              "data: {name: metaworld_expert} (ddp list dataset)", source=self.source, key="data")
        return self.parts["data"].build(task=self.recipe.task, seed=self.recipe.seed, env=self.parts.get("env"))

    def make_env(self, seed: int | None = None, **overrides):
        """A new environment from the recipe's ``env`` section (``overrides`` replace config fields)."""
        import dataclasses

        from ddp.errors import RecipeError

        part = self.parts.get("env")
        if part is None:
            raise RecipeError("this recipe has no env section", source=self.source, key="env")
        fields = {f.name for f in dataclasses.fields(part.config)}
        for key in overrides:
            if key not in fields:
                raise RecipeError(f"env '{part.plugin.name}' has no option {key!r}{suggest(key, sorted(fields))}",
                                  source=self.source, key=f"env.{key}")
        config = dataclasses.replace(part.config, **overrides) if overrides else part.config
        return Part(part.plugin, config).build(seed=seed)  # checked against the env contract

    def episodes(self):
        """The demonstrations (loaded once and cached)."""
        if self._episodes is None:
            self._episodes = self.dataset().load()
        return self._episodes

    def train(self, output_dir: str | os.PathLike | None = None, resume: bool = True, progress: bool = True):
        """Train with the recipe's ``train`` section; see :class:`ddp.train.Trainer`.

        Without a checkpoint to resume, training starts from ``model``'s current weights: the seed's
        initialisation after ``build``, or weights loaded with :meth:`load_checkpoint` (fine-tuning). A second
        ``train(resume=False)`` on the same experiment therefore continues from the trained weights; ``build``
        the recipe again for a fresh start. The normaliser is fitted to the demonstrations only when the
        model has none fitted: fine-tuned weights keep the input and action scaling they were trained under."""
        from ddp.train import Trainer

        return Trainer(self, output_dir=output_dir, progress=progress).fit(resume=resume)

    def load_checkpoint(self, path: str | os.PathLike, ema: bool = True, *, state: dict | None = None) -> "Experiment":
        """Load weights (the EMA weights by default, as evaluated in the paper) into ``model``.

        ``state`` is the checkpoint already read from ``path`` (to avoid reading it twice).
        """
        from ddp.checkpoint import describe_mismatch
        from ddp.safety import first_nonfinite
        from ddp.train import describe_changes

        state = load_checkpoint(path) if state is None else state
        if not isinstance(state.get("model"), dict):
            raise CheckpointError(f"{path}: the checkpoint holds no model weights ('model' is missing)")
        weights = state["model"]
        if ema and isinstance(state.get("ema"), dict):
            prefix = "module."
            weights = {k[len(prefix) :]: v for k, v in state["ema"].items() if k.startswith(prefix)}
        mismatch = describe_mismatch(self.model, weights)
        if mismatch:
            raise CheckpointError(f"{path}: weights do not fit this recipe's model: {mismatch}")
        relearned = self._scheduler_changes(path, state)
        if relearned:  # same shapes, other meaning: the weights would load and act wrongly
            raise CheckpointError(f"{path}: the weights were trained under other scheduler settings than this "
                                  f"recipe's ({describe_changes(relearned)}), which define what the network "
                                  f"learned to predict; keep the trained values (sampling options such as "
                                  f"num_inference_steps may differ)")
        bad = first_nonfinite(weights.items())
        if bad is not None:  # checked before loading: the model keeps its weights
            raise CheckpointError(f"{path}: the {'EMA ' if weights is not state['model'] else ''}weights hold NaN "
                                  f"or inf ({bad}): refusing to load them")
        try:
            self.model.load_state_dict(weights)
        except (RuntimeError, TypeError) as err:
            first = str(err).strip().splitlines()[0]
            raise CheckpointError(f"{path}: weights do not fit this recipe's model: {first}") from None
        self.checkpoint_path = Path(path)  # a detector calibration is saved beside it
        self.checkpoint_weights = "raw" if weights is state["model"] else "ema"  # what an evaluation reports
        self._warn_other_task(path, state)
        return self

    def _warn_other_task(self, path, state: dict) -> None:
        """One warning when the checkpoint was trained on another environment or task than this recipe's (its
        weights fit, so it loads: fine-tuning or a cross-task evaluation may mean it; a wrong --checkpoint
        would otherwise file one task's policy under another's results)."""
        import warnings

        from ddp.checkpoint import stored_recipe

        try:
            trained = stored_recipe(path, state).get("env")
        except CheckpointError:
            return
        now = self.resolved.get("env")
        if not (isinstance(trained, dict) and isinstance(now, dict)):
            return
        differ = [f"env.{k}: {trained.get(k)!r} -> {now.get(k)!r}" for k in ("name", "task")
                  if trained.get(k) != now.get(k)]
        if differ:
            warnings.warn(f"{path}: trained on another environment or task than this recipe's ({'; '.join(differ)})",
                          UserWarning, stacklevel=3)

    def _scheduler_changes(self, path, state: dict) -> dict:
        """Scheduler options that define what the checkpoint's networks learned (prediction type, noise schedule,
        flow times) and differ between its stored recipe and this one; each scheduler config declares the
        options free at inference (``free_at_inference``). None checked for a checkpoint without a recipe."""
        from ddp import registry
        from ddp.checkpoint import stored_recipe
        from ddp.recipe import recipe_changes

        if not isinstance(state.get("recipe"), str):
            return {}
        try:
            stored = stored_recipe(path, state)
        except CheckpointError:  # an unreadable stored recipe: nothing to compare (the weights' shapes still are)
            return {}
        out = {}
        for section in ("policy.scheduler", "world_model.scheduler"):
            part = self.parts.get(section)
            if part is None or (section.startswith("world_model") and not self.recipe.world_model.enabled):
                continue
            head = section.split(".")[0]
            before = stored.get(head).get("scheduler") if isinstance(stored.get(head), dict) else None
            if not isinstance(before, dict):
                continue
            free = set(getattr(type(part.config), "free_at_inference", ()))
            try:  # the trained scheduler's own free options (DDPM trained, DDIM sampled: DP3's pairing)
                free |= set(getattr(registry.get("scheduler", before.get("name")).config_cls, "free_at_inference", ()))
            except DDPError:
                pass
            now = (self.resolved.get(head) or {}).get("scheduler") or {}
            for key, change in recipe_changes(before, now).items():
                if key != "name" and key not in free:
                    out[f"{section}.{key}"] = change
        return out

    def _check_simulator_truth(self, env_config, module, key: str) -> None:
        """A part that reads the simulator's truth (a ``("privileged", ...)`` key: object displacements, the
        occlusion flag) refused where the env (``env_config``, the one the episodes run in) has none (its
        ``simulator_truth()`` is False: a real robot, where those keys read zero and the part would silently
        never fire)."""
        truth = getattr(env_config, "simulator_truth", None)
        if module is None or not callable(truth) or truth():
            return
        reads = [k for k in getattr(module, "in_keys", []) if isinstance(k, tuple) and k[:1] == ("privileged",)]
        if reads:
            what = "a protocol's detector " if key == "eval.protocols" else ""
            raise RecipeError(f"{what}'{type(module).__name__}' reads the simulator's {reads[0]}, which this env does "
                              f"not have (a real robot: it reads zero there); use a detector / tracker that works "
                              f"from the observations (e.g. discrepancy, pointcloud, foundationpose), or protocols "
                              f"without an oracle", source=self.source, key=key)

    def make_controller(self, *, detector: dict | None = None, imagine: bool | None = None,
                        track: bool | None = None, tracker: bool = True, seed: int | None = None,
                        forecast_every_cycle: bool | None = None, async_forecast: bool | None = None,
                        env: dict | None = None):
        """The DDP controller (Algorithm 2) around ``model`` from the recipe's ``controller`` section.

        ``detector`` replaces the recipe's detector section (e.g. ``{"name": "never"}``); ``imagine``
        / ``track`` / ``forecast_every_cycle`` / ``async_forecast`` override the recipe's flags; ``tracker=False`` drops
        tracking and recovery. ``env``: the env overrides the controller will run under (``eval.env``, a
        protocol's, ``--env``): parts that read the simulator's truth are checked against that env.
        """
        from ddp.inference import DDPController, Subtask
        from ddp.schema import resolve_part

        c = self.recipe.controller
        env_part = self.parts.get("env")
        # the env contract's action_hold (read from the class: an env may predate it; only "hold" needs it)
        hold = getattr(env_part.plugin.factory, "action_hold", None) if env_part is not None else None
        if c.on_nonfinite == "hold" and hold is None:
            what = f"env '{env_part.plugin.name}' declares no action_hold" if env_part else "the recipe has no env"
            raise RecipeError(f"'hold' needs to know how the env holds still, but {what}", source=self.source,
                              key="controller.on_nonfinite")
        det_part = self.parts["controller.detector"]
        if detector is not None:
            det_part = resolve_part("detector", detector, key="controller.detector", source="<protocol>")
        trk_part = self.parts.get("controller.tracker") if tracker else None
        subtasks = [
            Subtask(target=s.target, trigger=self.parts[f"controller.subtasks[{i}].trigger"].build() if s.trigger else None)
            for i, s in enumerate(c.subtasks)
        ]
        det = det_part.build()
        trk = trk_part.build() if trk_part is not None else None
        env_config = env_part.config if env_part is not None else None
        if env_config is not None and env:
            env_config = dataclasses.replace(env_config, **env)
        self._check_simulator_truth(env_config, det, "controller.detector" if detector is None else "eval.protocols")
        self._check_simulator_truth(env_config, trk, "controller.tracker")
        return DDPController(
            self.model.eval(),
            detector=det,
            tracker=trk,
            recovery=self.parts["controller.recovery"].build() if tracker else None,
            subtasks=subtasks,
            imagine=c.imagine if imagine is None else imagine,
            track=c.track if track is None else track,
            forecast_every_cycle=c.forecast_every_cycle if forecast_every_cycle is None else forecast_every_cycle,
            forecast_samples=c.forecast_samples,
            async_forecast=c.async_forecast if async_forecast is None else async_forecast,
            seed=self.recipe.seed if seed is None else seed,
            on_nonfinite=c.on_nonfinite,
            hold=hold,
            num_points=self.recipe.task.num_points,
            resume_after_recovery=c.resume_after_recovery,
            recheck_until_id=c.recheck_until_id,
        )

    def evaluate(self, protocols=None, **kwargs):
        """Run evaluation protocols; see :func:`ddp.evaluate.evaluate`."""
        from ddp.evaluate import evaluate

        return evaluate(self, protocols, **kwargs)

    def parameter_counts(self) -> dict[str, int]:
        """Parameters per part (encoder, policy, world model) and in total."""
        m = self.model
        counts = {
            "encoder": sum(p.numel() for p in m.encoder.parameters()),
            "policy": sum(p.numel() for p in m.policy_net.parameters()),
        }
        if m.world_model_net is not None:
            counts["world_model"] = sum(p.numel() for p in m.world_model_net.parameters())
        counts["total"] = sum(p.numel() for p in m.parameters())
        return counts


def blame_override(err: RecipeError, overrides: list[str]) -> RecipeError:
    """``err`` re-attributed to the ``--set`` override that wrote its key, if one did."""
    if not err.key:
        return err
    key, under = err.key, []  # under: overrides inside the section the error names (a rule across its options)
    for text in reversed(overrides):  # the last override writing the key wins
        dotted = text.partition("=")[0].strip()
        if key == dotted or key.startswith((dotted + ".", dotted + "[")):
            if not under:
                return RecipeError(err.reason, source=f"--set {text}", key=key)
            break  # it wrote the whole section; later overrides wrote inside it
        if dotted.startswith((key + ".", key + "[")):
            under.append(text)
    # of those, the ones whose option (its last name, without an index) the message names; else all of them

    def option(text: str) -> str:
        return re.sub(r"\[[0-9]+\]", "", text.partition("=")[0].strip()).rsplit(".", 1)[-1]

    named = [t for t in under if re.search(rf"\b{re.escape(option(t))}\b", err.reason)]
    blamed = named[:1] or under
    if not blamed:
        return err
    return RecipeError(err.reason, source=", ".join(f"--set {t}" for t in blamed), key=err.key)


def build(recipe: str | os.PathLike | dict, overrides: Iterable[str] = ()) -> Experiment:
    """Load, validate and assemble a recipe: ``build("recipes/quickstart.yaml")``.

    ``overrides`` are dotted assignments, e.g. ``["policy.scheduler.num_inference_steps=5"]``.
    """
    overrides = list(overrides)
    data, source = load_recipe(recipe, overrides)
    try:
        return Experiment(data, source)
    except RecipeError as err:
        raise blame_override(err, overrides) from None


def experiment_from_checkpoint(path: str | os.PathLike, ema: bool = True, *, trust_plugins: bool = False,
                               overrides: Iterable[str] = ()) -> Experiment:
    """Rebuild the experiment stored inside a checkpoint and load its weights.

    The weights load as plain tensors (never code). The stored recipe's ``plugins:`` modules
    are NOT imported unless ``trust_plugins`` is true: a checkpoint someone sent you would
    otherwise run their code. The modules left out are named in one warning line.
    """
    import warnings

    from ddp.checkpoint import stored_recipe
    from ddp.recipe import apply_overrides

    state = load_checkpoint(path)
    overrides = list(overrides)
    data = apply_overrides(stored_recipe(path, state), overrides)
    modules = data.get("plugins") or []
    if modules and not trust_plugins:
        warnings.warn(f"{path}: not importing the plugin modules its recipe lists ({', '.join(map(str, modules))}); "
                      "pass trust_plugins=True (--trust-plugins) if you trust their code", stacklevel=2)
    try:
        exp = Experiment(data, f"{path}#recipe", trust_plugins=trust_plugins)
    except RecipeError as err:
        raise blame_override(err, overrides) from None
    return exp.load_checkpoint(path, ema=ema, state=state)
