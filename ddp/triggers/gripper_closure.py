"""Subtask ends when the gripper has closed (the paper's trigger for picking)."""

from __future__ import annotations

from dataclasses import dataclass

from ddp.errors import RecipeError
from ddp.registry import register

MAX_WIDTH = 0.5  # metres: a larger finger distance reads as centimetres or millimetres


@dataclass
class GripperClosureConfig:
    width_below: float = 0.045  # finger distance (m) under which the gripper counts as closed
    left: tuple[int, int] = (3, 6)  # agent_pos slices of the two finger positions (DP3's 9-d layout)
    right: tuple[int, int] = (6, 9)
    min_chunks: int = 1  # ignore a closed gripper in the subtask's first chunks
    # A grasp on an object wider than width_below (MetaWorld's mug holds the fingers at 0.056 m): also fire
    # when the width is below settled_below and the fingers stopped moving (width change under settle_tol
    # between the last two frames). None: only width_below counts.
    settled_below: float | None = None
    settle_tol: float = 0.002
    # fingers closer than this hold nothing (closed on air: MetaWorld's 0.030 m against 0.045-0.056 m round its
    # objects): no fire, the subtask goes on. None: any closure counts (the paper's trigger)
    empty_below: float | None = None
    # fire only on a closing seen in this subtask: the fingers must first read open (width at or above
    # settled_below, else width_below) in one of its cycles, so a subtask that starts while the previous one's
    # object is still held does not end at once. False: the paper's trigger (the width alone)
    require_open: bool = False

    def __post_init__(self):
        for name in ("width_below", "settled_below", "empty_below"):
            value = getattr(self, name)
            if value is not None and not 0 < value <= MAX_WIDTH:
                raise ValueError(f"{name} must be in (0, {MAX_WIDTH}] metres; got {value}")
        if self.empty_below is not None and not self.empty_below < self.width_below:
            raise ValueError(f"empty_below must be < width_below ({self.width_below}); got {self.empty_below}")
        for name in ("left", "right"):
            span = getattr(self, name)
            if len(span) != 2 or not 0 <= span[0] < span[1] or span[1] - span[0] != 3:
                raise ValueError(f"{name} must be an agent_pos slice [start, start + 3) of one finger's xyz; "
                                 f"got {list(span)}")
        if self.min_chunks < 0:
            raise ValueError(f"min_chunks must be >= 0; got {self.min_chunks}")
        if self.settled_below is not None and not self.settled_below > self.width_below:
            raise ValueError(f"settled_below must be > width_below ({self.width_below}); got {self.settled_below}")
        if not self.settle_tol > 0:
            raise ValueError(f"settle_tol must be > 0; got {self.settle_tol}")


@register("trigger", "gripper_closure", config=GripperClosureConfig)
class GripperClosureTrigger:
    """Fires when the distance between the finger positions in ``agent_pos`` drops below ``width_below``, or
    (with ``settled_below``) when they have stopped under ``settled_below``: closed on a wider object; with
    ``empty_below``, not when they closed further than that (on nothing); with ``require_open``, only after
    the fingers read open in this subtask (an edge, not a level)."""

    def __init__(self, config: GripperClosureConfig):
        self.config = config

    def width(self, agent_pos) -> float:
        c = self.config
        if agent_pos.shape[-1] < max(c.left[1], c.right[1]):
            raise RecipeError(f"agent_pos has {agent_pos.shape[-1]} dims; the gripper_closure finger slices left "
                              f"{list(c.left)} / right {list(c.right)} need {max(c.left[1], c.right[1])}",
                              key="controller.subtasks[*].trigger")
        return float((agent_pos[..., c.left[0] : c.left[1]] - agent_pos[..., c.right[0] : c.right[1]]).norm(dim=-1))

    def fired(self, obs, chunk_index: int, subtask_chunks: int, state: dict | None = None) -> bool:
        c, agent_pos = self.config, obs["agent_pos"]
        width = self.width(agent_pos[-1])
        if c.require_open:
            if state is None:
                raise ValueError("gripper_closure: require_open needs the controller's per-subtask state "
                                 "(fired(..., state=))")
            if width >= (c.settled_below if c.settled_below is not None else c.width_below):
                state["opened"] = True
            if not state.get("opened"):
                return False  # still closed from before this subtask: no closing seen yet
        if subtask_chunks < c.min_chunks:
            return False
        if c.empty_below is not None and width < c.empty_below:
            return False  # closed on nothing: the grasp missed, the subtask is not done
        if width < c.width_below:
            return True
        if c.settled_below is None or agent_pos.dim() < 2 or agent_pos.shape[0] < 2 or width >= c.settled_below:
            return False
        return abs(width - self.width(agent_pos[-2])) < c.settle_tol  # closed on an object, no longer moving
