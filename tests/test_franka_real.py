"""The real Franka backend (franky), tested for real against franky-sim on loopback.

franky-sim (``bash scripts/setup_franky_sim.sh`` puts it in ``.venv-franky-sim``, or
``$FRANKY_SIM_VENV``) speaks the libfranka protocol exactly as a Franka does; its server
(``ddp/envs/franka/franky_sim_server.py``) also renders depth frames from its live MuJoCo scene,
standing in for the RealSense. The server runs as a separate process started here and stopped by
its PID. Only when that environment is missing are the live tests skipped.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import pytest

from ddp.envs.franka.cameras import CalibrationError, load_calibration, make_camera
from ddp.envs.franka.env import FrankaEnvConfig
from ddp.envs.franka.real import RealBackendConfig, limit_target, quat_angle, quat_from_rotvec
from ddp.safety import NonFiniteError
from ddp.envs.franka.tasks.stack import GREEN_HALF, PINK_HALF

ROOT = Path(__file__).resolve().parents[1]
SERVER = ROOT / "ddp" / "envs" / "franka" / "franky_sim_server.py"
FRANKY_SIM_VENV = Path(os.environ.get("FRANKY_SIM_VENV", ROOT / ".venv-franky-sim"))
FRANKY_SIM_PYTHON = FRANKY_SIM_VENV / "bin" / "python"
DOWN_WXYZ = np.array([0.0, 1.0, 0.0, 0.0])  # 180 degrees about x: the hand points down


# ------------------------------------------------------------------------------------ no server
def test_limit_target_clips_to_box_and_step():
    cur = np.array([0.5, 0.0, 0.3])
    # far outside the box: clipped into it, then shortened to one step from the measured pose
    pos, quat, limited = limit_target(cur, DOWN_WXYZ, [2.0, 0.0, -1.0], DOWN_WXYZ, [0.2, -0.4, 0.01], [0.7, 0.4, 0.5], 0.05, 0.3)
    assert limited
    assert np.linalg.norm(pos - cur) == pytest.approx(0.05)
    assert np.all(pos >= [0.2, -0.4, 0.01]) and np.all(pos <= [0.7, 0.4, 0.5])
    # a small step inside the box passes unchanged
    pos, quat, limited = limit_target(cur, DOWN_WXYZ, cur + 0.01, DOWN_WXYZ, [0.2, -0.4, 0.01], [0.7, 0.4, 0.5], 0.05, 0.3)
    assert not limited and np.allclose(pos, cur + 0.01) and np.allclose(quat, DOWN_WXYZ)
    # a large rotation is cut to max_rotation
    target_q = quat_from_rotvec([1.0, 0.0, 0.0])  # 1 rad about x from identity
    pos, quat, limited = limit_target(cur, [1.0, 0, 0, 0], cur, target_q, [0, -1, 0], [1, 1, 1], 0.05, 0.3)
    assert limited and quat_angle([1.0, 0, 0, 0], quat) == pytest.approx(0.3, abs=1e-6)
    # out of reach (arm stretched, near its singularity): pulled back until the wrist is within max_reach
    far = np.array([0.7, 0.0, 0.45])
    pos, _, limited = limit_target(far, DOWN_WXYZ, far, DOWN_WXYZ, [0, -1, 0], [1, 1, 1], 1.0, 1.0, max_reach=0.72)
    wrist = pos + [0.0, 0.0, 0.2104] - [0.0, 0.0, 0.333]  # the hand points down: the wrist is above the TCP
    assert limited and np.linalg.norm(wrist) == pytest.approx(0.72) and pos[0] < 0.7
    near = np.array([0.55, -0.1, 0.02])  # a block on the table is within reach
    assert not limit_target(near, DOWN_WXYZ, near, DOWN_WXYZ, [0, -1, 0], [1, 1, 1], 1.0, 1.0, max_reach=0.72)[2]
    # the box wins: a pull-back toward the shoulder, or a step from a measured pose outside the box, is clipped
    pos, _, _ = limit_target(far, DOWN_WXYZ, far, DOWN_WXYZ, [0.69, -1, 0], [1, 1, 1], 1.0, 1.0, max_reach=0.72)
    assert pos[0] == pytest.approx(0.69)  # pulled back to x 0.652 without the box
    outside = np.array([0.1, 0.0, 0.3])
    pos, _, limited = limit_target(outside, DOWN_WXYZ, [0.6, 0.0, 0.3], DOWN_WXYZ, [0.2, -0.4, 0.01], [0.7, 0.4, 0.5],
                                   0.05, 0.3)
    assert limited and pos[0] == pytest.approx(0.2)
    # a NaN measured position would pass every step limit (NaN > x is False): refused, the arm is not moved
    with pytest.raises(ValueError, match="measured position must be 3 finite numbers"):
        limit_target([np.nan, 0.0, 0.3], DOWN_WXYZ, [0.5, 0.3, 0.4], DOWN_WXYZ, [0, -1, 0], [1, 1, 1], 0.01, 0.05)


def test_the_backend_never_moves_from_a_nan_measured_pose():
    """FrankyBackend.move_to measures its step limits from the arm's pose: a NaN reading stops it there."""
    from ddp.envs.franka.real import FrankyBackend, RealBackendConfig
    from ddp.safety import NonFiniteError

    class Robot:
        moves = []

        def poll_motion(self):
            pass

        def move(self, motion, asynchronous=False):
            self.moves.append(motion)

    backend = FrankyBackend.__new__(FrankyBackend)  # no franky here: the parts move_to reads before moving
    backend.config, backend.robot = RealBackendConfig(), Robot()
    backend.ee_pose = lambda: (np.array([np.nan, 0.0, 0.3]), DOWN_WXYZ)
    with pytest.raises(NonFiniteError, match="franky backend: refused a non-finite measured end-effector pose"):
        backend.move_to(np.array([0.5, 0.3, 0.4]), DOWN_WXYZ)
    assert backend.robot.moves == []


def test_require_finite_reads_bf16():
    from ddp.safety import NonFiniteError, require_finite

    require_finite("action", torch.zeros(3, dtype=torch.bfloat16), "test")
    require_finite("action", torch.tensor([1e300], dtype=torch.float64), "test")  # finite: not cast down to inf
    with pytest.raises(NonFiniteError, match="test: refused a non-finite action \\(1 of 3"):
        require_finite("action", torch.tensor([0.0, float("nan"), 1.0], dtype=torch.bfloat16), "test")


def test_control_never_sends_a_nonfinite_target():
    """A measured pose that reads NaN (a sensor fault) never turns into a NaN target: refused before move_to."""
    from ddp.envs.franka.control import FrankaControl
    from ddp.safety import NonFiniteError

    class Backend:
        pose = (np.array([0.5, 0.0, 0.3]), np.array([0.0, 1.0, 0.0, 0.0]))
        sent = []

        def ee_pose(self):
            return self.pose

        def move_to(self, pos, quat):
            self.sent.append(pos)

        def set_gripper(self, close):
            pass

    backend = Backend()
    control = FrankaControl(backend, workspace_low=[0.2, -0.4, 0.0], workspace_high=[0.7, 0.4, 0.5])
    control.reset()
    control.step(np.zeros(7))
    assert len(backend.sent) == 1
    backend.pose = (np.array([np.nan, 0.0, 0.3]), backend.pose[1])
    control.step(np.zeros(7))  # the commanded target moves from the last one, not from the NaN reading
    assert len(backend.sent) == 2 and np.isfinite(backend.sent[-1]).all()
    with pytest.raises(NonFiniteError, match="non-finite shift target"):  # its approach steps start at the reading
        control.shift([0.05, 0.0, 0.0])
    assert len(backend.sent) == 2
    with pytest.raises(ValueError, match="max_lead must be a finite number > 0; got nan"):
        FrankaControl(backend, workspace_low=[0.2, -0.4, 0.0], workspace_high=[0.7, 0.4, 0.5], max_lead=float("nan"))


@pytest.mark.parametrize("option", ["max_translation", "max_rotation", "max_lead", "kp", "control_period"])
def test_a_nan_control_setting_is_refused(option):
    from ddp.envs.franka.env import FrankaEnvConfig

    with pytest.raises(ValueError, match=f"{option} must be a finite number > 0; got nan"):
        FrankaEnvConfig(**{option: float("nan")})
    with pytest.raises(ValueError, match="workspace_min and workspace_max must be finite"):
        FrankaEnvConfig(workspace_min=(0.2, -0.45, float("nan")))


def test_calibration_loader(tmp_path):
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 0.0, 0.6]
    (tmp_path / "cal.yaml").write_text(
        "cameras:\n  policy:\n    serial: '123'\n    cam_to_base: " + json.dumps(pose.tolist()) + "\n"
    )
    cal = load_calibration(tmp_path / "cal.yaml")
    assert np.allclose(cal["policy"], pose) and np.allclose(cal["123"], pose) and cal.serials == {"policy": "123"}
    (tmp_path / "cal.json").write_text(json.dumps({"tracking": pose.tolist()}))
    assert np.allclose(load_calibration(tmp_path / "cal.json")["tracking"], pose)

    bad = pose.copy()
    bad[0, 0] = 2.0
    cases = {
        "missing.yaml": (None, "does not exist"),
        "shape.json": ({"policy": [[1, 0], [0, 1]]}, "must be 4x4"),
        "rot.json": ({"policy": bad.tolist()}, "not a proper rotation"),
        "key.json": ({"policy": {"pose": pose.tolist()}}, "unknown keys"),
        "empty.json": ([], "must map camera names"),
    }
    for name, (content, message) in cases.items():
        if content is not None:
            (tmp_path / name).write_text(json.dumps(content))
        with pytest.raises(CalibrationError, match=message) as info:
            load_calibration(tmp_path / name)
        assert "\n" not in str(info.value)
    (tmp_path / "broken.yaml").write_text("cameras: [unclosed\n")
    with pytest.raises(CalibrationError, match="cannot be parsed"):
        load_calibration(tmp_path / "broken.yaml")
    (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00cameras")
    with pytest.raises(CalibrationError, match="cannot be parsed"):
        load_calibration(tmp_path / "binary.yaml")
    mm = pose.copy()
    mm[:3, 3] = [1000.0, 0.0, 600.0]  # millimetres
    (tmp_path / "mm.json").write_text(json.dumps({"policy": mm.tolist()}))
    with pytest.raises(CalibrationError, match="1166 m from the robot base; metres are expected"):
        load_calibration(tmp_path / "mm.json")
    from ddp.errors import DDPError

    assert issubclass(CalibrationError, DDPError)  # the CLI prints it as one line


def test_config_validation_and_camera_errors():
    with pytest.raises(ValueError, match="dynamics_factor must be in"):
        RealBackendConfig(dynamics_factor=1.5)
    with pytest.raises(ValueError, match="workspace_low/high"):
        RealBackendConfig(workspace_low=(0.5, 0, 0), workspace_high=(0.4, 1, 1))
    with pytest.raises(ValueError, match="unknown keys"):
        RealBackendConfig.from_env_config({"real": {"robot_hots": "1.2.3.4"}})
    cfg = RealBackendConfig.from_env_config({"real": {"robot_host": "1.2.3.4", "motion_wait": "reached"}})
    assert cfg.robot_host == "1.2.3.4" and cfg.motion_wait == "reached"
    # a typo in the recipe's env.real is one line when the recipe is read, not first at the robot
    from ddp import build
    from ddp.errors import RecipeError

    with pytest.raises(RecipeError, match="env.real.robot_hots=x: env: real: unknown option 'robot_hots'; did you mean "
                                         "'robot_host'"):
        build(str(Path(__file__).resolve().parents[1] / "recipes" / "franka_stack.yaml"), ["env.real.robot_hots=x"])
    with pytest.raises(ValueError, match="cameras.policy.type must be one of"):
        make_camera("policy", {"type": "kinect"})
    with pytest.raises(CalibrationError, match="needs a calibration file"):
        make_camera("policy", {"type": "realsense"})


@pytest.mark.parametrize("key, value, message", [
    ("max_reach", float("nan"), "max_reach must be in"),  # NaN switched the reach limit off
    ("max_reach", 2.0, "max_reach must be in"),
    ("max_step_translation", float("inf"), "max_step_translation must be a finite number"),
    ("max_step_rotation", float("inf"), "max_step_rotation must be a finite number"),
    ("control_period", float("inf"), "control_period must be a finite number"),  # an endless sleep
    ("collision_force", -1.0, "collision_force must be a finite number"),
    ("gripper_open_width", 0.5, "gripper_open_width must be in"),
    ("home_joints", (0.0, -0.4, 0.0, 0.5, 0.0, 2.1, 0.78), r"home_joints\[3\] must be within the joint's limits"),
    ("home_joints", (0.0, float("nan"), 0.0, -2.5, 0.0, 2.1, 0.78), r"home_joints\[1\]"),
    ("workspace_high", (0.7, 0.45, float("inf")), "workspace_low/high must be 3 finite numbers"),
    ("reset_lift", -0.1, "reset_lift must be a finite number >= 0"),
    ("home_position", (float("nan"), 0.0, 0.3), "home_position must be 3 numbers"),  # every reset went there
])
def test_real_backend_settings_that_would_switch_a_limit_off_are_refused(key, value, message):
    with pytest.raises(ValueError, match=f"env.real.{message}"):
        RealBackendConfig(**{key: value})


class _FakeFranky:
    """The few franky calls the backend's reset makes, recorded in ``events`` in the order they happen."""

    def __init__(self):
        events, self.events = [], []
        self.events = events
        self.RealtimeConfig = type("RealtimeConfig", (), {"Enforce": 1, "Ignore": 0})
        self.ReferenceType = type("ReferenceType", (), {"Absolute": "absolute"})
        self.Affine = lambda position, quaternion: (np.asarray(position), np.asarray(quaternion))
        self.CartesianMotion = lambda affine, ref: ("cartesian", affine[0])
        self.JointMotion = lambda q: ("joint", tuple(q))

        class Future:
            def wait(self, timeout):
                return True

        class Gripper:
            max_width, width = 0.08, 0.02

            def __init__(self, host):
                pass

            def move_async(self, width, speed):
                events.append(("gripper", "open"))
                return Future()

            def grasp_async(self, *args):
                events.append(("gripper", "close"))
                return Future()

        class Robot:
            has_errors = False

            def __init__(self, host, realtime_config=None):
                self.pose = np.array([0.5, 0.0, 0.02]), np.array([1.0, 0.0, 0.0, 0.0])  # low, over the table

            def set_collision_behavior(self, *args):
                pass

            def join_motion(self, timeout):
                return True

            def move(self, motion, asynchronous=False):
                events.append(motion)
                if motion[0] == "cartesian":
                    self.pose = (np.asarray(motion[1]), self.pose[1])

            @property
            def current_cartesian_state(self):
                x, y, z, w = 0.0, 0.0, 0.0, 1.0
                pose = type("P", (), {"translation": self.pose[0], "quaternion": np.array([x, y, z, w])})
                return type("S", (), {"pose": type("E", (), {"end_effector_pose": pose})})

        self.Robot, self.Gripper = Robot, Gripper


def test_a_real_reset_lifts_first_and_waits_for_the_operator_before_the_gripper_opens(monkeypatch):
    """The hand may hold the pot in the air when an episode times out: the reset goes straight up (inside the
    box, never down) before the joint motion sweeps the arm home, and on hardware waits for the operator
    (Enter) before it opens the gripper, at every reset (an evaluation builds a new backend per protocol, so
    a backend's first reset is no evaluation's first)."""
    from ddp.envs.franka import real

    franky = _FakeFranky()
    monkeypatch.setattr(real, "_import_franky", lambda: franky)
    backend = real.FrankyBackend(RealBackendConfig(), cameras={})
    asked = []
    backend.confirm = lambda message: (asked.append(message), franky.events.append(("operator",)))
    backend.reset()
    assert [e[0] for e in franky.events] == ["cartesian", "operator", "gripper", "joint"]
    np.testing.assert_allclose(franky.events[0][1], [0.5, 0.0, 0.10])  # 8 cm straight up
    assert "take what the gripper holds" in asked[0]
    franky.events.clear()
    backend.robot.pose = (np.array([0.5, 0.0, 0.6]), backend.robot.pose[1])  # above the box's top (0.5)
    backend.reset()
    assert [e[0] for e in franky.events] == ["cartesian", "operator", "gripper", "joint"] and len(asked) == 2
    np.testing.assert_allclose(franky.events[0][1], [0.5, 0.0, 0.6])  # stays: clipping to the box would go down
    quiet = real.FrankyBackend(RealBackendConfig(operator_reset=False, reset_lift=0.0), cameras={})
    franky.events.clear()
    quiet.reset()
    quiet.reset()
    assert [e[0] for e in franky.events] == ["gripper", "joint", "gripper", "joint"]
    franky.events.clear()  # a NaN pose reading: the lift's target max(nan, z) would be NaN, sent unchecked
    backend.robot.pose = (np.array([0.5, 0.0, float("nan")]), backend.robot.pose[1])
    with pytest.raises(NonFiniteError, match=r"franky backend \(reset lift\): refused a non-finite measured end"):
        backend.reset()
    assert franky.events == []  # nothing moved
    monkeypatch.setattr("builtins.input", lambda prompt: (_ for _ in ()).throw(EOFError()))
    with pytest.raises(RuntimeError, match="no terminal to read Enter from; set env.real.operator_reset=false"):
        real.FrankyBackend.confirm("go")


def test_missing_extras_name_the_install(monkeypatch):
    from ddp.envs.franka import cameras, real

    monkeypatch.setitem(sys.modules, "franky", None)  # import franky -> ImportError
    with pytest.raises(ImportError, match=r"pip install 'ddp\[real\]'"):
        real._import_franky()
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    with pytest.raises(ImportError, match=r"pip install 'ddp\[real\]'"):
        cameras._import_realsense()


# ------------------------------------------------------------------------------------ RealSense
def record_realsense(path: Path, depth_mm: np.ndarray, rgb: np.ndarray, f: float, frames: int = 15) -> None:
    """Write a RealSense recording (depth z16 + colour rgb8, aligned, pinhole ``f``) with librealsense itself."""
    import pyrealsense2 as rs

    h, w = depth_mm.shape

    def stream(kind, uid, fmt, bpp):
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt = kind, 0, uid, w, h, 30, bpp, fmt
        k = rs.intrinsics()
        k.width, k.height, k.fx, k.fy, k.ppx, k.ppy = w, h, f, f, (w - 1) / 2, (h - 1) / 2
        k.model, k.coeffs = rs.distortion.none, [0.0] * 5
        s.intrinsics = k
        return s

    device = rs.software_device()
    depth_sensor, color_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, 0, rs.format.z16, 2))
    color_profile = color_sensor.add_video_stream(stream(rs.stream.color, 1, rs.format.rgb8, 3))
    depth_sensor.add_read_only_option(rs.option.depth_units, 0.001)
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    depth_profile.register_extrinsics_to(color_profile, identity)
    device.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(path), device)
    queue = rs.frame_queue(10)
    for sensor, profile in ((depth_sensor, depth_profile), (color_sensor, color_profile)):
        sensor.open(profile)
        sensor.start(queue)
    for i in range(frames):
        for sensor, profile, pixels, bpp in ((depth_sensor, depth_profile, depth_mm, 2), (color_sensor, color_profile, rgb, 3)):
            frame = rs.software_video_frame()
            frame.pixels, frame.bpp, frame.stride = pixels, bpp, w * bpp
            frame.timestamp, frame.frame_number = i * 33.3, i
            frame.domain = rs.timestamp_domain.hardware_clock
            frame.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(frame)
        time.sleep(0.005)
    for sensor in (depth_sensor, color_sensor):
        sensor.stop()
        sensor.close()
    del recorder  # closes the file


def test_realsense_camera_from_a_recording(tmp_path):
    """The RealSense source end to end (pipeline, depth-to-colour alignment, depth scale, intrinsics from
    the stream profile, extrinsics from the calibration file), fed by a recording instead of a device."""
    try:
        import pyrealsense2  # noqa: F401
    except ImportError as exc:
        why = f"pyrealsense2 unavailable ({exc}): bash scripts/setup_franky_sim.sh installs it and libusb"
        if os.environ.get("CI"):  # CI installs it: a setup that could not is a failure there, not a skip
            pytest.fail(why)
        pytest.skip(why)
    from ddp.envs.franka.pointcloud import backproject

    h, w, f = 48, 64, 50.0
    depth_mm = np.full((h, w), 800, np.uint16)  # a wall 0.8 m away ...
    depth_mm[10:20, 30:40] = 600  # ... and a box 0.6 m away
    depth_mm[0, 0] = 0  # no return
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = 200
    record_realsense(tmp_path / "rec.db3", depth_mm, rgb, f)

    # camera 1 m above the base origin looking straight down (OpenCV z forward = base -z)
    pose = np.array([[1.0, 0, 0, 0.5], [0, -1.0, 0, 0.0], [0, 0, -1.0, 1.0], [0, 0, 0, 1.0]])
    (tmp_path / "cal.yaml").write_text(f"cameras:\n  policy:\n    cam_to_base: {json.dumps(pose.tolist())}\n")
    calibration = load_calibration(tmp_path / "cal.yaml")
    frames = {}
    for align in ("depth", "color"):
        spec = {"type": "realsense", "recording": str(tmp_path / "rec.db3"), "width": w, "height": h,
                "warmup_frames": 2, "align_to": align}  # fmt: skip
        cam = make_camera("policy", spec, calibration)
        try:
            frames[align] = cam.read()
        finally:
            cam.close()
    for frame in frames.values():
        assert frame.depth.dtype == np.float32 and frame.depth.shape == (h, w)
        assert np.allclose(frame.intrinsics, [[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
        assert np.allclose(frame.cam_to_world, pose)
    # the depth stream as recorded, in metres
    assert np.array_equal(frames["depth"].depth, depth_mm.astype(np.float32) * np.float32(0.001))
    assert frames["depth"].rgb is None
    # aligned to colour: librealsense's re-projection leaves some holes (depth 0), as on hardware
    aligned = frames["color"]
    assert aligned.rgb.shape == (h, w, 3) and aligned.rgb[0, 0, 0] == 200
    assert {round(float(v), 4) for v in np.unique(aligned.depth)} <= {0.0, 0.6, 0.8} and (aligned.depth == 0).mean() < 0.2

    points = backproject(frames["depth"])
    assert len(points) == h * w - 1  # the pixel without a return is dropped
    box = points[np.isclose(points[:, 2], 0.4, atol=1e-4)]  # 1 m - 0.6 m
    assert len(box) == 100
    # pixel (u, v) -> base x = 0.5 + (u - cx) z / f, base y = -(v - cy) z / f
    assert box[:, 0].mean() == pytest.approx(0.5 + (34.5 - 31.5) * 0.6 / f, abs=1e-4)
    assert box[:, 1].mean() == pytest.approx(-(14.5 - 23.5) * 0.6 / f, abs=1e-4)


# --------------------------------------------------------------------------------- franky-sim
def start_franky_sim(tmp_dir: Path, scene: dict | None = None, timeout: float = 60.0):
    """Start the server on 127.0.0.1 (falling back to another loopback address if 1337 is taken)."""
    info_file = tmp_dir / "franky_sim.json"
    cmd = [str(FRANKY_SIM_PYTHON), str(SERVER), "--host", "127.0.0.1", "--fallback-hosts", "4",
           "--exit-with-parent", "--info-file", str(info_file)]  # fmt: skip
    if scene is not None:
        (tmp_dir / "scene.json").write_text(json.dumps(scene))
        cmd += ["--scene", str(tmp_dir / "scene.json")]
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), OMP_WAIT_POLICY="PASSIVE")
    log = open(tmp_dir / "franky_sim.log", "w")
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_dir)
    while not info_file.is_file():
        if proc.poll() is not None or time.monotonic() - t0 > timeout:
            stop_franky_sim(proc)
            raise RuntimeError(f"franky-sim did not start: {(tmp_dir / 'franky_sim.log').read_text()[-2000:]}")
        time.sleep(0.05)
    info = json.loads(info_file.read_text())
    info["startup_s"] = time.monotonic() - t0
    info["info_file"] = str(info_file)
    assert info["pid"] == proc.pid
    return proc, info


def stop_franky_sim(proc: subprocess.Popen) -> None:
    """SIGTERM by PID (the server shuts down cleanly), SIGKILL if it does not within 10 s."""
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(5)


#: the franka env as it would run on the robot: the paper's cloud (10 k pre-sample, FPS to 2048) from a
#: 160x120 depth camera, the tracking camera, rendering only the frames a policy consumes (2 per chunk)
ENV_OPTIONS = dict(
    task="stack", backend="real", image_height=120, image_width=160, tracking_camera=True, obs_every=8, obs_history=2
)


@pytest.fixture(scope="module")
def franky_sim(tmp_path_factory):
    if not FRANKY_SIM_PYTHON.exists():
        pytest.skip(f"franky-sim environment missing at {FRANKY_SIM_VENV}: run bash scripts/setup_franky_sim.sh")
    from ddp.envs.franka.real import franky_sim_scene

    # the stack task's scene with the env's camera sizes (ENV_OPTIONS), shared by the tests below
    scene = franky_sim_scene(FrankaEnvConfig(**ENV_OPTIONS))
    proc, info = start_franky_sim(tmp_path_factory.mktemp("franky_sim"), scene)
    try:
        yield info
    finally:
        stop_franky_sim(proc)
        assert proc.returncode == 0, f"franky-sim exited with {proc.returncode}"
        assert not Path(info["info_file"]).exists(), "the server did not remove its info file on SIGTERM"


def go_to(backend, target, step=0.03, tol=3e-3, max_steps=40):
    """Approach a base-frame position in bounded steps, the hand pointing down."""
    for _ in range(max_steps):
        p, _ = backend.ee_pose()
        d = target - p
        if np.linalg.norm(d) < tol:
            return
        backend.move_to(p + d * min(1.0, step / np.linalg.norm(d)), DOWN_WXYZ)


def _settle(backend, seconds=0.3):
    backend.wait_until_still(5.0)
    time.sleep(seconds)


class _Spy:
    """``robot`` with each ``move``'s ``asynchronous`` flag recorded in ``handed``."""

    def __init__(self, robot, handed: list):
        self._robot, self._handed = robot, handed

    def move(self, motion, asynchronous=False, **kw):
        self._handed.append(asynchronous)
        return self._robot.move(motion, asynchronous=asynchronous, **kw)

    def __getattr__(self, name):
        return getattr(self._robot, name)


def test_backend_against_franky_sim(franky_sim, record_property):
    from ddp.envs.franka.real import make_real_backend

    print(f"\nfranky-sim start-up {franky_sim['startup_s']:.2f} s on {franky_sim['robot_host']}")
    cameras = {name: {"segmentation": True} for name in ("policy", "tracking")}
    backend = make_real_backend(
        {"real": {"franky_sim_info": franky_sim["info_file"], "dynamics_factor": 0.3, "cameras": cameras}}
    )
    try:
        assert backend.object_names == ("pink", "green")
        layout = {"pink": np.array([0.5, -0.08, 0.02]), "green": np.array([0.5, 0.1, 0.025])}
        backend.reset(layout)
        _settle(backend)

        # the arm's pose as franky reports it (libfranka O_T_EE) = the TCP in the server's MuJoCo model
        pos, quat = backend.ee_pose()
        truth = backend.scene.state()
        assert np.linalg.norm(pos - truth["tcp_position"]) < 2e-3
        assert quat_angle(quat, truth["tcp_quaternion"]) < 0.01
        assert np.allclose(backend.joint_positions(), truth["q"], atol=2e-3)
        assert np.allclose(backend.object_positions(), [layout["pink"], layout["green"]], atol=2e-3)

        # depth frames from the server's scene (arm at home, out of the way): the pink block's pixels back-project onto the block
        latencies = []
        for camera in ("policy", "tracking", "policy", "tracking", "policy"):
            t = time.perf_counter()
            frame = backend.render(camera)
            latencies.append(time.perf_counter() - t)
            assert frame.depth.dtype == np.float32 and frame.depth.shape == (120, 160)
            assert frame.intrinsics.shape == (3, 3) and frame.cam_to_world.shape == (4, 4)
            # the arm may hide one block from a camera: check every block that is in view
            seen = 0
            for index, centre in enumerate(backend.object_positions()):
                v, u = np.nonzero(frame.segmentation == index)
                if len(u) <= 10:
                    continue
                seen += 1
                z = frame.depth[v, u]
                k = frame.intrinsics
                cam = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=1)
                world = cam @ frame.cam_to_world[:3, :3].T + frame.cam_to_world[:3, 3]
                # visible surface points lie within the block's half-diagonal of its centre
                half = PINK_HALF if index == 0 else GREEN_HALF
                assert np.all(np.linalg.norm(world - centre, axis=1) < half * np.sqrt(3) + 3e-3), (camera, index)
            assert seen >= 1, f"{camera}: no block in view"
        # a relative motion composed in the BASE frame: +x, +y, -z move the TCP along the base axes
        # (franky's own relative moves are in the end-effector frame, where y and z are flipped)
        delta = np.array([0.03, 0.02, -0.03])
        start, _ = backend.ee_pose()
        backend.move_relative(delta)
        _settle(backend)
        moved = backend.ee_pose()[0] - start
        assert np.allclose(moved, delta, atol=3e-3), moved
        # one control period per move_to: each target is handed to franky without waiting for its motion, so
        # consecutive targets blend into one motion, and the call returns once the period is over (a lower
        # bound only: an upper one would time this machine's load, not the backend)
        steps, handed = [], []
        robot = backend.robot
        backend.robot = _Spy(robot, handed)
        try:
            for _ in range(8):
                t = time.perf_counter()
                backend.move_relative([0.0, -0.005, 0.0])
                steps.append(time.perf_counter() - t)
        finally:
            backend.robot = robot
        assert handed == [True] * 8
        assert min(steps) >= backend.control_period - 1e-3

        # the safety limits: one command 30 cm away moves at most max_step_translation
        start, q0 = backend.ee_pose()
        backend.move_to(start + np.array([0.0, 0.3, 0.0]), q0)
        _settle(backend)
        assert np.linalg.norm(backend.ee_pose()[0] - start) <= backend.config.max_step_translation + 2e-3
        assert backend.limited_steps >= 1
        # what a tracking shift counts as executed: targets beyond the reach are pulled back, inside the box
        far = backend.reachable(np.array([0.8, 0.45, 0.3]), q0)
        assert np.all(far <= np.asarray(backend.config.workspace_high) + 1e-9)
        assert np.linalg.norm(far - [0.8, 0.45, 0.3]) > 0.01  # 0.8 m out at the box corner: beyond max_reach
        near = start + np.array([0.0, 0.02, 0.0])
        np.testing.assert_allclose(backend.reachable(near, q0), near)  # within reach: unchanged

        latency = float(np.median(latencies[2:]))
        print(f"move_to per step {np.mean(steps) * 1e3:.1f} ms; depth frame over the socket {latency * 1e3:.1f} ms")
        record_property("move_to_s", float(np.mean(steps)))
        record_property("depth_latency_s", latency)

        # grasp the pink block and lift it
        pink = backend.object_positions()[0]
        go_to(backend, pink + [0, 0, 0.1])
        go_to(backend, pink)
        backend.set_gripper(True)
        # the fingers close in about 8 control periods; a loaded machine runs the simulator slower, so wait
        # (up to 40 periods) until the width has settled rather than a fixed count
        width = backend.gripper_width()
        for _ in range(40):
            backend.move_to(*backend.ee_pose())
            width, last = backend.gripper_width(), width
            if width < 0.041 and abs(width - last) < 1e-4:
                break
        assert 0.03 < width < 0.041  # squeezing a 4 cm block
        go_to(backend, pink + [0, 0, 0.15])
        _settle(backend, 0.2)
        assert backend.object_positions()[0][2] > pink[2] + 0.1, "the block was not lifted"
        backend.set_gripper(False)
    finally:
        backend.close()


def stacked(positions: np.ndarray, width: float) -> bool:
    """The stack task's success on the true poses: pink on green, centred, the gripper open."""
    from ddp.envs.franka.tasks.stack import GREEN_HALF, PINK_HALF

    pink, green = positions
    centred = np.linalg.norm(pink[:2] - green[:2]) < 0.02
    resting = abs((pink[2] - PINK_HALF) - (green[2] + GREEN_HALF)) < 0.006
    return bool(centred and resting and width > 2 * PINK_HALF + 0.004)


def test_stack_episode_with_scripted_oracle(franky_sim, tmp_path, record_property):
    """The franka env with ``backend: real`` on franky-sim: one stack-blocks episode by the scripted oracle."""
    import torch

    from ddp.envs.franka.env import FrankaEnv

    # the calibration path as on hardware: the policy camera's extrinsics from a file (here the truth)
    from ddp.envs.franka.cameras import FrankySimScene

    scene = FrankySimScene.from_info_file(franky_sim["info_file"])
    truth = scene.render("policy").cam_to_world
    scene.close()
    (tmp_path / "calibration.yaml").write_text(f"cameras:\n  policy:\n    cam_to_base: {json.dumps(truth.tolist())}\n")

    cfg = FrankaEnvConfig(
        **ENV_OPTIONS,
        real={"franky_sim_info": franky_sim["info_file"], "calibration": str(tmp_path / "calibration.yaml")},
    )
    t0 = time.perf_counter()
    env = FrankaEnv(cfg)
    try:
        oracle = env.task.oracle(variance=False)
        td = env.reset(seed=0)
        assert td["point_cloud"].shape == (2048, 3)
        assert td["tracking", "depth"].shape == (120, 160)
        pos0 = env.backend.object_positions()
        assert np.allclose(td["privileged", "object_pos"].numpy(), pos0, atol=1e-3)
        # the TCP starts at the task's home, pointing down
        assert np.allclose(td["agent_pos"][:3].numpy(), env.task.home, atol=3e-3)
        success_step, steps = None, []
        for t in range(cfg.episode_steps):
            td["action"] = torch.as_tensor(oracle(td))
            s0 = time.perf_counter()
            td = env.step(td)["next"]
            steps.append(time.perf_counter() - s0)
            positions = env.backend.object_positions()
            if stacked(positions, env.backend.gripper_width()) and oracle.finished:
                success_step = t + 1
                break
        wall = time.perf_counter() - t0
        print(
            f"stack episode: success at step {success_step}, {len(steps)} steps, {np.mean(steps) * 1e3:.0f} ms per "
            f"env step (median {np.median(steps) * 1e3:.0f}), {wall:.1f} s with reset; safety-limited targets: "
            f"{env.backend.limited_steps}"
        )
        record_property("stack_success_step", success_step)
        record_property("env_step_s", float(np.mean(steps)))
        assert success_step is not None, f"not stacked after {len(steps)} steps: objects {positions.tolist()}"
        # the observation carried the truth the oracle read, and the cloud saw the blocks
        assert np.allclose(td["privileged", "object_pos"].numpy(), positions, atol=5e-3)
    finally:
        env.close()


def test_parts_that_read_the_simulators_truth_are_refused_on_a_real_robot():
    """On hardware the privileged displacement reads zero: the Franka recipes' oracle tracker would never track
    and the oracle detector never fire, silently. Refused at build, with one line; franky-sim, whose scene
    knows the objects, keeps them."""
    from ddp import build
    from ddp.errors import RecipeError

    real = build("recipes/franka_stack.yaml", ["env.backend=real", "controller.detector.tau=1.0"])
    with pytest.raises(RecipeError, match=r"controller.tracker.*reads the simulator's \('privileged', 'displacement'\)"):
        real.make_controller()
    with pytest.raises(RecipeError, match=r"eval.protocols.*a protocol's detector 'OracleDetector' reads the simulator's"):
        real.make_controller(detector={"name": "oracle"}, tracker=False)
    oracle = build("recipes/franka_stack.yaml", ["env.backend=real", "controller.tracker=null",
                                                 "controller.detector={name: oracle}"])
    # refused before any rollout: id (detector never) would otherwise connect to a robot first
    with pytest.raises(RecipeError, match="controller.detector: 'OracleDetector' reads the simulator's"):
        oracle.evaluate(["id", "id_ddp"], episodes=1, progress=False)
    real.make_controller(tracker=False)  # the discrepancy detector works from the observations
    simulated = build("recipes/franka_stack.yaml", ["env.backend=real", "controller.detector.tau=1.0",
                                                     "env.real={franky_sim_info: /tmp/fsim.json}"])
    simulated.make_controller()
    # the env the episodes run in decides, not the recipe's env section: eval.env (or a protocol's, or
    # --env) may put a simulated recipe on the robot
    sim = build("recipes/franka_stack.yaml", ["controller.tracker=null", "controller.detector={name: oracle}"])
    sim.make_controller()  # in simulation the oracle reads the truth
    with pytest.raises(RecipeError, match="controller.detector: 'OracleDetector' reads the simulator's"):
        sim.make_controller(env={"backend": "real"})
    on_robot = build("recipes/franka_stack.yaml", ["controller.tracker=null", "controller.detector={name: oracle}",
                                                   "eval.env={backend: real}"])
    with pytest.raises(RecipeError, match="controller.detector: 'OracleDetector' reads the simulator's"):
        on_robot.evaluate(["id", "id_ddp"], episodes=1, progress=False)


def test_an_env_that_cannot_judge_success_reports_none_not_zero(tmp_path):
    """A real robot's episodes: the table says 'not judged', results.json holds null, no success plot."""
    from ddp.eval_report import markdown_table, protocol_result
    from ddp.plots import plot_report

    episodes = [{"seed": s, "success": None, "first_success_chunk": None, "chunks": 3} for s in range(4)]
    result = protocol_result(episodes, seconds=1.0, thresholds={})
    assert result["success_rate"] is None and result["successes"] is None and result["episodes"] == 4
    report = {"recipe": "franka_stack", "episodes": 4, "protocols": {"id_ddp": result}}
    assert "| franka_stack | not judged (4 episodes) |" in markdown_table({"franka_stack": report})
    assert not (tmp_path / "success.png").exists() and plot_report(report, tmp_path) == []
    from ddp.envs.franka.env import FrankaEnvConfig as Config

    assert Config(task="stack").judges_success() and not Config(task="stack", backend="real").judges_success()
    # judged in the env the episodes run in (eval.env / a protocol's / --env overrides on the recipe's)
    from ddp import build
    from ddp.eval_runner import judges_success

    exp = build("recipes/franka_stack.yaml")
    assert judges_success(exp) and judges_success(exp, {"max_episode_steps": 10})
    assert not judges_success(exp, {"backend": "real"})


def test_a_reflex_stops_the_arm_for_the_rest_of_the_episode_not_the_evaluation():
    """franky's collision reflex (RobotMotionError) ended the whole evaluation; now the arm holds still for the
    rest of that episode (no more motion commands, shifts apply nothing), task_info says motion_stopped, and
    the next episode moves again."""
    import warnings

    import torch
    from tensordict import TensorDict

    from ddp.envs.franka.backend import CameraFrame, FrankaBackend, RobotMotionError
    from ddp.envs.franka.env import FrankaEnv
    from ddp.envs.franka.tasks.base import DOWN
    from ddp.envs.franka.control import mat_to_quat

    class Robot(FrankaBackend):
        def __init__(self):
            self.pos, self.quat, self.moves, self.fail_at = np.array([0.45, 0.0, 0.2]), mat_to_quat(DOWN), 0, 3

        def reset(self, object_positions=None, home=True):
            self.pos = np.array([0.45, 0.0, 0.2])

        def ee_pose(self):
            return self.pos.copy(), self.quat.copy()

        def gripper_width(self):
            return 0.08

        def move_to(self, position, quaternion):
            self.moves += 1
            if self.moves == self.fail_at:
                raise RobotMotionError("the robot stopped the motion: ControlException: cartesian reflex")
            self.pos = np.asarray(position)

        def set_gripper(self, close):
            pass

        def render(self, camera):  # a table seen from 1 m above, 5 cm under the crop box's top layer
            k = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
            pose = np.eye(4)
            pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
            pose[:3, 3] = [0.5, 0.0, 1.0]
            return CameraFrame(depth=np.full((24, 32), 0.97, np.float32), intrinsics=k, cam_to_world=pose)

    robot = Robot()
    cfg = FrankaEnvConfig(task="press", num_points=16, presample=0, image_height=24, image_width=32,
                          crop_min=(0.3, -0.3, 0.01), crop_max=(0.7, 0.3, 0.3))
    env = FrankaEnv(cfg, backend=robot)
    env.reset(seed=0)
    action = torch.tensor([0.01, 0, 0, 0, 0, 0, -1.0])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(6):
            out = env.step(TensorDict({"action": action}, batch_size=[]))
    assert any("cartesian reflex; the arm holds still for the rest of episode 0" in str(w.message) for w in caught)
    assert robot.moves == 3  # nothing sent after the reflex
    assert out["next", "privileged", "task_info", "motion_stopped"].item() == 1.0
    assert np.all(env.shift_end_effector([0.02, 0.0, 0.0]) == 0.0) and robot.moves == 3
    env.reset(seed=1)
    env.step(TensorDict({"action": action}, batch_size=[]))
    assert robot.moves == 4  # a new episode moves again
