"""Depth cameras for the real Franka backend, each returning a :class:`CameraFrame`.

Sources:

* :class:`RealSenseCamera`: an Intel RealSense (the paper's L515 for the point cloud, a D455 for
  tracking) through ``pyrealsense2``. Depth is aligned to the colour stream (``align_to="color"``)
  so both share one pinhole model; the intrinsics come from the stream profile, the pose from the
  calibration file (``cam_to_base`` of the aligned stream's optical frame, OpenCV axes). With
  ``recording:`` it plays a RealSense recording (``.db3``; ``.bag`` before librealsense 2.57)
  through the same pipeline instead of a live device.
* :class:`FrankySimCamera`: depth rendered from the live MuJoCo scene of a franky-sim server
  (:mod:`ddp.envs.franka.franky_sim_server`), standing in for the RealSense in tests; its pose is
  the server's truth unless the calibration file names the camera.

:func:`load_calibration` reads the extrinsics: a YAML or JSON file mapping a camera name or
RealSense serial to a 4x4 ``cam_to_base`` (camera pose in the robot base frame, OpenCV axes)::

    cameras:
      policy:                       # the env's camera name (or a serial number)
        serial: "f1230452"          # optional: the RealSense that plays this role
        cam_to_base: [[0, -0.5, 0.87, 1.15], [-1, 0, 0, 0], [0, -0.87, -0.5, 0.6], [0, 0, 0, 1]]
      tracking:
        cam_to_base: [...]

(a flat mapping without the ``cameras:`` level, and a bare 4x4 list per camera, are accepted too).
"""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ddp.envs.franka.backend import CameraFrame
from ddp.errors import DDPError

__all__ = [
    "Calibration",
    "CalibrationError",
    "CameraSource",
    "FrankySimCamera",
    "FrankySimScene",
    "RealSenseCamera",
    "load_calibration",
    "make_camera",
]

INSTALL_HINT = "pip install 'ddp[real]'"


#: metres: a camera farther from the robot base than this is a calibration in other units (millimetres)
MAX_CAMERA_DISTANCE = 5.0


class CalibrationError(DDPError, ValueError):
    """A calibration file that cannot be used (one line, naming the file and the key; the CLI prints it as
    ``ddp: error: ...``)."""


class CameraSource:
    """Something that returns the latest :class:`CameraFrame` of one camera."""

    name: str = ""

    def read(self) -> CameraFrame:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


# ----------------------------------------------------------------------------------------------
# calibration
# ----------------------------------------------------------------------------------------------


def _check_pose(matrix: Any, where: str) -> np.ndarray:
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: cam_to_base must be a 4x4 list of numbers; got {matrix!r}") from None
    if m.shape != (4, 4):
        raise CalibrationError(f"{where}: cam_to_base must be 4x4; got shape {list(m.shape)}")
    if not np.all(np.isfinite(m)):
        raise CalibrationError(f"{where}: cam_to_base has non-finite entries")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise CalibrationError(f"{where}: cam_to_base's last row must be [0, 0, 0, 1]; got {m[3].tolist()}")
    if np.linalg.norm(m[:3, 3]) > MAX_CAMERA_DISTANCE:  # millimetres would put every point outside the crop
        raise CalibrationError(f"{where}: cam_to_base's translation {m[:3, 3].tolist()} is "
                               f"{np.linalg.norm(m[:3, 3]):.4g} m from the robot base; metres are expected")
    rot = m[:3, :3]
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if err > 1e-3 or np.linalg.det(rot) < 0:
        raise CalibrationError(
            f"{where}: cam_to_base's rotation is not a proper rotation (|R^T R - I| = {err:.2g}, "
            f"det = {np.linalg.det(rot):.3g})"
        )
    return m


class Calibration(dict):
    """``{camera name or serial: cam_to_base [4, 4]}``; ``serials`` maps a camera name to its device serial."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.serials: dict[str, str] = {}


def load_calibration(path: str | Path) -> Calibration:
    """Read camera extrinsics: ``{camera name or serial: cam_to_base [4, 4]}``.

    An entry with a ``serial`` is reachable under both its name and its serial, and a RealSense
    camera of that name opens that device. Raises :class:`CalibrationError` (one line) on a missing
    file, a parse error or an invalid pose.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file {str(path)!r} does not exist")
    try:
        text = path.read_text()
        if path.suffix.lower() == ".json":
            raw = json.loads(text)
        else:
            import yaml

            raw = yaml.safe_load(text)
    except Exception as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CalibrationError(f"calibration file {str(path)!r} cannot be parsed: {first}") from None
    if isinstance(raw, Mapping) and "cameras" in raw:
        raw = raw["cameras"]
    if not isinstance(raw, Mapping) or not raw:
        raise CalibrationError(
            f"calibration file {str(path)!r} must map camera names to {{cam_to_base: 4x4}}; got {type(raw).__name__}"
        )
    out = Calibration()
    for name, entry in raw.items():
        where = f"{path.name}: cameras.{name}"
        serial = None
        if isinstance(entry, Mapping):
            unknown = set(entry) - {"cam_to_base", "serial"}
            if unknown:
                raise CalibrationError(f"{where}: unknown keys {sorted(unknown)}; valid: ['cam_to_base', 'serial']")
            if "cam_to_base" not in entry:
                raise CalibrationError(f"{where}: missing cam_to_base (4x4 camera pose in the robot base frame)")
            matrix, serial = entry["cam_to_base"], entry.get("serial")
        else:
            matrix = entry
        pose = _check_pose(matrix, where)
        out[str(name)] = pose
        if serial is not None:
            out[str(serial)] = pose
            out.serials[str(name)] = str(serial)
    return out


def _lookup_extrinsics(calibration: Mapping[str, np.ndarray] | None, *keys: str | None) -> np.ndarray | None:
    if not calibration:
        return None
    for key in keys:
        if key is not None and str(key) in calibration:
            return np.asarray(calibration[str(key)], dtype=np.float64)
    return None


# ----------------------------------------------------------------------------------------------
# RealSense
# ----------------------------------------------------------------------------------------------


def _import_realsense():
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        detail = f" ({exc})" if "libusb" in str(exc) else ""
        raise ImportError(
            f"the RealSense camera needs pyrealsense2: {INSTALL_HINT} (and the libusb-1.0-0 system library){detail}"
        ) from None
    return rs


class RealSenseCamera(CameraSource):
    """A RealSense depth camera (L515 / D4xx): depth aligned to colour, metres, K from the profile.

    Args:
        name: the env's camera name ("policy", "tracking"); looked up in the calibration.
        cam_to_base: ``[4, 4]`` pose of the (aligned) optical frame in the base frame.
        serial: the device's serial number (None: the first device found).
        width, height, fps: depth stream; ``color_width``/``color_height`` default to the same.
        align_to: "color" aligns depth to the colour image (RGB returned, K of the colour stream);
            "depth" keeps the depth stream's geometry (no RGB).
        timeout_ms: how long ``read`` waits for a frame before raising.
        recording: play a RealSense recording (``.db3``, or ``.bag`` from librealsense < 2.57) instead of
            a live device, frame by frame, looping: the same pipeline, alignment and scaling code.
    """

    def __init__(
        self,
        name: str,
        cam_to_base: np.ndarray,
        serial: str | None = None,
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        color_width: int | None = None,
        color_height: int | None = None,
        align_to: str = "color",
        timeout_ms: int = 2000,
        warmup_frames: int = 10,
        recording: str | None = None,
    ):
        if align_to not in ("color", "depth"):
            raise ValueError(f"camera {name}: align_to must be 'color' or 'depth'; got {align_to!r}")
        rs = _import_realsense()
        self.name = name
        self.cam_to_base = _check_pose(cam_to_base, f"camera {name}")
        self.timeout_ms = int(timeout_ms)
        self._rs = rs
        config = rs.config()
        if recording:
            from pathlib import Path as _Path

            if not _Path(recording).is_file():
                raise FileNotFoundError(f"camera {name}: RealSense recording {str(recording)!r} does not exist")
            config.enable_device_from_file(str(recording), repeat_playback=True)
        elif serial:
            config.enable_device(str(serial))
        config.enable_stream(rs.stream.depth, int(width), int(height), rs.format.z16, int(fps))
        if align_to == "color":
            config.enable_stream(
                rs.stream.color, int(color_width or width), int(color_height or height), rs.format.rgb8, int(fps)
            )
        self._pipeline = rs.pipeline()
        try:
            profile = self._pipeline.start(config)
        except RuntimeError as exc:
            which = f"recording {recording}" if recording else f"serial {serial}" if serial else "any device"
            raise RuntimeError(f"camera {name}: cannot start the RealSense ({which}): {exc}") from None
        device = profile.get_device()
        self._playback = device.as_playback() if recording else None
        if self._playback is not None:
            self._playback.set_real_time(False)  # every read gets the next recorded frame
        self.depth_scale = float(device.first_depth_sensor().get_depth_scale())
        stream = rs.stream.color if align_to == "color" else rs.stream.depth
        intr = profile.get_stream(stream).as_video_stream_profile().get_intrinsics()
        self.intrinsics = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])
        self._align = rs.align(rs.stream.color) if align_to == "color" else None
        for _ in range(int(warmup_frames)):  # auto-exposure settles over the first frames
            self._pipeline.wait_for_frames(self.timeout_ms)

    def read(self) -> CameraFrame:
        frames = self._pipeline.wait_for_frames(self.timeout_ms)
        rgb = None
        if self._align is not None:
            frames = self._align.process(frames)
            color = frames.get_color_frame()
            rgb = np.asanyarray(color.get_data()).copy()
        depth_frame = frames.get_depth_frame()
        depth = np.asanyarray(depth_frame.get_data()).astype(np.float32) * self.depth_scale
        return CameraFrame(depth=depth, intrinsics=self.intrinsics.copy(), cam_to_world=self.cam_to_base.copy(), rgb=rgb)

    def close(self) -> None:
        try:
            if self._playback is not None:
                # stopping a non-real-time playback races librealsense's reader thread: measured, about 1
                # in 200 closes aborted the process (std::terminate); none in 320 with real time restored
                self._playback.set_real_time(True)
            self._pipeline.stop()
        except RuntimeError:
            pass


# ----------------------------------------------------------------------------------------------
# franky-sim
# ----------------------------------------------------------------------------------------------


class FrankySimScene:
    """Client of a franky-sim server's scene socket: depth frames, object poses, placement.

    One TCP connection on loopback, one request at a time (a lock makes it thread-safe).
    """

    def __init__(self, host: str, port: int, timeout: float = 10.0):
        from ddp.envs.franka import franky_sim_server as protocol

        self._protocol = protocol
        self.host, self.port = host, int(port)
        try:
            self._sock = socket.create_connection((host, self.port), timeout=timeout)
        except OSError as exc:
            raise ConnectionError(f"cannot reach the franky-sim scene socket at {host}:{port}: {exc}") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._lock = threading.Lock()
        self.info = self.request("info")[0]
        self.object_names: tuple[str, ...] = tuple(self.info["objects"])
        self.camera_names: tuple[str, ...] = tuple(self.info["cameras"])

    @classmethod
    def from_info_file(cls, path: str | Path, wait: float = 0.0) -> "FrankySimScene":
        """Connect using the JSON the server writes (``--info-file``), waiting up to ``wait`` s for it."""
        info = read_server_info(path, wait)
        return cls(info["scene_host"], info["scene_port"])

    def request(self, cmd: str, arrays: dict[str, np.ndarray] | None = None, **fields) -> tuple[dict, dict]:
        with self._lock:
            self._protocol.send_packet(self._sock, dict(cmd=cmd, **fields), arrays)
            header, out = self._protocol.recv_packet(self._sock)
        if not header.get("ok"):
            raise RuntimeError(f"franky-sim scene request {cmd!r} failed: {header.get('error')}")
        return header, out

    def render(self, camera: str, rgb: bool = False, segmentation: bool = False) -> CameraFrame:
        _, a = self.request("render", camera=camera, rgb=bool(rgb), segmentation=bool(segmentation))
        return CameraFrame(
            depth=a["depth"],
            intrinsics=a["intrinsics"],
            cam_to_world=a["cam_to_world"],
            segmentation=a.get("segmentation"),
            rgb=a.get("rgb"),
        )

    def object_positions(self) -> np.ndarray:
        return self.request("objects")[1]["positions"]

    def object_quaternions(self) -> np.ndarray:
        return self.request("objects")[1]["quaternions"]

    def place(self, positions: np.ndarray) -> None:
        self.request("place", {"positions": np.asarray(positions, dtype=np.float64)})

    def displace(self, deltas: np.ndarray) -> None:
        self.request("displace", {"deltas": np.asarray(deltas, dtype=np.float64)})

    def state(self) -> dict[str, Any]:
        header, a = self.request("state")
        return {**a, "finger_width": header["finger_width"], "sim_time": header["sim_time"]}

    def sim_time(self) -> float:
        return float(self.request("ping")[0]["sim_time"])

    def close(self) -> None:
        try:
            self._sock.close()
        except OSError:
            pass


def read_server_info(path: str | Path, wait: float = 0.0) -> dict:
    """The franky-sim server's info file (pid, hosts, ports), waiting up to ``wait`` s for it to appear."""
    path = Path(path)
    deadline = time.monotonic() + wait
    while not path.is_file():
        if time.monotonic() >= deadline:
            raise FileNotFoundError(f"franky-sim server info file {str(path)!r} not found (is the server running?)")
        time.sleep(0.05)
    return json.loads(path.read_text())


class FrankySimCamera(CameraSource):
    """A depth camera rendered from the franky-sim server's live MuJoCo scene.

    ``cam_to_base`` (from a calibration file) replaces the server's true camera pose, to exercise
    the calibration path exactly as on hardware; None keeps the truth.
    """

    def __init__(
        self,
        scene: FrankySimScene,
        name: str,
        server_camera: str | None = None,
        cam_to_base: np.ndarray | None = None,
        rgb: bool = False,
        segmentation: bool = False,
    ):
        server_camera = server_camera or name
        if server_camera not in scene.camera_names:
            raise ValueError(
                f"camera {name}: the franky-sim server has no camera {server_camera!r}; it has {list(scene.camera_names)}"
            )
        self.name, self.scene, self.server_camera = name, scene, server_camera
        self.cam_to_base = None if cam_to_base is None else _check_pose(cam_to_base, f"camera {name}")
        self.rgb, self.segmentation = bool(rgb), bool(segmentation)

    def read(self) -> CameraFrame:
        frame = self.scene.render(self.server_camera, rgb=self.rgb, segmentation=self.segmentation)
        if self.cam_to_base is not None:
            frame.cam_to_world = self.cam_to_base.copy()
        return frame


# ----------------------------------------------------------------------------------------------
# factory
# ----------------------------------------------------------------------------------------------

_SOURCE_KEYS = {
    "realsense": {"type", "serial", "width", "height", "fps", "color_width", "color_height", "align_to", "timeout_ms",
                  "warmup_frames", "recording"},
    "franky_sim": {"type", "server_camera", "rgb", "segmentation", "use_calibration"},
}


def make_camera(
    name: str,
    spec: Mapping[str, Any],
    calibration: Mapping[str, np.ndarray] | None = None,
    scene: FrankySimScene | None = None,
) -> CameraSource:
    """Build one camera from its config entry (``{type: realsense | franky_sim, ...}``)."""
    spec = dict(spec)
    kind = spec.get("type", "realsense")
    if kind not in _SOURCE_KEYS:
        raise ValueError(f"cameras.{name}.type must be one of {sorted(_SOURCE_KEYS)}; got {kind!r}")
    unknown = set(spec) - _SOURCE_KEYS[kind]
    if unknown:
        raise ValueError(f"cameras.{name}: unknown keys {sorted(unknown)} for a {kind} camera; valid: "
                         f"{sorted(_SOURCE_KEYS[kind])}")
    spec.pop("type", None)
    if kind == "franky_sim":
        if scene is None:
            raise ValueError(f"cameras.{name}: a franky_sim camera needs franky_sim_info (the server's info file)")
        use_cal = spec.pop("use_calibration", True)
        pose = _lookup_extrinsics(calibration, name) if use_cal else None
        return FrankySimCamera(scene, name, cam_to_base=pose, **spec)
    if not calibration:
        raise CalibrationError(f"cameras.{name}: a RealSense camera needs a calibration file (env.real.calibration)")
    if not spec.get("serial") and not spec.get("recording"):
        spec["serial"] = getattr(calibration, "serials", {}).get(name)  # None: the first device found
    pose = _lookup_extrinsics(calibration, name, spec.get("serial"))
    if pose is None:
        serial = f" or serial {spec['serial']!r}" if spec.get("serial") else ""
        raise CalibrationError(
            f"cameras.{name}: the calibration file has no cam_to_base for {name!r}{serial}; it has {sorted(calibration)}"
        )
    return RealSenseCamera(name, pose, **spec)
