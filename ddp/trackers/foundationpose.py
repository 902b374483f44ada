"""FoundationPose tracker: Delta p_Cj from NVIDIA's FoundationPose 6D pose estimator (the paper's tracker).

The paper queries FoundationPose(++) for each displaced object's resting pose
``p_Cj`` in SE(3) and compares it with the expected ID pose ``p_Cj^exp``
(Sec. 3.3, "Simplified Object Tracking under OOD"). This adapter does that
per environment: on the first observation of an episode (``chunk_index ==
0``) it registers every object (RGB-D + mask + the object's mesh -> the 4x4
object-in-camera pose) and keeps that pose, in the base frame, as
``p^exp``; on later calls it follows each object (``track_one``, or a fresh
``register`` with ``mode: register``) and reports the base-frame motion of a
chosen object point (its mesh origin by default). Carried objects (near the
end-effector) read zero, as in the ``pointcloud`` tracker.

FoundationPose is not a PyPI package: it is a checkout of NVlabs/FoundationPose
(GitHub) with its CUDA extensions built (its ``build_all.sh``) and its two
networks' weights in ``<checkout>/weights/`` (refiner ``2023-10-28-18-33-37``,
scorer ``2024-01-11-20-02-45``). This module imports it lazily, only when the
tracker is built, and never downloads anything: without the package, its
weights, a GPU or the meshes, building the tracker fails with one line that
says what to install. FoundationPose++'s bundled ``FoundationPose/`` folder has
the same ``estimater`` API and works as ``repo`` too (its 2D tracker and
Kalman filter are not used).

Masks for registration come from the tracking camera's segmentation image
(simulation) or, on hardware, from the ``pointcloud`` tracker's geometric
isolation (table removal + clustering near ``isolation.expected_positions``).

The FoundationPose call sits behind :class:`ObjectPoseEstimator`; the tracker
takes any factory of such estimators (``estimator_factory``), which is how
its geometry is tested with poses read from the simulator.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, Protocol

import numpy as np
import torch

from ddp.errors import PluginError, RecipeError
from ddp.registry import register
from ddp.trackers import geometry as geo
from ddp.trackers.base import CarriedState, ObjectTracker, tracking_in_keys
from ddp.trackers.pointcloud import IsolationConfig, ObjectIsolator

#: FoundationPose's weight folders (refiner, scorer), as its predictors hard-code them
WEIGHT_RUNS = ("2023-10-28-18-33-37", "2024-01-11-20-02-45")

INSTALL_HINT = (
    "clone NVlabs/FoundationPose (GitHub), build it (its build_all.sh: nvdiffrast, pytorch3d, mycpp), "
    "put its refiner and scorer weights in <checkout>/weights/ and set controller.tracker.repo to the checkout"
)


class ObjectPoseEstimator(Protocol):
    """One object's 6D pose from RGB-D, in the OpenCV camera frame (4x4, metres)."""

    def register(self, K: np.ndarray, rgb: np.ndarray | None, depth: np.ndarray, mask: np.ndarray,
                 iterations: int) -> np.ndarray:
        """Pose from scratch, given the object's pixels ``mask`` [H, W] bool."""

    def track(self, K: np.ndarray, rgb: np.ndarray | None, depth: np.ndarray, iterations: int) -> np.ndarray:
        """Pose refined from the previous one (after a ``register``)."""


#: object index -> a fresh estimator for that object (one per environment and object)
EstimatorFactory = Callable[[int], ObjectPoseEstimator]


@dataclass
class FoundationPoseTrackerConfig:
    # FoundationPose checkout (added to sys.path); None: `module` is importable as is. Both name code to import:
    # a recipe read from a checkpoint may set them only when trusted (--trust-plugins)
    repo: str | None = field(default=None, metadata={"imports_code": True})
    module: str = field(default="estimater", metadata={"imports_code": True})  # FoundationPose, ScorePredictor, ...
    weights_dir: str | None = None  # checked for the two weight folders; default <repo>/weights (where FP reads)
    meshes: list[str] = field(default_factory=list)  # one mesh file per object, env object order, in metres
    mesh_scale: float = 1.0  # multiply mesh coordinates (e.g. 0.001 for millimetre meshes)
    num_objects: int | None = None  # default len(meshes)
    mode: Literal["track", "register"] = "track"  # follow with track_one, or register from scratch every call
    register_iterations: int = 5  # refiner iterations of register (FoundationPose's demo: 5)
    track_iterations: int = 2  # refiner iterations of track_one (demo: 2)
    point: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # object-frame point whose motion is reported
    masks: Literal["auto", "mask", "geometry"] = "auto"  # registration masks: segmentation image or geometry
    isolation: IsolationConfig = field(default_factory=IsolationConfig)  # geometric masks (hardware)
    min_mask_pixels: int = 20  # fewer object pixels: not visible
    # mode track: a tracked pose is checked against the object's observed points (segmentation mask, or the
    # geometric cluster found near the tracked position); farther than this (m) from their centroid, or no
    # points there, the object is registered again from its mask (track_one drifts once it loses an object:
    # fast moves, occlusion); null: no check
    track_tolerance: float | None = 0.05
    carried_radius: float = 0.05  # m from the end-effector; 0 disables the carried check
    ee_dims: list[int] = field(default_factory=lambda: [0, 1, 2])
    min_offset: float = 0.01  # m; smaller motions are reported as zero
    device: str = "cuda:0"
    debug_dir: str | None = None  # FoundationPose's debug output; default a temporary folder

    def __post_init__(self):
        if self.mesh_scale <= 0:
            raise ValueError(f"mesh_scale must be > 0; got {self.mesh_scale}")
        if len(self.point) != 3 or len(self.ee_dims) != 3:
            raise ValueError("point and ee_dims must have 3 entries")
        if self.register_iterations < 1 or self.track_iterations < 1:
            raise ValueError("register_iterations and track_iterations must be >= 1")
        if self.track_tolerance is not None and not (np.isfinite(self.track_tolerance) and self.track_tolerance > 0):
            raise ValueError(f"track_tolerance must be a finite number > 0 (metres) or null; got {self.track_tolerance}")
        k = self.num_objects if self.num_objects is not None else len(self.meshes)
        if self.meshes and k > len(self.meshes):
            raise ValueError(f"num_objects is {k} but meshes lists {len(self.meshes)}: one mesh per object")
        if k:
            self.isolation.check_objects(k, f"{k} object(s)")


def _fail(message: str) -> PluginError:
    return PluginError("tracker 'foundationpose': " + " ".join(str(message).split()))


# --------------------------------------------------------------------------- the real FoundationPose
class FoundationPoseEstimator:
    """:class:`ObjectPoseEstimator` around one ``estimater.FoundationPose`` instance."""

    def __init__(self, estimator):
        self.estimator = estimator

    @staticmethod
    def _rgb(rgb, depth):
        if rgb is None:
            raise RecipeError("foundationpose needs the tracking camera's colour image (\"tracking\", \"rgb\") "
                              "[H, W, 3] uint8; enable rgb on the env's tracking camera", key="controller.tracker")
        return np.ascontiguousarray(rgb[..., :3], dtype=np.uint8)

    def register(self, K, rgb, depth, mask, iterations):
        return np.asarray(self.estimator.register(
            K=np.asarray(K, dtype=np.float64), rgb=self._rgb(rgb, depth), depth=np.asarray(depth, dtype=np.float32),
            ob_mask=np.asarray(mask, dtype=bool), iteration=iterations,
        )).reshape(4, 4)

    def track(self, K, rgb, depth, iterations):
        return np.asarray(self.estimator.track_one(
            rgb=self._rgb(rgb, depth), depth=np.asarray(depth, dtype=np.float32),
            K=np.asarray(K, dtype=np.float64), iteration=iterations,
        )).reshape(4, 4)


def foundationpose_factory(config: FoundationPoseTrackerConfig) -> EstimatorFactory:
    """Import FoundationPose, check its weights and the meshes, load both networks once; one-line errors."""
    if config.repo is not None:
        repo = Path(config.repo).expanduser().resolve()
        if not repo.is_dir():
            raise _fail(f"repo {config.repo} is not a directory; {INSTALL_HINT}")
        if str(repo) not in sys.path:
            sys.path.insert(0, str(repo))
    try:
        spec = importlib.util.find_spec(config.module)
    except (ImportError, ValueError):
        spec = None
    if spec is None or spec.origin is None:
        where = f" in {config.repo}" if config.repo else " (set repo to a FoundationPose checkout)"
        raise _fail(f"cannot find FoundationPose's module '{config.module}'{where}: {INSTALL_HINT}")
    code_dir = Path(spec.origin).resolve().parent
    expected_weights = code_dir / "weights"
    weights = Path(config.weights_dir).expanduser().resolve() if config.weights_dir else expected_weights
    missing = [r for r in WEIGHT_RUNS
               if not ((weights / r / "model_best.pth").is_file() and (weights / r / "config.yml").is_file())]
    if missing:
        raise _fail(f"FoundationPose weights missing in {weights} ({', '.join(missing)}/model_best.pth and "
                    f"config.yml): download the refiner and scorer weights named in FoundationPose's readme "
                    f"into that folder")
    if weights != expected_weights.resolve():
        raise _fail(f"FoundationPose loads its weights from {expected_weights} (hard-coded); "
                    f"link weights_dir {weights} there")
    if not config.meshes:
        raise _fail("set meshes: one mesh file per tracked object, in the env's object order")
    absent = [m for m in config.meshes if not Path(m).expanduser().is_file()]
    if absent:
        raise _fail(f"mesh files not found: {', '.join(absent)}")
    if not torch.cuda.is_available():
        raise _fail("FoundationPose needs a CUDA GPU; none is visible to torch")
    try:
        fp = importlib.import_module(config.module)
        trimesh = getattr(fp, "trimesh", None) or importlib.import_module("trimesh")
    except Exception as err:  # noqa: BLE001 - any import failure of the third-party stack
        raise _fail(f"importing FoundationPose failed ({type(err).__name__}: {err}); install its requirements "
                    f"(requirements.txt, build_all.sh)") from None
    for name in ("FoundationPose", "ScorePredictor", "PoseRefinePredictor"):
        if not hasattr(fp, name):
            raise _fail(f"module '{config.module}' ({spec.origin}) has no {name}: is it FoundationPose's estimater.py?")

    meshes = []
    for path in config.meshes:
        mesh = trimesh.load(str(Path(path).expanduser()), force="mesh")
        if config.mesh_scale != 1.0:
            mesh.apply_scale(config.mesh_scale)
        meshes.append(mesh)
    scorer, refiner = fp.ScorePredictor(), fp.PoseRefinePredictor()
    dr = getattr(fp, "dr", None)
    glctx = dr.RasterizeCudaContext(config.device) if dr is not None else None
    debug_dir = config.debug_dir or tempfile.mkdtemp(prefix="ddp_foundationpose_")
    os.makedirs(debug_dir, exist_ok=True)

    def make(k: int) -> ObjectPoseEstimator:
        if k >= len(meshes):
            raise ValueError(f"foundationpose tracker: object {k} has no mesh ({len(meshes)} meshes configured)")
        mesh = meshes[k]
        est = fp.FoundationPose(model_pts=mesh.vertices, model_normals=mesh.vertex_normals, mesh=mesh,
                                scorer=scorer, refiner=refiner, glctx=glctx, debug=0, debug_dir=debug_dir)
        return FoundationPoseEstimator(est)

    return make


# --------------------------------------------------------------------------- the tracker
@dataclass
class _ObjectPose(CarriedState):
    """An object's reference pose and, inherited, its carried-check state (``last``: the reported point)."""

    ref: np.ndarray  # reference pose in the base frame (4x4): p^exp
    # the centroid of the object's observed points minus its pose's origin, at its last registration (base
    # frame): where a tracked pose's visible surface is expected (a large or off-centre object's surface
    # centroid lies far from its origin)
    surface: np.ndarray | None = None
    # the centroid of the points registration saw minus the reported point (base frame): where the object's
    # pixels are looked for (its reported point, the mesh origin by default, may lie off the object or nearer
    # a neighbour's points than its own)
    seen: np.ndarray | None = None

    def look_at(self) -> np.ndarray:
        """Where to look for the object's points: its last position plus the surface offset registration saw."""
        return self.last if self.seen is None else self.last + self.seen


@register("tracker", "foundationpose", config=FoundationPoseTrackerConfig)
class FoundationPoseTracker(ObjectTracker):
    """Delta p_Cj from FoundationPose 6D poses (RGB-D + mask + mesh), expressed in the robot base frame."""

    default_in_keys = tracking_in_keys(rgb=("tracking", "rgb"))  # segmentation: registration masks in simulation

    def __init__(self, config: FoundationPoseTrackerConfig, estimator_factory: EstimatorFactory | None = None):
        super().__init__()
        self.config = config
        self.factory = estimator_factory if estimator_factory is not None else foundationpose_factory(config)
        self.num_objects = config.num_objects if config.num_objects is not None else len(config.meshes)
        if self.num_objects < 1:
            raise _fail("set meshes (one per object) or num_objects")
        self.isolator = ObjectIsolator(config.isolation, config.masks, 1, config.min_mask_pixels)
        self.estimators: dict[tuple[int, int], ObjectPoseEstimator] = {}
        self.states: dict[int, list] = {}
        self.masked: dict[int, bool] = {}  # per env row: its episode registers from segmentation masks
        self.point = np.asarray(config.point, dtype=np.float64)
        self.reregistered = 0  # mode track: poses that disagreed with the observed points (a diagnostic)

    def reset(self):
        self.states, self.masked = {}, {}

    def _estimator(self, b: int, k: int) -> ObjectPoseEstimator:
        if (b, k) not in self.estimators:
            self.estimators[(b, k)] = self.factory(k)
        return self.estimators[(b, k)]

    def _saw(self, state, pose, found, T) -> None:
        """After a registration on ``found`` (mask, centroid): where its surface and points lie from the pose."""
        if pose is None or found is None or not np.all(np.isfinite(pose)):
            return
        world = T @ pose
        state.surface = found[1] - world[:3, 3]
        state.seen = found[1] - self._position(world)

    def _found(self, depth, K, T, seg, ee, anchors) -> list:
        """Per object ``(mask [H, W] bool, centroid of its points [3])``, None where it was not found."""
        found = self.isolator.isolate(depth, K, T, seg, self.num_objects, ee, anchors=anchors)
        out = []
        for f in found:
            if f is None:
                out.append(None)
                continue
            m = np.zeros(depth.size, dtype=bool)
            m[f[1]] = True
            out.append((m.reshape(depth.shape), np.asarray(f[0], dtype=np.float64).mean(0)))
        return out

    def _agrees(self, pose, k: int, state, depth, K, T, seg, ee) -> bool:
        """Whether a tracked object-in-camera ``pose`` puts the object's visible surface (its origin plus the
        surface offset seen at its last registration) within ``track_tolerance`` of the centroid of its
        observed points (segmentation pixels, or the geometric cluster found near the tracked position); no
        points there (lost, or hidden) disagrees."""
        if pose is None or not np.all(np.isfinite(pose)):
            return False
        origin = (T @ pose)[:3, 3]
        expected = origin + (state.surface if state.surface is not None else 0.0)
        anchors = [expected if j == k else None for j in range(self.num_objects)]
        found = self.isolator.isolate(depth, K, T, seg, self.num_objects, ee, anchors=anchors)[k]
        if found is None:
            return False
        return float(np.linalg.norm(np.asarray(found[0]).mean(0) - expected)) <= self.config.track_tolerance

    def _position(self, pose_world: np.ndarray) -> np.ndarray:
        return geo.transform_points(pose_world, self.point[None])[0]

    def _reference(self, b, depth, K, T, rgb, seg, ee) -> list:
        anchors = self.config.isolation.expected_positions
        if not self.isolator.uses_mask(seg) and anchors is None:
            raise RecipeError("without a segmentation image set isolation.expected_positions (each object's "
                              "approximate ID position, to find its registration mask)",
                              key="controller.tracker.isolation.expected_positions")
        found = self._found(depth, K, T, seg, ee, anchors or [None] * self.num_objects)
        states = []
        for k, f in enumerate(found):
            if f is None:
                states.append(None)
                continue
            pose = self._estimator(b, k).register(K, rgb, depth, f[0], self.config.register_iterations)
            world = T @ pose
            position = self._position(world)
            states.append(_ObjectPose(ref=world, last=position, surface=f[1] - world[:3, 3], seen=f[1] - position))
        return states

    def _track_env(self, b, states, depth, K, T, rgb, seg, ee):
        c = self.config
        n = self.num_objects
        offsets, visible, carried = np.zeros((n, 3)), np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        found = None
        if c.mode == "register":
            found = self._found(depth, K, T, seg, ee, [s.look_at() if s is not None else None for s in states])
        for k, s in enumerate(states):
            if s is None:
                continue
            near = s.near_gripper(ee, c.carried_radius)
            est = self._estimator(b, k)
            if found is not None:
                f = found[k]
                pose = est.register(K, rgb, depth, f[0], c.register_iterations) if f is not None else None
                self._saw(s, pose, f, T)
            else:
                pose = est.track(K, rgb, depth, c.track_iterations)
                if c.track_tolerance is not None and not self._agrees(pose, k, s, depth, K, T, seg, ee):
                    # lost: registered again from the object's pixels near where it was last seen
                    anchors = [s_.look_at() if s_ is not None else None for s_ in states]
                    f = self._found(depth, K, T, seg, ee, anchors)[k]
                    pose = est.register(K, rgb, depth, f[0], c.register_iterations) if f is not None else None
                    self._saw(s, pose, f, T)
                    self.reregistered += 1
            disp = position = None
            if pose is not None and np.all(np.isfinite(pose)):
                world = T @ pose  # object in base frame = camera in base frame @ object in camera
                position = self._position(world)
                disp = position - self._position(s.ref)  # Delta p = p - p^exp
                visible[k] = True
            offsets[k], carried[k] = s.robot_aware_offset(disp, position, ee, near, c.carried_radius, c.min_offset)
        return offsets, visible, carried

    def forward(self, td):
        x = self._read_inputs(td, "rgb")
        td, B, rgb, seg, ee, chunk = x.td, x.B, x.images["rgb"], x.segmentation, x.ee, x.chunk
        depth, K, T = x.depth.astype(np.float32), x.K.astype(np.float64), x.T.astype(np.float64)

        results = []
        for b in range(B):
            new_episode = b not in self.states or (chunk is not None and chunk[b] == 0)
            args = (depth[b], K[b], T[b], None if rgb is None else rgb[b], self._row_segmentation(b, seg, new_episode),
                    None if ee is None else ee[b])
            if new_episode:
                self.states[b] = self._reference(b, *args)  # p^exp: the episode's first (ID) frame
                self._warn_unseen(b, self.states[b])
                n = self.num_objects
                visible = np.array([s is not None for s in self.states[b]])
                results.append((np.zeros((n, 3)), visible, np.zeros(n, dtype=bool)))
                continue
            results.append(self._track_env(b, self.states[b], *args))
        return self._write(td, results, x.unbatched)
