"""A suite file and the runs it expands into: tasks x methods x seeds, each a full recipe.

```yaml
name: metaworld_cpu
tasks:                       # label -> a recipe, or {recipe: PATH, set: [...], benchmark: NAME, protocols: [...]}
  drawer-open: recipes/metaworld/quickstart_ddp.yaml
  button-press: {recipe: recipes/metaworld/quickstart_ddp.yaml, set: [env.task=button-press]}
methods:                     # label -> {overlay: PATH, set: [...], protocols: [...]}; {} = the task recipe
  ddp: {}
  dp3: {overlay: recipes/methods/dp3.yaml, protocols: [id, ood_base, ood_tracking]}
seeds: [0, 1]
protocols: [id, ood_tracking, ood_ddp]   # default for methods without their own (else each recipe's)
episodes: 20                 # per protocol (else each recipe's eval.episodes)
set: [train.max_steps=3000]  # applied to every run, after the task's and the method's
```

A task's ``protocols`` (e.g. no displacement protocols on Adroit) keep, of each method's protocols, those
it lists. An overlay's keys are merged onto the task's recipe (an overlay's own ``base:`` and ``name:``
are ignored), so ``recipes/methods/dp3.yaml`` turns any task recipe into its DP3 baseline.
Each run gets ``name: <suite>_<task>_<method>_s<seed>``, ``seed``, and its own output dir
``runs/suites/<suite>/<task>__<method>__seed<seed>``. Paths in the suite file are relative to the
working directory (the repository root).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from ddp.config import without_neutral_defaults
from ddp.errors import RecipeError
from ddp.shipped import locate

__all__ = ["RunSpec", "SuiteSpec", "load_suite"]

#: recipe settings that say how a run is evaluated, not what it measures: left out of its hash, so a suite
#: can step its environments as a batch (``eval.num_envs``: the same episodes, seeds and noise, about half
#: the evaluation time on a CPU), move them to another device or record videos without
#: running again what is stored (``eval.output_dir`` stays in: the suite derives it from the run's id, and
#: results stored before this list existed keep their hash)
EXECUTION_ONLY = {"eval": ("num_envs", "parallel", "device", "video", "video_episodes", "video_size", "video_fps",
                           "video_camera")}
#: also left out since hash version 2: how often training checkpoints and logs (the weights are the same;
#: a suite may checkpoint more often so that --time-limit loses less), and a recipe's own eval.protocols /
#: eval.episodes where the suite sets them (the suite's values are the ones evaluated)
NOT_MEASURED = {"train": ("checkpoint_every_epochs", "log_every_steps", "logger")}
#: and env options written at the value their env config declares neutral (``cache_neutral_defaults``: options
#: added after results were stored, whose default is what ran before), so that a recipe may spell out such a
#: default (``env.pause_fingers: false``) without making its stored runs another run


def _env_config_class(recipe: dict) -> type | None:
    """The config class of the recipe's env plugin (None when there is none or it is unknown)."""
    env = recipe.get("env")
    if not isinstance(env, dict) or not isinstance(env.get("name"), str):
        return None
    from ddp import registry

    try:
        return registry.get("env", env["name"]).config_cls
    except Exception:  # noqa: BLE001 - an unknown env is reported where the recipe is built, not here
        return None

KNOWN = {"name", "tasks", "methods", "seeds", "protocols", "episodes", "set", "results_dir", "reference"}


def _plain(label) -> bool:
    """Letters, digits, '-' and '_' only (a name that is safe in a path and in a comma-separated list)."""
    return isinstance(label, str) and bool(label) and label.replace("-", "").replace("_", "").isalnum()


@dataclass(frozen=True)
class RunSpec:
    """One training + evaluation run of a suite: everything a worker needs (picklable)."""

    suite: str
    task: str
    method: str
    seed: int
    benchmark: str
    recipe: dict  # the full recipe (bases merged, overlay and overrides applied)
    protocols: tuple[str, ...] | None
    episodes: int | None
    #: re-evaluate only these protocols from the run's checkpoint (``ddp suite --reevaluate``); not its identity
    reevaluate: tuple[str, ...] | None = None

    @property
    def run_id(self) -> str:
        return f"{self.task}__{self.method}__seed{self.seed}"

    @property
    def recipe_hash(self) -> str:
        """What the run is: a changed recipe, protocol list or episode count is another run; a setting of
        how it is evaluated (``EXECUTION_ONLY``) or logged (``NOT_MEASURED``) is not, nor the recipe's own
        ``eval.protocols`` / ``eval.episodes`` where the suite sets them."""
        left_out = {"eval": set(EXECUTION_ONLY["eval"]), **{k: set(v) for k, v in NOT_MEASURED.items()}}
        if self.protocols is not None:
            left_out["eval"].add("protocols")
        if self.episodes is not None:
            left_out["eval"].add("episodes")
        return self._hash(left_out, version=2)

    @property
    def legacy_hash(self) -> str:
        """The hash results were stored under before version 2 (``ResultStore`` accepts it and restamps)."""
        return self._hash({"eval": set(EXECUTION_ONLY["eval"])}, version=1)

    def _hash(self, left_out: dict[str, set], version: int) -> str:
        recipe = {k: ({kk: vv for kk, vv in v.items() if kk not in left_out[k]} if k in left_out and isinstance(v, dict)
                      else v) for k, v in self.recipe.items()}
        config_cls = _env_config_class(self.recipe) if version > 1 else None
        if config_cls is not None:
            recipe["env"] = without_neutral_defaults(recipe["env"], config_cls)
        data = {"recipe": recipe, "protocols": self.protocols, "episodes": self.episodes}
        if version > 1:
            data["hash_version"] = version
        return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class SuiteSpec:
    name: str
    runs: list[RunSpec]
    seeds: list[int]
    tasks: dict[str, str]  # label -> benchmark
    methods: list[str]
    results_dir: Path
    source: str = ""
    protocols: dict[str, list[str] | None] = field(default_factory=dict)
    reference: dict | None = None  # {"label", "values": method -> protocol -> benchmark -> task | avg -> %}


def load_reference(value, *, source: str) -> dict | None:
    """A suite's ``reference`` (published numbers shown beside its results): a YAML file path or the mapping
    itself, ``{label, values: method -> protocol -> benchmark -> task (or avg) -> percent, tolerance}``
    (``tolerance``: the percentage points a result may differ from it and still count as reproduced; 10)."""
    if value is None:
        return None
    from ddp.recipe import _read_yaml

    where = "reference"
    if isinstance(value, str):
        file = locate(value)
        if not file.is_file():
            raise RecipeError(f"reference file not found: {value}", source=source, key=where)
        where, value = value, _read_yaml(file, referenced_by=source)
    if not isinstance(value, dict) or not isinstance(value.get("values"), dict):
        raise RecipeError("must be {label, values: method -> protocol -> benchmark -> task -> percent}",
                          source=source, key=where)
    def mapping(node, path: str) -> dict:
        if node is None:
            return {}
        if not isinstance(node, dict):
            raise RecipeError(f"{path} must be a mapping (method -> protocol -> benchmark -> task -> percent), "
                              f"got {node!r}", source=source, key=where)
        return node

    for m, protocols in mapping(value["values"], "values").items():
        for p, benches in mapping(protocols, m).items():
            for b, tasks in mapping(benches, f"{m}.{p}").items():
                for t, v in mapping(tasks, f"{m}.{p}.{b}").items():
                    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 100:
                        raise RecipeError(f"{m}.{p}.{b}.{t} must be a percentage in [0, 100], got {v!r}",
                                          source=source, key=where)
    tolerance = value.get("tolerance", 10)
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not 0 <= tolerance <= 100:
        raise RecipeError(f"tolerance must be percentage points in [0, 100], got {tolerance!r}",
                          source=source, key=where)
    return {"label": str(value.get("label", "reference")), "values": value["values"], "tolerance": float(tolerance)}


def _strings(value, *, key: str, source: str) -> list[str]:
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise RecipeError(f"must be a list of strings, got {value!r}", source=source, key=key)
    return list(value)


def _overlay(path: str, *, key: str, source: str) -> dict:
    from ddp.recipe import _read_yaml

    file = locate(path)
    if not file.is_file():
        raise RecipeError(f"overlay file not found: {path}", source=source, key=key)
    data = _read_yaml(file, referenced_by=source)
    data.pop("base", None)
    data.pop("name", None)
    return data


def load_suite(path: str | Path) -> SuiteSpec:
    """Read and expand a suite file; one-line ``RecipeError`` naming the offending key."""
    from ddp.errors import suggest
    from ddp.protocols.base import check_protocols, check_protocols_for_model
    from ddp.experiment import blame_override
    from ddp.recipe import _read_yaml, apply_overrides, load_yaml_tree, merge
    from ddp.schema import validate

    source = str(path)
    path = locate(path)
    if not path.is_file():
        raise RecipeError(f"suite file not found: {source}", source=source)
    data = _read_yaml(path)
    unknown = sorted(set(data) - KNOWN)
    if unknown:
        raise RecipeError(f"unknown key '{unknown[0]}'{suggest(unknown[0], KNOWN)} (known: {', '.join(sorted(KNOWN))})",
                          source=source, key=unknown[0])
    name = data.get("name") or Path(path).stem
    if not _plain(name):
        raise RecipeError(f"must be a name of letters, digits, '-' and '_', got {name!r}", source=source, key="name")
    tasks, methods = data.get("tasks"), data.get("methods") or {"default": {}}
    if not isinstance(tasks, dict) or not tasks:
        raise RecipeError("must map task labels to recipes", source=source, key="tasks")
    if not isinstance(methods, dict):
        raise RecipeError("must map method labels to {overlay, set, protocols}", source=source, key="methods")
    # labels name result files and run folders (<task>__<method>__seed<k>) and are chosen by --tasks a,b
    for kind, labels in (("tasks", tasks), ("methods", methods)):
        for label in labels:
            if not _plain(label) or "__" in label or label.startswith("_") or label.endswith("_"):
                raise RecipeError(f"label {label!r} must be letters, digits, '-' and '_' without '__' or an '_' at "
                                  "either end (it names result files and run folders <task>__<method>__seed<k>)",
                                  source=source, key=f"{kind}.{label}")
    seeds = data.get("seeds", [0])
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and not isinstance(s, bool)
                                                           for s in seeds):
        raise RecipeError(f"must be a non-empty list of integers, got {seeds!r}", source=source, key="seeds")
    if len(set(seeds)) != len(seeds):
        raise RecipeError(f"repeats a seed: {seeds}", source=source, key="seeds")
    episodes = data.get("episodes")
    if episodes is not None and (isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1):
        raise RecipeError(f"must be a whole number >= 1, got {episodes!r}", source=source, key="episodes")
    default_protocols = _strings(data.get("protocols"), key="protocols", source=source) or None
    if default_protocols:
        check_protocols(default_protocols, source=source, key="protocols")
    common = _strings(data.get("set"), key="set", source=source)

    runs, task_bench, method_protocols = [], {}, {}
    for label, task in tasks.items():
        if isinstance(task, str):
            task = {"recipe": task}
        if not isinstance(task, dict) or not isinstance(task.get("recipe"), str):
            raise RecipeError("needs a recipe path", source=source, key=f"tasks.{label}")
        extra = sorted(set(task) - {"recipe", "set", "benchmark", "protocols"})
        if extra:
            raise RecipeError(f"unknown key '{extra[0]}' (known: recipe, set, benchmark, protocols)", source=source,
                              key=f"tasks.{label}")
        task_protocols = _strings(task.get("protocols"), key=f"tasks.{label}.protocols", source=source)
        if task_protocols:
            check_protocols(task_protocols, source=source, key=f"tasks.{label}.protocols")
        if not locate(task["recipe"]).is_file():
            raise RecipeError(f"recipe file not found: {task['recipe']}", source=source, key=f"tasks.{label}.recipe")
        base = load_yaml_tree(task["recipe"])
        task_set = _strings(task.get("set"), key=f"tasks.{label}.set", source=source)
        task_bench[label] = str(task.get("benchmark", name))
        for m_label, method in methods.items():
            method = method or {}
            if not isinstance(method, dict):
                raise RecipeError("must be a mapping {overlay, set, protocols}", source=source,
                                  key=f"methods.{m_label}")
            extra = sorted(set(method) - {"overlay", "set", "protocols"})
            if extra:
                raise RecipeError(f"unknown key '{extra[0]}' (known: overlay, set, protocols)", source=source,
                                  key=f"methods.{m_label}")
            recipe = base
            if method.get("overlay"):
                recipe = merge(recipe, _overlay(method["overlay"], key=f"methods.{m_label}.overlay", source=source))
            protocols = _strings(method.get("protocols"), key=f"methods.{m_label}.protocols", source=source)
            if protocols:
                check_protocols(protocols, source=source, key=f"methods.{m_label}.protocols")
            method_protocols[m_label] = protocols or default_protocols
            overrides = task_set + _strings(method.get("set"), key=f"methods.{m_label}.set", source=source) + common
            chosen = method_protocols[m_label]
            if task_protocols:
                chosen = [p for p in (chosen or task_protocols) if p in task_protocols]
                if not chosen:
                    raise RecipeError(f"no protocol of method {m_label!r} is among the task's {task_protocols}",
                                      source=source, key=f"tasks.{label}.protocols")
            for seed in seeds:
                run_dir = f"runs/suites/{name}/{label}__{m_label}__seed{seed}"
                r = apply_overrides(recipe, overrides)
                r = apply_overrides(r, [f"name={name}_{label}_{m_label}_s{seed}", f"seed={seed}"])
                r = merge(r, {"train": {"output_dir": run_dir}, "eval": {"output_dir": f"{run_dir}/eval"}})
                try:  # every run checked before any starts: a typo fails now, not hours in
                    checked, _, _ = validate(r, f"{source} [{label} / {m_label}]", import_plugins=True)
                except RecipeError as err:
                    raise blame_override(err, overrides) from None
                # and the protocols it will be evaluated on (twice, or DDP's without a world model: after training)
                check_protocols_for_model(chosen or checked.eval.protocols,
                                          has_world_model=checked.world_model.enabled, source=source,
                                          key=f"methods.{m_label}.protocols" if chosen else f"tasks.{label}.recipe")
                runs.append(RunSpec(name, label, m_label, seed, task_bench[label], r,
                                    tuple(chosen) if chosen else None, episodes))
    runs.sort(key=lambda r: seeds.index(r.seed))  # seed-major: every task and method once before any repeats
    if data.get("results_dir") is not None and not isinstance(data["results_dir"], str):
        raise RecipeError(f"must be a folder path, got {data['results_dir']!r}", source=source, key="results_dir")
    results_dir = Path(data.get("results_dir") or f"results/suites/{name}")
    reference = load_reference(data.get("reference"), source=source)
    return SuiteSpec(name, runs, list(seeds), task_bench, list(methods), results_dir, source, method_protocols,
                     reference)


def select(suite: SuiteSpec, *, tasks: list[str] | None = None, methods: list[str] | None = None,
           seeds: list[int] | None = None) -> SuiteSpec:
    """The suite restricted to some task labels, method labels and seeds (None: all); an unknown one is a
    one-line RecipeError naming the closest label. Results stay in the same store."""
    from dataclasses import replace

    from ddp.errors import suggest

    for key, wanted, known in (("tasks", tasks, list(suite.tasks)), ("methods", methods, suite.methods),
                               ("seeds", seeds, suite.seeds)):
        for value in wanted or []:
            if value not in known:
                raise RecipeError(f"{value!r} is not in the suite{suggest(str(value), [str(k) for k in known])} "
                                  f"(it has: {', '.join(str(k) for k in known)})", source=suite.source, key=key)
    runs = [r for r in suite.runs if (tasks is None or r.task in tasks) and (methods is None or r.method in methods)
            and (seeds is None or r.seed in seeds)]
    return replace(suite, runs=runs)
