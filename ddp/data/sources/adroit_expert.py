"""Adroit demonstrations from the packaged DAPG expert policies, generated once and cached on disk.

DP3 (and the paper, which follows it on Adroit) trains on 10 expert
demonstrations per task. No installable package ships Adroit
demonstrations, so they are generated here: the DAPG expert MLP of the task
(``ddp/assets/adroit/<task>_expert.npz``, Apache-2.0, see the ``NOTICE``
next to it) reads the gymnasium observation (the env's ``("privileged",
"state")``) and its mean action, clipped to [-1, 1], is executed; only
successful episodes are kept, and each step stores the point cloud,
agent_pos and full state seen *before* its action.

The weights are plain NumPy archives loaded with ``np.load(...,
allow_pickle=False)`` from the installed package (``importlib.resources``),
so an installed ``ddp`` needs no other file.

The demos use the recipe's ``env`` section (task, camera, crop, image size,
number of points, agent_pos choice) with the evaluation-only options
neutralised (occlusion, termination at success, chunked rendering).
Episodes last ``max_steps`` (default: the env's horizon, door and hammer
200, pen 100) or end ``stop_after_success`` steps after the first success
(default null: DP3 records whole episodes). Caching (hash in
``<path>/generation.json``, atomic writes, reuse of a larger cache) is
:class:`ddp.data.cached_demos.CachedExpertDemos`.

Seeding: attempt ``i`` resets the env with seed ``seed + i`` (the door
position, nail-board height or pen goal are drawn from it). ``seed``
defaults to 0, not to the recipe's seed, so that training seeds share one
dataset.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np

from ddp.data.cached_demos import CachedDemosConfig, CachedExpertDemos
from ddp.envs.adroit_tasks import ADROIT_TASKS
from ddp.errors import DDPError, RecipeError
from ddp.registry import register

__all__ = ["AdroitExpert", "AdroitExpertConfig", "AdroitExpertDemos", "load_expert_weights"]

CACHE_FORMAT = "ddp-adroit-expert"
CACHE_VERSION = 1

#: env options that only matter at evaluation: reset to their defaults for demos (and the cache hash)
_EVAL_ONLY = ("obs_every", "obs_history", "chunk_len", "occlusion_chunk", "occlusion_chunks", "occlusion_mode",
              "terminate_on_success")  # fmt: skip

_ARRAYS = ("W0", "b0", "W1", "b1", "W2", "b2", "in_shift", "in_scale", "out_shift", "out_scale")


def load_expert_weights(task: str) -> dict[str, np.ndarray]:
    """The packaged DAPG expert of ``task`` as float64 arrays (no pickle: ``allow_pickle=False``)."""
    if task not in ADROIT_TASKS:
        raise ValueError(f"no Adroit expert for task {task!r} (known: {', '.join(ADROIT_TASKS)})")
    spec = ADROIT_TASKS[task]
    ref = resources.files("ddp") / "assets" / "adroit" / spec.expert
    try:
        with ref.open("rb") as f, np.load(f, allow_pickle=False) as npz:
            arrays = {k: np.asarray(npz[k], dtype=np.float64) for k in npz.files}
    except FileNotFoundError:
        raise DDPError(f"ddp/assets/adroit/{spec.expert}: the Adroit expert weights are not installed") from None
    missing = [k for k in _ARRAYS if k not in arrays]
    if missing:
        raise DDPError(f"ddp/assets/adroit/{spec.expert}: missing arrays {missing}")
    if arrays["W0"].shape[1] != spec.state_dim or arrays["W2"].shape[0] != spec.action_dim:
        raise DDPError(
            f"ddp/assets/adroit/{spec.expert}: the MLP maps {arrays['W0'].shape[1]} -> {arrays['W2'].shape[0]}, "
            f"the {task} env has observation {spec.state_dim} and action {spec.action_dim}"
        )
    return arrays


class AdroitExpert:
    """The DAPG expert of an Adroit task as a ``tensordict -> action`` callable (its mean action).

    Reads ``("privileged", "state")``, normalises it ``(obs - in_shift) / (in_scale + 1e-8)``,
    applies ``W2 tanh(W1 tanh(W0 x + b0) + b1) + b2``, de-normalises ``out * out_scale + out_shift``
    and clips to [-1, 1]. Computed in float64.
    """

    def __init__(self, task: str):
        self.task = task
        self.p = load_expert_weights(task)

    def act(self, state: np.ndarray) -> np.ndarray:
        p = self.p
        x = (np.asarray(state, dtype=np.float64) - p["in_shift"]) / (p["in_scale"] + 1e-8)
        h = np.tanh(p["W0"] @ x + p["b0"])
        h = np.tanh(p["W1"] @ h + p["b1"])
        out = p["W2"] @ h + p["b2"]
        return np.clip(out * p["out_scale"] + p["out_shift"], -1.0, 1.0).astype(np.float32)

    def __call__(self, tensordict) -> np.ndarray:
        return self.act(tensordict.get(("privileged", "state")).detach().cpu().double().numpy())


@dataclass
class AdroitExpertConfig(CachedDemosConfig):
    """Options of the ``adroit_expert`` data source.

    Attributes:
        episodes: successful demonstrations to keep (DP3 and the paper: 10).
        max_steps: steps per episode at most (null: the env's ``max_episode_steps``;
            door and hammer 200, pen 100).
        stop_after_success: end an episode this many steps after the first success
            (null: DP3's whole episodes).
        seed: seed of the first attempt (attempt i uses seed + i); null: the recipe's seed.
        path: cache directory; ``{task}``, ``{episodes}``, ``{seed}``, ``{num_points}`` and
            ``{image_size}`` are filled in.
        regenerate: ignore a matching cache and generate again.
        max_attempts: give up after this many episodes (null: 2 * episodes + 10).
    """

    episodes: int = 10
    max_steps: int | None = None
    stop_after_success: int | None = None
    path: str = "data/adroit/{task}"


class AdroitExpertDemos(CachedExpertDemos):
    """Adroit DAPG-expert demos (successful episodes only), cached under data/adroit/<task>."""

    name = "adroit_expert"
    env_name = "adroit"
    cache_format = CACHE_FORMAT
    cache_version = CACHE_VERSION
    software = ("mujoco", "gymnasium-robotics")
    eval_only = _EVAL_ONLY
    record_keys = {"point_cloud": "point_cloud", "agent_pos": "agent_pos", "full_state": ("privileged", "state")}

    def __init__(self, config: AdroitExpertConfig, *, task, seed: int = 0, env=None):
        self._env_config = env.config if env is not None else None
        super().__init__(config, task=task, seed=seed, env=env)

    def check_task(self, task) -> None:
        ec = self._env_config
        want = (ec.task_spec.action_dim, ec.agent_pos_dim, 3)
        if (task.action_dim, task.agent_pos_dim, task.point_dim) != want:
            raise RecipeError(
                f"adroit {ec.task} demos (agent_pos {ec.agent_pos!r}) have action_dim {want[0]}, agent_pos_dim "
                f"{want[1]}, point_dim 3; the recipe's task says {task.action_dim}, {task.agent_pos_dim}, "
                f"{task.point_dim}",
                key="task",
            )

    def make_expert(self) -> AdroitExpert:
        return AdroitExpert(self.env_config.task)


register("dataset", "adroit_expert", config=AdroitExpertConfig)(AdroitExpertDemos)
