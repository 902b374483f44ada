"""Depth image -> world-frame point cloud -> crop -> farthest point sampling.

Simulator-agnostic helpers used by the MetaWorld env (and reusable by any
MuJoCo-rendered simulator). They follow DP3's observation pipeline, which
the paper adopts ("following DP3", Sec. 4 and Appendix): a single depth
camera, back-projected to the world frame, cropped to a workspace box and
down-sampled with farthest point sampling (FPS) to a fixed number of xyz
points.

Conventions (MuJoCo cameras): the camera frame has x to the right, y up and
looks along -z; ``R = data.cam_xmat[cam].reshape(3, 3)`` has the camera axes
as columns, so ``world = R @ p_cam + cam_xpos``. The focal length in pixels
is ``f = 0.5 * H / tan(0.5 * fovy)``. Depth images are METRIC distances
along the optical axis (what ``mujoco.Renderer`` returns with depth
rendering enabled), row 0 at the top of the image.

FPS uses a numba-compiled loop when numba is installed (``pip install
"ddp[sim]"``) and an equivalent vectorised numpy loop otherwise; both pick
exactly the same indices.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

__all__ = [
    "camera_rays",
    "depth_to_points",
    "crop_points",
    "farthest_point_sample",
    "DepthToCloud",
]


def camera_rays(height: int, width: int, fovy_deg: float) -> np.ndarray:
    """Per-pixel rays in the camera frame, scaled so that ``z = -1``.

    ``rays[i * width + j] * depth[i, j]`` is the camera-frame point seen by
    pixel (row ``i``, column ``j``) at metric depth ``depth[i, j]``.
    Returns float64 ``[height * width, 3]``.
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive; got {height}x{width}")
    if not 0.0 < fovy_deg < 180.0:
        raise ValueError(f"fovy must be in (0, 180) degrees; got {fovy_deg}")
    f = 0.5 * height / math.tan(0.5 * math.radians(fovy_deg))
    cols = (np.arange(width, dtype=np.float64) + 0.5 - 0.5 * width) / f
    rows = -(np.arange(height, dtype=np.float64) + 0.5 - 0.5 * height) / f
    x, y = np.meshgrid(cols, rows)  # [H, W] each; row 0 is the top of the image
    return np.stack([x.ravel(), y.ravel(), -np.ones(height * width)], axis=1)


def depth_to_points(
    depth: np.ndarray, rays: np.ndarray, cam_pos: np.ndarray, cam_rot: np.ndarray
) -> np.ndarray:
    """Back-project a metric depth image to world-frame points.

    Args:
        depth: ``[H, W]`` metric depth along the optical axis.
        rays: ``camera_rays(H, W, fovy)``.
        cam_pos: ``[3]`` camera position in the world frame.
        cam_rot: ``[3, 3]`` camera orientation (columns = camera axes in world).

    Returns float32 ``[H * W, 3]``.
    """
    d = np.asarray(depth, dtype=np.float64).reshape(-1, 1)
    if d.shape[0] != rays.shape[0]:
        raise ValueError(f"depth has {d.shape[0]} pixels but rays were built for {rays.shape[0]}")
    p_cam = rays * d
    rot = np.asarray(cam_rot, dtype=np.float64).reshape(3, 3)
    return (p_cam @ rot.T + np.asarray(cam_pos, dtype=np.float64)).astype(np.float32)


def crop_points(points: np.ndarray, low, high) -> np.ndarray:
    """Keep the points inside the axis-aligned box ``low <= p <= high``."""
    low = np.asarray(low, dtype=points.dtype)
    high = np.asarray(high, dtype=points.dtype)
    keep = np.all((points >= low) & (points <= high), axis=1)
    return points[keep]


# ----------------------------------------------------------------------------
# Farthest point sampling
# ----------------------------------------------------------------------------


def _fps_numpy(x: np.ndarray, y: np.ndarray, z: np.ndarray, n: int, start: int) -> np.ndarray:
    """Reference FPS: same arithmetic and tie-breaking as the compiled kernel."""
    dist = np.full(x.shape[0], np.inf)
    idx = np.empty(n, dtype=np.int64)
    cur = start
    for i in range(n):
        idx[i] = cur
        dx = x - x[cur]
        dy = y - y[cur]
        dz = z - z[cur]
        np.minimum(dist, dx * dx + dy * dy + dz * dz, out=dist)
        cur = int(np.argmax(dist))  # first maximum
    return idx


def _fps_loop(x, y, z, n, start):  # compiled by numba in _fps_kernel()
    num = x.shape[0]
    dist = np.full(num, np.inf)
    idx = np.empty(n, dtype=np.int64)
    cur = start
    for i in range(n):
        idx[i] = cur
        px = x[cur]
        py = y[cur]
        pz = z[cur]
        for j in range(num):  # a branch-free loop the compiler vectorises
            dx = x[j] - px
            dy = y[j] - py
            dz = z[j] - pz
            dist[j] = min(dist[j], dx * dx + dy * dy + dz * dz)
        cur = np.argmax(dist)  # first maximum
    return idx


_KERNEL: Callable | None = None


def _fps_kernel() -> Callable:
    """The numba-compiled FPS loop, or the numpy fallback without numba."""
    global _KERNEL
    if _KERNEL is None:
        try:
            import numba
        except ImportError:
            _KERNEL = _fps_numpy
        else:
            _KERNEL = numba.njit(cache=True, nogil=True)(_fps_loop)
    return _KERNEL


def farthest_point_sample(
    points: np.ndarray,
    n: int,
    *,
    start: int = 0,
    generator: np.random.Generator | None = None,
    backend: str = "auto",
) -> np.ndarray:
    """Indices of ``n`` points chosen by farthest point sampling.

    Greedy FPS: start at ``points[start]`` (or at a point drawn from
    ``generator`` when one is given), then repeatedly add the point farthest
    from the points chosen so far. Ties go to the lowest index, so the result
    is deterministic. With fewer than ``n`` input points, every point is
    returned once (in FPS order) and the list is padded by repeating it from
    the start.

    Args:
        points: ``[N, 3]`` array (N >= 1).
        n: number of indices to return (>= 1).
        start: index of the first point when no generator is given.
        generator: draws the first point (``generator.integers(N)``).
        backend: ``"auto"`` (numba if installed), ``"numba"`` or ``"numpy"``.

    Returns int64 ``[n]``.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3]; got {tuple(pts.shape)}")
    num = pts.shape[0]
    if num == 0:
        raise ValueError("farthest_point_sample needs at least one point; got an empty cloud")
    if n < 1:
        raise ValueError(f"n must be >= 1; got {n}")
    if generator is not None:
        start = int(generator.integers(num))
    if not 0 <= start < num:
        raise ValueError(f"start must index the {num} points; got {start}")
    if backend == "auto":
        kernel = _fps_kernel()
    elif backend == "numba":
        kernel = _fps_kernel()
        if kernel is _fps_numpy:
            raise ImportError('numba is not installed: pip install "ddp[sim]" (or use backend="numpy")')
    elif backend == "numpy":
        kernel = _fps_numpy
    else:
        raise ValueError(f"backend must be one of 'auto', 'numba', 'numpy'; got {backend!r}")
    x, y, z = (np.ascontiguousarray(pts[:, k]) for k in range(3))
    idx = kernel(x, y, z, min(n, num), start)
    if num < n:
        idx = np.resize(idx, n)
    return idx


class DepthToCloud:
    """Depth image -> cropped, FPS-down-sampled world point cloud (DP3-style).

    The per-pixel rays are computed once for the image size and field of
    view. Calling the object with a depth image and the camera pose returns
    float32 ``[num_points, 3]`` points. An empty crop (camera looking away
    from the box) returns ``num_points`` copies of the box centre rather
    than failing.
    """

    def __init__(self, height: int, width: int, fovy_deg: float, crop_low, crop_high, num_points: int):
        if num_points < 1:
            raise ValueError(f"num_points must be >= 1; got {num_points}")
        self.rays = camera_rays(height, width, fovy_deg)
        self.crop_low = np.asarray(crop_low, dtype=np.float32)
        self.crop_high = np.asarray(crop_high, dtype=np.float32)
        if self.crop_low.shape != (3,) or self.crop_high.shape != (3,):
            raise ValueError("crop_low and crop_high must have 3 entries each")
        if np.any(self.crop_low >= self.crop_high):
            raise ValueError(f"crop_low must be below crop_high on every axis; got {crop_low} and {crop_high}")
        self.num_points = num_points

    def __call__(self, depth: np.ndarray, cam_pos: np.ndarray, cam_rot: np.ndarray) -> np.ndarray:
        pts = crop_points(depth_to_points(depth, self.rays, cam_pos, cam_rot), self.crop_low, self.crop_high)
        if pts.shape[0] == 0:
            centre = 0.5 * (self.crop_low + self.crop_high)
            return np.repeat(centre[None], self.num_points, axis=0)
        return pts[farthest_point_sample(pts, self.num_points)]
