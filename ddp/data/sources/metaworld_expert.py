"""MetaWorld demonstrations from the task's scripted expert, generated once and cached on disk.

The paper trains on "a fixed dataset of 50 demonstrations per task"
generated DP3-style: MetaWorld's scripted policy
(``metaworld.policies.ENV_POLICY_MAP``) reads the 39-d simulator state (the
env's ``("privileged", "state")``), episodes of at most ``max_steps`` steps
are kept only when they succeed, and each step stores the point cloud and
agent_pos seen *before* its action. A point cloud is rendered at every step
(all frames are training data), whatever the recipe's ``obs_every`` says.

The demos use the recipe's ``env`` section (task, camera, crop, image size,
number of points, MT1 initial states) with the evaluation-only options
neutralised: no displacement, oracle tracking or occlusion, no termination
at success. Their hash (with ``episodes``, ``seed``, ``max_steps`` and
``stop_after_success``) is stored in ``<path>/generation.json``; ``load()``
memory-maps the cache when it matches (a cache with more episodes than asked
for serves the first ones: generation is sequential) and regenerates
otherwise. The cache is written to a temporary directory and renamed into
place, so an interrupted run never leaves a half-written cache.

Seeding: attempt ``i`` resets the env with seed ``seed + i``; the MetaWorld
env maps seed ``s`` to MT1 initial state ``s % 50`` (within
``env.task_indices``). ``seed`` defaults to 0, not to the recipe's seed, so
that training seeds 0, 1, 2 share one dataset as in the paper.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ddp.config import to_dict
from ddp.data.demos import generate_demos
from ddp.data.episodes import Episodes
from ddp.errors import DDPError, RecipeError
from ddp.registry import register

__all__ = ["MetaWorldExpertConfig", "MetaWorldExpertDemos", "MetaWorldExpert", "demo_env_config"]

log = logging.getLogger(__name__)

GENERATION_FILE = "generation.json"
CACHE_FORMAT = "ddp-metaworld-expert"
CACHE_VERSION = 1

#: env options that only matter at evaluation: reset to their defaults for demos (and the cache hash)
_EVAL_ONLY = (
    "obs_every", "obs_history", "chunk_len", "displacement", "displacement_chunk", "displacement_delta",
    "oracle_tracking", "settle_steps", "occlusion_chunk", "occlusion_chunks", "occlusion_mode",
    "terminate_on_success",
)  # fmt: skip


@dataclass
class MetaWorldExpertConfig:
    """Options of the ``metaworld_expert`` data source.

    Attributes:
        episodes: successful demonstrations to keep (the paper: 50; DP3: 10).
        max_steps: steps per episode at most (DP3: 200).
        stop_after_success: end an episode this many steps after the first success
            (null: DP3's full ``max_steps`` length).
        seed: seed of the first attempt (attempt i uses seed + i); null: the recipe's seed.
        path: cache directory; ``{task}``, ``{episodes}``, ``{seed}``, ``{num_points}`` and
            ``{image_size}`` are filled in.
        regenerate: ignore a matching cache and generate again.
        max_attempts: give up after this many episodes (null: 2 * episodes + 10).
    """

    episodes: int = 50
    max_steps: int = 200
    stop_after_success: int | None = 10
    seed: int | None = 0
    path: str = "data/metaworld/{task}"
    regenerate: bool = False
    max_attempts: int | None = None

    def __post_init__(self):
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1; got {self.episodes}")
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1; got {self.max_steps}")
        if self.stop_after_success is not None and self.stop_after_success < 0:
            raise ValueError(f"stop_after_success must be >= 0 or null; got {self.stop_after_success}")
        if self.max_attempts is not None and self.max_attempts < self.episodes:
            raise ValueError(f"max_attempts must be >= episodes ({self.episodes}); got {self.max_attempts}")
        if not self.path:
            raise ValueError("path must not be empty")


def demo_env_config(env_config, max_steps: int):
    """The env config used for demos: the recipe's, with evaluation-only options at their defaults."""
    defaults = {f.name: f.default for f in dataclasses.fields(env_config) if f.name in _EVAL_ONLY}
    return dataclasses.replace(env_config, **defaults, render_point_cloud=True, max_episode_steps=max_steps)


def _digest(data) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


class MetaWorldExpert:
    """MetaWorld's scripted policy as a ``tensordict -> action`` callable (reads ``("privileged", "state")``).

    With ``id_frame=True`` the expert reads the state with the applied displacement and
    end-effector shifts removed (``id_frame_state``): it acts as if nothing had moved, the
    situation the paper's oracle tracking is meant to rescue.
    """

    def __init__(self, task: str, id_frame: bool = False):
        try:
            from metaworld.policies import ENV_POLICY_MAP
        except ImportError as err:
            raise ImportError(f'metaworld demonstrations need metaworld ({err}): pip install "ddp[sim]"') from None
        name = f"{task}-v3"
        if name not in ENV_POLICY_MAP:
            raise ValueError(f"metaworld has no scripted policy for task {task!r}")
        self.policy = ENV_POLICY_MAP[name]()
        self.id_frame = None
        if id_frame:
            from ddp.envs.metaworld_tasks import PAPER_TASKS

            self.id_frame = PAPER_TASKS[task]

    def __call__(self, tensordict) -> np.ndarray:
        state = tensordict.get(("privileged", "state")).detach().cpu().double().numpy()
        if self.id_frame is not None:
            from ddp.envs.metaworld_tasks import id_frame_state

            p = tensordict.get("privileged")
            state = id_frame_state(self.id_frame, state, p["displacement"].numpy(), p["ee_offset"].numpy())
        with warnings.catch_warnings():  # the policies warn that their gains exceed [-1, 1]
            warnings.filterwarnings("ignore", message="Constant")
            action = self.policy.get_action(state)
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def expert_succeeds(env, expert, seed: int) -> bool:
    """Run ``expert`` for one episode of ``env`` from ``seed``; True at the first success."""
    td = env.reset(seed=seed)
    while True:
        td["action"] = torch.as_tensor(expert(td), dtype=torch.float32)
        td = env.step(td)["next"]
        if bool(td["success"]):
            return True
        if bool(td["done"]):
            return False


class MetaWorldExpertDemos:
    """MetaWorld scripted-expert demos (successful episodes only), cached under data/metaworld/<task>."""

    def __init__(self, config: MetaWorldExpertConfig, *, task, seed: int = 0, env=None):
        if env is None or env.plugin.name != "metaworld":
            got = "no env section" if env is None else f"env '{env.plugin.name}'"
            raise RecipeError(
                f"data 'metaworld_expert' needs a metaworld env section (env: {{name: metaworld, task: ...}}); "
                f"got {got}",
                key="env",
            )
        if (task.action_dim, task.agent_pos_dim, task.point_dim) != (4, 9, 3):
            raise RecipeError(
                "metaworld demos have action_dim 4, agent_pos_dim 9, point_dim 3; the recipe's task says "
                f"{task.action_dim}, {task.agent_pos_dim}, {task.point_dim}",
                key="task",
            )
        self.cfg = config
        self.env_part = env
        self.seed = config.seed if config.seed is not None else seed
        self.env_config = demo_env_config(env.config, config.max_steps)
        ec = self.env_config
        self.path = Path(
            config.path.format(
                task=ec.task, episodes=config.episodes, seed=self.seed, num_points=ec.num_points,
                image_size=ec.image_size,
            )
        )  # fmt: skip
        self.stats: dict | None = None

    # ------------------------------------------------------------- identity
    def generation_params(self) -> dict:
        """What the cached demos depend on (compared with ``<path>/generation.json``)."""
        env_cfg = to_dict(self.env_config)
        return {
            "format": CACHE_FORMAT,
            "version": CACHE_VERSION,
            "task": self.env_config.task,
            "seed": self.seed,
            "max_steps": self.cfg.max_steps,
            "stop_after_success": self.cfg.stop_after_success,
            "env_config": env_cfg,
            "env_config_hash": _digest(env_cfg),
        }

    def _matches(self, meta: dict) -> bool:
        want = self.generation_params()
        keys = ("format", "version", "task", "seed", "max_steps", "stop_after_success", "env_config_hash")
        return all(meta.get(k) == want[k] for k in keys) and int(meta.get("episodes", 0)) >= self.cfg.episodes

    def cached_meta(self) -> dict | None:
        """The cache's generation.json if it matches this config, else None."""
        meta_file = self.path / GENERATION_FILE
        if not meta_file.is_file():
            return None
        try:
            meta = json.loads(meta_file.read_text())
        except (OSError, ValueError):
            return None
        return meta if self._matches(meta) else None

    # ------------------------------------------------------------ generation
    def make_env(self):
        """A MetaWorld env with the demo config (point cloud rendered at every step)."""
        return self.env_part.plugin.factory(self.env_config, seed=self.seed)

    def generate(self, progress: bool = True) -> tuple[Episodes, dict]:
        """Generate the demos in memory (no cache): ``(episodes, stats)``."""
        expert = MetaWorldExpert(self.env_config.task)
        demos, stats = generate_demos(
            self.make_env,
            expert,
            episodes=self.cfg.episodes,
            seed=self.seed,
            max_steps=self.cfg.max_steps,
            keep_only_success=True,
            progress=progress,
            stop_after_success=self.cfg.stop_after_success,
            max_attempts=self.cfg.max_attempts,
            record_keys={"point_cloud": "point_cloud", "agent_pos": "agent_pos", "full_state": ("privileged", "state")},
            desc=f"demos {self.env_config.task}",
        )
        self.stats = stats
        return demos, stats

    def _check_path_is_ours(self) -> None:
        path = self.path
        if path.exists() and not (path / GENERATION_FILE).is_file():
            if not path.is_dir() or any(path.iterdir()):
                raise DDPError(
                    f"{path}: exists and is not a metaworld_expert demo cache (no {GENERATION_FILE}); "
                    "choose another data.path or remove it"
                )

    def save(self, demos: Episodes, stats: dict) -> Path:
        """Write the cache atomically: a temporary sibling directory renamed onto ``path``."""
        path = self.path
        self._check_path_is_ours()
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
        try:
            os.chmod(tmp, 0o755)  # mkdtemp makes it private
            demos.save(tmp)
            meta = {**self.generation_params(), "episodes": demos.num_episodes, "stats": stats, "created": time.time()}
            (tmp / GENERATION_FILE).write_text(json.dumps(meta, indent=1))
            old = None
            if path.exists():
                old = path.with_name(f".{path.name}.old-{uuid.uuid4().hex[:8]}")
                os.rename(path, old)
            os.rename(tmp, path)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    def prepare(self, progress: bool = True, regenerate: bool | None = None) -> dict:
        """Make sure the cache holds the demos; generate and save them if needed.

        Returns ``{"path", "generated" (bool), "episodes" (what ``load()`` returns),
        "cache_episodes" (what the cache holds), "stats"}`` (``stats`` of the run
        that generated the cache).
        """
        regenerate = self.cfg.regenerate if regenerate is None else regenerate
        meta = None if regenerate else self.cached_meta()
        generated = meta is None
        if generated:
            self._check_path_is_ours()
            log.info("generating %d %s demos into %s", self.cfg.episodes, self.env_config.task, self.path)
            demos, stats = self.generate(progress=progress)
            self.save(demos, stats)
            meta = {"episodes": demos.num_episodes, "stats": stats}
        return {
            "path": self.path,
            "generated": generated,
            "episodes": min(self.cfg.episodes, int(meta["episodes"])),
            "cache_episodes": int(meta["episodes"]),
            "stats": meta["stats"],
        }

    def load(self) -> Episodes:
        """The demos, memory-mapped from the cache (generated first if missing or stale)."""
        info = self.prepare(progress=True)
        try:
            demos = Episodes.load(self.path)
        except Exception as err:  # noqa: BLE001 - a damaged cache is regenerated once
            if not info["generated"]:
                log.warning("%s: unreadable demo cache (%s); regenerating", self.path, err)
                self.prepare(progress=True, regenerate=True)
                demos = Episodes.load(self.path)
            else:
                raise
        if demos.num_episodes > self.cfg.episodes:  # a larger cache: its first episodes are ours
            demos = Episodes(demos.steps[: int(demos.episode_ends[self.cfg.episodes - 1])],
                             demos.episode_ends[: self.cfg.episodes].clone())  # fmt: skip
        return demos


register("dataset", "metaworld_expert", config=MetaWorldExpertConfig)(MetaWorldExpertDemos)
