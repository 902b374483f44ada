"""Expert demonstrations generated once and cached on disk: the shared machinery of expert data sources.

A data source such as ``metaworld_expert`` or ``adroit_expert`` subclasses
:class:`CachedExpertDemos` and says three things: which env plugin it needs
(``env_name``), which env options only matter at evaluation (``eval_only``:
reset to their defaults for the demos and left out of the cache hash) and
how to build the expert (``make_expert``). The rest is here:

* rollouts through :func:`ddp.data.demos.generate_demos` (successful
  episodes only, attempt ``i`` seeded ``seed + i``);
* the cache directory ``path`` (formatted with ``{task}``, ``{episodes}``,
  ``{seed}``, ``{num_points}``, ``{image_size}`` where the env config has
  them) holding the episodes and ``generation.json``: the generation
  parameters, their hash, the stats of the run;
* ``load()`` memory-maps a matching cache (one with more episodes serves
  its first ones: generation is sequential) and regenerates otherwise; a
  damaged cache is regenerated once;
* the cache is written to a temporary sibling directory and renamed into
  place, so an interrupted run never leaves a half-written cache, and a
  directory that is not a cache of this format is never overwritten;
* checking, (re)generating and mapping happen under an exclusive ``flock``
  on the sibling file ``.<name>.lock``, so runs started together on one
  machine (``ddp suite --workers``, a local Ray) wait for the first one's
  demos instead of generating the same cache again, and a run with other
  settings on the same path cannot replace the cache between another's
  check and its read.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ClassVar

from ddp.atomic_file import atomic_directory
from ddp.config import to_dict, without_neutral_defaults
from ddp.data.demos import generate_demos
from ddp.data.episodes import Episodes
from ddp.errors import DDPError, RecipeError
from ddp.file_lock import exclusive_lock
from ddp.schema import Part

__all__ = ["CachedDemosConfig", "CachedExpertDemos", "GENERATION_FILE", "demo_env_config"]

log = logging.getLogger(__name__)

GENERATION_FILE = "generation.json"


@dataclass
class CachedDemosConfig:
    """Options every cached expert source has (subclass it to change defaults or add options).

    Attributes:
        episodes: successful demonstrations to keep.
        max_steps: steps per episode at most (null: the env's episode length).
        stop_after_success: end an episode this many steps after the first success
            (null: the full ``max_steps`` length).
        seed: seed of the first attempt (attempt i uses seed + i); null: the recipe's seed.
        path: cache directory; ``{task}``, ``{episodes}``, ``{seed}``, ``{num_points}`` and
            ``{image_size}`` are filled in.
        regenerate: ignore a matching cache and generate again.
        max_attempts: give up after this many episodes (null: 2 * episodes + 10).
    """

    episodes: int = 50
    max_steps: int | None = 200
    stop_after_success: int | None = 10
    seed: int | None = 0
    path: str = "data/{task}"
    regenerate: bool = False
    max_attempts: int | None = None

    def __post_init__(self):
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1; got {self.episodes}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1 or null; got {self.max_steps}")
        if self.stop_after_success is not None and self.stop_after_success < 0:
            raise ValueError(f"stop_after_success must be >= 0 or null; got {self.stop_after_success}")
        if self.max_attempts is not None and self.max_attempts < self.episodes:
            raise ValueError(f"max_attempts must be >= episodes ({self.episodes}); got {self.max_attempts}")
        if not self.path:
            raise ValueError("path must not be empty")


def demo_env_config(env_config, max_steps: int, eval_only: tuple[str, ...]):
    """The env config used for demos: the recipe's, with ``eval_only`` options at their defaults.

    A point cloud is rendered at every step (all frames are training data) and
    episodes last ``max_steps``.
    """
    fields = {f.name: f for f in dataclasses.fields(env_config)}
    defaults = {}
    for name in eval_only:
        if name in fields:
            f = fields[name]
            defaults[name] = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    extra = {k: v for k, v in {"render_point_cloud": True, "max_episode_steps": max_steps}.items() if k in fields}
    return dataclasses.replace(env_config, **defaults, **extra)


def _digest(data) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


class CachedExpertDemos:
    """Base of expert data sources whose demos are generated by rollouts and cached under ``path``.

    Subclasses set ``name`` (the data plugin's name), ``env_name`` (the env plugin
    they need), ``cache_format``/``cache_version`` (bump the version when the stored
    arrays change meaning), ``eval_only``, ``record_keys`` and implement
    ``make_expert()``; ``check_task(task)`` may validate the recipe's task dimensions.
    """

    name: ClassVar[str] = ""
    env_name: ClassVar[str] = ""
    cache_format: ClassVar[str] = ""
    cache_version: ClassVar[int] = 1
    eval_only: ClassVar[tuple[str, ...]] = ()
    record_keys: ClassVar[dict] = {"point_cloud": "point_cloud", "agent_pos": "agent_pos"}
    #: distributions whose versions decide the demos (the simulator, the expert): recorded in the cache, and a
    #: cache made under other versions is used with a warning (``data.regenerate=true`` makes it again)
    software: ClassVar[tuple[str, ...]] = ("mujoco",)

    def __init__(self, config: CachedDemosConfig, *, task, seed: int = 0, env=None):
        if env is None or env.plugin.name != self.env_name:
            got = "no env section" if env is None else f"env '{env.plugin.name}'"
            raise RecipeError(
                f"data '{self.name}' needs a {self.env_name} env section (env: {{name: {self.env_name}, ...}}); "
                f"got {got}",
                key="env",
            )
        self.check_task(task)
        if config.max_steps is None:
            config = dataclasses.replace(config, max_steps=self.env_horizon(env.config))
        self.cfg = config
        self.env_part = env
        self.seed = config.seed if config.seed is not None else seed
        self.env_config = demo_env_config(env.config, config.max_steps, self.eval_only)
        ec = self.env_config
        fields = {
            "task": getattr(ec, "task", self.env_name), "episodes": config.episodes, "seed": self.seed,
            "num_points": getattr(ec, "num_points", ""), "image_size": getattr(ec, "image_size", ""),
        }  # fmt: skip
        try:
            self.path = Path(config.path.format(**fields))
        except (KeyError, IndexError, ValueError) as err:
            raise RecipeError(
                f"data.path {config.path!r}: unknown placeholder {err} (use {', '.join('{' + k + '}' for k in fields)})",
                key="data.path",
            ) from None
        self.stats: dict | None = None

    # ---------------------------------------------------------- subclass hooks
    def check_task(self, task) -> None:
        """Raise a RecipeError when the recipe's task dimensions do not match the demos."""

    def env_horizon(self, env_config) -> int:
        """Episode length used when ``max_steps`` is null: the env's ``max_episode_steps``."""
        return int(env_config.max_episode_steps)

    def make_expert(self) -> Callable:
        """The expert: ``tensordict -> action`` (optionally with ``reset()``)."""
        raise NotImplementedError(f"{type(self).__name__} must implement make_expert()")

    @property
    def label(self) -> str:
        return str(getattr(self.env_config, "task", self.env_name))

    # ------------------------------------------------------------- identity
    def generation_params(self) -> dict:
        """What the cached demos depend on (compared with ``<path>/generation.json``)."""
        env_cfg = to_dict(self.env_config)
        # env options added after caches were written leave the hash alone at their default value, so
        # the demos cached before them stay valid (an env config declares them in ``cache_neutral_defaults``)
        env_cfg = without_neutral_defaults(env_cfg, type(self.env_config))
        return {
            "format": self.cache_format,
            "version": self.cache_version,
            "task": self.label,
            "seed": self.seed,
            "max_steps": self.cfg.max_steps,
            "stop_after_success": self.cfg.stop_after_success,
            "env_config": env_cfg,
            "env_config_hash": _digest(env_cfg),
        }

    def software_versions(self) -> dict[str, str | None]:
        """The installed version of each distribution in ``software`` (None: not installed)."""
        from importlib.metadata import PackageNotFoundError, version

        versions = {}
        for dist in self.software:
            try:
                versions[dist] = version(dist)
            except PackageNotFoundError:
                versions[dist] = None
        return versions

    def _warn_if_other_software(self, meta: dict) -> None:
        """One warning when the cache was generated under other versions of ``software`` than installed (a cache
        written before versions were recorded says nothing)."""
        recorded = meta.get("software")
        if not isinstance(recorded, dict):
            return
        now = self.software_versions()
        changed = [f"{d} {recorded.get(d)} (now {v})" for d, v in now.items() if recorded.get(d) != v]
        if changed:
            warnings.warn(f"{self.path}: demos generated under {', '.join(changed)}; they may differ from what "
                          f"this install makes (data.regenerate=true makes them again)", RuntimeWarning, stacklevel=4)

    @property
    def states_per_draw(self) -> int | None:
        """Seeds this far apart repeat an initial state in the demo env (None: they never do, or the env config
        has no ``demo_initial_states(block)`` to draw further ones from)."""
        period = getattr(self.env_config, "initial_states_per_draw", None)
        return period if period is not None and callable(getattr(self.env_config, "demo_initial_states", None)) else None

    def _matches(self, meta: dict) -> bool:
        want = self.generation_params()
        keys = ("format", "version", "task", "seed", "max_steps", "stop_after_success", "env_config_hash")
        if not (all(meta.get(k) == want[k] for k in keys) and int(meta.get("episodes", 0)) >= self.cfg.episodes):
            return False
        return not self._replays_states(meta)

    def _replays_states(self, meta: dict) -> bool:
        """A cache written before attempts moved to another draw past ``states_per_draw``: its seeds that far
        past the first one replayed earlier states (the same demo twice), so it is regenerated. Caches whose
        attempts all fit one draw are what the present code makes, and stay."""
        period, stats = self.states_per_draw, meta.get("stats")
        if period is None or not isinstance(stats, dict) or "states_per_draw" in stats:
            return False
        return any(int(s) - self.seed >= period for s in stats.get("seeds", []))

    def cached_meta(self) -> dict | None:
        """The cache's generation.json if it matches this config, else None."""
        meta_file = self.path / GENERATION_FILE
        if not meta_file.is_file():
            return None
        try:
            meta = json.loads(meta_file.read_text())
        except (OSError, ValueError):
            return None
        try:  # a generation.json of another shape (a list, a text count): not this config's cache
            return meta if isinstance(meta, dict) and self._matches(meta) else None
        except (TypeError, ValueError, AttributeError):
            return None

    # ------------------------------------------------------------ generation
    def make_env(self):
        """The env with the demo config (point cloud rendered at every step)."""
        return Part(self.env_part.plugin, self.env_config).build(seed=self.seed)  # checked against the env contract

    def make_block_env(self, block: int):
        """The demo env drawing block ``block``'s initial states (the env config's ``demo_initial_states``)."""
        config = dataclasses.replace(self.env_config, **self.env_config.demo_initial_states(block))
        return Part(self.env_part.plugin, config).build(seed=self.seed)

    def generate(self, progress: bool = True) -> tuple[Episodes, dict]:
        """Generate the demos in memory (no cache): ``(episodes, stats)``."""
        demos, stats = generate_demos(
            self.make_env,
            self.make_expert(),
            episodes=self.cfg.episodes,
            seed=self.seed,
            max_steps=self.cfg.max_steps,
            keep_only_success=True,
            progress=progress,
            stop_after_success=self.cfg.stop_after_success,
            max_attempts=self.cfg.max_attempts,
            record_keys=self.record_keys,
            desc=f"demos {self.label}",
            states_per_draw=self.states_per_draw,
            make_block_env=self.make_block_env,
        )
        self.stats = stats
        return demos, stats

    def _check_path_is_ours(self) -> None:
        path = self.path
        if path.exists() and not (path / GENERATION_FILE).is_file():
            if not path.is_dir() or any(path.iterdir()):
                raise DDPError(
                    f"{path}: exists and is not a {self.name} demo cache (no {GENERATION_FILE}); "
                    "choose another data.path or remove it"
                )

    def save(self, demos: Episodes, stats: dict) -> Path:
        """Write the cache atomically: a temporary sibling directory renamed onto ``path``."""
        path = self.path
        self._check_path_is_ours()

        def write(tmp: Path) -> None:
            demos.save(tmp)
            meta = {**self.generation_params(), "episodes": demos.num_episodes, "stats": stats,
                    "software": self.software_versions(), "created": time.time()}
            (tmp / GENERATION_FILE).write_text(json.dumps(meta, indent=1))

        return atomic_directory(path, write)

    def prepare(self, progress: bool = True, regenerate: bool | None = None) -> dict:
        """Make sure the cache holds the demos; generate and save them if needed.

        Returns ``{"path", "generated" (bool), "episodes" (what ``load()`` returns),
        "cache_episodes" (what the cache holds), "stats"}`` (``stats`` of the run
        that generated the cache).
        """
        with exclusive_lock(self.path):  # another process generating this cache: wait for it, then use it
            return self._prepare_locked(progress, regenerate)

    def _prepare_locked(self, progress: bool, regenerate: bool | None) -> dict:
        """:meth:`prepare`'s work; the caller holds the cache's lock."""
        regenerate = self.cfg.regenerate if regenerate is None else regenerate
        meta = None if regenerate else self.cached_meta()
        generated = meta is None
        if generated:
            self._check_path_is_ours()
            log.info("generating %d %s demos into %s", self.cfg.episodes, self.label, self.path)
            demos, stats = self.generate(progress=progress)
            self.save(demos, stats)
            meta = {"episodes": demos.num_episodes, "stats": stats}
        else:
            self._warn_if_other_software(meta)
        return {
            "path": self.path,
            "generated": generated,
            "episodes": min(self.cfg.episodes, int(meta["episodes"])),
            "cache_episodes": int(meta["episodes"]),
            "stats": meta["stats"],
        }

    def load(self) -> Episodes:
        """The demos, memory-mapped from the cache (generated first if missing or stale). The cache is
        checked and mapped under its lock: another run replacing it (other settings, one path) waits, and
        the mapping keeps the files it opened."""
        with exclusive_lock(self.path):
            info = self._prepare_locked(progress=True, regenerate=None)
            try:
                demos = Episodes.load(self.path)
            except Exception as err:  # noqa: BLE001 - a damaged cache is regenerated once
                if info["generated"]:
                    raise
                log.warning("%s: unreadable demo cache (%s); regenerating", self.path, err)
                self._prepare_locked(progress=True, regenerate=True)
                demos = Episodes.load(self.path)
        if demos.num_episodes > self.cfg.episodes:  # a larger cache: its first episodes are ours
            demos = Episodes(demos.steps[: int(demos.episode_ends[self.cfg.episodes - 1])],
                             demos.episode_ends[: self.cfg.episodes].clone())  # fmt: skip
        return demos
