"""One environment step = one action chunk: what the DDP controller talks to.

``ChunkedEnv(base, action_steps=N, obs_steps=M)`` wraps a one-action-per-step
TorchRL env. Its action is ``action`` [N, A] plus ``ee_shift`` [3] (an
end-effector shift requested by the controller's tracking or recovery, zero
for none), executed *before* the chunk through ``base.shift_end_effector``.
Observations are the base env's stacked over the last M steps
(``point_cloud`` [M, P, 3], ``agent_pos`` [M, D]), ``privileged`` from the
last step, ``success`` = any success so far in the episode (revoked for good
once the base env's optional ``failed`` flag is set), ``reward`` = the
chunk's sum, ``chunk_index`` (chunks executed since reset) and, where the base
env tells its episode's seed (an ``episode_seed`` attribute, as every built-in
env has), ``episode_seed`` (int64 [1]): the controller keys each episode's
random streams by it, so an episode draws the same noise whatever env row or
batch size runs it.

The chunk and the frame stack are torchrl's own transforms on the base env:
``UnsqueezeTransform`` + ``CatFrames(N=M)`` stack the last M frames (the
reset frame repeated at the start, as ``padding="same"`` does) and
``MultiAction`` runs the N actions, skipping the rest of a chunk once an
inner step is done. What ``ChunkedEnv`` adds on top: the end-effector
shift before the chunk, the whole-chunk finite check, the episode's
success so far, the chunk counter and the per-step video frames.

When the base env's config has ``obs_every`` / ``obs_history`` fields they
are set to N / M, so point clouds are rendered only for the frames the
policy consumes.

With ``video=VideoSettings(...)`` the first episodes are recorded through the
base env's ``render_rgb`` (one frame per simulated step), each frame labelled
with the controller's decision for its chunk (``ddp.video``).
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.transforms import CatFrames, Compose, MultiAction, Transform, UnsqueezeTransform

from ddp.safety import require_finite
from ddp.video import ChunkLabel, EpisodeRecorder, VideoSettings

STACKED = ("point_cloud", "agent_pos")


def chunk_render_config(config, action_steps: int, obs_steps: int):
    """``config`` with rendering limited to the frames a chunked policy reads (when supported)."""
    names = {f.name for f in dataclasses.fields(config)}
    if {"obs_every", "obs_history"} <= names:
        return dataclasses.replace(config, obs_every=action_steps, obs_history=obs_steps)
    return config


class _EachStep(Transform):
    """Calls ``callback(next_tensordict)`` after every inner step of a chunk (placed before ``MultiAction``)."""

    def __init__(self, callback):
        super().__init__()
        self.callback = callback

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self.callback(next_tensordict)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset


def stacked_chunks(base: EnvBase, obs_steps: int, each_step=None) -> TransformedEnv:
    """``base`` seen through torchrl's transforms: the last ``obs_steps`` frames of ``point_cloud`` /
    ``agent_pos`` stacked on a new leading dim, and an ``[N, A]`` action run as N steps
    (``each_step(next_td)`` after each)."""
    obs = base.observation_spec.keys()
    transforms = []
    for key in STACKED:
        if key in obs:
            dim = -1 - len(base.observation_spec[key].shape)
            transforms += [UnsqueezeTransform(dim=dim, in_keys=[key]), CatFrames(N=obs_steps, dim=dim, in_keys=[key])]
    if each_step is not None:
        transforms.append(_EachStep(each_step))
    transforms.append(MultiAction(stack_rewards=True))
    return TransformedEnv(base, Compose(*transforms))


class ChunkedEnv(EnvBase):
    """Executes N-step action chunks on ``base`` and returns the last M observations."""

    def __init__(self, base: EnvBase, action_steps: int, obs_steps: int, safe_lift: float = 0.0,
                 video: VideoSettings | None = None):
        super().__init__(device=base.device, batch_size=torch.Size([]))
        if action_steps < obs_steps:
            raise ValueError(f"action_steps ({action_steps}) must be >= obs_steps ({obs_steps})")
        if video is not None and not callable(getattr(base, "render_rgb", None)):
            raise ValueError(f"{type(base).__name__} cannot record videos: it has no render_rgb(width, height) method")
        self.recorder = EpisodeRecorder(video) if video is not None else None
        self.base = base
        self.action_steps = action_steps
        self.obs_steps = obs_steps
        self.safe_lift = safe_lift
        self._chunks = stacked_chunks(base, obs_steps, self._after_inner_step)
        obs = base.observation_spec
        spec = {}
        for key in STACKED:
            if key in obs.keys():
                inner = obs[key]
                spec[key] = Unbounded(shape=(obs_steps, *inner.shape), dtype=inner.dtype, device=self.device)
        for key in obs.keys():
            if key not in STACKED and key != "success":
                spec[key] = obs[key].clone()
        spec["success"] = Categorical(2, shape=(1,), dtype=torch.bool, device=self.device)
        spec["chunk_index"] = Unbounded(shape=(1,), dtype=torch.int64, device=self.device)
        self._tells_seed = hasattr(base, "episode_seed")
        if self._tells_seed:
            spec["episode_seed"] = Unbounded(shape=(1,), dtype=torch.int64, device=self.device)
        # the end-effector shift the env executed before this chunk (the requested ee_shift, clipped to the
        # workspace), so that a recovery can undo exactly what a tracking shift did
        spec["ee_shift_applied"] = Unbounded(shape=(3,), dtype=torch.float32, device=self.device)
        self.observation_spec = Composite(spec, device=self.device)
        a = base.action_spec
        self.full_action_spec = Composite(
            action=Bounded(
                a.space.low.expand(action_steps, *a.shape), a.space.high.expand(action_steps, *a.shape),
                shape=(action_steps, *a.shape), dtype=a.dtype, device=self.device,
            ),
            ee_shift=Unbounded(shape=(3,), dtype=torch.float32, device=self.device),
            device=self.device,
        )
        self.reward_spec = base.reward_spec.clone()
        self.done_spec = base.full_done_spec.clone()
        self._chunk = 0
        self._success = False
        self._failed = False
        self._ended = False
        self._label: ChunkLabel | None = None

    def _set_seed(self, seed: int | None) -> None:
        self.base.set_seed(seed)

    def _observation(self, last: TensorDictBase, applied=None) -> TensorDictBase:
        out = last.exclude("reward", "done", "terminated", "truncated", "success")
        out.set("success", torch.tensor([self._success], device=self.device))
        out.set("chunk_index", torch.tensor([self._chunk], dtype=torch.int64, device=self.device))
        if self._tells_seed:
            out.set("episode_seed", torch.tensor([int(self.base.episode_seed)], dtype=torch.int64, device=self.device))
        shift = torch.zeros(3) if applied is None else torch.as_tensor(applied, dtype=torch.float32).reshape(3)
        out.set("ee_shift_applied", shift.to(self.device))
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, seed: int | None = None, **kwargs) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"chunked env: reset() takes seed=; got {', '.join(sorted(kwargs))}")
        # reset(seed=s) plays episode s, as the base env's does (it was dropped: another episode, mislabelled)
        first = self._chunks.reset() if seed is None else self._chunks.reset(seed=seed)
        self._chunk = 0
        self._success = self._failed = self._ended = False
        if self.recorder is not None:
            self.recorder.start_episode(int(self.base.episode_seed) if self._tells_seed else None)
            self._record(None)
        out = self._observation(first)
        for key in ("done", "terminated", "truncated"):
            out.set(key, torch.zeros(1, dtype=torch.bool, device=self.device))
        return out

    def _after_inner_step(self, step: TensorDictBase) -> None:
        """After each action of the chunk: the episode's success so far, the video frame. An env's optional
        ``"failed"`` flag (the task failed for good: a press past its depth) revokes an earlier success."""
        self._failed = self._failed or bool(step.get("failed", torch.zeros(1, dtype=torch.bool)).any())
        success = self._success or bool(step.get("success", torch.zeros(1, dtype=torch.bool)).any())
        self._success = success and not self._failed
        if self._label is not None:
            self._label.success = self._success
            self._record(self._label)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shift = tensordict.get("ee_shift", None)
        # the whole chunk is checked before any of it runs: no half-executed chunk ends in a refusal
        if self._ended:  # the base env has no done guard: the shift and an action would run on the ended episode
            raise RuntimeError("chunked env: the episode has ended (done); reset() before the next step")
        action = tensordict.get("action")
        wanted = (self.action_steps, *self.base.action_spec.shape)
        if tuple(action.shape[-len(wanted):]) != wanted:  # another length runs that many steps as one chunk
            raise ValueError(f"chunked env: an action chunk is {list(wanted)} ({self.action_steps} actions of "
                             f"{list(self.base.action_spec.shape)}); got shape {list(action.shape)}")
        require_finite("action chunk", action, "chunked env")
        if shift is not None:
            if shift.numel() != 3:
                raise ValueError(f"chunked env: ee_shift is 3 numbers (x, y, z); got shape {list(shift.shape)}")
            require_finite("end-effector shift", shift, "chunked env")
        applied = None
        if shift is not None and bool(shift.abs().max() > 0):
            applied = self.base.shift_end_effector(shift.detach().cpu().numpy(), safe_lift=self.safe_lift)
        if self.recorder is not None:
            self._label = ChunkLabel.from_tensordict(tensordict, self._chunk, self._success)
        inner = tensordict.select("action").exclude("next")
        last = self._chunks.step(inner).get("next")
        self._label = None
        self._chunk += 1
        reward = last.get("reward").reshape(-1, *self.reward_spec.shape).sum(0)
        out = self._observation(last, applied)
        out.set("reward", reward)
        for key in ("done", "terminated", "truncated"):
            out.set(key, last.get(key))
        self._ended = bool(last.get("done").any())
        if self.recorder is not None and self._ended:
            self.recorder.finish()
        return out

    def _record(self, label: ChunkLabel | None) -> None:
        if self.recorder.recording:
            s = self.recorder.settings
            self.recorder.add(self.base.render_rgb(s.size, s.size, camera=s.camera), label)

    def close(self, *, raise_if_closed: bool = True) -> None:
        if self.recorder is not None:  # an episode still running (the collector's last reset) is not a video
            self.recorder.discard()
        self.base.close()
        super().close()
