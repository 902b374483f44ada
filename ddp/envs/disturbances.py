"""OOD disturbance schedules: mid-episode displacements and camera occlusions.

The paper's simulated OOD protocol (Appendix, "Details of Simulation OOD
Experiments" and Table "Detailed OOD Disturbance Parameters for MetaWorld
Tasks") moves objects by a fixed vector at the START of a given action chunk
and, with oracle tracking, shifts the end-effector by the same vector:

* single-stage tasks: object and end-effector move together once;
* two-stage tasks (pick-and-move): the end-effector tracks the object at the
  displacement chunk and "snaps back" by ``-delta`` at a later chunk, once
  the object is grasped (pick-place additionally lifts 5 cm before the
  teleport and lowers afterwards: "Safe Lift").

Chunk indices are 0-based: chunk ``k`` starts at env step ``k * chunk_len``
(the state after ``k * chunk_len`` actions). An event at chunk ``k`` happens
right before the first action of chunk ``k`` is executed, so the first
observation that shows it is the one returned by that step.

The camera occlusion follows the real-robot experiment ("we block the camera
mid-task"): observations returned by the steps of chunks ``k .. k+L-1``
(i.e. after ``t`` actions with ``k*c < t <= (k+L)*c``) are replaced by a
degenerate cloud. So for a policy whose chunks are ``chunk_len`` actions long,
exactly ``L`` planning observations (those at the ends of those chunks, and
every step in between) are blind.

The clock is the env's, not the policy's: ``chunk_len`` (8, the DDP recipes'
``action_steps``) is an env option that evaluation does not tie to the
policy. A policy with shorter chunks (the FlowPolicy overlay's 3) meets the
same move at the same env step, in the middle of one of its chunks, and a
blind span of ``L * chunk_len`` steps covers more of its observations: every
method is compared under one disturbance schedule in simulated time.

These dataclasses are simulator-agnostic; ``PAPER_METAWORLD_DISPLACEMENTS``
is the paper's table verbatim (the MetaWorld binding lives in
``ddp.envs.metaworld_tasks``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from ddp.config import check_choices

__all__ = ["Displacement", "Occlusion", "OCCLUSION_MODES", "PAPER_METAWORLD_DISPLACEMENTS"]

OcclusionMode = Literal["zeros", "drop", "noise"]
OCCLUSION_MODES = get_args(OcclusionMode)


@dataclass(frozen=True)
class Displacement:
    """One mid-episode displacement (a row of the paper's appendix table).

    Attributes:
        bodies: simulator body names moved by ``delta`` (the first one is the
            object the robot interacts with).
        delta: ``[dx, dy, dz]`` in metres, world frame.
        chunk: 0-based action-chunk index at whose start the move happens.
        tracking: ``"single_stage"`` (end-effector follows once) or
            ``"two_stage"`` (follows, then snaps back at ``snap_back_chunk``).
        snap_back_chunk: chunk at whose start the end-effector moves by
            ``-delta`` (two-stage only).
        safe_lift: metres to lift the end-effector before the tracking
            teleport and lower it afterwards (0 = teleport directly).
    """

    bodies: tuple[str, ...]
    delta: tuple[float, float, float]
    chunk: int
    tracking: Literal["single_stage", "two_stage"] = "single_stage"
    snap_back_chunk: int | None = None
    safe_lift: float = 0.0

    def __post_init__(self):
        if not self.bodies:
            raise ValueError("Displacement.bodies must name at least one body")
        if len(self.delta) != 3:
            raise ValueError(f"Displacement.delta must have 3 entries; got {self.delta!r}")
        if self.chunk < 0:
            raise ValueError(f"Displacement.chunk must be >= 0; got {self.chunk}")
        check_choices(self, "Displacement.")
        if self.tracking == "two_stage":
            if self.snap_back_chunk is None or self.snap_back_chunk <= self.chunk:
                raise ValueError(
                    f"a two-stage Displacement needs snap_back_chunk > chunk ({self.chunk}); got {self.snap_back_chunk}"
                )
        elif self.snap_back_chunk is not None:
            raise ValueError(f"only two-stage displacements snap back; got snap_back_chunk={self.snap_back_chunk}")
        if self.safe_lift < 0:
            raise ValueError(f"Displacement.safe_lift must be >= 0; got {self.safe_lift}")

    def step(self, chunk_len: int) -> int:
        """Env step (number of actions already taken) at which the move happens."""
        return self.chunk * chunk_len

    def snap_back_step(self, chunk_len: int) -> int | None:
        """Env step of the two-stage snap-back, or None."""
        return None if self.snap_back_chunk is None else self.snap_back_chunk * chunk_len

    def acted_on(self, chunk_len: int, max_episode_steps: int) -> bool:
        """Whether a chunk acts after the move is observed: the first observation showing it comes
        ``chunk_len`` steps after it, and must not end the episode (else an "OOD" protocol measures an
        episode no policy could react to). The envs refuse a schedule where this is False."""
        return self.step(chunk_len) + chunk_len < max_episode_steps

    def snaps_back_in(self, chunk_len: int, max_episode_steps: int) -> bool:
        """Whether the two-stage snap-back (if any) happens within the episode."""
        snap = self.snap_back_step(chunk_len)
        return snap is None or snap < max_episode_steps

    def replace(self, *, chunk: int | None = None, delta=None) -> "Displacement":
        """A copy with another chunk and/or vector (the snap-back keeps its distance in chunks)."""
        new_chunk = self.chunk if chunk is None else chunk
        snap = self.snap_back_chunk
        if snap is not None and chunk is not None:
            snap = snap + (chunk - self.chunk)
        new_delta = self.delta if delta is None else tuple(float(v) for v in delta)
        return Displacement(self.bodies, new_delta, new_chunk, self.tracking, snap, self.safe_lift)


@dataclass(frozen=True)
class Occlusion:
    """The camera is blind during chunks ``chunk .. chunk + length - 1``.

    ``mode`` picks the degenerate cloud: ``"zeros"`` (every point at the
    origin), ``"drop"`` (every point collapsed onto one random point of the
    crop box: the cloud carries no geometry) or ``"noise"`` (points uniform
    in the crop box).
    """

    chunk: int
    length: int = 1
    mode: OcclusionMode = "zeros"

    def __post_init__(self):
        if self.chunk < 0:
            raise ValueError(f"Occlusion.chunk must be >= 0; got {self.chunk}")
        if self.length < 1:
            raise ValueError(f"Occlusion.length must be >= 1 chunk; got {self.length}")
        check_choices(self, "Occlusion.")

    def covers(self, t: int, chunk_len: int) -> bool:
        """Whether the observation after ``t`` actions is occluded."""
        return self.chunk * chunk_len < t <= (self.chunk + self.length) * chunk_len

    def corrupt(self, num_points: int, crop_low, crop_high, rng: np.random.Generator) -> np.ndarray:
        """A degenerate float32 ``[num_points, 3]`` cloud for this mode."""
        low = np.asarray(crop_low, dtype=np.float64)
        high = np.asarray(crop_high, dtype=np.float64)
        if self.mode == "zeros":
            return np.zeros((num_points, 3), dtype=np.float32)
        if self.mode == "drop":
            point = rng.uniform(low, high)
            return np.repeat(point[None], num_points, axis=0).astype(np.float32)
        return rng.uniform(low, high, size=(num_points, 3)).astype(np.float32)


#: The paper's Table "Detailed OOD Disturbance Parameters for MetaWorld Tasks",
#: with the snap-back chunks of its "Detailed Breakdown of Multi-Subtask
#: Interventions" (pick-place, push, sweep: chunk 6; coffee-pull: chunk 8) and
#: the 5 cm "Safe Lift" of pick-place. Hammer's ``nailHead`` is a site inside
#: ``box``, so moving ``box`` moves the nail.
PAPER_METAWORLD_DISPLACEMENTS: dict[str, Displacement] = {
    "assembly": Displacement(("peg",), (-0.25, 0.0, 0.0), chunk=6),
    "button-press": Displacement(("box",), (-0.25, 0.0, 0.0), chunk=3),
    "drawer-open": Displacement(("drawer",), (0.0, 0.0, 0.10), chunk=2),
    "hammer": Displacement(("box",), (0.0, 0.10, 0.0), chunk=5),
    "door-unlock": Displacement(("door",), (0.0, 0.10, 0.0), chunk=2),
    "soccer": Displacement(("goal_whole",), (-0.20, 0.10, 0.0), chunk=2),
    "pick-place": Displacement(
        ("obj",), (-0.20, -0.10, 0.0), chunk=2, tracking="two_stage", snap_back_chunk=6, safe_lift=0.05
    ),
    "push": Displacement(("obj",), (-0.25, 0.0, 0.0), chunk=2, tracking="two_stage", snap_back_chunk=6),
    "sweep": Displacement(("obj",), (0.20, 0.10, 0.0), chunk=2, tracking="two_stage", snap_back_chunk=6),
    "coffee-pull": Displacement(
        ("obj", "coffee_machine"), (-0.20, 0.0, 0.0), chunk=2, tracking="two_stage", snap_back_chunk=8
    ),
}
