"""The simulated Franka suite: env specs, seeding, ID layout, scripted oracles, OOD displacement,
occlusion, cameras, recipes and the franka_oracle demo source.

Simulator tests skip when robosuite is not installed; config and control checks run without it.
Small images and clouds keep the file fast (one robosuite model per task, shared by the tests).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ddp.envs.franka.control import FrankaControl, agent_pos, mat_to_quat, quat_to_mat, rotvec_to_mat
from ddp.envs.franka.env import FrankaEnvConfig
from ddp.envs.franka.tasks import TASKS
from ddp.envs.franka.tasks.base import DOWN

SMALL = dict(num_points=64, presample=600, image_height=48, image_width=64, tracking_image_height=24,
             tracking_image_width=32)  # fmt: skip


# --------------------------------------------------------------------------------- without the simulator
def test_config_validation_names_field_and_value():
    with pytest.raises(ValueError, match=r"task must be one of stack, pour, press; got 'stak'; did you mean 'stack'\?"):
        FrankaEnvConfig(task="stak")
    with pytest.raises(ValueError, match="displacement needs backend 'sim'"):
        FrankaEnvConfig(backend="real", displacement=True)
    with pytest.raises(ValueError, match=r"displacement_chunks needs one entry per scheduled .*\(2\); got 1"):
        FrankaEnvConfig(task="stack", displacement=True, displacement_chunks=[3])
    # a move no chunk acts on (the protocol would measure an undisturbed episode)
    with pytest.raises(ValueError, match=r"displacement of button at step 96 is first observed at step 104 .* "
                                         r"max_episode_steps 96 no chunk acts on it"):
        FrankaEnvConfig(task="press", displacement=True, displacement_chunks=[12])
    FrankaEnvConfig(task="press", displacement=True, displacement_chunks=[10])  # observed at 88: acted on
    # a snap-back only the oracle makes: checked with oracle tracking, past the episode's last step
    FrankaEnvConfig(task="pour", displacement=True, displacement_chunks=[20])  # its snap-back (step 248) never runs
    with pytest.raises(ValueError, match=r"oracle's snap-back of cup starts at step 248, past the episode's last step "
                                         r"239"):
        FrankaEnvConfig(task="pour", displacement=True, displacement_chunks=[20], oracle_tracking=True)
    FrankaEnvConfig(task="pour", displacement=True, displacement_chunks=[20], oracle_tracking=True,
                    max_episode_steps=250)
    with pytest.raises(ValueError, match=r"obs_history \(3\) must be <= obs_every \(2\)"):
        FrankaEnvConfig(obs_every=2, obs_history=3)
    with pytest.raises(ValueError, match="oracle_tracking=True needs displacement=True"):
        FrankaEnvConfig(oracle_tracking=True)
    with pytest.raises(ValueError, match="crop_min must be below crop_max"):
        FrankaEnvConfig(crop_min=(0.5, 0.0, 0.0), crop_max=(0.4, 0.1, 0.1))
    assert FrankaEnvConfig(task="pour").max_episode_steps == TASKS["pour"].max_episode_steps


def test_id_layout_is_uniform_on_a_10cm_line():
    rng = np.random.default_rng(0)
    for task in TASKS.values():
        for name, (start, end) in task.id_lines.items():
            start, end = np.asarray(start), np.asarray(end)
            assert np.linalg.norm(end - start) == pytest.approx(0.10)
            u = []
            for _ in range(200):
                p = task.sample_layout(rng)[name]
                t = np.dot(p - start, end - start) / 0.01
                assert np.linalg.norm(start + t * (end - start) - p) < 1e-9  # on the line
                u.append(t)
            assert 0.0 <= min(u) < 0.1 and 0.9 < max(u) <= 1.0  # spread over the whole segment
        for row in task.displacements:  # every scheduled displacement leaves the ID zone entirely
            for name in row.bodies:
                for t in (0.0, 1.0):
                    start, end = (np.asarray(p) for p in task.id_lines[name])
                    assert task.outside_id_zone(name, start + t * (end - start) + np.asarray(row.delta))
                    assert not task.outside_id_zone(name, start + t * (end - start))


class _FakeBackend:
    def __init__(self):
        self.pos, self.quat, self.moves, self.grip = np.array([0.4, 0.0, 0.3]), mat_to_quat(DOWN), [], []

    def ee_pose(self):
        return self.pos.copy(), self.quat.copy()

    def move_to(self, position, quaternion):
        self.moves.append((np.asarray(position), np.asarray(quaternion)))
        self.pos, self.quat = np.asarray(position), np.asarray(quaternion)

    def set_gripper(self, close):
        self.grip.append(close)


def test_a_backend_with_its_own_safety_box_clips_the_env_inside_both():
    """The real robot's box (RealBackendConfig.workspace_low/high) and the env's (workspace_min/max): targets,
    shifts and their applied amounts are computed in the intersection, as the backend executes them."""
    import types

    from ddp.envs.franka.env import FrankaEnv

    backend = _FakeBackend()
    backend.config = types.SimpleNamespace(workspace_low=(0.25, -0.45, 0.005), workspace_high=(0.70, 0.45, 0.50))
    env = FrankaEnv(FrankaEnvConfig(task="press", **SMALL), backend=backend)
    lo, hi = FrankaEnvConfig().workspace_min, FrankaEnvConfig().workspace_max
    np.testing.assert_allclose(env.control.low, np.maximum(lo, (0.25, -0.45, 0.005)))
    np.testing.assert_allclose(env.control.high, np.minimum(hi, (0.70, 0.45, 0.50)))
    backend.config.workspace_low = (0.9, -0.45, 0.005)
    backend.config.workspace_high = (1.0, 0.45, 0.5)
    with pytest.raises(ValueError, match="do not overlap"):
        FrankaEnv(FrankaEnvConfig(task="press", **SMALL), backend=backend)


def test_control_clips_translation_rotation_and_workspace():
    backend = _FakeBackend()
    ctl = FrankaControl(backend, workspace_low=(0.2, -0.4, 0.0), workspace_high=(0.7, 0.4, 0.32),
                        max_translation=0.02, max_rotation=0.1)  # fmt: skip
    ctl.reset()
    executed = ctl.step([0.5, -0.005, 0.5, 0.0, 0.0, 0.3, 1.0])
    np.testing.assert_allclose(executed, [0.02, -0.005, 0.02, 0.0, 0.0, 0.1, 1.0])
    pos, quat = backend.moves[-1]
    np.testing.assert_allclose(pos, [0.42, -0.005, 0.32])  # z clipped to the workspace top
    np.testing.assert_allclose(quat_to_mat(quat), rotvec_to_mat([0, 0, 0.1]) @ DOWN, atol=1e-9)
    assert backend.grip == [True]
    ctl.step([0, 0, 0, 0, 0, 0, 1.0])
    assert backend.grip == [True]  # the gripper is commanded only when it changes
    ap = agent_pos(pos, quat, 0.04)
    assert ap.shape == (15,) and np.linalg.norm(ap[3:6] - ap[6:9]) == pytest.approx(0.04)
    # a NaN gripper command would read as "open" (NaN > 0 is False): refused, nothing sent
    from ddp.safety import NonFiniteError

    moves = len(backend.moves)
    with pytest.raises(NonFiniteError, match="franka control: refused a non-finite action"):
        ctl.step([0, 0, 0, 0, 0, 0, float("nan")])
    with pytest.raises(NonFiniteError, match="franka control: refused a non-finite end-effector shift"):
        ctl.shift([0.0, float("nan"), 0.0])
    assert len(backend.moves) == moves and backend.grip == [True]


def test_a_real_cameras_frame_with_nothing_in_the_crop_box_is_an_error_not_a_constant_cloud():
    """A dead depth stream, or an inverted cam_to_base that puts every point behind the camera: a simulated
    view may be empty (the box's centre stands in), a real camera's stops the episode with one line."""
    from ddp.envs.franka.backend import CameraFrame
    from ddp.envs.franka.pointcloud import FrameToCloud

    k = np.array([[100.0, 0, 16], [0, 100.0, 12], [0, 0, 1]])
    looking_down = np.eye(4)
    looking_down[:3, :3] = np.diag([1.0, -1.0, -1.0])
    looking_down[:3, 3] = [0.5, 0.0, 1.0]
    table = CameraFrame(depth=np.full((24, 32), 0.95, np.float32), intrinsics=k, cam_to_world=looking_down)
    inverted = dataclasses.replace(table, cam_to_world=np.linalg.inv(looking_down))
    box = dict(crop_low=(0.3, -0.3, 0.01), crop_high=(0.7, 0.3, 0.3))
    rng = np.random.default_rng(0)
    cloud = FrameToCloud(16, 0, **box, on_empty="raise")(table, rng)  # 5 cm above the table top: in the box
    assert cloud.shape == (16, 3) and np.all(cloud[:, 2] > 0.01)
    with pytest.raises(RuntimeError, match=r"no point in the crop box .* \(768 pixels with a depth return\): check "
                                           "the camera's depth stream, its cam_to_base calibration"):
        FrameToCloud(16, 0, **box, on_empty="raise")(inverted, rng)
    np.testing.assert_allclose(FrameToCloud(16, 0, **box)(inverted, rng), [[0.5, 0.0, 0.155]] * 16, atol=1e-6)


def test_a_shift_counts_what_the_backend_can_reach_as_applied():
    """A real arm pulls targets beyond its reach back (RealBackendConfig.max_reach): the shift's applied
    amount, which the recovery undoes, is what the arm holds, not what was asked."""
    backend = _FakeBackend()
    backend.reachable = lambda position, quaternion: np.minimum(position, [0.5, 1.0, 1.0])  # x at most 0.5
    ctl = FrankaControl(backend, workspace_low=(0.2, -0.4, 0.0), workspace_high=(0.7, 0.4, 0.5))
    ctl.reset()
    applied = ctl.shift([0.25, 0.05, 0.0])
    np.testing.assert_allclose(applied, [0.1, 0.05, 0.0])  # asked 0.25 in x; x = 0.4 + 0.1 is as far as it goes
    np.testing.assert_allclose(ctl.target_pos, [0.5, 0.05, 0.3])
    assert all(m[0][0] <= 0.5 + 1e-12 for m in backend.moves)


def test_a_shift_whose_lift_is_blocked_does_not_move_across():
    """safe_lift exists so that the hand does not drag through the scene: a lift that stops short (blocked, or
    too slow) cancels the move across, and the applied shift, which the recovery undoes, is zero."""
    backend = _FakeBackend()
    real_move = backend.move_to

    def blocked_above(position, quaternion):  # something above the hand: z cannot pass 0.31
        real_move(np.minimum(position, [1.0, 1.0, 0.31]), quaternion)

    backend.move_to = blocked_above
    ctl = FrankaControl(backend, workspace_low=(0.2, -0.4, 0.0), workspace_high=(0.7, 0.4, 0.5))
    ctl.reset()
    with pytest.warns(RuntimeWarning, match="lift stopped 0.040 m short of its height; the shift is not applied"):
        applied = ctl.shift([0.0, 0.1, 0.0], safe_lift=0.05, max_steps=10)
    np.testing.assert_allclose(applied, 0.0)
    assert max(abs(m[0][1]) for m in backend.moves) < 1e-12  # never moved across
    np.testing.assert_allclose(backend.pos, [0.4, 0.0, 0.3])  # back down where it started
    free = _FakeBackend()
    ctl = FrankaControl(free, workspace_low=(0.2, -0.4, 0.0), workspace_high=(0.7, 0.4, 0.5))
    ctl.reset()
    np.testing.assert_allclose(ctl.shift([0.0, 0.1, 0.0], safe_lift=0.05), [0.0, 0.1, 0.0])
    assert max(m[0][2] for m in free.moves) == pytest.approx(0.35)  # up, across, down


def test_the_orientation_stays_within_max_tilt_of_the_home_pose():
    """Per-step rotation limits alone let a steady bias turn the hand without bound (30 chunks of a small roll
    wind the wrist past its limits); the commanded orientation stops at max_tilt from the reset's."""
    from ddp.envs.franka.control import rotation_angle

    backend = _FakeBackend()
    ctl = FrankaControl(backend, workspace_low=(0.2, -0.4, 0.0), workspace_high=(0.7, 0.4, 0.5), max_tilt=1.0)
    ctl.reset()
    for _ in range(100):  # 100 x 0.1 rad about x: 10 rad asked for
        ctl.step([0, 0, 0, 0.1, 0, 0, -1.0])
    _, quat = backend.moves[-1]
    assert rotation_angle(DOWN, quat_to_mat(quat)) == pytest.approx(1.0, abs=1e-6)
    # on the way: the rotation toward the limit is the one asked for (about base x)
    np.testing.assert_allclose(quat_to_mat(quat), rotvec_to_mat([1.0, 0, 0]) @ DOWN, atol=1e-6)
    for _ in range(5):  # turning back is free
        ctl.step([0, 0, 0, -0.1, 0, 0, -1.0])
    assert rotation_angle(DOWN, quat_to_mat(backend.moves[-1][1])) == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(ValueError, match="max_tilt must be at most pi"):
        FrankaControl(backend, workspace_low=(0.2, -0.4, 0.0), workspace_high=(0.7, 0.4, 0.5), max_tilt=4.0)
    with pytest.raises(ValueError, match="max_tilt must be in"):
        FrankaEnvConfig(task="press", max_tilt=float("nan"))
    assert FrankaEnvConfig(task="pour").max_tilt == pytest.approx(2.4)  # pour's demos turn up to 121 degrees


# ------------------------------------------------------------------------------------- with the simulator
@pytest.fixture(scope="module")
def envs():
    """``make(task, **config)``: a FrankaEnv; envs with the same task and image sizes share one robosuite model."""
    pytest.importorskip("robosuite")
    from ddp.envs.franka.env import FrankaEnv, make_sim_backend

    backends = {}

    def make(task, **options):
        cfg = FrankaEnvConfig(task=task, **{**SMALL, **options})
        key = (task, cfg.image_height, cfg.image_width, cfg.tracking_image_height, cfg.tracking_image_width)
        if key not in backends:
            backends[key] = make_sim_backend(dataclasses.replace(cfg, tracking_camera=True, tracking_rgb=True))
        return FrankaEnv(cfg, backend=backends[key])

    yield make
    for backend in backends.values():
        backend.close()


def _run_oracle(env, seed, oracle, steps=None):
    oracle.reset()
    td = env.reset(seed=seed)
    success, first = False, None
    for t in range(steps or env.config.episode_steps):
        td["action"] = torch.as_tensor(oracle(td))
        td = env.step(td)["next"]
        if bool(td["success"]) and first is None:
            first, success = t, True
            break
    return success, td


@pytest.mark.parametrize("task", ["stack", "pour", "press"])
def test_env_specs(envs, task):
    from torchrl.envs.utils import check_env_specs

    env = envs(task, tracking_camera=True, tracking_rgb=task == "stack")
    check_env_specs(env, seed=0)
    td = env.reset(seed=0)
    k = len(env.task.object_names)
    assert td["point_cloud"].shape == (64, 3) and td["agent_pos"].shape == (15,)
    assert td["privileged", "object_pos"].shape == (k, 3) and td["privileged", "displacement"].shape == (k, 3)
    assert td["tracking", "segmentation"].dtype == torch.int32 and td["tracking", "depth"].shape == (24, 32)
    assert env.action_spec.shape == (7,)
    # the task's diagnostics ride along under privileged/task_info, one float per name in info_keys
    info = td["privileged", "task_info"]
    assert set(info.keys()) == set(env.task.info_keys) and set(env.task.info_keys) == set(env.task_info())
    assert all(float(info[name]) == pytest.approx(v) for name, v in env.task_info().items())
    if task == "stack":
        rgb = td["tracking", "rgb"]
        assert rgb.shape == (24, 32, 3) and rgb.dtype == torch.uint8 and int(rgb.max()) > 0


def test_seeding_reproduces_layout_clouds_and_trajectories(envs):
    env = envs("stack")
    actions = torch.tensor([[0.02, 0.0, -0.02, 0.0, 0.0, 0.05, -1.0]] * 5 + [[0.0, 0.02, 0.0, 0.0, 0.0, 0.0, 1.0]] * 5)

    def roll(seed):
        td = env.reset(seed=seed)
        out = [td["point_cloud"].clone()]
        for a in actions:
            td["action"] = a
            td = env.step(td)["next"]
            out.append(td["agent_pos"].clone())
        return td["privileged", "object_pos"].clone(), out

    pos_a, traj_a = roll(7)
    pos_b, traj_b = roll(7)
    pos_c, _ = roll(8)
    assert torch.equal(pos_a, pos_b) and all(torch.equal(a, b) for a, b in zip(traj_a, traj_b))
    assert not torch.allclose(pos_a, pos_c)
    assert env.steps_done == 10


def test_cloud_sees_the_objects_and_tracking_geometry_is_consistent(envs):
    from ddp.envs.franka.pointcloud import backproject

    env = envs("stack", num_points=512, presample=3000, image_height=96, image_width=128, tracking_camera=True,
               tracking_image_height=96, tracking_image_width=128)  # fmt: skip
    td = env.reset(seed=3)
    cloud, objects = td["point_cloud"].numpy(), td["privileged", "object_pos"].numpy()
    lo, hi = env.config.crop_box
    assert np.all(cloud >= np.asarray(lo) - 1e-6) and np.all(cloud <= np.asarray(hi) + 1e-6)
    for k, p in enumerate(objects):  # points on each block's visible faces (half sizes 2 / 2.5 cm)
        assert (np.linalg.norm(cloud - p, axis=1) < 0.04).sum() >= 10, env.task.object_names[k]
    frame = env.backend.render("tracking")
    rot = frame.cam_to_world[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-6)
    pts = backproject(frame)
    seg = frame.segmentation.reshape(-1)[frame.depth.reshape(-1) > 0]
    for k, p in enumerate(objects):  # the segmented pixels back-project onto the object
        mine = pts[seg == k]
        assert len(mine) >= 5 and np.linalg.norm(mine.mean(0) - p) < 0.03


@pytest.mark.parametrize("task,seeds", [("stack", (0, 1)), ("press", (0, 1)), ("pour", (0,))])
def test_scripted_oracle_succeeds(envs, task, seeds):
    env = envs(task, render_point_cloud=False)
    oracle = env.task.oracle()
    for seed in seeds:
        success, _ = _run_oracle(env, seed, oracle)
        assert success, f"{task} oracle failed on seed {seed}: {env.task_info()}"


def test_press_fails_when_under_or_over_pressed(envs):
    env = envs("press", render_point_cloud=False)
    td = env.reset(seed=0)
    button = td["privileged", "object_pos"][0].numpy()

    def press_to(z, steps=12):
        nonlocal td
        for target in [np.r_[button[:2], 0.12], np.r_[button[:2], z], np.r_[button[:2], 0.12]]:
            for _ in range(steps):
                d = np.clip(target - td["privileged", "ee_target"].numpy(), -0.02, 0.02)
                td["action"] = torch.tensor([*d, 0, 0, 0, 1.0], dtype=torch.float32)
                td = env.step(td)["next"]
        return bool(td["success"])

    assert not press_to(0.06)  # stops above the cap: under-pressed, no success (may retry)
    assert env.task_state["max_depth"] < 0.006
    assert not press_to(0.0)  # drives far below the activation depth: over-pressed
    assert env.task_state["over_pressed"] and env.task_state["max_depth"] > 0.014
    assert float(td["privileged", "task_info", "over_pressed"]) == 1.0  # what an evaluation reports per episode
    assert float(td["privileged", "task_info", "max_depth"]) == pytest.approx(env.task_state["max_depth"])
    assert not press_to(0.052)  # a correct press afterwards does not undo the over-press
    assert bool(td["failed"])  # the env's flag: the episode failed for good
    # a good press, then an over-press: the success is revoked (it counted: success was read at any step)
    td = env.reset(seed=0)
    assert not bool(td["failed"])
    assert press_to(0.052) and not bool(td["failed"])
    assert not press_to(0.0) and bool(td["failed"])


@pytest.mark.parametrize("task", ["press", "stack"])
def test_displacement_leaves_the_id_zone_and_success_follows_the_objects(envs, task):
    env = envs(task, render_point_cloud=False, displacement=True)
    plan = env.task.displacements
    reactive, blind = env.task.oracle(), env.task.oracle(id_frame=True)
    success, td = _run_oracle(env, 0, reactive)
    assert success  # the oracle that sees the true positions still succeeds
    disp = td["privileged", "displacement"].numpy()
    for row in plan:
        for name in row.bodies:
            k = env.task.object_names.index(name)
            if name == "pink":  # placed on the displaced green block: it moved with the scene
                continue
            np.testing.assert_allclose(disp[k], row.delta, atol=1e-6)
            assert env.task.outside_id_zone(name, td["privileged", "object_pos"][k].numpy())
    success, _ = _run_oracle(env, 0, blind)
    assert not success  # acting on the ID positions misses the moved objects: no false success
    tracked = envs(task, render_point_cloud=False, displacement=True, oracle_tracking=True)
    success, td = _run_oracle(tracked, 0, env.task.oracle(id_frame=True))
    assert success  # with the env's oracle tracking the ID-frame oracle succeeds again
    assert np.linalg.norm(td["privileged", "ee_offset"].numpy()) > 0.1


def test_shift_end_effector_moves_the_arm_and_carried_objects(envs):
    env = envs("stack", render_point_cloud=False, displacement=True, displacement_chunks=[0, 18])  # green: after these steps
    oracle = env.task.oracle()
    oracle.reset()
    td = env.reset(seed=2)
    td["action"] = torch.as_tensor(oracle(td))
    td = env.step(td)["next"]  # the pink block was displaced before this step
    pink_disp = td["privileged", "displacement"][0].numpy().copy()
    assert np.linalg.norm(pink_disp) > 0.1
    while not env.backend.grasped()[0]:  # until the block is held
        assert env.steps_done < 60, "the oracle did not grasp the pink block"
        td["action"] = torch.as_tensor(oracle(td))
        td = env.step(td)["next"]
    steps = env.steps_done
    before = td["agent_pos"][:3].numpy().copy()
    applied = env.shift_end_effector(-pink_disp)
    after = env.backend.ee_pose()[0]
    np.testing.assert_allclose(applied, -pink_disp, atol=1e-9)
    assert np.linalg.norm(after - (before - pink_disp)) < 0.02
    assert env.steps_done == steps  # not counted as env steps
    td["action"] = torch.zeros(7)
    td["action"][6] = 1.0
    td = env.step(td)["next"]
    assert np.allclose(td["privileged", "displacement"][0].numpy(), 0.0)  # carried back: no longer displaced
    np.testing.assert_allclose(td["privileged", "ee_offset"].numpy(), -pink_disp, atol=1e-9)


def test_occlusion_blinds_the_chosen_chunks(envs):
    env = envs("press", occlusion_chunk=1, occlusion_chunks=2, chunk_len=4)
    td = env.reset(seed=0)
    flags = []
    for _ in range(14):
        td["action"] = torch.zeros(7)
        td = env.step(td)["next"]
        flags.append(bool(td["privileged", "occluded"]))
        if flags[-1]:
            assert torch.count_nonzero(td["point_cloud"]) == 0
        else:
            assert torch.count_nonzero(td["point_cloud"]) > 0
    assert flags == [False] * 4 + [True] * 8 + [False] * 2  # observations after actions 5..12


def test_a_video_camera_the_scene_lacks_names_the_ones_it_has(envs):
    """A wrong eval.video_camera was KeyError('side'): the message named neither the cameras nor the closest."""
    env = envs("press")
    env.reset(seed=0)
    assert env.render_rgb(16, 16, camera="policy").shape == (16, 16, 3)
    with pytest.raises(ValueError, match=r"video camera must be one of \[.*'policy'.*\]; got 'polcy'; did you mean "
                                         r"'policy'"):
        env.render_rgb(16, 16, camera="polcy")


def test_recipes_build():
    from conftest import RECIPES
    from ddp import build

    expected = {"stack": (0.0002, 2), "pour": (0.0004, 2), "press": (0.0012, 1)}
    for task, (tau, subtasks) in expected.items():
        exp = build(RECIPES / f"franka_{task}.yaml")
        assert exp.parts["env"].config.task == task and exp.recipe.task.action_dim == 7
        assert exp.recipe.controller.detector["tau"] == tau and len(exp.recipe.controller.subtasks) == subtasks
        assert exp.recipe.policy.denoiser["down_dims"] == [128, 256, 384]
        cpu = build(RECIPES / f"franka/cpu_{task}.yaml")
        assert cpu.parts["env"].config.task == task and cpu.recipe.task.num_points == 256
        assert [s.target for s in cpu.recipe.controller.subtasks] == [s.target for s in exp.recipe.controller.subtasks]


def test_oracle_demos_source_shapes_and_cache(tmp_path, envs):
    from conftest import RECIPES
    from ddp import build

    envs("press")  # skip without robosuite
    overrides = [f"data.path={tmp_path}/{{task}}", "data.episodes=2", *(f"env.{k}={v}" for k, v in SMALL.items()),
                 "task.num_points=64"]  # fmt: skip
    exp = build(RECIPES / "franka/cpu_press.yaml", overrides)
    src = exp.dataset()
    info = src.prepare(progress=False)
    assert info["generated"] and info["episodes"] == 2 and info["stats"]["success_rate"] > 0
    demos = src.load()
    steps = demos.steps
    assert demos.num_episodes == 2
    assert steps["point_cloud"].shape[1:] == (64, 3) and steps["agent_pos"].shape[1:] == (15,)
    assert steps["action"].shape[1:] == (7,) and steps["object_pos"].shape[1:] == (1, 3)
    assert float(steps["action"][:, :3].abs().max()) <= 0.02 + 1e-6
    again = build(RECIPES / "franka/cpu_press.yaml", overrides).dataset().prepare(progress=False)
    assert not again["generated"]  # the cache is reused
    one = build(RECIPES / "franka/cpu_press.yaml", [*overrides, "data.episodes=1"]).dataset()
    assert not one.prepare(progress=False)["generated"] and one.load().num_episodes == 1
    changed = build(RECIPES / "franka/cpu_press.yaml", [*overrides, "env.presample=500"]).dataset()
    assert changed.cached_meta() is None  # another env config: another cache key
