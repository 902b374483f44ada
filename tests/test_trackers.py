"""Trackers: geometry helpers, the point-cloud tracker and the FoundationPose adapter on a small MuJoCo scene.

The scene (a table, two boxes, an occluding plate, two cameras) is built here,
independent of any env: depth and segmentation are rendered with
``mujoco.Renderer`` and handed to the trackers in the OpenCV convention of
``ddp.envs.franka.backend.CameraFrame``.
"""

from __future__ import annotations

import importlib
import math
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict

import ddp
from ddp.errors import DDPError, RecipeError
from ddp.schema import resolve_part
from ddp.trackers import geometry as geo
from ddp.trackers.foundationpose import FoundationPoseTracker, FoundationPoseTrackerConfig
from ddp.trackers.pointcloud import IsolationConfig, PointCloudTracker, PointCloudTrackerConfig

mujoco = pytest.importorskip("mujoco")

H, W, FOVY = 180, 240, 50.0
A0 = np.array([0.45, -0.10, 0.025])  # box "a" (5 cm cube) centre
B0 = np.array([0.50, 0.15, 0.025])  # box "b" (6 x 6 x 5 cm)
OFF_VIEW = np.array([3.0, 3.0, -3.0])
XML = f"""
<mujoco>
  <visual><quality shadowsize="0" offsamples="0"/><map znear="0.01" zfar="5"/></visual>
  <worldbody>
    <geom name="table" type="box" size="0.6 0.6 0.02" pos="0.5 0 -0.02"/>
    <body name="a" pos="{A0[0]} {A0[1]} {A0[2]}"><freejoint/><geom type="box" size="0.025 0.025 0.025"/></body>
    <body name="b" pos="{B0[0]} {B0[1]} {B0[2]}"><freejoint/><geom type="box" size="0.03 0.03 0.025"/></body>
    <body name="plate" mocap="true" pos="{OFF_VIEW[0]} {OFF_VIEW[1]} {OFF_VIEW[2]}">
      <geom type="box" size="0.01 0.08 0.1" contype="0" conaffinity="0"/>
    </body>
    <camera name="front" pos="1.3 0 0.7" xyaxes="0 1 0 -0.5 0 0.866" fovy="{FOVY}"/>
    <camera name="side" pos="0.6 -0.9 0.8" xyaxes="1 0 0 0 0.6 0.8" fovy="{FOVY}"/>
  </worldbody>
</mujoco>"""


class Scene:
    """The test scene: place the boxes, render an OpenCV-convention tracking frame."""

    def __init__(self):
        self.model = mujoco.MjModel.from_xml_string(XML)
        self.data = mujoco.MjData(self.model)
        self.renderer = mujoco.Renderer(self.model, H, W)
        self.objects = [self.model.body("a").id, self.model.body("b").id]
        self.reset()

    def reset(self):
        mujoco.mj_resetData(self.model, self.data)
        mujoco.mj_forward(self.model, self.data)

    def place(self, k: int, pos, quat=(1.0, 0.0, 0.0, 0.0)):
        adr = self.model.jnt_qposadr[self.model.body_jntadr[self.objects[k]]]
        self.data.qpos[adr : adr + 3] = pos
        self.data.qpos[adr + 3 : adr + 7] = quat
        mujoco.mj_forward(self.model, self.data)

    def move_plate(self, pos):
        self.data.mocap_pos[0] = pos
        mujoco.mj_forward(self.model, self.data)

    def object_pose(self, k: int) -> np.ndarray:
        b = self.objects[k]
        return geo.make_transform(self.data.xmat[b].reshape(3, 3), self.data.xpos[b])

    def frame(self, camera: str = "front") -> dict:
        r = self.renderer
        r.enable_depth_rendering()
        r.update_scene(self.data, camera=camera)
        depth = r.render().astype(np.float32)
        r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        r.update_scene(self.data, camera=camera)
        ids = r.render()
        r.disable_segmentation_rendering()
        geom_body = self.model.geom_bodyid
        seg = np.full((H, W), -1, dtype=np.int32)
        is_geom = (ids[..., 1] == mujoco.mjtObj.mjOBJ_GEOM) & (ids[..., 0] >= 0)
        body = np.where(is_geom, geom_body[np.clip(ids[..., 0], 0, None)], -1)
        for k, b in enumerate(self.objects):
            seg[body == b] = k
        depth[~is_geom] = 0.0  # no return from the background
        cam = self.model.camera(camera).id
        return {
            "depth": depth,
            "intrinsics": geo.intrinsics_from_fovy(FOVY, H, W),
            "cam_to_world": geo.mujoco_camera_to_opencv(self.data.cam_xpos[cam], self.data.cam_xmat[cam]),
            "segmentation": seg,
            "rgb": np.zeros((H, W, 3), dtype=np.uint8),
        }

    def close(self):
        self.renderer.close()


@pytest.fixture(scope="module")
def scene():
    s = Scene()
    yield s
    s.close()


@pytest.fixture(autouse=True)
def _fresh(scene):
    scene.reset()
    scene.move_plate(OFF_VIEW)


def observation(frames: list[dict], chunks: list[int], ee=None, segmentation: bool = True) -> TensorDict:
    """A batched ChunkedEnv-like observation: tracking keys, agent_pos [B, 2, 15], chunk_index [B, 1]."""
    keys = ["depth", "intrinsics", "cam_to_world", "rgb"] + (["segmentation"] if segmentation else [])
    tracking = {k: torch.as_tensor(np.stack([f[k] for f in frames])) for k in keys}
    agent = torch.zeros(len(frames), 2, 15)
    ee = [np.array([0.3, 0.0, 0.6])] * len(frames) if ee is None else ee
    agent[:, :, :3] = torch.as_tensor(np.stack(ee), dtype=torch.float32)[:, None]
    return TensorDict(
        {"tracking": tracking, "agent_pos": agent, "chunk_index": torch.tensor(chunks).reshape(-1, 1)},
        batch_size=[len(frames)],
    )


def track(tracker, scene, chunk, ee=None, segmentation=True, camera="front"):
    out = tracker(observation([scene.frame(camera)], [chunk], None if ee is None else [ee], segmentation))
    return tuple(out["ddp", k][0].numpy() for k in ("offsets", "object_visible", "object_carried"))


def pointcloud(**kw) -> PointCloudTracker:
    iso = kw.pop("isolation", {})
    return PointCloudTracker(PointCloudTrackerConfig(
        num_objects=2, isolation=IsolationConfig(expected_positions=[A0.tolist(), B0.tolist()], **iso), **kw))


def mm(x) -> float:
    return 1000.0 * float(np.linalg.norm(x))


# --------------------------------------------------------------------------- geometry
def test_rendered_depth_backprojects_onto_the_scene(scene):
    f = scene.frame()
    pts, pix = geo.backproject(f["depth"], f["intrinsics"], f["cam_to_world"])
    seg = f["segmentation"].reshape(-1)[pix]
    table = pts[seg == -1]
    np.testing.assert_allclose(table[:, 2], 0.0, atol=1e-4)  # the table top is z = 0 in the base frame
    a = pts[seg == 0]
    assert abs(a[:, 2].max() - 0.05) < 1e-4  # the top face of the 5 cm cube
    assert np.all(np.abs(a[:, :2] - A0[:2]) <= 0.025 + 1e-4)  # inside its footprint
    # projecting the cube's centre lands on its pixels (OpenCV K and cam_to_world agree)
    cam = geo.transform_points(geo.invert_transform(f["cam_to_world"]), A0[None])
    u, v = np.round(geo.project(cam, f["intrinsics"])[0]).astype(int)
    assert f["segmentation"][v, u] == 0


def test_icp_recovers_a_rigid_motion_and_kabsch_is_exact():
    rng = np.random.default_rng(0)
    src = rng.uniform(-0.05, 0.05, size=(400, 3)) * [1.0, 0.6, 0.3]
    a = math.radians(12)
    R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    t = np.array([0.02, -0.01, 0.005])
    dst = src @ R.T + t
    R2, t2 = geo.kabsch(src, dst)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    res = geo.icp(src, dst[rng.permutation(len(dst))], iterations=60)
    np.testing.assert_allclose(res.transform[:3, :3], R, atol=1e-3)
    np.testing.assert_allclose(res.transform[:3, 3], t, atol=1e-3)
    only_t = geo.icp(src, src + t, init=geo.make_transform(t=t * 0.5), rotation=False, iterations=60)
    np.testing.assert_allclose(only_t.transform[:3, 3], t, atol=1e-4)
    np.testing.assert_allclose(only_t.transform[:3, :3], np.eye(3))


def test_plane_and_voxel_clusters():
    rng = np.random.default_rng(1)
    table = np.c_[rng.uniform(0, 1, (3000, 2)), rng.normal(0.1, 0.001, 3000)]
    blob1 = rng.uniform(0, 0.04, (300, 3)) + [0.2, 0.2, 0.11]
    blob2 = rng.uniform(0, 0.04, (200, 3)) + [0.6, 0.5, 0.11]
    n, d, inl = geo.fit_plane_ransac(np.r_[table, blob1, blob2], threshold=0.004)
    assert n[2] > 0.999 and abs(-d / n[2] - 0.1) < 1e-3
    assert inl[:3000].mean() > 0.99 and inl[3000:].mean() < 0.05
    labels = geo.voxel_components(np.r_[blob2, blob1], 0.01)
    assert set(labels[200:]) == {0} and set(labels[:200]) == {1}  # ordered by size; two components
    # image-grid components: two blobs, and a depth step that splits one of them
    depth = np.zeros((20, 30))
    depth[2:8, 2:10] = 1.0
    depth[10:18, 12:28] = 1.0
    depth[10:18, 20:28] = 1.2  # 20 cm behind the left half: another surface
    for step in (1, 2):
        pix = np.flatnonzero(depth[::step, ::step] > 0)
        rows, cols = np.unravel_index(pix, depth[::step, ::step].shape)
        pix = rows * step * 30 + cols * step  # flat indices in the full image
        labels = geo.pixel_components(pix, depth.shape, depth, 0.05, step=step)
        r, c = pix // 30, pix % 30
        assert labels.max() == 2
        assert len(set(labels[(r < 8)])) == 1 and len(set(labels[(r >= 10) & (c < 20)])) == 1
        assert len({labels[(r < 8)][0], labels[(r >= 10) & (c < 20)][0], labels[(r >= 10) & (c >= 20)][0]}) == 3


def test_pose_displacement_is_camera_independent():
    cam1 = geo.make_transform(np.diag([1.0, -1.0, -1.0]), [0.5, 0.0, 1.0])
    a = math.radians(30)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    cam2 = geo.make_transform(turn @ cam1[:3, :3], [0.2, 0.3, 0.9])
    obj_then = geo.make_transform(t=[0.4, 0.1, 0.02])
    obj_now = geo.make_transform(t=[0.5, -0.05, 0.02])
    pose_then = geo.invert_transform(cam1) @ obj_then
    pose_now = geo.invert_transform(cam2) @ obj_now
    np.testing.assert_allclose(geo.pose_displacement(pose_now, pose_then, cam2, cam1), [0.1, -0.15, 0.0], atol=1e-12)


# --------------------------------------------------------------------------- pointcloud tracker
DELTAS = [(0.06, -0.04, 0.0), (-0.15, 0.10, 0.0), (0.10, -0.12, 0.0)]


@pytest.mark.parametrize("segmentation,clustering,stride",
                         [(True, "pixels", 1), (False, "pixels", 1), (False, "voxels", 1), (False, "pixels", 2)],
                         ids=["segmentation", "geometry", "geometry-voxels", "geometry-stride2"])
def test_pointcloud_tracker_measures_a_moved_box(scene, segmentation, clustering, stride):
    tracker = pointcloud(isolation={"clustering": clustering}, pixel_stride=stride)
    off, vis, _ = track(tracker, scene, 0, segmentation=segmentation)
    assert vis.all() and np.all(off == 0)
    for delta in DELTAS:
        scene.place(0, A0 + delta)
        off, vis, carried = track(tracker, scene, 1, segmentation=segmentation)
        assert vis.all() and not carried.any()
        assert mm(off[0] - delta) < 4.0 * stride, (delta, off[0])  # half the pixels: twice the tolerance
        assert np.all(off[1] == 0)  # the other box did not move


def test_pointcloud_tracker_known_table_height_and_touching_boxes(scene):
    tracker = pointcloud(isolation={"table_height": 0.0})
    track(tracker, scene, 0, segmentation=False)
    delta = np.array([0.05, 0.19, 0.0])  # ends 5 mm from box b: one voxel cluster
    scene.place(0, A0 + delta)
    off, vis, _ = track(tracker, scene, 1, segmentation=False)
    assert vis.all()
    assert mm(off[0] - delta) < 5.0, off[0]
    assert np.all(off[1] == 0)


def test_pointcloud_tracker_with_rigid_icp_and_without_refinement(scene):
    for refine in ("rigid", "none"):
        tracker = pointcloud(refine=refine)
        track(tracker, scene, 0)
        scene.place(0, A0 + [0.08, 0.05, 0.0])
        off, _, _ = track(tracker, scene, 1)
        assert mm(off[0] - [0.08, 0.05, 0.0]) < 5.0, (refine, off[0])
        scene.reset()


@pytest.mark.parametrize("segmentation", [True, False], ids=["segmentation", "geometry"])
def test_carried_object_reads_zero_and_is_reanchored_where_it_is_put_down(scene, segmentation):
    tracker = pointcloud()
    track(tracker, scene, 0, segmentation=segmentation)
    # the gripper holds box a and carries it 20 cm (without segmentation the box is mostly inside the
    # gripper's exclusion zone: partly or not visible, its position follows the end-effector)
    for step, shift in enumerate([0.0, 0.1, 0.2]):
        pos = A0 + [0.0, shift, 0.0]
        scene.place(0, pos)
        off, vis, carried = track(tracker, scene, 1 + step, ee=pos + [0, 0, 0.03], segmentation=segmentation)
        assert carried[0] and not carried[1] and np.all(off == 0)
        assert vis[1]
    # released: the gripper goes up, the box stays where it was put
    off, vis, carried = track(tracker, scene, 4, ee=A0 + [0.0, 0.2, 0.3], segmentation=segmentation)
    assert not carried.any() and vis.all() and np.all(off == 0)
    # now someone displaces it: measured from where the robot put it, not from the episode start
    scene.place(0, A0 + [0.0, 0.2, 0.0] + [-0.1, 0.05, 0.0])
    off, _, _ = track(tracker, scene, 5, ee=A0 + [0.0, 0.2, 0.3], segmentation=segmentation)
    assert mm(off[0] - [-0.1, 0.05, 0.0]) < 4.0, off[0]
    if not segmentation:
        return
    # a disabled carried check reports the robot's motion too
    plain = pointcloud(carried_radius=0.0)
    scene.place(0, A0)
    track(plain, scene, 0)
    scene.place(0, A0 + [0.0, 0.1, 0.0])
    off, _, carried = track(plain, scene, 1, ee=A0 + [0.0, 0.1, 0.03])
    assert not carried.any() and mm(off[0] - [0.0, 0.1, 0.0]) < 4.0


def test_gripper_passing_by_does_not_swallow_a_displacement(scene):
    tracker = pointcloud()
    track(tracker, scene, 0)
    delta = np.array([0.05, 0.1, 0.0])
    scene.place(1, B0 + delta)
    off, _, _ = track(tracker, scene, 1)
    assert mm(off[1] - delta) < 4.0
    # the gripper comes down next to box b (e.g. to stack onto it) and leaves without moving it
    off, _, carried = track(tracker, scene, 2, ee=B0 + delta + [0.0, 0.0, 0.045])
    assert carried[1] and np.all(off[1] == 0)
    off, _, carried = track(tracker, scene, 3, ee=B0 + delta + [0.0, 0.0, 0.3])
    assert not carried.any() and mm(off[1] - delta) < 4.0


def test_an_object_displaced_away_from_a_hovering_gripper_is_not_taken_as_put_down(scene):
    """The gripper comes within reach of box a (about to grasp it); then someone moves the box 15 cm while the
    gripper stays: the box did not move with the hand, so it reads displaced (not re-anchored there)."""
    tracker = pointcloud()
    track(tracker, scene, 0)
    hover = A0 + [0.0, 0.0, 0.045]
    off, _, carried = track(tracker, scene, 1, ee=hover)
    assert carried[0] and np.all(off[0] == 0)
    delta = np.array([0.0, 0.15, 0.0])
    scene.place(0, A0 + delta)
    off, _, carried = track(tracker, scene, 2, ee=hover)
    assert not carried[0] and mm(off[0] - delta) < 4.0, off[0]


def test_partly_hidden_object_that_did_not_move_reads_zero(scene):
    tracker = pointcloud()
    track(tracker, scene, 0)
    full = (scene.frame()["segmentation"] == 0).sum()
    for y in (-0.045, 0.115):  # the plate hides one side of box a, then the other
        scene.move_plate([0.75, A0[1] + y, 0.2])
        part = (scene.frame()["segmentation"] == 0).sum()
        assert 0.2 * full < part < 0.8 * full
        off, vis, _ = track(tracker, scene, 1)
        assert vis.all() and np.all(off == 0), off


@pytest.mark.parametrize("segmentation", [True, False], ids=["segmentation", "geometry"])
def test_occluded_object_reads_zero_and_not_visible(scene, segmentation):
    tracker = pointcloud()
    track(tracker, scene, 0, segmentation=segmentation)
    scene.place(0, A0 + [0.05, 0.0, 0.0])
    scene.move_plate([0.75, A0[1], 0.2])  # a plate between the camera and box a
    assert (scene.frame()["segmentation"] == 0).sum() == 0
    off, vis, _ = track(tracker, scene, 1, segmentation=segmentation)
    assert not vis[0] and np.all(off[0] == 0)
    assert vis[1] and np.all(off[1] == 0)
    scene.move_plate(OFF_VIEW)  # visible again: measured again
    off, vis, _ = track(tracker, scene, 2, segmentation=segmentation)
    assert vis.all() and mm(off[0] - [0.05, 0.0, 0.0]) < 4.0


def test_an_object_hidden_on_the_first_frame_is_said_and_a_count_from_labels_is_checked(scene):
    """An object not found on the episode's first frame read offset 0 and not visible for the whole episode,
    silently; without num_objects the count came from that frame's labels, so a hidden last object left the
    count short (the controller then blamed the recipe's subtask target)."""
    from ddp.errors import RecipeError

    scene.move_plate([0.75, A0[1], 0.2])  # box a (label 0) hidden on the first frame
    with pytest.warns(RuntimeWarning, match=r"environment 0: object\(s\) \[0\] not found on the episode's first frame"):
        track(pointcloud(), scene, 0)
    scene.move_plate(OFF_VIEW)
    scene.place(1, B0 + [0.0, 0.0, -1.0])  # box b (label 1, the last) below the table: not in view
    counted = PointCloudTracker(PointCloudTrackerConfig())  # count from the labels
    off, _, _ = track(counted, scene, 0)
    assert off.shape == (1, 3)
    scene.place(1, B0)  # back in view: label 1 appears
    with pytest.raises(RecipeError, match=r"controller.tracker.num_objects: the segmentation shows object label 1, "
                                          r"but the episode's first frame showed 1 object"):
        track(counted, scene, 1)


def test_reference_is_per_environment_and_reset_at_chunk_zero(scene):
    tracker = pointcloud()
    start = scene.frame()
    out = tracker(observation([start, start], [0, 0]))
    assert out["ddp", "offsets"].shape == (2, 2, 3) and out["ddp", "offsets"].abs().max() == 0
    d1 = np.array([0.07, 0.03, 0.0])
    scene.place(0, A0 + d1)
    moved = scene.frame()
    # env 0 continues its episode; env 1 starts a new one in the moved scene (its new reference)
    out = tracker(observation([moved, moved], [1, 0]))["ddp", "offsets"].numpy()
    assert mm(out[0, 0] - d1) < 4.0 and np.all(out[1] == 0)
    d2 = np.array([-0.05, 0.04, 0.0])
    scene.place(0, A0 + d1 + d2)
    again = scene.frame()
    out = tracker(observation([again, again], [2, 1]))["ddp", "offsets"].numpy()
    assert mm(out[0, 0] - (d1 + d2)) < 4.0 and mm(out[1, 0] - d2) < 4.0
    # unbatched call, after reset(): the first call sets the reference
    tracker.reset()
    out = tracker(observation([again], [3])[0])
    assert out["ddp", "offsets"].shape == (2, 3) and out["ddp", "offsets"].abs().max() == 0


def test_pointcloud_tracker_config_errors():
    with pytest.raises(DDPError, match="controller.tracker.isolation"):
        resolve_part("tracker", {"name": "pointcloud", "isolation": {"workspace": [0, 1]}},
                     key="controller.tracker", source="r.yaml")
    tracker = PointCloudTracker(PointCloudTrackerConfig(num_objects=2))
    td = observation([{"depth": np.ones((4, 4), np.float32), "intrinsics": np.eye(3), "cam_to_world": np.eye(4),
                       "rgb": np.zeros((4, 4, 3), np.uint8)}], [0], segmentation=False)
    with pytest.raises(RecipeError, match="controller.tracker.isolation.expected_positions: without a segmentation"):
        tracker(td)
    # no tracking camera in the observation (MetaWorld, franka without tracking_camera): one line, not an
    # IndexError deep in the tracker
    with pytest.raises(RecipeError, match=r"controller.tracker: tracker 'PointCloudTracker' reads \('tracking', "
                                          r"'depth'\), which the observation lacks"):
        tracker(TensorDict({"agent_pos": torch.zeros(1, 2, 15)}, batch_size=[1]))
    with pytest.raises(ValueError, match=r"num_objects is 1 but isolation.expected_positions lists 2 position\(s\)"):
        PointCloudTrackerConfig(num_objects=1, isolation=IsolationConfig(expected_positions=[[0, 0, 0], [1, 0, 0]]))
    with pytest.raises(ValueError, match=r"num_objects is 3 but meshes lists 2"):
        FoundationPoseTrackerConfig(meshes=["a.obj", "b.obj"], num_objects=3)
    with pytest.raises(ValueError, match=r"2 object\(s\) but isolation.expected_positions lists 1"):
        FoundationPoseTrackerConfig(num_objects=2, isolation=IsolationConfig(expected_positions=[[0, 0, 0]]))


def test_trackers_are_registered_and_build_from_a_recipe_section():
    assert {"oracle", "pointcloud", "foundationpose"} <= set(ddp.list_plugins("tracker"))
    part = resolve_part("tracker", {"name": "pointcloud", "num_objects": 2, "refine": "rigid"},
                        key="controller.tracker", source="r.yaml")
    assert isinstance(part.build(), PointCloudTracker)


# --------------------------------------------------------------------------- foundationpose
def test_foundationpose_without_the_package_fails_at_build_with_one_line():
    with pytest.raises(DDPError) as err:
        resolve_part("tracker", {"name": "foundationpose", "meshes": ["a.obj"]},
                     key="controller.tracker", source="r.yaml").build()
    msg = str(err.value)
    assert "\n" not in msg and "NVlabs/FoundationPose" in msg and "build_all.sh" in msg and "weights" in msg


def test_foundationpose_without_weights_fails_at_build_with_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "path", list(sys.path))  # the adapter puts repo on sys.path
    # a checkout whose estimater.py must never be imported: the weights check comes first
    (tmp_path / "estimater.py").write_text("raise RuntimeError('imported')\n")
    (tmp_path / "weights" / "2023-10-28-18-33-37").mkdir(parents=True)
    with pytest.raises(DDPError) as err:
        FoundationPoseTracker(FoundationPoseTrackerConfig(repo=str(tmp_path), module="estimater_ddp_test_missing"))
    assert "cannot find" in str(err.value)
    (tmp_path / "estimater_ddp_test.py").write_text("raise RuntimeError('imported')\n")
    importlib.invalidate_caches()
    with pytest.raises(DDPError) as err:
        FoundationPoseTracker(FoundationPoseTrackerConfig(repo=str(tmp_path), module="estimater_ddp_test",
                                                          meshes=["a.obj"]))
    msg = str(err.value)
    assert "\n" not in msg and "weights missing" in msg and "2024-01-11-20-02-45" in msg and "imported" not in msg


class SimulatorPoses:
    """A pose source returning the simulator's object pose in the OpenCV camera frame (FoundationPose's output)."""

    def __init__(self, scene: Scene, k: int, calls: list):
        self.scene, self.k, self.calls = scene, k, calls

    def _pose(self, K, depth):
        f = self.scene.last_frame
        assert np.array_equal(depth, f["depth"]) and np.allclose(K, f["intrinsics"])
        return geo.invert_transform(f["cam_to_world"]) @ self.scene.object_pose(self.k)

    def register(self, K, rgb, depth, mask, iterations):
        f = self.scene.last_frame
        assert mask.shape == depth.shape and mask.dtype == bool
        assert np.array_equal(mask, f["segmentation"] == self.k)  # the object's own pixels
        self.calls.append(("register", self.k, iterations))
        return self._pose(K, depth)

    def track(self, K, rgb, depth, iterations):
        self.calls.append(("track", self.k, iterations))
        return self._pose(K, depth)


def _fp_observe(tracker, scene, chunk, camera="front", ee=None):
    scene.last_frame = scene.frame(camera)
    out = tracker(observation([scene.last_frame], [chunk], None if ee is None else [ee]))
    return out["ddp", "offsets"][0].numpy().astype(np.float64), out["ddp", "object_visible"][0].numpy()


def _quat_z(angle):
    return (math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2))


@pytest.mark.parametrize("mode", ["track", "register"])
def test_foundationpose_geometry_from_simulator_poses(scene, mode):
    calls = []
    point = [0.02, 0.0, 0.0]  # an off-centre object point: rotation matters
    tracker = FoundationPoseTracker(
        FoundationPoseTrackerConfig(num_objects=2, mode=mode, point=point, min_offset=0.0, register_iterations=4),
        estimator_factory=lambda k: SimulatorPoses(scene, k, calls),
    )
    off, vis = _fp_observe(tracker, scene, 0)
    assert vis.all() and np.all(off == 0) and calls == [("register", 0, 4), ("register", 1, 4)]
    # box a slides and turns; the tracking camera is also moved (cam_to_world changes between frames)
    delta, angle = np.array([0.08, -0.05, 0.0]), math.radians(35)
    scene.place(0, A0 + delta, _quat_z(angle))
    off, vis = _fp_observe(tracker, scene, 1, camera="side")
    rot = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    truth = (A0 + delta + rot @ point) - (A0 + point)
    np.testing.assert_allclose(off[0], truth, atol=1e-5)
    np.testing.assert_allclose(off[1], 0.0, atol=1e-5)
    assert vis.all()
    assert calls[-1][0] == ("track" if mode == "track" else "register")
    # carried objects read zero
    off, _ = _fp_observe(tracker, scene, 2, ee=A0 + delta + [0, 0, 0.03])
    assert np.all(off[0] == 0)


class LostTrack(SimulatorPoses):
    """track_one that lost its object: it keeps answering the pose it last registered (FoundationPose's
    tracker drifts that way after a fast move or an occlusion)."""

    def register(self, K, rgb, depth, mask, iterations):
        self.stale = super().register(K, rgb, depth, mask, iterations)
        return self.stale

    def track(self, K, rgb, depth, iterations):
        self.calls.append(("track", self.k, iterations))
        return self.stale


def test_foundationpose_track_mode_registers_again_when_the_pose_leaves_the_objects_pixels(scene):
    """mode: track checks each tracked pose against the object's observed points: a pose 9 cm from them (the
    lost tracker's stale answer) is registered again from the object's mask, so the move is reported; a pose
    that agrees is kept (no extra registration)."""
    calls = []
    tracker = FoundationPoseTracker(FoundationPoseTrackerConfig(num_objects=2, min_offset=0.0),
                                    estimator_factory=lambda k: LostTrack(scene, k, calls))
    _fp_observe(tracker, scene, 0)
    off, vis = _fp_observe(tracker, scene, 1)  # nothing moved: the stale pose is right
    assert np.allclose(off, 0.0, atol=1e-6) and tracker.reregistered == 0
    scene.place(0, A0 + [0.08, -0.04, 0.0])
    off, vis = _fp_observe(tracker, scene, 2)
    np.testing.assert_allclose(off[0], [0.08, -0.04, 0.0], atol=1e-5)  # before: 0 (the stale pose accepted)
    assert tracker.reregistered == 1 and calls[-3:] == [("track", 0, 2), ("register", 0, 5), ("track", 1, 2)]
    unchecked = FoundationPoseTracker(FoundationPoseTrackerConfig(num_objects=2, min_offset=0.0, track_tolerance=None),
                                      estimator_factory=lambda k: LostTrack(scene, k, []))
    scene.place(0, A0)
    _fp_observe(unchecked, scene, 0)
    scene.place(0, A0 + [0.08, -0.04, 0.0])
    assert np.allclose(_fp_observe(unchecked, scene, 1)[0][0], 0.0)  # the check off: the lost pose is believed
    with pytest.raises(ValueError, match="track_tolerance must be a finite number > 0"):
        FoundationPoseTrackerConfig(num_objects=1, track_tolerance=float("nan"))


class CornerOrigin(SimulatorPoses):
    """Poses of a mesh whose origin sits 8 cm off the object's centre (a corner-origin CAD export)."""

    def _pose(self, K, depth):
        shift = np.eye(4)
        shift[:3, 3] = [0.08, 0.0, 0.0]
        return super()._pose(K, depth) @ shift


def test_foundationpose_track_check_expects_the_surface_where_registration_saw_it(scene):
    """The visible surface of an object whose mesh origin is off its centre lies far from that origin: the
    check compares the centroid with where registration saw the surface, so a right pose is not registered
    again every cycle."""
    tracker = FoundationPoseTracker(FoundationPoseTrackerConfig(num_objects=2, min_offset=0.0),
                                    estimator_factory=lambda k: CornerOrigin(scene, k, []))
    _fp_observe(tracker, scene, 0)
    for chunk in (1, 2, 3):
        off, vis = _fp_observe(tracker, scene, chunk)
    assert tracker.reregistered == 0 and vis.all() and np.allclose(off, 0.0, atol=1e-6)


class RegistersOnTheMask(SimulatorPoses):
    """FoundationPose registering on whichever object the mask holds (most of its pixels), with a mesh origin
    off the object's centre: 25 cm in +y, right onto box b's centre for box a."""

    SHIFT = [0.05, 0.25, 0.0]

    def register(self, K, rgb, depth, mask, iterations):
        f = self.scene.last_frame
        labels = f["segmentation"][mask]
        k = int(np.bincount(labels[labels >= 0]).argmax())
        self.calls.append(("register", self.k, k))
        shift = np.eye(4)
        shift[:3, 3] = self.SHIFT
        return geo.invert_transform(f["cam_to_world"]) @ self.scene.object_pose(k) @ shift


def test_foundationpose_geometric_masks_are_looked_for_where_the_surface_was_seen(scene):
    """Geometric registration masks (hardware) are found near where each object's points were seen, not near
    its reported point (the mesh origin): box a's origin lies on box b, and looking there gave a box b's mask
    (a false 26 cm displacement of a)."""
    calls = []
    tracker = FoundationPoseTracker(
        FoundationPoseTrackerConfig(num_objects=2, mode="register", masks="geometry", min_offset=0.0,
                                    isolation=IsolationConfig(expected_positions=[A0.tolist(), B0.tolist()])),
        estimator_factory=lambda k: RegistersOnTheMask(scene, k, calls))
    off, vis = _fp_observe(tracker, scene, 0)
    assert vis.all() and calls == [("register", 0, 0), ("register", 1, 1)]
    off, vis = _fp_observe(tracker, scene, 1)  # nothing moved
    assert calls[-2:] == [("register", 0, 0), ("register", 1, 1)] and np.allclose(off, 0.0, atol=1e-5)
    scene.place(0, A0 + [0.06, -0.04, 0.0])
    off, vis = _fp_observe(tracker, scene, 2)
    np.testing.assert_allclose(off[0], [0.06, -0.04, 0.0], atol=1e-5)
    np.testing.assert_allclose(off[1], 0.0, atol=1e-5)


def _unlabelled(frame: dict) -> dict:
    """What FrankaEnv writes for a tracking camera that renders no segmentation (a RealSense): every pixel -1."""
    return {**frame, "segmentation": np.full_like(frame["segmentation"], -1)}


def test_a_camera_without_segmentation_is_tracked_by_geometry_in_auto_mode(scene):
    """In auto mode an episode whose first tracking frame has no labelled pixel isolates objects by geometry:
    masks from the env's all -1 image read every object as not visible with a zero offset (hardware tracked
    nothing, silently)."""
    def observe(tracker, chunk):
        out = tracker(observation([_unlabelled(scene.frame())], [chunk]))
        return out["ddp", "offsets"][0].numpy(), out["ddp", "object_visible"][0].numpy()

    tracker = pointcloud()  # segmentation: auto
    off, vis = observe(tracker, 0)
    assert vis.all() and np.all(off == 0) and tracker.masked == {0: False}
    scene.place(0, A0 + np.array([0.0, 0.1, 0.0]))
    off, vis = observe(tracker, 1)
    assert vis.all() and mm(off[0] - [0.0, 0.1, 0.0]) < 4.0 and np.all(off[1] == 0)
    # labelled frames keep the masks (the simulator's path), decided again at the next episode's first frame
    scene.reset()
    scene.move_plate(OFF_VIEW)
    track(tracker, scene, 0)
    assert tracker.masked == {0: True}
    # without expected positions (nowhere to look by geometry; in simulation every object may be hidden at the
    # first frame) the masks stay, with a warning: not visible, not an error
    blind = PointCloudTracker(PointCloudTrackerConfig(num_objects=2))
    with pytest.warns(RuntimeWarning, match="labels no pixel"):
        out = blind(observation([_unlabelled(scene.frame())], [0]))
    assert blind.masked == {0: True} and not out["ddp", "object_visible"][0].any()
    # FoundationPose's registration masks likewise: found by geometry near each object's expected position
    calls = []
    fp = FoundationPoseTracker(
        FoundationPoseTrackerConfig(num_objects=2, mode="register", min_offset=0.0,
                                    isolation=IsolationConfig(expected_positions=[A0.tolist(), B0.tolist()])),
        estimator_factory=lambda k: RegistersOnTheMask(scene, k, calls))
    scene.last_frame = scene.frame()  # the estimator reads the true labels; the tracker sees none
    out = fp(observation([_unlabelled(scene.last_frame)], [0]))
    assert out["ddp", "object_visible"][0].all() and calls == [("register", 0, 0), ("register", 1, 1)]
    # the colour image stays optional for the trackers (a depth-only estimator); the camera's depth is not
    td = observation([scene.last_frame], [0])
    del td["tracking", "rgb"]
    depth_only = FoundationPoseTracker(FoundationPoseTrackerConfig(num_objects=2, mode="register"),
                                       estimator_factory=lambda k: SimulatorPoses(scene, k, []))
    assert depth_only(td)["ddp", "object_visible"][0].all()


def test_foundationpose_default_offsets_match_the_box_displacement(scene):
    tracker = FoundationPoseTracker(FoundationPoseTrackerConfig(num_objects=2),
                                    estimator_factory=lambda k: SimulatorPoses(scene, k, []))
    _fp_observe(tracker, scene, 0)
    scene.place(1, B0 + [-0.1, 0.05, 0.0])
    off, _ = _fp_observe(tracker, scene, 1)
    np.testing.assert_allclose(off[1], [-0.1, 0.05, 0.0], atol=1e-5)
    assert np.all(off[0] == 0)
    scene.place(1, B0 + [0.004, 0.0, 0.0])  # under min_offset (1 cm): not a displacement
    off, _ = _fp_observe(tracker, scene, 2)
    assert np.all(off == 0)
