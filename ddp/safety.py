"""What stands between a model and a robot: observation checks, finite actions, holding still.

The controller validates every observation at its boundary (:func:`check_observation`):
a missing key, a wrong shape or a non-float dtype is one :class:`ObservationError`
line; a point count or channel count other than the recipe's warns once. Non-finite
values are not an error there: the environment they come from is marked, counted as
OOD and, when the policy cannot act from imagination instead, *held*.

Holding is the env's business, since only the env knows what its action dimensions
mean. An env plugin declares ``action_hold = HoldSpec(...)``: delta dimensions (end-
effector translations, gripper increments) hold at zero; absolute dimensions (a
gripper command, joint targets) repeat the last finite command of the episode, or the
declared reset value before the first one. :func:`require_finite` is the env side:
every env refuses a non-finite action or end-effector shift.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from ddp.errors import DDPError


class ObservationError(DDPError):
    """An observation the controller cannot read (missing key, wrong shape or dtype)."""


class NonFiniteError(DDPError):
    """A non-finite value where only finite ones may go (an action, a shift, model weights)."""


@dataclass(frozen=True)
class HoldSpec:
    """How an env's action space holds still.

    ``absolute``: the action dimensions that are absolute commands (``"all"``, or a
    tuple of indices); the others are deltas and hold at 0. ``reset``: the value an
    absolute dimension holds at before the episode's first finite action (missing: it
    cannot be held then, and the controller raises).
    """

    absolute: tuple[int, ...] | str = ()
    reset: dict[int, float] = field(default_factory=dict)

    def absolute_dims(self, action_dim: int) -> list[int]:
        if self.absolute == "all":
            return list(range(action_dim))
        outside = [d for d in self.absolute if not 0 <= d < action_dim]
        if outside:  # a spec written for another action space would hold that command at 0
            raise ValueError(f"HoldSpec: absolute action dimension {outside[0]} is outside the {action_dim} "
                             f"dimensions of the action")
        return list(self.absolute)

    def action(self, last: torch.Tensor | None, action_dim: int, steps: int) -> torch.Tensor | None:
        """The N-step hold chunk [steps, action_dim], or None if an absolute dim has no value yet."""
        held = torch.zeros(action_dim)
        for d in self.absolute_dims(action_dim):
            if last is not None:
                held[d] = last[d]
            elif d in self.reset:
                held[d] = self.reset[d]
            else:
                return None
        return held.expand(steps, action_dim).clone()


#: envs whose actions are all deltas (translations, gripper increments)
DELTAS = HoldSpec()


def require_finite(name: str, value, where: str) -> None:
    """Refuse a non-finite action (the env side of "a robot never receives a non-finite action")."""
    arr = (value.detach().to(torch.promote_types(value.dtype, torch.float32)).cpu().numpy()  # bf16: no numpy dtype
           if isinstance(value, torch.Tensor)
           else np.asarray(value, dtype=np.float64))
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).sum())
        raise NonFiniteError(f"{where}: refused a non-finite {name} ({bad} of {arr.size} values are NaN or inf)")


def first_nonfinite(named_tensors) -> str | None:
    """The name of the first float tensor holding NaN or inf in ``(name, tensor)`` pairs (a module's
    parameters and buffers, a state dict's items), or None."""
    for name, t in named_tensors:
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            return name
    return None


@dataclass
class ObservationSpec:
    """What the model reads: the recipe's task shapes and the policy's M."""

    obs_steps: int
    agent_pos_dim: int
    point_dim: int
    num_points: int | None = None
    warned: set = field(default_factory=set)

    def _warn_once(self, tag: str, message: str) -> None:
        if tag not in self.warned:
            self.warned.add(tag)
            warnings.warn(message, stacklevel=4)


def _get(td, key, name: str):
    value = td.get(key, None)
    if value is None:
        keys = ", ".join(sorted(str(k) for k in td.keys()))
        raise ObservationError(f"observation has no '{name}' (key {key!r}; keys: {keys})")
    if not isinstance(value, torch.Tensor):
        raise ObservationError(f"observation '{name}' must be a tensor; got {type(value).__name__}")
    return value


def check_observation(td, spec: ObservationSpec, keys: dict, dtype: torch.dtype = torch.float32):
    """Validate a batched controller input.

    Returns ``(point_cloud [B, M, P, C], agent_pos [B, M, D], chunk_index [B] list, finite [B] bool)``:
    float tensors of ``dtype`` cut to the last M steps, and which environments' inputs are all finite.
    """
    B = td.batch_size[0] if td.batch_dims else 1
    if B == 0:
        raise ObservationError("observation batch is empty (0 environments)")
    pc = _get(td, keys["point_cloud"], "point_cloud")
    pos = _get(td, keys["agent_pos"], "agent_pos")
    chunk = _get(td, keys["chunk_index"], "chunk_index")
    M = spec.obs_steps
    for name, x, event in (("point_cloud", pc, "[B, M, P, C]"), ("agent_pos", pos, "[B, M, D]")):
        if x.dtype == torch.bool or x.is_complex() or x.is_quantized:  # every float or integer dtype is cast
            raise ObservationError(f"observation '{name}' must be a float or integer tensor (integers are cast); "
                                   f"got {x.dtype}")
        if x.dim() != len(event.split(",")) or x.shape[0] != B:
            raise ObservationError(f"observation '{name}' must be {event} with B = {B}; got shape {tuple(x.shape)}")
        if x.shape[1] < M:
            raise ObservationError(
                f"observation '{name}' holds {x.shape[1]} step(s); the policy reads the last M = {M} (policy.obs_steps)"
            )
    if pc.shape[2] == 0:
        raise ObservationError("observation 'point_cloud' has 0 points")
    if pc.shape[3] < spec.point_dim:
        raise ObservationError(
            f"observation 'point_cloud' has {pc.shape[3]} channels per point; the model reads {spec.point_dim} "
            "(task.point_dim)"
        )
    if pos.shape[2] != spec.agent_pos_dim:
        raise ObservationError(
            f"observation 'agent_pos' has {pos.shape[2]} features; the model expects {spec.agent_pos_dim} "
            "(task.agent_pos_dim)"
        )
    if pc.shape[3] > spec.point_dim:
        spec._warn_once("channels", f"point clouds have {pc.shape[3]} channels per point; the model reads the first "
                                    f"{spec.point_dim} (task.point_dim) and ignores the rest")
    if spec.num_points is not None and pc.shape[2] != spec.num_points:
        spec._warn_once("points", f"point clouds have {pc.shape[2]} points; the model was trained on "
                                  f"{spec.num_points} (task.num_points): expect a shifted input distribution")
    if chunk.numel() != B:
        raise ObservationError(f"observation 'chunk_index' must hold one index per environment ({B}); "
                               f"got shape {tuple(chunk.shape)}")
    pc = pc[:, -M:, :, : spec.point_dim].to(dtype)
    pos = pos[:, -M:].to(dtype)
    finite = torch.isfinite(pc).flatten(1).all(1) & torch.isfinite(pos).flatten(1).all(1)
    return pc, pos, chunk.reshape(B).long().tolist(), finite.cpu()
