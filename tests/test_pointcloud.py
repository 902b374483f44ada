"""ddp.envs.pointcloud: back-projection, crop and farthest point sampling (no simulator needed)."""

import math

import numpy as np
import pytest

from ddp.envs.pointcloud import (
    DepthToCloud,
    camera_rays,
    crop_points,
    depth_to_points,
    farthest_point_sample,
)


def _rot_x(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _plane_depth(height, width, fovy, cam_pos, cam_rot, plane_z=0.0):
    """Analytic metric depth of the plane z = plane_z seen by a pinhole camera (independent ray maths)."""
    f = 0.5 * height / math.tan(0.5 * math.radians(fovy))
    depth = np.empty((height, width))
    for i in range(height):
        for j in range(width):
            d_cam = np.array([(j + 0.5 - width / 2) / f, -(i + 0.5 - height / 2) / f, -1.0])
            d_world = cam_rot @ d_cam
            depth[i, j] = (plane_z - cam_pos[2]) / d_world[2]  # z_cam = -1 -> depth = ray parameter
    return depth


def test_camera_looking_down_sees_a_flat_plane_with_the_right_extent():
    h, w, fovy, height_above = 24, 32, 60.0, 1.5
    cam_pos = np.array([0.2, -0.1, height_above])
    depth = np.full((h, w), height_above)  # a plane orthogonal to the optical axis
    pts = depth_to_points(depth, camera_rays(h, w, fovy), cam_pos, np.eye(3))
    assert pts.shape == (h * w, 3) and pts.dtype == np.float32
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-6)
    # vertical half-extent = d * tan(fovy/2) * (1 - 1/h) at the pixel centres
    half_y = height_above * math.tan(math.radians(fovy / 2)) * (1 - 1 / h)
    np.testing.assert_allclose(pts[:, 1].max() - cam_pos[1], half_y, rtol=1e-5)
    np.testing.assert_allclose(pts[:, 1].min() - cam_pos[1], -half_y, rtol=1e-5)
    half_x = half_y * w / h * (1 - 1 / w) / (1 - 1 / h)
    np.testing.assert_allclose(pts[:, 0].max() - cam_pos[0], half_x, rtol=1e-5)
    grid = pts.reshape(h, w, 3)
    assert grid[0, 0, 1] > grid[-1, 0, 1], "row 0 is the top of the image (camera y up)"
    assert grid[0, 0, 0] < grid[0, -1, 0], "column 0 is the left of the image (camera x right)"


def test_tilted_camera_back_projects_a_known_plane():
    h, w, fovy = 20, 20, 45.0
    cam_pos = np.array([0.0, -1.0, 0.8])
    cam_rot = _rot_x(math.radians(50.0))  # pitched up from looking straight down: sees the plane obliquely
    depth = _plane_depth(h, w, fovy, cam_pos, cam_rot, plane_z=0.1)
    assert np.all(depth > 0) and depth.std() > 0.05, "the plane is seen at varying depths"
    pts = depth_to_points(depth, camera_rays(h, w, fovy), cam_pos, cam_rot)
    np.testing.assert_allclose(pts[:, 2], 0.1, atol=1e-5)
    # the optical axis hits the plane where the central pixels point
    axis = cam_rot @ np.array([0.0, 0.0, -1.0])
    hit = cam_pos + axis * (0.1 - cam_pos[2]) / axis[2]
    centre = pts.reshape(h, w, 3)[h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1].reshape(-1, 3).mean(0)
    np.testing.assert_allclose(centre, hit, atol=0.02)


def test_crop_keeps_only_the_box():
    pts = np.array([[0, 0, 0], [1, 1, 1], [2, 0, 0], [0.5, -0.1, 0.5]], dtype=np.float32)
    kept = crop_points(pts, (0, 0, 0), (1, 1, 1))
    np.testing.assert_array_equal(kept, pts[:2])


def test_fps_returns_distinct_points_and_covers_the_extremes():
    line = np.stack([np.linspace(0.0, 1.0, 101), np.zeros(101), np.zeros(101)], 1)
    idx = farthest_point_sample(line, 3, start=50)
    assert idx.dtype == np.int64
    assert idx.tolist() == [50, 0, 100], "from the middle, FPS picks both ends (ties -> lowest index)"

    pts = np.random.default_rng(0).random((500, 3))
    idx = farthest_point_sample(pts, 64)
    assert len(set(idx.tolist())) == 64
    sample = pts[idx]
    # greedy FPS: every point lies closer to the sample than any two samples lie to each other
    covering = np.linalg.norm(pts[:, None] - sample[None], axis=-1).min(1).max()
    pair = np.linalg.norm(sample[:, None] - sample[None], axis=-1)
    separation = pair[~np.eye(64, dtype=bool)].min()
    assert covering <= separation + 1e-12


def test_fps_is_deterministic_given_a_generator():
    pts = np.random.default_rng(1).random((300, 3))
    a = farthest_point_sample(pts, 32, generator=np.random.default_rng(7))
    b = farthest_point_sample(pts, 32, generator=np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    starts = {int(farthest_point_sample(pts, 1, generator=np.random.default_rng(s))[0]) for s in range(10)}
    assert len(starts) > 1, "the generator draws the start point"


def test_fps_backends_agree():
    pytest.importorskip("numba")
    pts = np.random.default_rng(2).random((2000, 3)).astype(np.float32)
    np.testing.assert_array_equal(
        farthest_point_sample(pts, 128, start=5, backend="numba"),
        farthest_point_sample(pts, 128, start=5, backend="numpy"),
    )


def test_fps_pads_small_clouds_and_rejects_bad_input():
    pts = np.random.default_rng(3).random((5, 3))
    idx = farthest_point_sample(pts, 12)
    assert idx.shape == (12,) and set(idx.tolist()) == set(range(5))
    with pytest.raises(ValueError, match="at least one point"):
        farthest_point_sample(np.zeros((0, 3)), 4)
    with pytest.raises(ValueError, match=r"shape \[N, 3\]"):
        farthest_point_sample(np.zeros((4, 2)), 2)
    with pytest.raises(ValueError, match="backend"):
        farthest_point_sample(pts, 2, backend="cuda")


def test_depth_to_cloud_crops_and_samples():
    h = w = 16
    cam_pos = np.array([0.0, 0.0, 1.0])
    depth = np.full((h, w), 1.0)
    depth[:, : w // 2] = 0.5  # left half: a step at z = 0.5
    to_cloud = DepthToCloud(h, w, 60.0, (-1, -1, 0.25), (1, 1, 1), num_points=20)
    cloud = to_cloud(depth, cam_pos, np.eye(3))
    assert cloud.shape == (20, 3) and cloud.dtype == np.float32
    np.testing.assert_allclose(cloud[:, 2], 0.5, atol=1e-6)  # the floor (z = 0) is cropped away
    empty = DepthToCloud(h, w, 60.0, (5, 5, 5), (6, 6, 6), num_points=4)(depth, cam_pos, np.eye(3))
    np.testing.assert_allclose(empty, np.full((4, 3), 5.5))
    with pytest.raises(ValueError, match="crop_low must be below crop_high"):
        DepthToCloud(h, w, 60.0, (0, 0, 1), (1, 1, 0), num_points=4)


def test_a_displacement_is_acted_on_only_if_a_chunk_follows_its_first_observation():
    """The rule both envs refuse schedules by: the move at step k*c is first observed at k*c + c, which must
    not be the episode's end; the oracle's snap-back must start within the episode."""
    from ddp.envs.disturbances import Displacement

    move = Displacement(("obj",), (0.1, 0.0, 0.0), chunk=3, tracking="two_stage", snap_back_chunk=5)
    assert move.acted_on(8, 33) and not move.acted_on(8, 32)  # observed at step 32
    assert move.snaps_back_in(8, 41) and not move.snaps_back_in(8, 40)  # the snap-back at step 40
    assert Displacement(("obj",), (0.1, 0.0, 0.0), chunk=3).snaps_back_in(8, 1)  # single-stage: none
