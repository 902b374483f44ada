"""Geometry shared by the trackers: depth back-projection, rigid transforms, ICP, plane and cluster finding.

Conventions (those of ``ddp.envs.franka.backend.CameraFrame``, RealSense and
FoundationPose): camera frames follow OpenCV (x right, y down, z forward);
``K`` is the 3x3 pinhole matrix with pixel ``(u, v) = (column, row)`` centred
on integer coordinates; ``cam_to_world`` is the 4x4 camera pose in the robot
base frame; depth is metric along the optical axis, 0 where there is no
return. Positions are metres in the base frame.

Everything here is plain numpy (the nearest-neighbour search is a chunked
brute force, no KD-tree), so this module stays cheap to import.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "intrinsics_from_fovy",
    "mujoco_camera_to_opencv",
    "backproject",
    "project",
    "make_transform",
    "invert_transform",
    "transform_points",
    "kabsch",
    "nearest_neighbors",
    "icp",
    "estimate_normals",
    "ICPResult",
    "fit_plane_ransac",
    "voxel_components",
    "pixel_components",
    "pose_displacement",
    "subsample",
]

# MuJoCo / OpenGL camera axes (x right, y up, looking along -z) -> OpenCV (x right, y down, z forward)
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


# --------------------------------------------------------------------------- cameras
def intrinsics_from_fovy(fovy_deg: float, height: int, width: int) -> np.ndarray:
    """OpenCV ``K`` of a MuJoCo/OpenGL camera with vertical field of view ``fovy_deg`` (square pixels).

    OpenGL pixel ``j`` spans ``[j, j + 1]`` (centre ``j + 0.5``); OpenCV puts pixel centres on integers,
    so the principal point is ``((W - 1) / 2, (H - 1) / 2)``.
    """
    if not 0.0 < fovy_deg < 180.0:
        raise ValueError(f"fovy must be in (0, 180) degrees; got {fovy_deg}")
    f = 0.5 * height / math.tan(0.5 * math.radians(fovy_deg))
    return np.array([[f, 0.0, 0.5 * (width - 1)], [0.0, f, 0.5 * (height - 1)], [0.0, 0.0, 1.0]])


def mujoco_camera_to_opencv(cam_xpos: np.ndarray, cam_xmat: np.ndarray) -> np.ndarray:
    """4x4 OpenCV ``cam_to_world`` from MuJoCo's ``data.cam_xpos[i]`` and ``data.cam_xmat[i]``."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(cam_xmat, dtype=np.float64).reshape(3, 3) @ _GL_TO_CV
    T[:3, 3] = np.asarray(cam_xpos, dtype=np.float64)
    return T


def backproject(
    depth: np.ndarray,
    K: np.ndarray,
    cam_to_world: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    stride: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Points seen by the valid pixels of a depth image.

    Args:
        depth: ``[H, W]`` metric depth; pixels ``<= 0`` or non-finite are skipped.
        K: ``[3, 3]`` intrinsics.
        cam_to_world: OpenCV camera pose; None returns camera-frame points.
        mask: optional ``[H, W]`` bool, pixels to keep.
        stride: keep every ``stride``-th row and column.

    Returns:
        ``points`` ``[N, 3]`` float64 and ``pixels`` ``[N]`` the flat indices ``row * W + col`` they came from.
    """
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)
    if stride > 1:
        keep = np.zeros_like(valid)
        keep[::stride, ::stride] = True
        valid &= keep
    rows, cols = np.nonzero(valid)
    z = depth[rows, cols]
    K = np.asarray(K, dtype=np.float64)
    x = (cols - K[0, 2]) * z / K[0, 0]
    y = (rows - K[1, 2]) * z / K[1, 1]
    pts = np.stack([x, y, z], axis=1)
    if cam_to_world is not None:
        pts = transform_points(cam_to_world, pts)
    return pts, rows * W + cols


def project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``[N, 2]`` (u, v) of camera-frame points (OpenCV)."""
    p = np.asarray(points_cam, dtype=np.float64)
    uv = p @ np.asarray(K, dtype=np.float64).T
    return uv[:, :2] / uv[:, 2:3]


# --------------------------------------------------------------------------- rigid transforms
def make_transform(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def pose_displacement(
    pose_cam: np.ndarray,
    ref_pose_cam: np.ndarray,
    cam_to_world: np.ndarray,
    ref_cam_to_world: np.ndarray | None = None,
    point: np.ndarray | None = None,
) -> np.ndarray:
    """Delta p_C = p_C - p_C^exp in the base frame, from two object-in-camera poses.

    ``pose_cam`` / ``ref_pose_cam``: 4x4 object poses in the OpenCV camera frame now and at the
    reference (e.g. FoundationPose's ``register`` / ``track_one`` output); ``cam_to_world`` /
    ``ref_cam_to_world`` the camera poses when each was taken (the same camera by default).
    ``point``: the object-frame point whose motion is reported (default its origin).
    """
    ref_cam_to_world = cam_to_world if ref_cam_to_world is None else ref_cam_to_world
    p = np.zeros(3) if point is None else np.asarray(point, dtype=np.float64)
    now = transform_points(np.asarray(cam_to_world) @ np.asarray(pose_cam), p[None])[0]
    ref = transform_points(np.asarray(ref_cam_to_world) @ np.asarray(ref_pose_cam), p[None])[0]
    return now - ref


# --------------------------------------------------------------------------- registration
def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation ``R`` and translation ``t`` with ``R @ src_i + t ~ dst_i`` (no reflection)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def nearest_neighbors(src: np.ndarray, dst: np.ndarray, chunk: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """For every ``src`` point, the index of its nearest ``dst`` point and the squared distance (brute force)."""
    idx = np.empty(len(src), dtype=np.int64)
    d2 = np.empty(len(src))
    dst_sq = (dst**2).sum(1)
    for s in range(0, len(src), chunk):
        a = src[s : s + chunk]
        d = (a**2).sum(1)[:, None] - 2.0 * a @ dst.T + dst_sq[None]
        j = d.argmin(1)
        idx[s : s + chunk] = j
        d2[s : s + chunk] = np.maximum(d[np.arange(len(a)), j], 0.0)
    return idx, d2


class ICPResult:
    """``transform`` (4x4, maps source to target), ``rmse`` of the inlier pairs, ``inlier_fraction``."""

    __slots__ = ("transform", "rmse", "inlier_fraction", "iterations")

    def __init__(self, transform, rmse, inlier_fraction, iterations):
        self.transform, self.rmse, self.inlier_fraction, self.iterations = transform, rmse, inlier_fraction, iterations

    def __repr__(self) -> str:
        return f"ICPResult(t={self.transform[:3, 3]}, rmse={self.rmse:.4g}, inliers={self.inlier_fraction:.2f})"


def estimate_normals(points: np.ndarray, k: int = 10, viewpoint: np.ndarray | None = None) -> np.ndarray:
    """Unit normals ``[N, 3]`` from the ``k`` nearest neighbours (PCA); oriented toward ``viewpoint`` if given.

    Points whose neighbours lie along a line get a zero normal (undefined).
    """
    pts = np.asarray(points, dtype=np.float64)
    k = min(k, len(pts))
    normals = np.empty_like(pts)
    sq = (pts**2).sum(1)
    for s in range(0, len(pts), 1024):
        a = pts[s : s + 1024]
        d = (a**2).sum(1)[:, None] - 2.0 * a @ pts.T + sq[None]
        nb = np.argpartition(d, k - 1, axis=1)[:, :k]
        q = pts[nb] - pts[nb].mean(1, keepdims=True)  # [n, k, 3]
        val, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))
        # a neighbourhood spread along one line (a single image row) has no defined normal: zero
        flat = val[:, 1] > 0.25 * val[:, 2]
        normals[s : s + 1024] = vec[:, :, 0] * flat[:, None]  # eigenvector of the smallest eigenvalue
    if viewpoint is not None:
        flip = ((np.asarray(viewpoint) - pts) * normals).sum(1) < 0
        normals[flip] *= -1
    return normals


def icp(
    source: np.ndarray,
    target: np.ndarray,
    init: np.ndarray | None = None,
    iterations: int = 30,
    max_distance: float | None = None,
    rotation: bool = True,
    tolerance: float = 1e-6,
    target_normals: np.ndarray | None = None,
    plane_weight: float = 0.9,
    source_normals: np.ndarray | None = None,
    max_normal_angle: float = 60.0,
) -> ICPResult:
    """ICP aligning ``source`` onto ``target``: point-to-point, or point-to-plane with ``target_normals``.

    Each iteration pairs every moved source point with its nearest target point, drops pairs farther
    than ``max_distance`` (all kept when None) and solves the best rigid motion, or the best
    translation when ``rotation`` is False. Point-to-point uses Kabsch (translation: the mean
    residual). With normals the residual along each normal is weighted by ``plane_weight`` and the
    full residual by ``1 - plane_weight`` (which keeps directions that no face constrains defined;
    the rotation is linearised per step). With ``source_normals`` too, pairs whose normals differ by
    more than ``max_normal_angle`` degrees are dropped (a face seen in only one cloud does not pull
    onto another face); zero normals mean "unknown" (no plane term, no check). Stops when a step
    moves the source by less than ``tolerance`` metres.
    """
    cos_max = math.cos(math.radians(max_normal_angle))
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    T = np.eye(4) if init is None else np.array(init, dtype=np.float64)
    rmse, frac, it = float("inf"), 0.0, 0
    for it in range(1, iterations + 1):
        moved = transform_points(T, src)
        j, d2 = nearest_neighbors(moved, dst)
        keep = d2 <= max_distance**2 if max_distance is not None else np.ones(len(d2), dtype=bool)
        if source_normals is not None and target_normals is not None:
            ns, nt = source_normals @ T[:3, :3].T, target_normals[j]
            known = (np.abs(ns).sum(1) > 0) & (np.abs(nt).sum(1) > 0)
            keep &= ~known | ((ns * nt).sum(1) >= cos_max)
        if keep.sum() < 3:
            break
        frac = float(keep.mean())
        rmse = float(np.sqrt(d2[keep].mean()))
        p, q = moved[keep], dst[j[keep]]
        if target_normals is None:
            if rotation:
                R, t = kabsch(p, q)
            else:
                R, t = np.eye(3), (q - p).mean(0)
        else:
            R, t = _plane_step(p, q, np.asarray(target_normals)[j[keep]], rotation, plane_weight)
        step = make_transform(R, t)
        T = step @ T
        change = np.abs(transform_points(step, p) - p).max()
        if change < tolerance:
            break
    return ICPResult(T, rmse, frac, it)


def _plane_step(p, q, n, rotation: bool, w: float):
    """One Gauss-Newton step of w * sum (n.(R p + t - q))^2 + (1 - w) * sum |R p + t - q|^2."""
    r = q - p
    if not rotation:
        A = w * n.T @ n + (1 - w) * len(p) * np.eye(3)
        b = w * n.T @ (n * r).sum(1) + (1 - w) * r.sum(0)
        return np.eye(3), np.linalg.solve(A, b)
    c = p.mean(0)  # linearise about the centroid for conditioning
    pc = p - c
    # x = [omega, t']: R p + t ~ p + omega x (p - c) + t'  (t' absorbs the centre)
    J_plane = np.concatenate([np.cross(pc, n), n], axis=1)  # d(n.(.))/dx
    A = w * J_plane.T @ J_plane
    b = w * J_plane.T @ (n * r).sum(1)
    # point term: residual r - (omega x pc + t') ; Jacobian rows per axis
    S = np.zeros((len(p), 3, 6))
    S[:, :, 3:] = np.eye(3)
    S[:, 0, 1], S[:, 0, 2] = pc[:, 2], -pc[:, 1]
    S[:, 1, 0], S[:, 1, 2] = -pc[:, 2], pc[:, 0]
    S[:, 2, 0], S[:, 2, 1] = pc[:, 1], -pc[:, 0]
    A += (1 - w) * np.einsum("nki,nkj->ij", S, S)
    b += (1 - w) * np.einsum("nki,nk->i", S, r)
    x = np.linalg.solve(A + 1e-12 * np.eye(6), b)
    omega, tp = x[:3], x[3:]
    angle = np.linalg.norm(omega)
    if angle < 1e-12:
        R = np.eye(3)
    else:
        k = omega / angle
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx
    return R, c + tp - R @ c


# --------------------------------------------------------------------------- scene segmentation
def fit_plane_ransac(
    points: np.ndarray,
    threshold: float = 0.005,
    iterations: int = 200,
    up: np.ndarray | None = (0.0, 0.0, 1.0),
    max_tilt_deg: float = 30.0,
    seed: int = 0,
) -> tuple[np.ndarray, float, np.ndarray]:
    """The plane ``n . x + d = 0`` with the most points within ``threshold`` (RANSAC, then least squares).

    ``up`` orients the normal (``n . up > 0``) and rejects planes tilted more than ``max_tilt_deg`` from
    it (None accepts any plane). Returns ``(n, d, inlier_mask)``; raises ``ValueError`` without a plane.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 3:
        raise ValueError(f"need at least 3 points to fit a plane; got {len(pts)}")
    rng = np.random.default_rng(seed)
    upv = None if up is None else np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    best, best_count = None, -1
    idx = rng.integers(0, len(pts), size=(iterations, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    sample = pts if len(pts) <= 5000 else pts[rng.choice(len(pts), 5000, replace=False)]
    for i in range(iterations):
        if norms[i] < 1e-12:
            continue
        n = normals[i] / norms[i]
        if upv is not None:
            if n @ upv < 0:
                n = -n
            if n @ upv < cos_tilt:
                continue
        count = int((np.abs(sample @ n - n @ a[i]) < threshold).sum())
        if count > best_count:
            best, best_count = (n, -n @ a[i]), count
    if best is None:
        raise ValueError("no plane found (every sampled plane was degenerate or too tilted)")
    n, d = best
    inliers = np.abs(pts @ n + d) < threshold
    # least-squares refinement on the inliers: the normal is the direction of least variance
    q = pts[inliers]
    centre = q.mean(0)
    n2 = np.linalg.svd(q - centre, full_matrices=False)[2][-1]
    if n2 @ n < 0:
        n2 = -n2
    d2 = -n2 @ centre
    return n2, float(d2), np.abs(pts @ n2 + d2) < threshold


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of ``n`` nodes joined by edges ``(a[i], b[i])``: labels ordered by size."""
    parent = np.arange(n)
    # label propagation with pointer jumping: every node ends pointing at its component's smallest index
    while len(a):
        pa, pb = parent[a], parent[b]
        low = np.minimum(pa, pb)
        before = parent.copy()
        np.minimum.at(parent, pa, low)
        np.minimum.at(parent, pb, low)
        while True:  # compress paths
            nxt = parent[parent]
            if np.array_equal(nxt, parent):
                break
            parent = nxt
        if np.array_equal(parent, before):
            break
    _, comp, counts = np.unique(parent, return_inverse=True, return_counts=True)
    order = np.argsort(-counts, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[comp]


def voxel_components(points: np.ndarray, voxel: float) -> np.ndarray:
    """Connected components of the occupied voxels (26-neighbourhood); a label per point (0..C-1).

    Labels are ordered by decreasing component size.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    v = np.floor((pts - pts.min(0)) / voxel).astype(np.int64) + 1  # >= 1 so that neighbours stay >= 0
    dims = v.max(0) + 2
    key = (v[:, 0] * dims[1] + v[:, 1]) * dims[2] + v[:, 2]
    vox, point_vox = np.unique(key, return_inverse=True)  # sorted occupied voxel keys
    n = len(vox)
    offsets = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)]
    edges_a, edges_b = [], []
    for dx, dy, dz in offsets:
        nk = vox + (dx * dims[1] + dy) * dims[2] + dz
        pos = np.minimum(np.searchsorted(vox, nk), n - 1)
        hit = vox[pos] == nk
        edges_a.append(np.nonzero(hit)[0])
        edges_b.append(pos[hit])
    return _components(n, np.concatenate(edges_a), np.concatenate(edges_b))[point_vox]


def pixel_components(pixels: np.ndarray, shape: tuple[int, int], depth: np.ndarray, max_jump: float,
                     step: int = 1) -> np.ndarray:
    """Connected components over the image grid: a label per listed pixel (0..C-1, largest first).

    ``pixels``: flat indices ``row * W + col`` of the pixels to group (e.g. the points above the
    table); two of them are connected when they are 8-neighbours on the grid of every ``step``-th
    row and column and their depths differ by less than ``max_jump`` metres. Unlike voxels this
    does not depend on how sparsely a far or slanted surface is sampled.
    """
    H, W = shape
    pixels = np.asarray(pixels, dtype=np.int64)
    if len(pixels) == 0:
        return np.zeros(0, dtype=np.int64)
    index = np.full(H * W, -1, dtype=np.int64)
    index[pixels] = np.arange(len(pixels))
    z = np.asarray(depth, dtype=np.float64).reshape(-1)
    rows, cols = pixels // W, pixels % W
    edges_a, edges_b = [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        r2, c2 = rows + dr * step, cols + dc * step
        ok = (r2 < H) & (c2 >= 0) & (c2 < W)
        q = np.where(ok, r2 * W + np.clip(c2, 0, W - 1), 0)
        j = np.where(ok, index[q], -1)
        hit = (j >= 0) & (np.abs(z[pixels] - z[q]) < max_jump)
        edges_a.append(np.nonzero(hit)[0])
        edges_b.append(j[hit])
    return _components(len(pixels), np.concatenate(edges_a), np.concatenate(edges_b))


def subsample(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    """At most ``max_points`` of ``points``, chosen uniformly at random (reproducibly)."""
    if len(points) <= max_points:
        return points
    rng = np.random.default_rng(seed)
    return points[np.sort(rng.choice(len(points), max_points, replace=False))]
