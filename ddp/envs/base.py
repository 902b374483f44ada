"""One point-cloud env for every simulator and robot: :class:`PointCloudEnv` and the adapter it asks for.

Every env of the library (``synthetic_reach``, ``metaworld``, ``adroit``,
``franka`` in simulation and on hardware) is a one-action-per-step TorchRL
env with the same observation layout and the same episode logic; only the
simulator differs. :class:`PointCloudEnv` owns that shared logic once:

* specs: ``point_cloud`` [num_points, 3], ``agent_pos`` [D], ``success``,
  ``("privileged", ...)`` (the adapter's keys plus ``occluded``), the
  adapter's extra observation keys, a [-1, 1] (or adapter-given) action box,
  ``reward``, ``done`` / ``terminated`` / ``truncated``;
* seeding (:class:`ddp.envs.seeding.EpisodeSeeds`): seed i is layout i, a
  reset without a seed takes the next one, ``_rng`` is the episode's stream;
* a step: decode the action (float64, shape checked, non-finite refused),
  run the scheduled disturbances due before it, step the simulator, count
  the step, update the observation, assemble the output;
* the cloud schedule: the occlusion's blind cloud while
  ``ddp.envs.disturbances.Occlusion.covers`` the step (at reset too), a new
  cloud when ``render_due`` says so (always at reset), else the last one;
* ``terminated`` = success with ``terminate_on_success``, ``truncated`` after
  ``max_episode_steps``.

An adapter (a subclass) provides the simulator, the way the FrankaBackend
split puts a robot behind the Franka env:

=========================  =====================================================
``action_dim``             actions per step (int, set before ``_build_specs``)
``agent_pos_dim``          proprioception size
``_privileged_spec()``     ``{key: spec}`` of its privileged keys
``_sim_reset(seed)``       start the episode (``_rng`` is already the episode's)
``_sim_step(action)``      run one float64 action; return ``(reward, success)``
``_agent_pos()``           proprioception now (array)
``_privileged()``          ``{key: tensor}`` matching ``_privileged_spec``
``_render_cloud()``        a float32 ``[num_points, 3]`` cloud now
``_close_sim()``           free the simulator / renderers / connection
=========================  =====================================================

and may override ``_before_action(t)`` (scheduled disturbances),
``_episode_rng(seed)``, ``_render_due(t)``, ``_extra_spec()`` /
``_render_extras()`` / ``_extra_output()`` (observation keys beside the
cloud, e.g. the Franka tracking camera), ``_action_bounds()`` and
``shift_end_effector`` (the default refuses: no tracking on this env).

The config is a dataclass derived from :class:`ObservationOptions` (the
shared fields: ``num_points``, ``max_episode_steps``, ``terminate_on_success``,
``render_point_cloud``, ``chunk_len``, ``crop_min`` / ``crop_max``,
``occlusion_chunk`` / ``occlusion_chunks`` / ``occlusion_mode``; an env
redeclares a field to change its default), which checks them and builds the
occlusion schedule. A config with ``obs_every`` / ``obs_history`` renders
only the frames a chunked policy reads (``ddp.envs.chunked.chunk_render_config``).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from ddp.config import check_choices
from ddp.envs.disturbances import Occlusion, OcclusionMode
from ddp.envs.seeding import EpisodeSeeds
from ddp.errors import DDPError
from ddp.safety import require_finite

__all__ = ["ObservationOptions", "PointCloudEnv", "render_due"]


def render_due(t: int, obs_every: int, obs_history: int) -> bool:
    """Whether an env configured with ``obs_every`` / ``obs_history`` renders after ``t`` actions:
    the last ``obs_history`` frames of every ``obs_every``-step chunk (and the chunk start)."""
    return t % obs_every == 0 or t % obs_every > obs_every - obs_history


@dataclass
class ObservationOptions:
    """The fields, checks and occlusion schedule shared by every env config (their dataclass base).

    Attributes:
        num_points: points per cloud.
        max_episode_steps: steps before ``truncated`` (an env may resolve None to its task's horizon).
        terminate_on_success: end the episode (``terminated``) at the first success.
        render_point_cloud: return the ``point_cloud`` key (False: proprioception only, fast).
        chunk_len: actions per chunk; disturbance / occlusion chunk ``k`` starts at step ``k * chunk_len``.
        crop_min, crop_max: the workspace box kept in the cloud (and where ``noise`` / ``drop``
            occlusion draws its points).
        occlusion_chunk: first blind chunk (None: no occlusion).
        occlusion_chunks: number of blind chunks.
        occlusion_mode: the blind cloud: ``"zeros"``, ``"drop"`` or ``"noise"``
            (``ddp.envs.disturbances.Occlusion``).
    """

    num_points: int = 512
    max_episode_steps: int | None = 200
    terminate_on_success: bool = False
    render_point_cloud: bool = True
    chunk_len: int = 8
    crop_min: tuple[float, float, float] | None = (-1.0, -1.0, -1.0)
    crop_max: tuple[float, float, float] | None = (1.0, 1.0, 1.0)
    occlusion_chunk: int | None = None
    occlusion_chunks: int = 1
    occlusion_mode: OcclusionMode = "zeros"

    def __post_init__(self):
        self.check_observation_options()

    def check_observation_options(self, positive: tuple[str, ...] = ()) -> None:
        """One-line ``ValueError`` for a bad shared field; ``positive`` names more fields that must be >= 1."""
        names = ("max_episode_steps", "num_points", "chunk_len", "occlusion_chunks", *positive)
        if hasattr(self, "obs_every"):
            names += ("obs_every", "obs_history")
        for name in names:
            value = getattr(self, name)
            if not isinstance(value, numbers.Real) or value < 1:  # None, set from Python, was a TypeError here
                raise ValueError(f"{name} must be a number >= 1; got {value!r}")
        if hasattr(self, "obs_every") and self.obs_history > self.obs_every:
            raise ValueError(f"obs_history ({self.obs_history}) must be <= obs_every ({self.obs_every})")
        lo, hi = self.crop_min, self.crop_max
        if len(lo) != 3 or len(hi) != 3:
            raise ValueError(f"crop_min and crop_max need 3 entries (x, y, z); got {list(lo)} and {list(hi)}")
        if any(a >= b for a, b in zip(lo, hi)):
            raise ValueError(f"crop_min must be below crop_max on every axis; got {list(lo)} and {list(hi)}")
        if self.occlusion_chunk is not None and self.occlusion_chunk < 0:
            raise ValueError(f"occlusion_chunk must be >= 0; got {self.occlusion_chunk}")
        check_choices(self)
        if self.occlusion_chunk is not None and not self.render_point_cloud:
            raise ValueError("occlusion_chunk needs render_point_cloud=True (it corrupts the point cloud)")
        if self.occlusion_chunk is not None and self.max_episode_steps is not None:
            shown = (self.occlusion_chunk + 1) * self.chunk_len  # the first observation it blinds
            if shown >= self.max_episode_steps:  # an "occlusion" protocol would measure an unoccluded episode
                raise ValueError(f"occlusion_chunk {self.occlusion_chunk} is first observed at step {shown} ("
                                 f"{self.chunk_len} actions per chunk): with max_episode_steps "
                                 f"{self.max_episode_steps} no chunk acts on it (it needs max_episode_steps > {shown})")

    def occlusion_schedule(self) -> Occlusion | None:
        """The camera occlusion these options ask for (None: none)."""
        if self.occlusion_chunk is None:
            return None
        return Occlusion(self.occlusion_chunk, self.occlusion_chunks, self.occlusion_mode)


class PointCloudEnv(EpisodeSeeds, EnvBase):
    """The shared episode, observation and spec logic of every env (see the module docstring)."""

    #: used in error messages, e.g. "metaworld env"
    env_name: str = "env"
    action_dim: int
    agent_pos_dim: int

    def __init__(self, config, *, seed: int | None = None, device="cpu"):
        super().__init__(device=device, batch_size=torch.Size([]))
        self.config = config
        self._occlusion_plan: Occlusion | None = config.occlusion_schedule()
        self._init_seeds(seed)
        self._steps = 0
        self._rng = np.random.default_rng(0)
        self._success = False
        self._occluded = False
        self._cloud = np.zeros((config.num_points, 3), dtype=np.float32)

    # ------------------------------------------------------------ tensor helpers
    def _f32(self, x) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x, dtype=np.float32), device=self.device)

    def _flag(self, b) -> torch.Tensor:
        return torch.tensor([bool(b)], dtype=torch.bool, device=self.device)

    def _int(self, i) -> torch.Tensor:
        return torch.tensor([int(i)], dtype=torch.int64, device=self.device)

    def _vec_spec(self, *shape) -> Unbounded:
        return Unbounded(shape=shape, dtype=torch.float32, device=self.device)

    def _flag_spec(self) -> Categorical:
        return Categorical(2, shape=(1,), dtype=torch.bool, device=self.device)

    def _int_spec(self, *shape) -> Unbounded:
        return Unbounded(shape=shape, dtype=torch.int64, device=self.device)

    # ------------------------------------------------------------------- specs
    def _build_specs(self) -> None:
        """The specs of this env; adapters call it at the end of their constructor."""
        cfg, dev = self.config, self.device
        privileged = Composite({**self._privileged_spec(), "occluded": self._flag_spec()}, device=dev)
        obs = {"agent_pos": self._vec_spec(self.agent_pos_dim), "success": self._flag_spec(), "privileged": privileged}
        if cfg.render_point_cloud:
            obs["point_cloud"] = self._vec_spec(cfg.num_points, 3)
        obs.update(self._extra_spec())
        self.observation_spec = Composite(obs, device=dev)
        low, high = self._action_bounds()
        self.action_spec = Bounded(low, high, shape=(self.action_dim,), dtype=torch.float32, device=dev)
        self.reward_spec = self._vec_spec(1)
        self.done_spec = Composite(
            done=self._flag_spec(), terminated=self._flag_spec(), truncated=self._flag_spec(), device=dev
        )

    def _action_bounds(self):
        """The action box; [-1, 1] on every dimension unless the adapter says otherwise."""
        return -1.0, 1.0

    def _extra_spec(self) -> dict:
        return {}

    # -------------------------------------------------------------- TorchRL API
    def _reset(self, tensordict: TensorDictBase | None = None, seed: int | None = None, **kwargs) -> TensorDictBase:
        seed = self._episode_seed(seed)
        self._rng = self._episode_rng(seed)
        self._steps = 0
        self._success = False
        self._sim_reset(seed)
        self._observe(first=True)
        return self._output(reward=None)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().to("cpu", torch.float64).numpy()
        if action.size != self.action_dim:
            raise ValueError(f"{self.env_name}: action needs {self.action_dim} values; got shape {list(action.shape)}")
        action = action.reshape(self.action_dim)
        require_finite("action", action, self.env_name)
        self._before_action(self._steps)
        reward, success = self._sim_step(action)
        self._success = bool(success)
        self._steps += 1
        self._observe(first=False)
        return self._output(reward=float(reward))

    def _episode_rng(self, seed: int) -> np.random.Generator:
        """The episode's random stream (occlusion noise, point sampling)."""
        return np.random.default_rng(seed)

    def _before_action(self, t: int) -> None:
        """Disturbances scheduled before action ``t`` (none by default)."""

    # ------------------------------------------------------------- observation
    def _observe(self, first: bool) -> None:
        """After ``_steps`` actions: the blind cloud while occluded, a new cloud when due, else the last one."""
        cfg, t = self.config, self._steps
        due = first or self._render_due(t)
        if cfg.render_point_cloud:
            occ = self._occlusion_plan
            self._occluded = occ is not None and occ.covers(t, cfg.chunk_len)
            if self._occluded:
                self._cloud = occ.corrupt(cfg.num_points, cfg.crop_min, cfg.crop_max, self._rng)
            elif due:
                self._cloud = self._render_cloud()
        if due:
            self._render_extras()

    def _render_due(self, t: int) -> bool:
        """Whether the frame after ``t`` actions is rendered: with ``obs_every`` / ``obs_history`` on the config
        (ChunkedEnv sets them), only the frames the policy reads; without them, every frame."""
        cfg = self.config
        return render_due(t, getattr(cfg, "obs_every", 1), getattr(cfg, "obs_history", 1))

    def _render_extras(self) -> None:
        """Render observation keys beside the cloud (when a frame is due)."""

    def _extra_output(self) -> dict:
        return {}

    def _output(self, *, reward: float | None) -> TensorDictBase:
        cfg, dev = self.config, self.device
        terminated = self._success and cfg.terminate_on_success
        truncated = self._steps >= cfg.max_episode_steps
        out = {
            "agent_pos": self._f32(self._agent_pos()),
            "success": self._flag(self._success),
            "privileged": {**self._privileged(), "occluded": self._flag(self._occluded)},
            "done": self._flag(terminated or truncated),
            "terminated": self._flag(terminated),
            "truncated": self._flag(truncated),
        }
        if cfg.render_point_cloud:
            out["point_cloud"] = torch.as_tensor(self._cloud.copy(), device=dev)
        out.update(self._extra_output())
        if reward is not None:
            out["reward"] = torch.tensor([reward], dtype=torch.float32, device=dev)
        return TensorDict(out, batch_size=torch.Size([]), device=dev)

    # ------------------------------------------------------------ public API
    @property
    def steps_done(self) -> int:
        """Actions executed since the last reset."""
        return self._steps

    @property
    def episode_seed(self) -> int:
        """The seed of the current episode's reset."""
        return self._seed

    def shift_end_effector(self, delta, *, safe_lift: float = 0.0, settle_steps: int | None = None) -> np.ndarray:
        """Not supported by this env (no tracking): an adapter with an end-effector overrides it."""
        raise DDPError(
            f"the {self.env_name} has no end-effector shift; "
            "use a controller without a tracker (controller.tracker: null)"
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Free the simulator (renderers, EGL contexts, robot connection)."""
        if not self.__dict__.get("_sim_closed", False):
            self.__dict__["_sim_closed"] = True
            self._close_sim()
        super().close(raise_if_closed=raise_if_closed)

    def _close_sim(self) -> None:
        """Free what the adapter holds (nothing by default)."""
