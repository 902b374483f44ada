"""The MetaWorld env: specs, point clouds, the paper's displacement / oracle protocol, occlusion, seeding.

Simulator tests skip when metaworld is not installed; config validation runs without it.
"""

import dataclasses
import re
import subprocess
import sys

import numpy as np
import pytest
import torch

from ddp.config import from_dict, to_dict
from ddp.envs.metaworld import MetaWorldEnvConfig
from ddp.envs.metaworld_tasks import PAPER_TASKS
from ddp.errors import RecipeError

SMALL = dict(image_size=32, num_points=64)  # cheap clouds where geometry does not matter


@pytest.fixture
def make_env():
    pytest.importorskip("metaworld")
    from ddp.envs.metaworld import MetaWorldEnv

    envs = []

    def make(**options):
        env = MetaWorldEnv(MetaWorldEnvConfig(**options))
        envs.append(env)
        return env

    yield make
    for env in envs:
        env.close()


def _step(env, td, action):
    td["action"] = torch.as_tensor(action, dtype=torch.float32)
    return env.step(td)["next"]


def _run_expert(env, seed, id_frame):
    """Scripted expert through the TorchRL env; True at the first success."""
    from ddp.data.sources.metaworld_expert import MetaWorldExpert, expert_succeeds

    return expert_succeeds(env, MetaWorldExpert(env.config.task, id_frame=id_frame), seed)


def test_config_validation_names_field_and_value():
    with pytest.raises(ValueError, match=r"task must be one of .*got 'buton-press'; did you mean 'button-press'\?"):
        MetaWorldEnvConfig(task="buton-press")
    assert MetaWorldEnvConfig(task="push-v3").task == "push"
    with pytest.raises(ValueError, match="oracle_tracking=True needs displacement=True"):
        MetaWorldEnvConfig(task="push", oracle_tracking=True)
    with pytest.raises(ValueError, match="paper's tasks .*got task 'reach'"):
        MetaWorldEnvConfig(task="reach", displacement=True)
    with pytest.raises(ValueError, match=r"obs_history \(3\) must be <= obs_every \(2\)"):
        MetaWorldEnvConfig(obs_every=2, obs_history=3)
    with pytest.raises(ValueError, match="task_indices"):
        MetaWorldEnvConfig(task_indices=(10, 60))
    with pytest.raises(ValueError, match="crop_min must be below crop_max"):
        MetaWorldEnvConfig(crop_min=(0, 0, 1), crop_max=(1, 1, 0))
    with pytest.raises(ValueError, match="occlusion_mode"):
        MetaWorldEnvConfig(occlusion_chunk=1, occlusion_mode="blur")
    with pytest.raises(ValueError, match=r"task_indices needs 2 entries \[start, stop\); got \[0\]"):
        MetaWorldEnvConfig(task_indices=(0,))
    with pytest.raises(ValueError, match=r"camera_pos needs 3 entries; got \[1, 2\]"):
        MetaWorldEnvConfig(camera_pos=(1, 2))
    # a move the episode never reaches: the "OOD" protocol would measure an undisturbed episode
    with pytest.raises(ValueError, match=r"displacement_chunk 30 starts at step 240 .*no chunk acts after the move "
                                         r"is observed \(it needs max_episode_steps > 248\)"):
        MetaWorldEnvConfig(task="assembly", displacement=True, displacement_chunk=30)
    with pytest.raises(ValueError, match=r"displacement_chunk 24 starts at step 192"):  # seen at 200: the end
        MetaWorldEnvConfig(task="assembly", displacement=True, displacement_chunk=24)
    MetaWorldEnvConfig(task="assembly", displacement=True, displacement_chunk=23)  # seen at 192, one chunk acts
    with pytest.raises(ValueError, match=r"snap-back chunk 6 starts at step 48, past the episode's last step 39 "
                                         r"\(max_episode_steps 40\)"):
        MetaWorldEnvConfig(task="sweep", displacement=True, oracle_tracking=True, max_episode_steps=40)
    MetaWorldEnvConfig(task="sweep", displacement=True, max_episode_steps=40)  # no snap-back without the oracle


def test_config_round_trips_through_a_recipe_dict():
    cfg = MetaWorldEnvConfig(task="coffee-pull", displacement=True, displacement_delta=(-0.1, 0.0, 0.0),
                             oracle_tracking=True, occlusion_chunk=3)
    again = from_dict(MetaWorldEnvConfig, to_dict(cfg))
    assert again == cfg
    plan = again.displacement_schedule()
    assert plan.delta == (-0.1, 0.0, 0.0) and plan.chunk == 2 and plan.snap_back_chunk == 8
    with pytest.raises(RecipeError, match="env.chunk_len.*did you mean|unknown option"):
        from_dict(MetaWorldEnvConfig, {"chunk_length": 8}, key="env")


def test_envs_import_without_the_simulator():
    code = (
        "import sys; sys.modules['metaworld'] = None; sys.modules['mujoco'] = None\n"
        "import ddp.envs\n"
        "from ddp.envs.metaworld import MetaWorldEnv\n"
        "try:\n    MetaWorldEnv()\nexcept ImportError as err:\n    print(err)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert 'pip install "ddp[sim]"' in out.stdout


# ---------------------------------------------------------------------- specs


@pytest.mark.parametrize("task", list(PAPER_TASKS))
def test_check_env_specs_with_every_disturbance(make_env, task):
    from torchrl.envs.utils import check_env_specs

    # chunk_len=1: a chunk is a step; check_env_specs rolls out 3 steps, so the rollout below goes past every
    # task's displacement (chunks 2-6) and snap-back (6-8) and checks each step against the spec
    env = make_env(task=task, chunk_len=1, displacement=True, oracle_tracking=True,
                   occlusion_chunk=1, occlusion_mode="noise", **SMALL)
    check_env_specs(env, seed=0)
    assert env.observation_spec["privileged", "object_pos"].shape == (len(PAPER_TASKS[task].bodies), 3)
    steps = env.rollout(10, break_when_any_done=False)
    keys = list(env.observation_spec.keys(True, True))
    assert all(env.observation_spec.is_in(steps[i]["next"].select(*keys)) for i in range(10))
    moved = steps["next", "privileged", "displacement"].flatten(1).norm(dim=-1)
    assert bool((moved > 0.05).any())  # the move happened inside the checked steps


def test_any_metaworld_task_and_the_registry(make_env):
    from torchrl.envs.utils import check_env_specs

    from ddp import registry

    plugin = registry.get("env", "metaworld")
    env = plugin.factory(plugin.config_cls(task="reach", **SMALL), seed=3, device="cpu")
    try:
        check_env_specs(env)
        assert "object_pos" not in env.observation_spec["privileged"].keys()
        fast = make_env(task="reach", render_point_cloud=False)
        assert "point_cloud" not in fast.reset().keys()
    finally:
        env.close()


# --------------------------------------------------------------- point cloud


def test_point_cloud_has_the_table_and_the_object(make_env):
    env = make_env(task="button-press")  # defaults: 84 px, 512 points, DP3 camera and crop
    td = env.reset(seed=0)
    pc = td["point_cloud"].numpy()
    cfg = env.config
    assert pc.shape == (512, 3) and pc.dtype == np.float32
    assert np.all(pc >= np.array(cfg.crop_min) - 1e-6) and np.all(pc <= np.array(cfg.crop_max) + 1e-6)
    assert (np.abs(pc[:, 2]) < 0.01).mean() > 0.3, "the table plane (z ~ 0) fills much of the cloud"
    box = td["privileged", "object_pos"][0].numpy()  # button box: centre at z = 0.115
    near = np.all(np.abs(pc - box) < [0.12, 0.12, 0.12], axis=1) & (pc[:, 2] > 0.02)
    assert near.sum() > 20, "points on the button box"
    assert len(np.unique(pc, axis=0)) == 512

    above = make_env(task="button-press", crop_min=(-0.6, 0.3, 0.005)).reset(seed=0)["point_cloud"].numpy()
    assert above[:, 2].min() >= 0.005, "raising the crop floor drops the table"


def test_visible_sites_draw_the_goal_marker_into_the_cloud(make_env):
    """push's goal changes with the initial state and is a site: hidden (the default), no point lies on
    it; with visible_sites [goal] the cloud has points there (the table is cropped away in both)."""
    counts = {}
    for sites in ((), ("goal",)):
        env = make_env(task="push", num_points=512, crop_min=(-0.6, 0.3, 0.005), visible_sites=sites)
        near = []
        for seed in range(3):
            td = env.reset(seed=seed)
            goal, puck = td["privileged", "goal"].numpy(), td["privileged", "object_pos"][0].numpy()
            assert np.linalg.norm(goal - puck) > 0.1  # the puck does not stand in for the marker
            near.append(int((np.linalg.norm(td["point_cloud"].numpy() - goal, axis=1) < 0.03).sum()))
        counts[sites] = near
    assert counts[()] == [0, 0, 0] and min(counts[("goal",)]) >= 1, counts
    with pytest.raises(ValueError, match="visible_sites: no site 'gaol'.*did you mean 'goal'"):
        make_env(task="push", **SMALL, visible_sites=("gaol",))


# -------------------------------------------------------------- displacement


def _box_points(pc, centre):
    sel = np.all(np.abs(pc[:, :2] - centre[:2]) < 0.12, axis=1) & (pc[:, 2] > 0.03)
    return pc[sel]


def test_displacement_moves_object_goal_and_cloud(make_env):
    opts = dict(task="button-press", chunk_len=2)  # displacement chunk 3 -> before step 6
    plain, moved = make_env(**opts), make_env(displacement=True, **opts)
    a, b = plain.reset(seed=1), moved.reset(seed=1)
    box0 = a["privileged", "object_pos"][0].numpy()
    for t in range(8):
        a, b = _step(plain, a, np.zeros(4)), _step(moved, b, np.zeros(4))
        if t == 5:  # the 6th step is the first one after the move
            assert b["privileged", "displacement"].abs().sum() == 0
    delta = np.array([-0.25, 0.0, 0.0])
    np.testing.assert_allclose(b["privileged", "object_pos"][0].numpy() - box0, delta, atol=1e-5)
    np.testing.assert_allclose(b["privileged", "displacement"][0].numpy(), delta, atol=1e-6)
    np.testing.assert_allclose((b["privileged", "goal"] - a["privileged", "goal"]).numpy(), delta, atol=1e-5)
    # the goal is not clipped in MetaWorld's state observation
    np.testing.assert_allclose(b["privileged", "state"][36:39].numpy(), b["privileged", "goal"].numpy(), atol=1e-6)
    # the button (state object 1) moved with its box
    button_shift = (b["privileged", "state"][4:7] - a["privileged", "state"][4:7]).numpy()
    np.testing.assert_allclose(button_shift, delta, atol=2e-3)

    before, after = _box_points(a["point_cloud"].numpy(), box0), _box_points(b["point_cloud"].numpy(), box0 + delta)
    assert len(before) > 20 and len(after) > 20
    np.testing.assert_allclose(after.mean(0) - before.mean(0), delta, atol=0.03)
    assert len(_box_points(b["point_cloud"].numpy(), box0)) < len(before) / 3, "the old place is empty"
    assert a["privileged", "ee_offset"].abs().sum() == 0 and b["privileged", "ee_offset"].abs().sum() == 0


@pytest.mark.filterwarnings("ignore:Constant")  # metaworld's policies warn about their own gains
def test_scripted_expert_needs_oracle_tracking_under_displacement(make_env):
    """An expert that keeps acting in the ID frame succeeds with oracle tracking and fails without."""
    opts = dict(task="button-press", render_point_cloud=False, terminate_on_success=True, displacement=True)
    tracked, untracked = make_env(oracle_tracking=True, **opts), make_env(**opts)
    assert _run_expert(tracked, seed=0, id_frame=True)
    assert not _run_expert(untracked, seed=0, id_frame=True)
    assert _run_expert(untracked, seed=0, id_frame=False), "the state expert re-targets the moved button"


def test_oracle_tracking_and_two_stage_snap_back(make_env):
    for task in ("coffee-pull", "pick-place"):
        spec = PAPER_TASKS[task]
        plan = spec.displacement
        env = make_env(task=task, chunk_len=1, displacement=True, oracle_tracking=True, render_point_cloud=False)
        td = env.reset(seed=2)
        obj0 = td["privileged", "object_pos"].numpy()
        hand0 = td["agent_pos"][:3].numpy()
        delta = np.array(plan.delta)
        for t in range(plan.snap_back_chunk + 1):
            td = _step(env, td, np.zeros(4))
            if t == plan.chunk:  # tracked: every body and the hand moved by delta
                np.testing.assert_allclose(td["privileged", "ee_offset"].numpy(), delta, atol=1e-6)
                moved = td["privileged", "object_pos"].numpy() - obj0
                np.testing.assert_allclose(moved, np.broadcast_to(delta, obj0.shape), atol=0.01)
                np.testing.assert_allclose(td["agent_pos"][:3].numpy() - hand0, delta, atol=0.03)
        # snapped back: hand home, carried object's displacement cleared, the rest stays displaced
        np.testing.assert_allclose(td["privileged", "ee_offset"].numpy(), 0.0, atol=1e-6)
        np.testing.assert_allclose(td["agent_pos"][:3].numpy(), hand0, atol=0.03)
        disp = td["privileged", "displacement"].numpy()
        for k, body in enumerate(spec.bodies):
            expected = np.zeros(3) if body in spec.carried else delta
            np.testing.assert_allclose(disp[k], expected, atol=1e-6)


def _finger_width(env) -> float:
    right, left = env._fingers
    return float(np.linalg.norm(env.sim.data.site_xpos[right] - env.sim.data.site_xpos[left]))


def test_pause_fingers_stops_a_closing_gripper_during_a_shift(make_env):
    """Fingers that began closing on air finish closing during the settled shift unless paused."""
    widths = {}
    for pause in (False, True):
        env = make_env(task="pick-place", render_point_cloud=False, pause_fingers=pause)
        td = env.reset(seed=7)
        for _ in range(2):  # the close command has just started
            td = _step(env, td, [0.0, 0.0, 0.0, 1.0])
        before = _finger_width(env)
        env.shift_end_effector([-0.2, -0.1, 0.0], safe_lift=0.05)
        widths[pause] = (before, _finger_width(env))
    assert widths[False][1] < widths[False][0] - 0.03, widths
    np.testing.assert_allclose(widths[True][1], widths[True][0], atol=1e-3)
    # a safe lift with no settling collapsed to its last waypoint (the hand dragged across the table)
    with pytest.raises(ValueError, match="safe_lift needs settle_steps >= 1"):
        env.shift_end_effector([-0.2, -0.1, 0.0], safe_lift=0.05, settle_steps=0)


@pytest.mark.filterwarnings("ignore:Constant")  # metaworld's policies warn about their own gains
def test_pause_fingers_keeps_a_grasped_object_in_hand(make_env):
    """Paused fingers still squeeze: a lifted puck travels with the shifted hand (a pause that released the
    actuators' grip, or opened the gripper, drops it; unpaused fingers carry it too)."""
    from ddp.data.sources.metaworld_expert import MetaWorldExpert

    env = make_env(task="pick-place", render_point_cloud=False, pause_fingers=True)
    expert = MetaWorldExpert("pick-place")
    td = env.reset(seed=3)
    puck0 = td["privileged", "object_pos"][0].numpy().copy()
    for _ in range(150):
        td = _step(env, td, expert(td))
        if td["privileged", "object_pos"][0, 2] > puck0[2] + 0.03:
            break
    else:
        pytest.fail("the expert did not lift the puck")
    data = env.sim.data
    puck, hand = data.xpos[env._body_ids[0]].copy(), data.xpos[env._hand].copy()
    env.shift_end_effector([0.08, 0.0, 0.0])
    moved, hand_moved = data.xpos[env._body_ids[0]] - puck, data.xpos[env._hand] - hand
    assert hand_moved[0] > 0.06, hand_moved
    np.testing.assert_allclose(moved, hand_moved, atol=0.01)


def test_a_goal_marker_moves_with_the_displaced_goal(make_env):
    """Soccer's net moves, and with it the success target; MetaWorld keeps the ``goal`` site on the target,
    so a visible marker (the suite draws it into soccer's cloud) must move too, not mark the old place."""
    env = make_env(task="soccer", num_points=512, crop_min=(-0.6, 0.3, 0.005), visible_sites=("goal",))
    td = env.reset(seed=1000)
    model, data = env.sim.model, env.sim.data
    site = model.site("goal").id
    old = data.site_xpos[site].copy()
    np.testing.assert_allclose(old, env.sim._target_pos, atol=1e-9)
    env.displace_objects([-0.2, 0.1, 0.0])
    np.testing.assert_allclose(data.site_xpos[site], env.sim._target_pos, atol=1e-9)
    np.testing.assert_allclose(data.site_xpos[site] - old, [-0.2, 0.1, 0.0], atol=1e-9)
    td = env.reset(seed=1000)  # undone at reset
    np.testing.assert_allclose(data.site_xpos[site], old, atol=1e-9)
    # a task whose target stays (pick-place: the puck moves, the goal does not) keeps its marker
    env = make_env(task="pick-place", **SMALL, visible_sites=("goal",))
    env.reset(seed=1000)
    before = env.sim.data.site_xpos[env.sim.model.site("goal").id].copy()
    env.displace_objects([-0.2, -0.1, 0.0])
    np.testing.assert_allclose(env.sim.data.site_xpos[env.sim.model.site("goal").id], before, atol=1e-9)


def test_model_edits_are_undone_on_reset(make_env):
    fresh = make_env(task="coffee-pull", **SMALL)
    env = make_env(task="coffee-pull", chunk_len=1, displacement=True, oracle_tracking=True, **SMALL)
    ref = fresh.reset(seed=4)
    td = env.reset(seed=4)
    for _ in range(5):
        td = _step(env, td, np.zeros(4))
    assert np.abs(td["privileged", "object_pos"] - ref["privileged", "object_pos"]).max() > 0.1
    td = env.reset(seed=4)
    for key in [("privileged", "object_pos"), ("privileged", "goal"), ("privileged", "state"), "point_cloud"]:
        torch.testing.assert_close(td[key], ref[key], atol=1e-6, rtol=0, msg=f"{key} after reset")
    assert td["privileged", "displacement"].abs().sum() == 0 and td["privileged", "ee_offset"].abs().sum() == 0


# ---------------------------------------------------------------- determinism


def test_same_seed_same_episode(make_env):
    env_a, env_b = make_env(task="pick-place", **SMALL), make_env(task="pick-place", **SMALL)
    first, again = env_a.reset(seed=7), env_a.reset(seed=7)
    assert first["privileged", "task_index"].item() == 7
    assert (first == again).all()
    other = env_a.reset(seed=8)
    assert not torch.equal(other["privileged", "state"], first["privileged", "state"])

    actions = np.random.default_rng(0).uniform(-1, 1, (15, 4))
    tds = [env_a.reset(seed=7), env_b.reset(seed=7)]
    for action in actions:
        tds = [_step(env, td, action) for env, td in zip((env_a, env_b), tds)]
        assert (tds[0] == tds[1]).all()
    assert not torch.equal(tds[0]["point_cloud"], first["point_cloud"]), "the arm moved"

    env_a.set_seed(49)
    assert env_a.reset()["privileged", "task_index"].item() == 49
    assert env_a.reset()["privileged", "task_index"].item() == 0, "unseeded resets continue with seed + 1"


def test_calibration_draws_initial_states_the_evaluation_never_does(make_env):
    """Seeds 50 apart replay one layout; a detector's calibration rollouts (seeds eval.seed + 100000) go to
    the next MT1 draw instead, so none replays an evaluated layout."""
    from ddp import build
    from ddp.eval_runner import calibration_env

    evaluated = MetaWorldEnvConfig(task="pick-place", seed_tasks=1, **SMALL)
    env = make_env(**{**evaluated.__dict__, "visible_sites": ()})
    first = env.reset(seed=1000)["privileged", "state"]
    assert torch.equal(env.reset(seed=101000)["privileged", "state"], first)  # 101000 % 50 == 1000 % 50
    held_out = evaluated.held_out_initial_states()
    assert held_out == {"seed_tasks": 2}
    other = make_env(**{**evaluated.__dict__, "visible_sites": (), **held_out})
    calibrated = torch.stack([other.reset(seed=101000 + i)["privileged", "state"] for i in range(50)])
    evaluated_states = torch.stack([env.reset(seed=1000 + i)["privileged", "state"] for i in range(50)])
    assert torch.cdist(calibrated[:, 4:7], evaluated_states[:, 4:7]).min() > 1e-4  # no object start shared

    exp = build("recipes/metaworld/quickstart_ddp.yaml")
    assert calibration_env(exp)["seed_tasks"] == 2  # eval.env says seed_tasks 1
    exp = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["eval.calibration_env={}"])
    assert calibration_env(exp)["seed_tasks"] == 1  # asked for the evaluation's own env
    exp = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["eval.calibration_env={seed_task: 3}"])
    with pytest.raises(RecipeError, match="eval.calibration_env.*no option 'seed_task'.*seed_tasks"):
        calibration_env(exp)
    exp = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["eval.calibration_env={settle_steps: -1}"])
    with pytest.raises(RecipeError, match="eval.calibration_env.*settle_steps must be >= 0"):  # a value the config refuses
        calibration_env(exp)


def test_calibration_seeds_past_one_draw_go_to_another_draw(monkeypatch):
    """MetaWorld repeats its 50 layouts every 50 seeds: calibration episodes beyond them (alpha small,
    threshold_on successful asking for more) take the next draw, so no two calibration episodes start from
    one layout (they counted as independent in the conformal threshold)."""
    from ddp import build, eval_runner

    calls = []

    def fake_rollouts(exp, ctrl, *, episodes, seed, overrides, **kw):
        calls.append((seed, episodes, overrides["seed_tasks"]))
        return [{"seed": seed + i} for i in range(episodes)]

    monkeypatch.setattr(eval_runner, "rollout_episodes", fake_rollouts)
    exp = build("recipes/metaworld/quickstart_ddp.yaml")  # evaluated on draw 1: held out from draw 2 on
    runs = eval_runner.calibration_episodes(exp, episodes=40, seed=100000, progress=False)
    assert calls == [(100000, 40, 2)]  # within one draw: as before
    calls.clear()
    runs = eval_runner.more_calibration_episodes(exp, runs, 75, cap=160, progress=False)
    assert calls == [(100040, 10, 2), (100050, 50, 3), (100100, 15, 4)]
    assert [r["seed"] for r in runs] == list(range(100000, 100115))
    layouts = {(tasks, s % 50) for s0, n, tasks in [(100000, 40, 2), *calls] for s in range(s0, s0 + n)}
    assert len(layouts) == 115  # every calibration episode its own initial state
    calls.clear()
    eval_runner.calibration_episodes(exp, episodes=30, seed=100030, progress=False)  # starts mid-draw
    assert calls == [(100030, 20, 2), (100050, 10, 3)]
    calls.clear()
    narrow = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["env.task_indices=[0, 10]"])
    eval_runner.calibration_episodes(narrow, episodes=25, seed=100000, progress=False)
    assert calls == [(100000, 10, 2), (100010, 10, 3), (100020, 5, 4)]  # 10 layouts per draw
    calls.clear()
    narrow = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["eval.env={seed_tasks: 1, task_indices: [0, 20]}"])
    eval_runner.calibration_episodes(narrow, episodes=25, seed=100000, progress=False)
    assert calls == [(100000, 20, 2), (100020, 5, 3)]  # the evaluated env's range counts
    calls.clear()
    own = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["eval.calibration_env={seed_tasks: 7}"])
    eval_runner.calibration_episodes(own, episodes=60, seed=100000, progress=False)
    assert calls == [(100000, 60, 7)]  # a calibration env the recipe names is used as it is


def test_evaluation_seeds_past_one_draw_go_to_another_draw_not_the_calibrations():
    """recipes/metaworld/base.yaml evaluates 100 episodes (the paper's count): seeds 50 apart replayed one
    layout (100 episodes, 50 initial states). The second 50 take a draw 1000 past the evaluated one, which
    the calibration's draws (evaluated + 1, + 2, ...) do not reach; 50 or fewer episodes run as before."""
    from ddp import build
    from ddp.eval_runner import calibration_env, evaluation_blocks

    exp = build("recipes/metaworld/quickstart_ddp.yaml")  # evaluates on draw 1
    over = {"seed_tasks": 1}
    assert evaluation_blocks(exp, over, 1000, 20) == [(over, 1000, 20)]
    assert evaluation_blocks(exp, over, 1000, 100) == [(over, 1000, 50), ({"seed_tasks": 1001}, 1050, 50)]
    assert evaluation_blocks(exp, over, 1030, 30) == [(over, 1030, 30)]  # 30 consecutive seeds: 30 layouts
    assert evaluation_blocks(exp, over, 1030, 60) == [(over, 1030, 50), ({"seed_tasks": 1001}, 1080, 10)]
    assert calibration_env(exp)["seed_tasks"] == 2 and calibration_env(exp, 3)["seed_tasks"] == 5
    narrow = {"seed_tasks": 1, "task_indices": (0, 10)}
    assert [b[1:] for b in evaluation_blocks(exp, narrow, 1000, 25)] == [(1000, 10), (1010, 10), (1020, 5)]
    assert [b[0]["seed_tasks"] for b in evaluation_blocks(exp, narrow, 1000, 25)] == [1, 1001, 2001]


def test_an_evaluation_of_more_episodes_than_layouts_rolls_out_each_block_on_its_draw(monkeypatch, tmp_path):
    from ddp import build, evaluate as evaluate_mod

    calls = []

    def fake_rollouts(exp, ctrl, *, episodes, seed, overrides, **kw):
        calls.append((seed, episodes, overrides["seed_tasks"]))
        return [{"seed": seed + i, "success": True, "chunks": 1, "first_success_chunk": 0} for i in range(episodes)]

    monkeypatch.setattr(evaluate_mod, "rollout_episodes", fake_rollouts)
    exp = build("recipes/metaworld/quickstart_ddp.yaml")
    report = exp.evaluate(["id"], episodes=100, output_dir=tmp_path, progress=False)
    assert calls == [(1000, 50, 1), (1050, 50, 1001)] and report["protocols"]["id"]["episodes"] == 100


# ------------------------------------------------------ occlusion, rendering


@pytest.mark.parametrize("mode", ["zeros", "drop", "noise"])
def test_occlusion_blinds_exactly_the_configured_chunks(make_env, mode):
    env = make_env(task="push", chunk_len=2, occlusion_chunk=2, occlusion_chunks=2, occlusion_mode=mode, **SMALL)
    td = env.reset(seed=0)
    low, high = np.array(env.config.crop_min), np.array(env.config.crop_max)
    blind = []
    for t in range(1, 11):
        td = _step(env, td, [0.0, 0.5, -0.5, 0.0])
        pc = td["point_cloud"].numpy()
        degenerate = {
            "zeros": np.all(pc == 0),
            "drop": len(np.unique(pc, axis=0)) == 1 and np.all((pc >= low) & (pc <= high)),
            "noise": np.all((pc >= low) & (pc <= high)) and (np.abs(pc[:, 2]) < 0.01).mean() < 0.1,
        }[mode]
        if degenerate:
            blind.append(t)
        assert td["privileged", "occluded"].item() == degenerate
    assert blind == [5, 6, 7, 8], "chunks 2 and 3 (steps 4..8) are blind from the first step after the start"


def test_obs_every_renders_only_consumed_steps(make_env):
    env = make_env(task="push", obs_every=4, obs_history=2, **SMALL)
    td = env.reset(seed=0)
    prev = td["point_cloud"].clone()
    rendered = []
    for t in range(1, 13):
        td = _step(env, td, [0.0, 1.0, -1.0, 0.0])
        if not torch.equal(td["point_cloud"], prev):
            rendered.append(t)
        prev = td["point_cloud"].clone()
    assert rendered == [3, 4, 7, 8, 11, 12]


def test_nonfinite_actions_and_shifts_are_refused(make_env):
    from ddp.safety import NonFiniteError

    env = make_env(task="button-press", image_size=32, num_points=64)
    td = env.reset()
    with pytest.raises(NonFiniteError, match="metaworld env: refused a non-finite action"):
        _step(env, td, [0.0, 0.0, float("nan"), 0.0])
    with pytest.raises(NonFiniteError, match="metaworld env: refused a non-finite end-effector shift"):
        env.shift_end_effector([float("inf"), 0.0, 0.0])
    _step(env, td, [0.0, 0.0, 0.0, 0.0])  # still usable


def test_detect_env_options_are_checked_on_top_of_each_protocol():
    """``ddp detect --env displacement_chunk=4`` completes ood_base's displacement (MetaWorld refuses a
    displacement chunk without a displacement, so --env alone would not pass); under a protocol that does not
    displace, the same option is refused in one line naming --env. A bad eval.env value names eval.env."""
    from ddp import build
    from ddp.detection import _check_env
    from ddp.eval_runner import env_overrides
    from ddp.protocols.base import get_protocol

    exp = build("recipes/metaworld/quickstart_ddp.yaml")
    _check_env(exp, {"displacement_chunk": 4}, ("ood_base",))
    over = env_overrides(exp, get_protocol("ood_base"), 200, extra={"displacement_chunk": 4})
    assert over["displacement"] is True and over["displacement_chunk"] == 4
    with pytest.raises(RecipeError, match="--env: .*displacement is False"):
        _check_env(exp, {"displacement_chunk": 4}, ("occlusion",))
    with pytest.raises(RecipeError, match="--env: env 'metaworld' has no option 'displacment_chunk'"):
        _check_env(exp, {"displacment_chunk": 4}, ("ood_base",))
    exp = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["eval.env={settle_steps: -1}"])
    with pytest.raises(RecipeError, match="eval.env.*settle_steps must be >= 0"):
        env_overrides(exp, get_protocol("id"), None)
    # a typo in eval.env is the recipe's (with the closest name), not "needed by this protocol"
    exp = build("recipes/metaworld/quickstart_ddp.yaml", overrides=["eval.env={max_episode_step: 50}"])
    with pytest.raises(RecipeError, match=r"eval.env: env 'metaworld' has no option 'max_episode_step'.*"
                                          r"max_episode_steps"):
        env_overrides(exp, get_protocol("ood_base"), None)



@pytest.mark.parametrize("options, message", [
    ("{visible_sites: obj}", "eval.env.visible_sites: expected tuple"),  # tuple("obj") read ('o', 'b', 'j')
    ("{camera: 3}", "eval.env.camera: expected str, got 3"),
    ("{max_episode_steps: 100.5}", "eval.env.max_episode_steps: expected int"),
    ("{crop_min: [.nan, 0, 0]}", "eval.env.crop_min[0]: must be a finite number"),
    ("{terminate_on_success: 'no'}", "eval.env.terminate_on_success: expected bool"),
])
def test_eval_env_values_are_type_checked_like_the_recipe(options, message):
    """eval.env is a free mapping (its keys depend on the env): its values reached the env config unchecked."""
    from ddp import build
    from ddp.eval_runner import env_overrides
    from ddp.protocols.base import get_protocol

    exp = build("recipes/metaworld/quickstart_ddp.yaml", overrides=[f"eval.env={options}"])
    with pytest.raises(RecipeError, match=re.escape(message)):
        env_overrides(exp, get_protocol("id"), None)



def test_env_option_values_from_python_may_be_numpy():
    """A caller's numpy values (np.int64 seeds, np.float32 settings, arrays for tuples) pass the type check."""
    from ddp import build
    from ddp.eval_runner import env_overrides
    from ddp.protocols.base import get_protocol

    exp = build("recipes/metaworld/quickstart_ddp.yaml")
    extra = {"seed_tasks": np.int64(3), "settle_steps": np.int64(5), "crop_min": np.array([-0.6, 0.3, 0.0]),
             "terminate_on_success": np.bool_(False)}
    over = env_overrides(exp, get_protocol("id"), None, extra=extra)
    assert over["seed_tasks"] == 3 and over["settle_steps"] == 5
    cfg = dataclasses.replace(exp.parts["env"].config, **over)  # as the evaluation's env factory makes it
    assert tuple(cfg.crop_min) == (-0.6, 0.3, 0.0) and cfg.seed_tasks == 3 and not cfg.terminate_on_success


def test_video_frames_turn_only_the_cameras_mounted_upside_down(make_env, monkeypatch):
    """MetaWorld's corner cameras are mounted upside down (turned for videos); the gripper cameras are upright
    (every frame was flipped, so their videos came out inverted)."""
    env = make_env(task="button-press", **SMALL)
    env.reset(seed=0)
    flips = {}
    monkeypatch.setattr(env._renderer, "rgb", lambda data, cam, w, h, upside_down: flips.setdefault(cam, upside_down))
    for camera in ("corner2", "behindGripper"):
        env.render_rgb(16, 16, camera=camera)
    by_name = {name: flips[env._renderer.camera_id(name, what="video camera")] for name in ("corner2", "behindGripper")}
    assert by_name == {"corner2": True, "behindGripper": False}


def test_an_upside_down_camera_gives_the_upright_view_not_its_mirror():
    """Two cameras at one place, one rolled half a turn: its frame turned upright equals the other's. A
    vertical flip alone (the earlier correction) gave the mirror image: the red box on the wrong side."""
    mujoco = pytest.importorskip("mujoco")
    from ddp.envs.mujoco_render import SceneRenderer, use_egl

    use_egl()
    model = mujoco.MjModel.from_xml_string("""<mujoco><worldbody>
        <light pos="0 0 3"/><geom type="plane" size="1 1 .1" rgba=".5 .5 .5 1"/>
        <geom type="box" pos=".3 .1 .05" size=".08 .08 .05" rgba="1 0 0 1"/>
        <geom type="box" pos="-.2 -.25 .05" size=".05 .05 .05" rgba="0 0 1 1"/>
        <camera name="upright" pos="0 0 1.5" xyaxes="1 0 0 0 1 0"/>
        <camera name="rolled" pos="0 0 1.5" xyaxes="-1 0 0 0 -1 0"/></worldbody></mujoco>""")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    renderer = SceneRenderer(model)
    try:
        upright = renderer.rgb(data, 0, 64, 48).astype(int)
        turned = renderer.rgb(data, 1, 64, 48, upside_down=True).astype(int)
    finally:
        renderer.close()
    red = (upright[..., 0] > 150) & (upright[..., 1] < 80)
    assert red[:, 32:].sum() > 20 and red[:, :32].sum() == 0  # the red box right of centre, as seen upright
    assert np.abs(upright - turned).mean() < 2.0
