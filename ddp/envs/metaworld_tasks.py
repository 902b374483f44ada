"""Per-task facts for the paper's ten MetaWorld OOD tasks.

Binds each row of the paper's appendix table (``PAPER_METAWORLD_DISPLACEMENTS``
in ``ddp.envs.disturbances``: bodies, vector, chunk, single/two-stage
tracking, snap-back chunk, safe lift) to the MetaWorld v3 simulator:

* ``goal_mask``: which coordinates of MetaWorld's success target
  (``env._target_pos``) move with the displaced body. Success is computed
  against ``_target_pos``, set at reset; it does not follow a moved body by
  itself. On single-stage tasks the goal is part of the moved body (assembly
  peg top, button hole, drawer target, hammer nail, door lock, soccer net) so
  it moves with it. On two-stage tasks the paper keeps "the final destination
  (goal) fixed" (pick-place, push, sweep) and the coffee-pull "target
  placement zone remains fixed", so it does not.
* ``carried``: bodies the gripper holds when a two-stage task snaps back:
  the snap-back returns them to their ID area, so their recorded
  displacement is cleared (the coffee machine stays displaced).
* ``state_slots``: for the 39-d MetaWorld state (obs[4:7] object 1, obs[11:14]
  object 2), what moved each object relative to its ID position: ``"object"``
  (the displacement of ``bodies[0]``), ``"ee"`` (it is held by the gripper,
  which the oracle shifted) or ``None`` (not moved). ``id_frame_state`` uses
  this to express the state in the un-displaced (ID) frame, i.e. what a
  policy that keeps imagining the ID scene would see.

``METAWORLD_V3_TASKS`` lists every MetaWorld v3 task name (without "-v3"),
so configs can be validated without importing the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ddp.envs.disturbances import PAPER_METAWORLD_DISPLACEMENTS, Displacement

__all__ = ["METAWORLD_V3_TASKS", "MetaWorldTask", "PAPER_TASKS", "env_name", "id_frame_state"]

METAWORLD_V3_TASKS: tuple[str, ...] = (
    "assembly", "basketball", "bin-picking", "box-close", "button-press-topdown",
    "button-press-topdown-wall", "button-press", "button-press-wall", "coffee-button", "coffee-pull",
    "coffee-push", "dial-turn", "disassemble", "door-close", "door-lock", "door-open", "door-unlock",
    "hand-insert", "drawer-close", "drawer-open", "faucet-open", "faucet-close", "hammer",
    "handle-press-side", "handle-press", "handle-pull-side", "handle-pull", "lever-pull",
    "pick-place-wall", "pick-out-of-hole", "pick-place", "plate-slide", "plate-slide-side",
    "plate-slide-back", "plate-slide-back-side", "peg-insert-side", "peg-unplug-side", "soccer",
    "stick-push", "stick-pull", "push", "push-wall", "push-back", "reach", "reach-wall",
    "shelf-place", "sweep-into", "sweep", "window-open", "window-close",
)  # fmt: skip

Slot = Literal["object", "ee"] | None


@dataclass(frozen=True)
class MetaWorldTask:
    """One OOD task: the paper's displacement plus its MetaWorld binding."""

    name: str
    displacement: Displacement
    goal_mask: tuple[float, float, float]
    carried: tuple[str, ...] = ()
    state_slots: tuple[Slot, Slot] = ("object", None)

    @property
    def bodies(self) -> tuple[str, ...]:
        """Displaceable bodies, in the order of the privileged ``object_pos``."""
        return self.displacement.bodies

    @property
    def env_name(self) -> str:
        return env_name(self.name)


_SINGLE = (1.0, 1.0, 1.0)
_FIXED = (0.0, 0.0, 0.0)
_T = PAPER_METAWORLD_DISPLACEMENTS

#: The ten MetaWorld tasks of the paper's OOD evaluation.
PAPER_TASKS: dict[str, MetaWorldTask] = {
    # the ring (object 1) is in the gripper when the peg moves at chunk 6
    "assembly": MetaWorldTask("assembly", _T["assembly"], _SINGLE, state_slots=("ee", None)),
    "button-press": MetaWorldTask("button-press", _T["button-press"], _SINGLE),
    "drawer-open": MetaWorldTask("drawer-open", _T["drawer-open"], _SINGLE),
    # object 1 = hammer (in the gripper at chunk 5), object 2 = nail (in the box)
    "hammer": MetaWorldTask("hammer", _T["hammer"], _SINGLE, state_slots=("ee", "object")),
    "door-unlock": MetaWorldTask("door-unlock", _T["door-unlock"], _SINGLE),
    # the ball (object 1) stays; only the net (and the goal in it) moves
    "soccer": MetaWorldTask("soccer", _T["soccer"], _SINGLE, state_slots=(None, None)),
    "pick-place": MetaWorldTask("pick-place", _T["pick-place"], _FIXED, carried=("obj",)),
    "push": MetaWorldTask("push", _T["push"], _FIXED, carried=("obj",)),
    "sweep": MetaWorldTask("sweep", _T["sweep"], _FIXED, carried=("obj",)),
    "coffee-pull": MetaWorldTask("coffee-pull", _T["coffee-pull"], _FIXED, carried=("obj",)),
}


def env_name(task: str) -> str:
    """MetaWorld's id for a task name: ``"button-press"`` -> ``"button-press-v3"``."""
    return f"{task}-v3"


def id_frame_state(
    task: MetaWorldTask, state: np.ndarray, displacement: np.ndarray, ee_offset: np.ndarray
) -> np.ndarray:
    """The 39-d MetaWorld state with the applied shifts removed.

    Subtracts ``ee_offset`` from the hand (and from objects held by it) and
    the displacement of ``bodies[0]`` from displaced objects and from the
    moved goal coordinates, in both the current (obs[0:18]) and the previous
    (obs[18:36]) frame. With oracle tracking the hand and the object move
    together, so this is the ID scene with the hand where the policy thinks
    it is; without tracking the object is seen where it was before the move.

    Args:
        task: the task's entry in ``PAPER_TASKS``.
        state: ``[39]`` MetaWorld observation.
        displacement: ``[K, 3]`` displacement currently applied to each body.
        ee_offset: ``[3]`` end-effector shift the oracle applied so far.
    """
    out = np.array(state, dtype=np.float64, copy=True)
    obj = np.asarray(displacement, dtype=np.float64).reshape(-1, 3)[0]
    ee = np.asarray(ee_offset, dtype=np.float64).reshape(3)
    shifts = {"object": obj, "ee": ee, None: np.zeros(3)}
    for base in (0, 18):  # current frame, previous frame
        out[base : base + 3] -= ee
        out[base + 4 : base + 7] -= shifts[task.state_slots[0]]
        out[base + 11 : base + 14] -= shifts[task.state_slots[1]]
    out[36:39] -= obj * np.asarray(task.goal_mask)
    return out
