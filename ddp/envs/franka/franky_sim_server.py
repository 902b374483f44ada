"""A franky-sim server with the stack-blocks scene and a local socket for depth frames and object poses.

This file is two things:

* the **wire protocol** (``send_packet`` / ``recv_packet``), importable from the main ``ddp``
  environment without franky-sim or MuJoCo (the client, :mod:`ddp.envs.franka.cameras`, uses it);
* a **script** run with the franky-sim environment's Python (``scripts/setup_franky_sim.sh``
  creates it; franky-sim pulls numpy 2 and MuJoCo 4, which the main environment's robosuite and
  MetaWorld pins exclude, so the server is a separate process)::

      .venv-franky-sim/bin/python ddp/envs/franka/franky_sim_server.py --info-file /tmp/fsim.json

  It builds franky-sim's ``MujocoSimulator`` with one FR3 + Franka Hand, appends the task's
  objects (``--scene``: the MJCF of a :class:`ddp.envs.franka.tasks.base.FrankaTask`, root bodies
  ``ddp_<name>``; default: the stack-blocks scene, a pink block and a green base block) and two
  depth cameras ("policy", "tracking") to the scene before the server starts, serves the libfranka
  protocol on ``--host`` (TCP 1337 robot, 1338 gripper), and serves scene requests on a second TCP
  port on the same loopback host. The table top is the ground plane, ``z = 0`` in the robot base
  frame (the tasks' convention). When everything listens it writes ``--info-file`` (JSON: pid,
  robot host, scene port, objects, cameras) atomically; SIGTERM / SIGINT stop it cleanly and remove
  the file; ``--exit-with-parent`` also stops it when the process that started it dies.

Protocol: a *packet* is a JSON header frame followed by one frame per array named in the header's
``"arrays"`` list; a frame is a 4-byte big-endian length and its payload; arrays travel as ``.npy``
bytes written and read with ``allow_pickle=False``. Requests carry ``"cmd"``; replies carry
``"ok"`` (and ``"error"`` when false). Commands:

``info``      objects, cameras, robot host, physics time step
``render``    ``camera``, ``rgb``/``segmentation`` flags -> ``depth`` [H,W] float32 metres (0: no return),
              ``intrinsics`` [3,3], ``cam_to_world`` [4,4] (OpenCV axes), optional ``rgb``, ``segmentation``
``objects``   -> ``positions`` [K,3], ``quaternions`` [K,4] (wxyz)
``place``     ``positions`` [K,3] -> objects set there, upright, at rest
``displace``  ``deltas`` [K,3] -> objects moved by the deltas, at rest
``state``     -> ``tcp_position`` [3], ``tcp_quaternion`` [4] (the hand's TCP in MuJoCo), ``q`` [7],
              ``finger_width``
``ping``      -> ``sim_time``

Every reply carries ``sim_time`` (simulated seconds) and ``server_s`` (time spent answering).
Whatever touches the live MuJoCo state (rendering, placing objects, copying joint positions for
queries) runs inside franky-sim's simulation thread, between two physics steps (a post-step
callback), so it never races the physics.
"""

from __future__ import annotations

import io
import json
import socket
import struct

import numpy as np

__all__ = ["send_packet", "recv_packet", "default_scene", "PROTOCOL_VERSION", "DEFAULT_OBJECTS", "DEFAULT_CAMERAS"]

PROTOCOL_VERSION = 1
_MAX_FRAME = 1 << 28  # 256 MiB: any frame larger than this is a protocol error

#: the stack-blocks scene (as ``ddp.envs.franka.tasks.stack``): pink 4 cm / 50 g, green 5 cm / 250 g
DEFAULT_OBJECTS = [
    {"name": "pink", "half_size": 0.02, "mass": 0.05, "rgba": [0.95, 0.45, 0.7, 1.0], "pos": [0.5, -0.1, 0.02]},
    {"name": "green", "half_size": 0.025, "mass": 0.25, "rgba": [0.2, 0.75, 0.3, 1.0], "pos": [0.5, 0.1, 0.025]},
]
#: depth cameras: "policy" faces the robot across the table (the paper's L515), "tracking" looks from the side
DEFAULT_CAMERAS = {
    "policy": {"pos": [1.15, 0.0, 0.6], "lookat": [0.45, 0.0, 0.05], "fovy": 55.0, "width": 160, "height": 120},
    "tracking": {"pos": [0.5, -0.85, 0.55], "lookat": [0.5, 0.0, 0.05], "fovy": 58.0, "width": 160, "height": 120},
}
#: the Franka Hand's TCP: 0.1034 m from the hand body along its z axis (franky-sim's default ee_tcp_xyz)
_TCP_OFFSET = 0.1034


# ----------------------------------------------------------------------------------------------
# wire protocol (shared with the client; numpy + stdlib only)
# ----------------------------------------------------------------------------------------------


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:], n - got)
        if k == 0:
            raise ConnectionError("franky-sim scene socket closed by the peer")
        got += k
    return bytes(buf)


def _send_frame(sock: socket.socket, payload: bytes) -> None:
    sock.sendall(struct.pack("!I", len(payload)) + payload)


def _recv_frame(sock: socket.socket) -> bytes:
    (n,) = struct.unpack("!I", _recv_exact(sock, 4))
    if n > _MAX_FRAME:
        raise ConnectionError(f"franky-sim scene protocol: frame of {n} bytes exceeds {_MAX_FRAME}")
    return _recv_exact(sock, n)


def send_packet(sock: socket.socket, header: dict, arrays: dict[str, np.ndarray] | None = None) -> None:
    """Send a JSON header and the named arrays (``.npy`` bytes, no pickle)."""
    arrays = arrays or {}
    header = dict(header, arrays=list(arrays))
    frames = [json.dumps(header).encode()]
    for value in arrays.values():
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.ascontiguousarray(value), allow_pickle=False)
        frames.append(buf.getvalue())
    sock.sendall(b"".join(struct.pack("!I", len(f)) + f for f in frames))


def recv_packet(sock: socket.socket) -> tuple[dict, dict[str, np.ndarray]]:
    """Receive one packet: ``(header, {name: array})``."""
    header = json.loads(_recv_frame(sock).decode())
    arrays = {}
    for name in header.get("arrays", []):
        arrays[name] = np.load(io.BytesIO(_recv_frame(sock)), allow_pickle=False)
    return header, arrays


def default_scene(objects: list[dict] = DEFAULT_OBJECTS, cameras: dict = DEFAULT_CAMERAS) -> dict:
    """A ``--scene`` description of free boxes: ``{asset, worldbody, objects, positions, cameras}``."""
    bodies = []
    for o in objects:
        h, m = float(o["half_size"]), float(o.get("mass", 0.05))
        inertia = m * (2 * h) ** 2 / 6.0
        bodies.append(
            f'<body name="ddp_{o["name"]}" pos="{" ".join(map(str, o["pos"]))}"><freejoint/>'
            f'<inertial pos="0 0 0" mass="{m}" diaginertia="{inertia} {inertia} {inertia}"/>'
            f'<geom type="box" size="{h} {h} {h}" rgba="{" ".join(map(str, o["rgba"]))}" '
            f'friction="1.5 0.02 0.001" condim="4"/></body>'
        )
    return {
        "asset": "",
        "worldbody": "".join(bodies),
        "objects": [o["name"] for o in objects],
        "positions": {o["name"]: list(o["pos"]) for o in objects},
        "cameras": cameras,
    }


# ----------------------------------------------------------------------------------------------
# the server (franky-sim environment only: imports mujoco and franky_sim lazily)
# ----------------------------------------------------------------------------------------------


def _look_at_xyaxes(pos, lookat, up=(0.0, 0.0, 1.0)) -> list[float]:
    """MuJoCo camera ``xyaxes`` for a camera at ``pos`` looking at ``lookat`` (camera looks along -z)."""
    pos, lookat, up = (np.asarray(v, dtype=float) for v in (pos, lookat, up))
    z = pos - lookat
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-6:  # looking straight down: any horizontal x will do
        x = np.array([0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return [*x.tolist(), *y.tolist()]


class _SimThreadCalls:
    """Run callables inside franky-sim's simulation thread (between two physics steps)."""

    def __init__(self):
        import queue
        import threading

        self._queue: queue.Queue = queue.Queue()
        self._threading = threading

    def post_step(self, _sim) -> None:
        while not self._queue.empty():
            fn, box, done = self._queue.get_nowait()
            try:
                box["result"] = fn()
            except BaseException as exc:  # reported to the caller, never kills the sim loop
                box["error"] = exc
            done.set()

    def call(self, fn, timeout: float = 10.0):
        box: dict = {}
        done = self._threading.Event()
        self._queue.put((fn, box, done))
        if not done.wait(timeout):
            raise TimeoutError(f"the simulation loop did not run the request within {timeout} s")
        if "error" in box:
            raise box["error"]
        return box.get("result")


class SceneServer:
    """Build the scene, run franky-sim, answer scene requests."""

    def __init__(self, hosts: list[str], scene_port: int, scene: dict, realtime):
        import mujoco
        import franky_sim
        from franky_sim.mujoco_simulator import MujocoSimulator

        self.mujoco = mujoco
        self.scene_desc = scene
        self.objects: list[str] = list(scene["objects"])
        self.cameras: dict = dict(scene.get("cameras") or DEFAULT_CAMERAS)
        self.realtime = realtime
        self.calls = _SimThreadCalls()

        sim = MujocoSimulator()
        sim.init()
        sim.add_robot()
        self._extend_scene(sim)
        self.sim = sim
        self.server = franky_sim.SimulationServer(sim, hostname_candidates=list(hosts))
        sim.register_post_step_callback(self.calls.post_step)
        self.server.init()  # binds 1337/1338 on the first free host and builds the MuJoCo model
        host = self.server.robot_servers[0].hostname
        self.host = host
        self.model = sim.model
        self._index_model()

        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((host, scene_port))
        self.listener.listen(4)
        self.scene_port = self.listener.getsockname()[1]

        # a private MjData for object / TCP queries: joint positions are copied from the live data
        self.rdata = mujoco.MjData(self.model)
        self.renderers: dict[tuple[int, int], object] = {}

    # ---- scene construction (before the server starts) ----
    def _extend_scene(self, sim) -> None:
        import xml.etree.ElementTree as ET

        scene = sim.scene
        visual = scene.find("visual")
        quality = visual.find("quality")
        quality.set("shadowsize", "0")  # software rendering: no shadows, no multisampling
        quality.set("offsamples", "0")
        width = max(int(c["width"]) for c in self.cameras.values())
        height = max(int(c["height"]) for c in self.cameras.values())
        ET.SubElement(visual, "global", offwidth=str(max(640, width)), offheight=str(max(480, height)))
        # the task's objects: assets and bodies from its MJCF, each root body at its initial position
        assets = ET.fromstring(f"<asset>{self.scene_desc.get('asset', '')}</asset>")
        scene.find("asset").extend(list(assets))
        bodies = ET.fromstring(f"<worldbody>{self.scene_desc.get('worldbody', '')}</worldbody>")
        positions = self.scene_desc.get("positions") or {}
        for body in bodies:
            name = body.get("name", "")
            if name.startswith("ddp_") and name[4:] in positions:
                body.set("pos", " ".join(f"{v:.6f}" for v in positions[name[4:]]))
            for geom in body.iter("geom"):  # geom group 3 holds franky-sim's collision meshes, hidden
                geom.set("group", "0")  # when rendering: the task's geoms go in a rendered group
            sim.worldbody.append(body)
        for name, cam in self.cameras.items():
            ET.SubElement(
                sim.worldbody,
                "camera",
                name=name,
                mode="fixed",
                pos=" ".join(map(str, cam["pos"])),
                xyaxes=" ".join(f"{v:.6f}" for v in _look_at_xyaxes(cam["pos"], cam["lookat"])),
                fovy=str(cam["fovy"]),
            )

    def _index_model(self) -> None:
        mj = self.mujoco
        m = self.model
        self.obj_body, self.obj_qadr, self.obj_dadr = [], [], []  # qadr -1: not free (moved by body_pos)
        for name in self.objects:
            bid = mj.mj_name2id(m, mj.mjtObj.mjOBJ_BODY, f"ddp_{name}")
            if bid < 0:
                raise ValueError(f"scene: object {name!r} has no root body 'ddp_{name}'")
            jid = int(m.body_jntadr[bid])
            free = jid >= 0 and m.jnt_type[jid] == mj.mjtJoint.mjJNT_FREE
            self.obj_body.append(bid)
            self.obj_qadr.append(int(m.jnt_qposadr[jid]) if free else -1)
            self.obj_dadr.append(int(m.jnt_dofadr[jid]) if free else -1)
        # geom -> object index: walk each geom's body up to an object's root body
        body_to_obj = np.full(m.nbody, -1, dtype=np.int32)
        for k, bid in enumerate(self.obj_body):
            body_to_obj[bid] = k
        for b in range(m.nbody):
            a = b
            while a > 0 and body_to_obj[a] < 0:
                a = int(m.body_parentid[a])
            if a > 0:
                body_to_obj[b] = body_to_obj[a]
        self.geom_to_obj = body_to_obj[m.geom_bodyid]
        self.hand_body = mj.mj_name2id(m, mj.mjtObj.mjOBJ_BODY, "robot0_hand")
        self.arm_qadr = [
            int(m.jnt_qposadr[mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, f"robot0_fr3_joint{i}")]) for i in range(1, 8)
        ]
        self.finger_qadr = [
            int(m.jnt_qposadr[mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, f"robot0_finger_joint{i}")]) for i in (1, 2)
        ]
        self.cam_ids = {name: mj.mj_name2id(m, mj.mjtObj.mjOBJ_CAMERA, name) for name in self.cameras}

    # ---- requests ----
    def _snapshot(self) -> tuple[float, np.ndarray]:
        data = self.sim.data
        return self.calls.call(lambda: (float(data.time), data.qpos.copy()))

    def _renderer(self, height: int, width: int):
        key = (height, width)
        if key not in self.renderers:
            self.renderers[key] = self.mujoco.Renderer(self.model, height, width)
        return self.renderers[key]

    def _render(self, name: str, header: dict, data) -> tuple[dict, dict]:
        mj = self.mujoco
        cam = self.cameras[name]
        h, w = int(cam["height"]), int(cam["width"])
        r = self._renderer(h, w)
        opt = mj.MjvOption()
        opt.sitegroup[:] = 0
        opt.geomgroup[3] = 0  # robot collision meshes: render the visual ones only
        r.update_scene(data, camera=self.cam_ids[name], scene_option=opt)
        r.enable_depth_rendering()
        depth = r.render().astype(np.float32)
        r.disable_depth_rendering()
        far = self.model.vis.map.zfar * self.model.stat.extent
        depth[depth >= 0.999 * far] = 0.0
        out = {"depth": depth}
        if header.get("rgb"):
            out["rgb"] = r.render().copy()
        if header.get("segmentation"):
            r.enable_segmentation_rendering()
            seg = r.render()
            r.disable_segmentation_rendering()
            geom_ids = seg[..., 0]
            is_geom = seg[..., 1] == int(mj.mjtObj.mjOBJ_GEOM)
            segmentation = np.full(geom_ids.shape, -1, dtype=np.int32)
            segmentation[is_geom] = self.geom_to_obj[geom_ids[is_geom]]
            out["segmentation"] = segmentation
        f = 0.5 * h / np.tan(0.5 * np.deg2rad(self.model.cam_fovy[self.cam_ids[name]]))
        out["intrinsics"] = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
        cam_to_world = np.eye(4)
        # MuJoCo camera axes (x right, y up, looking along -z) -> OpenCV (x right, y down, z forward)
        cam_to_world[:3, :3] = data.cam_xmat[self.cam_ids[name]].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
        cam_to_world[:3, 3] = data.cam_xpos[self.cam_ids[name]]
        out["cam_to_world"] = cam_to_world
        return {"sim_time": float(data.time)}, out

    def handle(self, header: dict, arrays: dict) -> tuple[dict, dict]:
        cmd = header.get("cmd")
        mj = self.mujoco
        data = self.sim.data
        if cmd == "ping":
            t, _ = self._snapshot()
            return {"sim_time": t}, {}
        if cmd == "info":
            t, _ = self._snapshot()
            return {
                "sim_time": t,
                "protocol": PROTOCOL_VERSION,
                "robot_host": self.host,
                "objects": self.objects,
                "cameras": self.cameras,
                "timestep": float(self.model.opt.timestep),
            }, {}
        if cmd == "render":
            name = header.get("camera")
            if name not in self.cameras:
                raise KeyError(f"unknown camera {name!r}; this server has {sorted(self.cameras)}")
            # rendered inside the simulation thread, between two steps: a consistent state, no GIL
            # hand-overs with the busy simulation loop (3-4x lower latency on 2 loaded cores), and
            # the renderers' GL contexts live in that one thread
            return self.calls.call(lambda: self._render(name, header, self.sim.data))
        if cmd == "objects":
            t, qpos = self._snapshot()
            self.rdata.qpos[:] = qpos
            mj.mj_kinematics(self.model, self.rdata)
            return {"sim_time": t}, {
                "positions": self.rdata.xpos[self.obj_body].copy(),
                "quaternions": self.rdata.xquat[self.obj_body].copy(),
            }
        if cmd in ("place", "displace"):
            key = "positions" if cmd == "place" else "deltas"
            values = np.asarray(arrays.get(key), dtype=float)
            if values.shape != (len(self.objects), 3):
                raise ValueError(f"{cmd}: {key} must be [{len(self.objects)}, 3]; got {list(values.shape)}")

            def apply():
                m = self.model
                for k, (bid, qa, da) in enumerate(zip(self.obj_body, self.obj_qadr, self.obj_dadr)):
                    if qa >= 0:  # free body: its joint's position, upright at rest on "place"
                        if cmd == "place":
                            data.qpos[qa : qa + 3] = values[k]
                            data.qpos[qa + 3 : qa + 7] = (1.0, 0.0, 0.0, 0.0)
                        else:
                            data.qpos[qa : qa + 3] += values[k]
                        data.qvel[da : da + 6] = 0.0
                    else:  # fixed or jointed body: its model position
                        parent = int(m.body_parentid[bid])
                        current = data.xpos[bid] - data.xpos[parent]
                        target = values[k] if cmd == "place" else data.xpos[bid] + values[k]
                        m.body_pos[bid] += target - data.xpos[parent] - current
                mj.mj_forward(m, data)
                return float(data.time)

            return {"sim_time": self.calls.call(apply)}, {}
        if cmd == "state":
            t, qpos = self._snapshot()
            self.rdata.qpos[:] = qpos
            mj.mj_kinematics(self.model, self.rdata)
            rot = self.rdata.xmat[self.hand_body].reshape(3, 3)
            tcp = self.rdata.xpos[self.hand_body] + rot @ np.array([0.0, 0.0, _TCP_OFFSET])
            quat = np.zeros(4)
            mj.mju_mat2Quat(quat, rot.reshape(-1))
            width = float(sum(qpos[a] for a in self.finger_qadr))
            return {"sim_time": t, "finger_width": width}, {
                "tcp_position": tcp,
                "tcp_quaternion": quat,
                "q": np.array([qpos[a] for a in self.arm_qadr]),
            }
        raise ValueError(f"unknown command {cmd!r}")

    # ---- main loop ----
    def serve(self, info_file: str | None, stop, parent_pid: int | None = None) -> None:
        import os
        import selectors
        import time

        self.server.run_async(realtime=self.realtime)
        if info_file:
            info = {
                "pid": os.getpid(),
                "robot_host": self.host,
                "robot_port": 1337,
                "gripper_port": 1338,
                "scene_host": self.host,
                "scene_port": self.scene_port,
                "protocol": PROTOCOL_VERSION,
                "objects": self.objects,
                "cameras": sorted(self.cameras),
            }
            tmp = info_file + ".tmp"
            with open(tmp, "w") as f:
                json.dump(info, f)
            os.replace(tmp, info_file)  # readers see the whole file or none
        sel = selectors.DefaultSelector()
        self.listener.setblocking(False)
        sel.register(self.listener, selectors.EVENT_READ)
        try:
            while not stop.is_set():
                if parent_pid is not None and os.getppid() != parent_pid:
                    break  # the process that started us died without stopping us
                for key, _ in sel.select(timeout=0.1):
                    sock = key.fileobj
                    if sock is self.listener:
                        conn, _ = self.listener.accept()
                        conn.setblocking(True)
                        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                        sel.register(conn, selectors.EVENT_READ)
                        continue
                    try:
                        header, arrays = recv_packet(sock)
                    except (ConnectionError, OSError, ValueError):
                        sel.unregister(sock)
                        sock.close()
                        continue
                    try:
                        t0 = time.perf_counter()
                        reply, out = self.handle(header, arrays)
                        reply["ok"] = True
                        reply["server_s"] = time.perf_counter() - t0
                    except Exception as exc:  # a bad request never stops the server
                        reply, out = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}, {}
                    try:
                        send_packet(sock, reply, out)
                    except OSError:
                        sel.unregister(sock)
                        sock.close()
                if not self.server.running or (self.server.async_thread and not self.server.async_thread.is_alive()):
                    raise RuntimeError("franky-sim's simulation loop stopped")
        finally:
            for key in list(sel.get_map().values()):
                key.fileobj.close()
            sel.close()
            if self.renderers and self.server.async_thread and self.server.async_thread.is_alive():
                try:  # close the GL contexts in the thread they are current in
                    self.calls.call(lambda: [r.close() for r in self.renderers.values()], timeout=5.0)
                except Exception:
                    pass
            self.server.cleanup()
            self.sim.cleanup()
            if info_file and os.path.exists(info_file):
                os.remove(info_file)


def main(argv=None) -> int:
    import argparse
    import os
    import signal
    import threading

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--host", default="127.0.0.1", help="loopback address for the robot, gripper and scene ports")
    p.add_argument(
        "--fallback-hosts",
        type=int,
        default=0,
        help="if 1337/1338 are taken on --host, try this many random 127.x.y.z addresses (the info file says which)",
    )
    p.add_argument("--scene-port", type=int, default=0, help="scene socket port (0: any free port)")
    p.add_argument("--info-file", default=None, help="write pid, host and ports here (JSON) once listening")
    p.add_argument(
        "--exit-with-parent", action="store_true", help="stop when the process that started the server exits"
    )
    p.add_argument("--realtime", type=float, default=0.0, help="0: as fast as possible; 1: real time")
    p.add_argument(
        "--scene",
        default=None,
        help="JSON file {asset, worldbody, objects, positions, cameras}: the task's MJCF (root bodies ddp_<name>), "
        "its object order, initial positions and the cameras {name: {pos, lookat, fovy, width, height}} "
        "(default: the stack blocks and DEFAULT_CAMERAS)",
    )
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    # the simulation thread is busy Python: hand the GIL over often, so scene requests are not kept
    # waiting for the default 5 ms switch interval at every step of a render
    import sys

    sys.setswitchinterval(5e-4)

    if args.scene:
        with open(args.scene) as f:
            scene = json.load(f)
    else:
        scene = default_scene()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    realtime = args.realtime if args.realtime > 0 else False
    rng = np.random.default_rng()
    hosts = [args.host] + [f"127.{a}.{b}.{c}" for a, b, c in rng.integers(1, 255, size=(args.fallback_hosts, 3))]
    server = SceneServer(hosts, args.scene_port, scene, realtime)
    print(f"franky-sim on {server.host} (robot 1337, gripper 1338), scene port {server.scene_port}", flush=True)
    server.serve(args.info_file, stop, parent_pid=os.getppid() if args.exit_with_parent else None)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
