"""Depth frame (OpenCV pinhole, any backend) -> base-frame point cloud: crop, random pre-sample, FPS.

The paper's real-robot pipeline (Appendix, "Visual Processing and Point Cloud
Downsampling"): the raw cloud is first randomly sub-sampled to an
intermediate size (10,000 points) and then reduced by farthest point
sampling to exactly 2,048 points. Here the cloud is also cropped to a
base-frame workspace box first (DP3's crop; the table top is dropped by
``crop_low[2] > 0``). Pixels with depth 0 (no return) are ignored.

FPS is :func:`ddp.envs.pointcloud.farthest_point_sample` (numba-compiled
when numba is installed).
"""

from __future__ import annotations

import numpy as np

from ddp.envs.franka.backend import CameraFrame
from ddp.envs.pointcloud import crop_points, farthest_point_sample

__all__ = ["FrameToCloud", "backproject"]


def _rays(height: int, width: int, intrinsics: np.ndarray) -> np.ndarray:
    k = np.asarray(intrinsics, dtype=np.float64)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([((u - cx) / fx).ravel(), ((v - cy) / fy).ravel(), np.ones(height * width)], axis=1)


def backproject(frame: CameraFrame, rays: np.ndarray | None = None) -> np.ndarray:
    """All points with a depth return, in the frame's world (base) frame: float32 ``[N, 3]``."""
    depth = np.asarray(frame.depth, dtype=np.float64)
    h, w = depth.shape
    if rays is None:
        rays = _rays(h, w, frame.intrinsics)
    d = depth.reshape(-1)
    valid = d > 0.0
    p_cam = rays[valid] * d[valid, None]
    pose = np.asarray(frame.cam_to_world, dtype=np.float64)
    return (p_cam @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)


class FrameToCloud:
    """``CameraFrame`` -> float32 ``[num_points, 3]``: back-project, crop, random pre-sample, FPS.

    Args:
        num_points: points after farthest point sampling (paper: 2048).
        presample: random sub-sample size before FPS (paper: 10,000; 0 = none).
        crop_low, crop_high: base-frame box kept.
        on_empty: a frame with no point in the box gives ``"centre"`` (``num_points`` copies of the box's
            centre: a simulated view can be empty) or ``"raise"`` (a real camera's: a dead depth stream or a
            wrong ``cam_to_base`` would otherwise drive the robot from a featureless cloud).
    """

    def __init__(self, num_points: int, presample: int, crop_low, crop_high, on_empty: str = "centre"):
        if num_points < 1:
            raise ValueError(f"num_points must be >= 1; got {num_points}")
        if on_empty not in ("centre", "raise"):
            raise ValueError(f"on_empty must be 'centre' or 'raise'; got {on_empty!r}")
        self.on_empty = on_empty
        self.num_points = int(num_points)
        self.presample = int(presample)
        self.crop_low = np.asarray(crop_low, dtype=np.float32)
        self.crop_high = np.asarray(crop_high, dtype=np.float32)
        self._rays: dict[tuple, np.ndarray] = {}

    def points(self, frame: CameraFrame) -> np.ndarray:
        """The cropped cloud before sub-sampling."""
        h, w = frame.depth.shape
        key = (h, w, *np.asarray(frame.intrinsics, dtype=np.float64).ravel().round(6))
        rays = self._rays.get(key)
        if rays is None:
            rays = self._rays[key] = _rays(h, w, frame.intrinsics)
        return crop_points(backproject(frame, rays), self.crop_low, self.crop_high)

    def __call__(self, frame: CameraFrame, rng: np.random.Generator) -> np.ndarray:
        pts = self.points(frame)
        if pts.shape[0] == 0 and self.on_empty == "raise":
            returns = int((np.asarray(frame.depth) > 0).sum())
            raise RuntimeError(f"the policy camera's frame has no point in the crop box {self.crop_low.tolist()}.."
                               f"{self.crop_high.tolist()} ({returns} pixels with a depth return): check the camera's "
                               "depth stream, its cam_to_base calibration and env.crop_min / crop_max")
        if pts.shape[0] == 0:
            centre = 0.5 * (self.crop_low + self.crop_high)
            return np.repeat(centre[None], self.num_points, axis=0).astype(np.float32)
        if self.presample > 0 and pts.shape[0] > self.presample:
            pts = pts[rng.choice(pts.shape[0], self.presample, replace=False)]
        start = int(rng.integers(pts.shape[0]))
        return pts[farthest_point_sample(pts, self.num_points, start=start)]
