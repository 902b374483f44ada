"""Point-cloud tracker: each target object's displacement Delta p_Cj = p_Cj - p_Cj^exp from depth alone.

No learned weights. Per environment it records, on the first observation of an
episode (``chunk_index == 0``, when the objects are in distribution), every
object's point cloud in the base frame: that is the expected pose
``p_Cj^exp``. On every later call it finds each object's points again and
reports how far the object moved: point-to-plane ICP of the current points
onto the reference cloud (that direction ignores the parts the arm hides;
pairs with incompatible normals are dropped; translation only by default,
partial views make the rotation poorly observable), started from the previous
estimate, from where the hand took a carried object and from the shift of the
visible centroid; a less plausible start wins only with a clearly better fit,
and a fit worse than ``max_fit_rmse`` means "not the object" (not visible).

Objects are isolated

- with the tracking camera's segmentation image where the env provides one
  (simulation: ``("tracking", "segmentation")``, object index per pixel; an
  episode whose first image has no labelled pixel, a camera that renders none,
  is isolated geometrically);
- otherwise geometrically (hardware): the table is removed (known height, or
  the dominant plane found by RANSAC; set ``table_height`` or ``workspace``
  where a floor or wall could out-vote the table), points near the gripper
  are dropped, an object whose reference cloud still fits the scene where it
  was keeps those points (this separates touching objects), the rest is
  grouped into connected clusters (image-grid neighbours with continuous
  depth, or touching voxels) and clusters of a plausible size are matched to
  objects by distance (to ``isolation.expected_positions`` at the reference
  frame, to the last known and reference positions afterwards).

Objects within ``carried_radius`` of the end-effector (``agent_pos``) may be
carried: they move because the robot moves them, so their offset reads zero
(``("ddp", "object_carried")`` True), and one hidden in the hand stays carried
until it is seen away from the gripper; an object that moved while near the
gripper is re-anchored where it is next seen (where the robot put it down),
one the gripper only passed by keeps its offset. Objects that cannot be seen
get a zero offset and ``("ddp", "object_visible")`` False. Offsets shorter
than ``min_offset`` read zero (the controller treats any non-zero offset as
a displacement).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ddp.errors import RecipeError
from ddp.registry import register
from ddp.trackers import geometry as geo
from ddp.trackers.base import CarriedState, ObjectTracker


@dataclass
class IsolationConfig:
    """How objects are found in a depth image without a segmentation image (on hardware)."""

    table_height: float | None = None  # base-frame z of the table top; None: fit the dominant plane (RANSAC)
    table_margin: float = 0.008  # m; points closer than this above the table belong to it
    workspace: list[float] | None = None  # [xmin, xmax, ymin, ymax, zmin, zmax] crop in the base frame
    clustering: Literal["pixels", "voxels"] = "pixels"  # image-grid neighbours, or touching voxels
    max_depth_jump: float = 0.02  # m; neighbouring pixels further apart in depth are not connected
    voxel_size: float = 0.01  # m; points in touching voxels form one cluster (clustering: voxels)
    min_cluster_points: int = 8
    max_cluster_extent: float = 0.3  # m; larger clusters (the arm, a wall) are not objects
    ee_exclusion_radius: float = 0.05  # m; drop points this close to the gripper (fingers, held object); 0 keeps all
    ee_exclusion_height: float = 0.15  # m; the dropped capsule runs this far up (base +z) from the end-effector
    expected_positions: list[list[float]] | None = None  # [K][3] approximate ID positions: which cluster is which
    max_association_distance: float = 0.3  # m; farther clusters are not the object
    stay_distance: float = 0.01  # m; an object whose reference cloud still fits the scene this well has not moved
    max_lift: float = 0.08  # m; an object not in the gripper lies at most this much higher than at the start

    def __post_init__(self):
        if self.workspace is not None and len(self.workspace) != 6:
            raise ValueError(f"isolation.workspace must be [xmin, xmax, ymin, ymax, zmin, zmax]; got {self.workspace}")
        if self.voxel_size <= 0:
            raise ValueError(f"isolation.voxel_size must be > 0; got {self.voxel_size}")
        if self.expected_positions is not None and any(len(p) != 3 for p in self.expected_positions):
            raise ValueError("isolation.expected_positions must be a list of [x, y, z] (one per object)")

    def check_objects(self, k: int, counted: str) -> None:
        """``expected_positions``, where set, names one position per each of the ``k`` tracked objects
        (``counted``: where k comes from, for the message)."""
        if self.expected_positions is not None and len(self.expected_positions) != k:
            raise ValueError(f"{counted} but isolation.expected_positions lists {len(self.expected_positions)} "
                             f"position(s): one per object")


@dataclass
class PointCloudTrackerConfig:
    num_objects: int | None = None  # K; None: len(isolation.expected_positions), else from the segmentation
    segmentation: Literal["auto", "mask", "geometry"] = "auto"  # auto: the segmentation image when labelled
    isolation: IsolationConfig = field(default_factory=IsolationConfig)
    refine: Literal["none", "translation", "rigid"] = "translation"  # ICP after the centroid shift
    icp_metric: Literal["point", "plane"] = "plane"  # point-to-point or point-to-plane ICP
    icp_direction: Literal["reverse", "forward"] = "reverse"  # current points onto the reference cloud, or back
    normal_check: bool = True  # drop ICP pairs with incompatible normals (faces seen in one view only)
    icp_iterations: int = 30
    icp_max_distance: float = 0.02  # m; farther point pairs are outliers
    max_fit_rmse: float = 0.008  # m; a worse ICP fit means the points found are not the object (not visible)
    max_points: int = 1500  # per object cloud, for ICP
    min_points: int = 10  # fewer visible points: the object is not visible
    pixel_stride: int = 1  # back-project every n-th row and column
    carried_radius: float = 0.05  # m from the end-effector; 0 disables the carried check
    ee_dims: list[int] = field(default_factory=lambda: [0, 1, 2])  # end-effector xyz inside agent_pos
    min_offset: float = 0.01  # m; smaller estimates are reported as zero (depth noise is not a displacement)

    def __post_init__(self):
        if self.num_objects is not None and self.num_objects < 1:
            raise ValueError(f"num_objects must be >= 1; got {self.num_objects}")
        if self.num_objects is not None:
            self.isolation.check_objects(self.num_objects, f"num_objects is {self.num_objects}")
        if len(self.ee_dims) != 3:
            raise ValueError(f"ee_dims must name 3 agent_pos dimensions; got {self.ee_dims}")
        if self.pixel_stride < 1 or self.min_points < 3 or self.max_points < self.min_points:
            raise ValueError("need pixel_stride >= 1 and 3 <= min_points <= max_points")


@dataclass
class _ObjectRef(CarriedState):
    """An object's reference cloud and, inherited, its carried-check state (``last``: its centroid's position)."""

    cloud: np.ndarray  # reference points (base frame, subsampled)
    centroid: np.ndarray  # their centroid
    normals: np.ndarray | None = None  # of the reference cloud (point-to-plane ICP onto it)
    bottom: float | None = None  # its lowest point above the table at the reference (geometry)


@dataclass
class _EnvRef:
    objects: list  # _ObjectRef or None (not seen on the reference frame)


_SIZE_COST = 0.05  # m of association distance per e-fold of size mismatch
_BETTER_FIT = 0.7  # an ICP start less plausible than the previous one must reach this fraction of its rmse


def _extent(points: np.ndarray) -> float:
    """The largest side of the axis-aligned bounding box."""
    return float(np.max(points.max(0) - points.min(0)))


class ObjectIsolator:
    """Splits one depth frame into per-object point sets: by segmentation image or by geometry."""

    def __init__(self, isolation: IsolationConfig, mode: str = "auto", stride: int = 1, min_points: int = 10):
        self.cfg = isolation
        self.mode = mode
        self.stride = stride
        self.min_points = min_points
        self.table = (np.array([0.0, 0.0, 1.0]), 0.0)  # the last frame's table plane n . x + d = 0

    def episode_masks(self, segmentation) -> bool:
        """Whether an episode whose first tracking frame has this ``segmentation`` image is isolated by mask.
        In ``auto`` mode an image without one labelled pixel is taken for a camera that renders no segmentation
        (the env fills it with -1: a RealSense, franky-sim without segmentation) where
        ``isolation.expected_positions`` says where to look: that episode uses geometry (masks there read every
        object as not visible, silently). Without those positions it keeps the masks (in simulation every
        object may be hidden at the first frame), with a warning."""
        if self.mode != "auto":
            return self.mode == "mask"
        if segmentation is None:
            return False
        if bool((np.asarray(segmentation) >= 0).any()):
            return True
        if self.cfg.expected_positions is not None:
            return False
        warnings.warn("tracker: the first tracking frame's segmentation image labels no pixel (a camera that renders "
                      "none, or every object hidden): no object is found by mask; set isolation.expected_positions "
                      "to look for them by geometry", RuntimeWarning, stacklevel=3)
        return True

    def uses_mask(self, segmentation) -> bool:
        if self.mode == "mask" and segmentation is None:
            raise RecipeError("'mask' needs the tracking camera's segmentation image; none in the input",
                              key="controller.tracker.segmentation")
        return self.mode == "mask" or (self.mode == "auto" and segmentation is not None)

    def isolate(self, depth, K, cam_to_world, segmentation, num_objects, ee=None, placed=None, anchors=None,
                reach=None, bottoms=None):
        """``[(points [N, 3], pixels [N]) or None]`` per object (None: not found).

        Geometry needs ``anchors`` (where to look for each object) and optionally ``placed`` (each
        object's reference cloud at its last known position) and ``reach`` (per object, how far from
        its anchors to look; default ``isolation.max_association_distance``) and ``bottoms`` (per
        object resting on something, its lowest point's height above the table at the reference;
        None: no support check, e.g. carried), see :meth:`by_geometry`.
        """
        if self.uses_mask(segmentation):
            return self.by_mask(depth, K, cam_to_world, segmentation, num_objects)
        pts, pix = self.scene_points(depth, K, cam_to_world, ee)
        placed = [None] * num_objects if placed is None else placed
        found = self.by_geometry(pts, placed, anchors, self.cfg.stay_distance, pix, np.asarray(depth), reach,
                                 bottoms)
        return [None if f is None or len(f) < self.min_points else (pts[f], pix[f]) for f in found]

    # ------------------------------------------------------------------ segmentation image
    def by_mask(self, depth, K, cam_to_world, segmentation, num_objects):
        pts, pix = geo.backproject(depth, K, cam_to_world, stride=self.stride)
        labels = np.asarray(segmentation).reshape(-1)[pix]
        out = []
        for k in range(num_objects):
            sel = labels == k
            out.append((pts[sel], pix[sel]) if sel.sum() >= self.min_points else None)
        return out

    # ------------------------------------------------------------------ geometry
    def scene_points(self, depth, K, cam_to_world, ee=None) -> tuple[np.ndarray, np.ndarray]:
        """Base-frame points above the table (inside the workspace, away from the fingers) and their pixels."""
        c = self.cfg
        pts, pix = geo.backproject(depth, K, cam_to_world, stride=self.stride)
        if c.workspace is not None:
            lo, hi = np.asarray(c.workspace[0::2]), np.asarray(c.workspace[1::2])
            inside = np.all((pts >= lo) & (pts <= hi), axis=1)
            pts, pix = pts[inside], pix[inside]
        if len(pts) < 3:
            return pts, pix
        self.table = (np.array([0.0, 0.0, 1.0]), -float(c.table_height or 0.0))
        if c.table_height is None:
            try:
                n, d, _ = geo.fit_plane_ransac(pts, threshold=0.5 * c.table_margin)
                self.table = (n, d)
            except ValueError:
                self.table = (np.array([0.0, 0.0, 1.0]), -float(pts[:, 2].min()))
        above = pts @ self.table[0] + self.table[1] > c.table_margin
        if ee is not None and c.ee_exclusion_radius > 0:
            rel = pts - ee
            up = np.clip(rel[:, 2], 0.0, c.ee_exclusion_height)  # closest point of the segment [ee, ee + h z]
            above &= np.linalg.norm(rel - np.outer(up, [0.0, 0.0, 1.0]), axis=1) > c.ee_exclusion_radius
        return pts[above], pix[above]

    def clusters(self, pts: np.ndarray, pix: np.ndarray | None = None, depth: np.ndarray | None = None) -> list:
        """Indices into ``pts`` of its object-sized connected clusters, largest first.

        Connected through the image grid (``pix``: each point's pixel in ``depth``) or, with
        ``clustering: voxels`` or without pixels, through touching voxels.
        """
        c = self.cfg
        if len(pts) == 0:
            return []
        if c.clustering == "pixels" and pix is not None and depth is not None:
            labels = geo.pixel_components(pix, depth.shape, depth, c.max_depth_jump, step=self.stride)
        else:
            labels = geo.voxel_components(pts, c.voxel_size)
        out = []
        for lab in range(labels.max() + 1):
            sel = labels == lab
            if sel.sum() < max(c.min_cluster_points, self.min_points):
                break  # labels are ordered by size
            p = pts[sel]
            if np.max(p.max(0) - p.min(0)) <= c.max_cluster_extent:
                out.append(np.nonzero(sel)[0])
        return out

    def by_geometry(self, pts: np.ndarray, placed: list, anchors: list, stay_distance: float,
                    pix: np.ndarray | None = None, depth: np.ndarray | None = None, reach: list | None = None,
                    bottoms: list | None = None) -> list:
        """Per-object indices into ``pts``: objects still where they were first, then clusters by distance.

        ``placed[k]``: object k's reference cloud moved to its last known position (None: unknown);
        an object is still there when most of that cloud has a scene point within ``stay_distance``
        (or, partly hidden, when the scene points around it lie on it), and the scene points near it
        are its own (this separates objects that touch). The remaining points are clustered
        (image-grid or voxel connected components) and matched to the remaining objects'
        ``anchors`` (nearest first, within ``reach``; an anchor is one position [3] or several [n, 3],
        e.g. the last known and the reference one), among clusters whose size is within a factor 2.5
        of the object's reference cloud.
        """
        out = [None] * len(anchors)
        free = np.ones(len(pts), dtype=bool)
        for k, cloud in enumerate(placed):
            if cloud is None or len(pts) == 0:
                continue
            lo, hi = cloud.min(0) - 2 * stay_distance, cloud.max(0) + 2 * stay_distance
            near = np.nonzero(free & np.all((pts >= lo) & (pts <= hi), axis=1))[0]
            if len(near) < self.min_points:
                continue
            _, d2 = geo.nearest_neighbors(cloud, pts[near])
            _, back = geo.nearest_neighbors(pts[near], cloud)
            fits = back <= stay_distance**2
            # still there: most of the cloud is seen where it was, or (partly hidden, e.g. behind the
            # arm) what is seen around it lies on it
            if np.mean(d2 <= stay_distance**2) < 0.7 and (np.mean(fits) < 0.8 or fits.sum() < self.min_points):
                continue
            mine = near[fits]
            out[k] = mine
            free[mine] = False
        rest = [a if out[k] is None else None for k, a in enumerate(anchors)]
        if any(a is not None for a in rest):
            idx = np.nonzero(free)[0]
            clusters = [idx[c] for c in self.clusters(pts[idx], None if pix is None else pix[idx], depth)]
            if bottoms is not None:  # objects rest on something: no cluster floating above their support
                n, d = self.table
                lowest = [float((pts[cl] @ n + d).min()) for cl in clusters]
            found = self.associate(pts, clusters, rest, reach or self.cfg.max_association_distance,
                                   sizes=[None if c is None else _extent(c) for c in placed],
                                   slack=2 * self.cfg.voxel_size,
                                   lowest=lowest if bottoms is not None else None,
                                   max_bottom=None if bottoms is None else
                                   [None if b is None else b + self.cfg.max_lift for b in bottoms])
            out = [o if o is not None else f for o, f in zip(out, found)]
        return out

    @staticmethod
    def associate(pts: np.ndarray, clusters: list, anchors: list, max_distance,
                  sizes: list | None = None, slack: float = 0.0, lowest: list | None = None,
                  max_bottom: list | None = None) -> list:
        """Greedy one-to-one matching of clusters (index arrays into ``pts``) to anchors (None: skip),
        nearest pairs first, within ``max_distance`` (one for all or one per object); ``sizes[k]``:
        object k's extent: clusters under half or over 2.5 times (+ ``slack``) that are not it, and
        a size mismatch costs like extra distance; ``max_bottom[k]``: the highest a cluster's lowest
        point (``lowest[j]``) may be for object k."""
        result = [None] * len(anchors)
        if not clusters:
            return result
        cents = np.stack([pts[c].mean(0) for c in clusters])
        extents = [_extent(pts[c]) for c in clusters]
        pairs = []
        for k, a in enumerate(anchors):
            if a is None:
                continue
            a = np.atleast_2d(np.asarray(a, dtype=np.float64))
            dist = np.linalg.norm(cents[:, None] - a[None], axis=2).min(1)
            size = None if sizes is None else sizes[k]
            reach = max_distance if np.isscalar(max_distance) else max_distance[k]
            top = None if max_bottom is None else max_bottom[k]
            for j in range(len(clusters)):
                if top is not None and lowest[j] > top:
                    continue  # floating: a piece of the arm, not an object resting on the table
                cost = float(dist[j])
                if size is not None:
                    if not 0.5 * size <= extents[j] <= 2.5 * size + slack:
                        continue  # a fragment (a finger) or something bigger (the arm, two objects)
                    cost += _SIZE_COST * abs(math.log(max(extents[j], 1e-6) / max(size, 1e-6)))
                if dist[j] <= reach:
                    pairs.append((cost, k, j))
        used = set()
        for _, k, j in sorted(pairs):
            if result[k] is None and j not in used:
                result[k] = clusters[j]
                used.add(j)
        return result


@register("tracker", "pointcloud", config=PointCloudTrackerConfig)
class PointCloudTracker(ObjectTracker):
    """Object displacement from depth: segmentation or table removal + clustering, centroid shift, ICP."""

    def __init__(self, config: PointCloudTrackerConfig):
        super().__init__()
        self.config = config
        self.isolator = ObjectIsolator(config.isolation, config.segmentation, config.pixel_stride, config.min_points)
        self.refs: dict[int, _EnvRef] = {}
        self.masked: dict[int, bool] = {}  # per env row: its episode isolates objects by segmentation mask

    def reset(self):
        self.refs, self.masked = {}, {}

    # ------------------------------------------------------------------ helpers
    def _num_objects(self, segmentation) -> int:
        c = self.config
        if c.num_objects is not None:
            return c.num_objects
        if c.isolation.expected_positions is not None:
            return len(c.isolation.expected_positions)
        if segmentation is not None and int(np.max(segmentation)) >= 0:
            return int(np.max(segmentation)) + 1
        raise RecipeError("cannot tell how many objects to track (no labelled segmentation image); set num_objects "
                          "(or isolation.expected_positions)", key="controller.tracker")

    def _check_count(self, segmentation, counted: int) -> None:
        """The object count taken from the first frame's labels (no ``num_objects``) must cover the labels seen
        since: an object hidden on that frame would be left out for the whole episode."""
        c = self.config
        if c.num_objects is not None or c.isolation.expected_positions is not None or segmentation is None:
            return
        top = int(np.max(segmentation))
        if top >= counted:
            raise RecipeError(f"the segmentation shows object label {top}, but the episode's first frame showed "
                              f"{counted} object(s) (one was hidden there): set the count", key="controller.tracker."
                              "num_objects")

    def _reference(self, depth, K, T, seg, ee) -> _EnvRef:
        K_obj = self._num_objects(seg)
        anchors = self.config.isolation.expected_positions
        if not self.isolator.uses_mask(seg) and anchors is None:
            raise RecipeError("without a segmentation image set isolation.expected_positions (each object's "
                              "approximate ID position [x, y, z] in the base frame)",
                              key="controller.tracker.isolation.expected_positions")
        found = self.isolator.isolate(depth, K, T, seg, K_obj, ee, anchors=anchors)
        objects = []
        for k, f in enumerate(found):
            if f is None:
                objects.append(None)
                continue
            cloud = geo.subsample(f[0], self.config.max_points, seed=k)
            c = f[0].mean(0)
            normals = geo.estimate_normals(cloud, viewpoint=T[:3, 3]) if self.config.icp_metric == "plane" else None
            n, d = self.isolator.table
            objects.append(_ObjectRef(cloud=cloud, centroid=c, last=c.copy(), anchor=np.zeros(3), normals=normals,
                                      bottom=float((f[0] @ n + d).min())))
        return _EnvRef(objects)

    def _measure(self, ref: _ObjectRef, points: np.ndarray, camera: np.ndarray) -> np.ndarray:
        """Displacement of the reference cloud's centroid: centroid shift, then ICP.

        ICP starts from the last estimate, from where the hand took a carried object and from the
        centroid shift; a later start must fit clearly better to win (an object partly hidden by the
        arm has a biased centroid but has not moved). None when no fit is within ``max_fit_rmse``
        (the points are not the object).
        """
        c = self.config
        shift = points.mean(0) - ref.centroid
        if c.refine == "none":
            return shift
        current = geo.subsample(points, c.max_points, seed=1)
        rotation = c.refine == "rigid"
        # starts, most plausible first: where it was last seen, where the hand took it, the centroid shift
        inits = [ref.last - ref.centroid] + ([ref.pred - ref.centroid] if ref.carried and ref.pred is not None
                                              else []) + [shift]
        best, best_rmse = None, np.inf
        for init in inits:
            if c.icp_direction == "forward":  # the reference cloud onto the current points
                normals = geo.estimate_normals(current, viewpoint=camera) if c.icp_metric == "plane" else None
                r = geo.icp(ref.cloud, current, init=geo.make_transform(t=init), iterations=c.icp_iterations,
                            max_distance=c.icp_max_distance, rotation=rotation, target_normals=normals)
                moved = r.transform
            else:  # the current points onto the reference cloud: points the arm hides do not pull
                src_n = geo.estimate_normals(current, viewpoint=camera) if ref.normals is not None else None
                r = geo.icp(current, ref.cloud, init=geo.make_transform(t=-init), iterations=c.icp_iterations,
                            max_distance=c.icp_max_distance, rotation=rotation, target_normals=ref.normals,
                            source_normals=src_n if c.normal_check else None)
                moved = geo.invert_transform(r.transform)
            # a less plausible start wins only with a clearly better fit (a partial view can slide
            # along a face: keep the explanation that needs no motion)
            if r.inlier_fraction >= 0.5 and r.rmse < _BETTER_FIT * best_rmse:
                best = geo.transform_points(moved, ref.centroid[None])[0] - ref.centroid
                best_rmse = r.rmse
        if best_rmse > c.max_fit_rmse:
            return None  # these points do not look like the object (e.g. a piece of the arm)
        return best

    def _track_env(self, ref: _EnvRef, depth, K, T, seg, ee):
        c = self.config
        n = len(ref.objects)
        offsets = np.zeros((n, 3))
        visible = np.zeros(n, dtype=bool)
        carried = np.zeros(n, dtype=bool)
        objs = ref.objects
        near = [o is not None and o.near_gripper(ee, c.carried_radius) for o in objs]
        # where to look: around the last known and the reference position, for a carried object near
        # where the hand has taken it or below it at the height it was picked from (put down there);
        # an object not in the hand rests on something (no floating clusters)
        anchors = [None if o is None else np.stack([o.pred, [o.pred[0], o.pred[1], o.last[2]]]) if o.carried
                   else np.stack([o.last, o.centroid]) for o in objs]
        reach = [3 * c.carried_radius if o is not None and o.carried else c.isolation.max_association_distance
                 for o in objs]
        bottoms = [None if o is None or o.carried else o.bottom for o in objs]
        placed = [o.cloud + (o.last - o.centroid) if o is not None else None for o in objs]
        found = self.isolator.isolate(depth, K, T, seg, n, ee, placed=placed, anchors=anchors, reach=reach,
                                      bottoms=bottoms)
        for k, (obj, f) in enumerate(zip(objs, found)):
            if obj is None:
                continue
            disp = None if f is None else self._measure(obj, f[0], T[:3, 3])
            visible[k] = disp is not None
            position = None if disp is None else obj.centroid + disp
            offsets[k], carried[k] = obj.robot_aware_offset(disp, position, ee, near[k], c.carried_radius,
                                                            c.min_offset)
        return offsets, visible, carried

    # ------------------------------------------------------------------ forward
    def forward(self, td):
        x = self._read_inputs(td)
        td, B, depth, K, T, seg, ee, chunk = x.td, x.B, x.depth, x.K, x.T, x.segmentation, x.ee, x.chunk

        results = []
        for b in range(B):
            ee_b = None if ee is None else ee[b]
            new_episode = b not in self.refs or (chunk is not None and chunk[b] == 0)
            seg_b = self._row_segmentation(b, seg, new_episode)
            if new_episode:
                self.refs[b] = self._reference(depth[b], K[b], T[b], seg_b, ee_b)
                self._warn_unseen(b, self.refs[b].objects)
            else:
                self._check_count(seg_b, len(self.refs[b].objects))
            results.append(self._track_env(self.refs[b], depth[b], K[b], T[b], seg_b, ee_b))
        sizes = {len(r[0]) for r in results}
        if len(sizes) != 1:
            raise RecipeError(f"the environments' first frames show different numbers of objects ({sorted(sizes)}): "
                              "set the count", key="controller.tracker.num_objects")
        return self._write(td, results, x.unbatched)
