"""What the depth-camera object trackers share: their TensorDict keys and the carried-object check.

A tracker reads the tracking camera (``("tracking", ...)``), the robot's
``agent_pos`` (the end-effector, for the carried check) and ``chunk_index``
(0 starts an episode: a new reference) and writes, per environment and target
object, the offset ``Delta p_Cj`` (``("ddp", "offsets")`` [B, K, 3]) and
whether the object is visible and may be carried (``("ddp", "object_visible")``,
``("ddp", "object_carried")`` [B, K] bool).

Objects within ``carried_radius`` of the end-effector may be carried: they
move because the robot moves them, so their offset reads zero, and one hidden
in the hand stays carried until it is seen away from the gripper; an object
that moved while near the gripper is re-anchored where it is next seen (where
the robot put it down), one the gripper only passed by keeps its offset
(:class:`CarriedState`). Holds no plugin: the trackers built on it register
themselves in their own modules.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from ddp.errors import RecipeError
from ddp.keys import KeyedModule, NestedKey


def tracking_in_keys(**images: NestedKey) -> dict[str, NestedKey]:
    """A tracker's ``default_in_keys``: the tracking camera's depth and pose, ``images``, the optional inputs.

    ``images``: further camera inputs the tracker needs (e.g. ``rgb=("tracking", "rgb")``), listed
    after the camera pose.
    """
    return {
        "depth": ("tracking", "depth"),
        "intrinsics": ("tracking", "intrinsics"),
        "cam_to_world": ("tracking", "cam_to_world"),
        **images,
        "segmentation": ("tracking", "segmentation"),  # optional: object index per pixel (simulation)
        "agent_pos": "agent_pos",  # optional: carried-object check
        "chunk_index": "chunk_index",  # optional: 0 starts an episode (new reference)
    }


def as_numpy(x) -> np.ndarray:
    """``x`` (a tensor on any device, or array-like) as a numpy array."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


@dataclass(kw_only=True)
class CarriedState:
    """One tracked object's state for the carried-object check (base of the trackers' per-object states)."""

    last: np.ndarray  # last known position (association, carried check)
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))  # displacement treated as "not displaced"
    carried: bool = False
    grasp_disp: np.ndarray | None = None  # displacement when it came near the gripper
    ee_rel: np.ndarray | None = None  # its position relative to the end-effector then
    pred: np.ndarray | None = None  # where it is if it moves with the hand (while carried)
    held_at: np.ndarray | None = None  # where it last was while near the gripper (measured, or else ``pred``)
    last_disp: np.ndarray = field(default_factory=lambda: np.zeros(3))  # last measured displacement

    def near_gripper(self, ee: np.ndarray | None, carried_radius: float) -> bool:
        """Whether the object may be in the gripper before this measurement.

        True for an object already taken as carried (then ``pred``, where it would be if it moves with
        the hand, is updated) and for one whose last known position is within ``carried_radius`` of the
        end-effector ``ee``.
        """
        if ee is None or carried_radius <= 0:
            return False
        if self.carried:
            self.pred = ee + self.ee_rel
            return True
        return float(np.linalg.norm(self.last - ee)) <= carried_radius

    def robot_aware_offset(self, disp: np.ndarray | None, position: np.ndarray | None, ee: np.ndarray | None,
                           near: bool, carried_radius: float, min_offset: float) -> tuple[np.ndarray, bool]:
        """The reported offset of the object and whether the robot may be carrying it.

        ``anchor`` is where the robot last put the object down. ``disp`` / ``position``: the
        displacement from the episode's reference and the position measured now (None: not
        measured); ``near``: :meth:`near_gripper` before this measurement.

        A measured object is near the gripper when it lies within ``carried_radius`` of the
        end-effector; an unmeasured one keeps its previous state (hidden in the hand, it stays carried).
        An object near the gripper may be moving with the robot: its offset reads zero. When it is next
        measured away from the gripper it is re-anchored where it is if it moved while near the gripper
        and is now where the hand left it (within ``carried_radius`` of where it last was while near: the
        robot put it down there); otherwise (the gripper only passed by, or someone moved it away from the
        hovering gripper) it reports its offset from the anchor. Offsets shorter than ``min_offset`` read
        zero.
        """
        zero = np.zeros(3)
        if disp is not None:
            self.last_disp, self.last = disp, position
            near = ee is not None and carried_radius > 0 and float(np.linalg.norm(position - ee)) <= carried_radius
        if near:
            if not self.carried:
                self.carried = True
                self.grasp_disp = np.array(self.last_disp, dtype=np.float64)
            self.ee_rel = self.last - ee if disp is not None or self.ee_rel is None else self.ee_rel
            # where it is while near the hand: measured, or (hidden in it) where the hand holds it
            self.held_at = np.array(position if disp is not None else self.pred if self.pred is not None
                                    else self.last, dtype=np.float64)
            return zero, True
        if disp is None:
            return zero, False
        if self.carried:
            self.carried = False
            moved = np.linalg.norm(disp - self.grasp_disp) >= min_offset
            left_there = self.held_at is None or np.linalg.norm(position - self.held_at) <= carried_radius
            if moved and left_there:
                self.anchor = disp  # moved by the robot: this is where it was put down
        off = disp - self.anchor
        return (off if np.linalg.norm(off) >= min_offset else zero), False


@dataclass
class TrackerInputs:
    """One call's inputs, batched (``td`` with a leading env dim; ``unbatched``: it had none)."""

    td: object
    unbatched: bool
    B: int
    depth: np.ndarray  # [B, H, W] metres
    K: np.ndarray  # [B, 3, 3] intrinsics
    T: np.ndarray  # [B, 4, 4] camera-to-world
    segmentation: np.ndarray | None  # [B, H, W] object index per pixel
    images: dict  # further camera inputs by name (None when absent)
    ee: np.ndarray | None  # [B, 3] latest end-effector position
    chunk: list | None  # chunk index per env (0 starts an episode)


class ObjectTracker(KeyedModule):
    """Base of the depth-camera trackers: their keys, the end-effector input and the output writing.

    Subclasses set ``config`` (with ``ee_dims``: the end-effector xyz inside ``agent_pos``) and keep a
    :class:`CarriedState` per object; a tracker needing more camera inputs sets
    ``default_in_keys = tracking_in_keys(rgb=...)``.
    """

    default_in_keys = tracking_in_keys()
    default_out_keys = {
        "offsets": ("ddp", "offsets"),
        "visible": ("ddp", "object_visible"),
        "carried": ("ddp", "object_carried"),
    }

    def _warn_unseen(self, b: int, references: list) -> None:
        """Warn (at each episode's start) about objects not found on its first frame: their reference is
        missing, so they read offset 0 and not visible for the whole episode (never tracked or recovered)."""
        missing = [k for k, r in enumerate(references) if r is None]
        if missing:
            whole = len(missing) == len(references)
            what = "no object found" if whole else f"object(s) {missing} not found"
            warnings.warn(f"{type(self).__name__}: environment {b}: {what} on the episode's first frame (hidden, or "
                          f"a bad depth frame): {'nothing is' if whole else 'they are not'} tracked this episode",
                          RuntimeWarning, stacklevel=3)

    def _row_segmentation(self, b: int, segmentation, new_episode: bool):
        """Row ``b``'s segmentation image when its episode isolates objects by masks, else None (geometry):
        decided by ``self.isolator.episode_masks`` on each episode's first frame and kept in ``self.masked``
        (a camera that renders no segmentation labels nothing: the episode uses geometry)."""
        seg_b = None if segmentation is None else segmentation[b]
        if new_episode:
            self.masked[b] = self.isolator.episode_masks(seg_b)
        return seg_b if self.masked[b] else None

    def _read_inputs(self, td, *images: str) -> "TrackerInputs":
        """The batched tracking inputs as numpy arrays (``images``: further camera inputs, e.g. ``"rgb"``)."""
        unbatched = td.batch_dims == 0
        if unbatched:
            td = td.unsqueeze(0)
        B = td.batch_size[0]
        for name in ("depth", "intrinsics", "cam_to_world"):  # further images stay optional (the tracker decides)
            if td.get(self.key(name), None) is None:  # read as None: an IndexError deep in the tracker
                raise RecipeError(f"tracker '{type(self).__name__}' reads {self.key(name)}, which the observation "
                                  f"lacks: it needs the env's tracking camera (on franka: env.tracking_camera: "
                                  f"true; MetaWorld, Adroit and the synthetic env have none: use the oracle tracker "
                                  f"there)", key="controller.tracker")
        optional = {}
        for name in (*images, "segmentation"):
            value = td.get(self.key(name), None)
            optional[name] = None if value is None else as_numpy(value)
        chunk = td.get(self.key("chunk_index"), None)
        return TrackerInputs(
            td=td, unbatched=unbatched, B=B, depth=as_numpy(td.get(self.key("depth"))),
            K=as_numpy(td.get(self.key("intrinsics"))), T=as_numpy(td.get(self.key("cam_to_world"))),
            segmentation=optional.pop("segmentation"), images=optional, ee=self._end_effector(td, B),
            chunk=None if chunk is None else chunk.reshape(B).tolist(),
        )  # fmt: skip

    def _end_effector(self, td, B: int) -> np.ndarray | None:
        """The latest end-effector position per environment [B, 3] (float64), or None without ``agent_pos``."""
        pos = td.get(self.key("agent_pos"), None)
        if pos is None:
            return None
        pos = as_numpy(pos).reshape(B, -1, pos.shape[-1])[:, -1]  # stacked [B, M, D]: the latest step
        return pos[:, self.config.ee_dims].astype(np.float64)

    def _write(self, td, results: list, unbatched: bool):
        """Sets the outputs from one ``(offsets [K, 3], visible [K], carried [K])`` per environment."""
        device = td.device if td.device is not None else torch.device("cpu")
        offsets = np.stack([r[0] for r in results])
        td.set(self.key("offsets"), torch.as_tensor(offsets, dtype=torch.float32, device=device))
        td.set(self.key("visible"), torch.as_tensor(np.stack([r[1] for r in results]), device=device))
        td.set(self.key("carried"), torch.as_tensor(np.stack([r[2] for r in results]), device=device))
        return td.squeeze(0) if unbatched else td
