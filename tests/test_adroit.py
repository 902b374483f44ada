"""The Adroit suite: env (specs, seeding, rendering schedule, occlusion), packaged experts, demos, recipes.

Simulator tests skip when gymnasium-robotics is not installed; config,
weights and recipe tests run without it. Small images and few points keep
the whole file well under a minute on two CPU cores.
"""

import subprocess
import sys
import zipfile
from importlib import resources

import numpy as np
import pytest
import torch

from conftest import RECIPES
from ddp.config import from_dict, to_dict
from ddp.envs.adroit import AdroitEnvConfig
from ddp.envs.adroit_tasks import ADROIT_TASKS, HAND_JOINTS
from ddp.errors import DDPError, RecipeError
from ddp.schema import validate

SMALL = dict(image_size=32, num_points=64)
TASKS = tuple(ADROIT_TASKS)


@pytest.fixture
def make_env():
    pytest.importorskip("gymnasium_robotics")
    from ddp.envs.adroit import AdroitEnv

    envs = []

    def make(**options):
        env = AdroitEnv(AdroitEnvConfig(**options))
        envs.append(env)
        return env

    yield make
    for env in envs:
        env.close()


def _step(env, td, action):
    td["action"] = torch.as_tensor(action, dtype=torch.float32)
    return env.step(td)["next"]


def _source(recipe: dict):
    rec, parts, _ = validate(recipe, "<test>")
    return parts["data"].build(task=rec.task, seed=rec.seed, env=parts.get("env"))


# ------------------------------------------------------------------ config (no simulator)
def test_config_validation_and_task_defaults():
    with pytest.raises(ValueError, match=r"task must be one of 'door', 'hammer', 'pen'; got 'dor'; did you mean 'door'\?"):
        AdroitEnvConfig(task="dor")
    with pytest.raises(RecipeError, match=r"env.task: must be one of 'door', 'hammer', 'pen'; got 'hamer'.*'hammer'"):
        from_dict(AdroitEnvConfig, {"task": "hamer"}, key="env")
    with pytest.raises(ValueError, match=r"obs_history \(3\) must be <= obs_every \(2\)"):
        AdroitEnvConfig(obs_every=2, obs_history=3)
    with pytest.raises(ValueError, match="crop_min must be below crop_max"):
        AdroitEnvConfig(crop_min=(0, 0, 1), crop_max=(1, 1, 0))
    with pytest.raises(ValueError, match="camera_quat must be a unit quaternion"):
        AdroitEnvConfig(camera_quat=(1.0, 1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="occlusion_chunk needs render_point_cloud=True"):
        AdroitEnvConfig(occlusion_chunk=1, render_point_cloud=False)
    # the original horizons (pen 100), DP3's 24 hand joints, round trip through a recipe dict
    assert [AdroitEnvConfig(task=t).max_episode_steps for t in TASKS] == [200, 200, 100]
    assert AdroitEnvConfig(task="door", max_episode_steps=50).max_episode_steps == 50
    assert AdroitEnvConfig(task="door").agent_pos_dim == 24 == len(HAND_JOINTS)
    assert AdroitEnvConfig(task="door", agent_pos="arm_hand").agent_pos_dim == 28
    cfg = AdroitEnvConfig(task="pen", occlusion_chunk=2, camera_pos=(0.0, -1.0, 1.0))
    assert from_dict(AdroitEnvConfig, to_dict(cfg)) == cfg


def test_env_imports_without_the_simulator():
    code = (
        "import sys; sys.modules['gymnasium_robotics'] = None; sys.modules['mujoco'] = None\n"
        "import ddp.envs, ddp.data.sources\n"
        "from ddp.envs.adroit import AdroitEnv\n"
        "try:\n    AdroitEnv()\nexcept ImportError as err:\n    print(err)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert 'the Adroit env needs gymnasium-robotics and mujoco' in out.stdout and 'pip install "ddp[sim]"' in out.stdout


def test_expert_weights_ship_in_the_package_without_pickle(monkeypatch):
    from ddp.data.sources import adroit_expert
    from ddp.data.sources.adroit_expert import load_expert_weights

    calls = []
    real_load = np.load

    def spy(*args, **kwargs):
        calls.append(kwargs.get("allow_pickle"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(adroit_expert.np, "load", spy)
    for task, spec in ADROIT_TASKS.items():
        ref = resources.files("ddp") / "assets" / "adroit" / spec.expert
        assert ref.is_file()
        with ref.open("rb") as f:  # a plain npz: no pickled member
            assert all(name.endswith(".npy") for name in zipfile.ZipFile(f).namelist())
        w = load_expert_weights(task)
        assert w["W0"].shape[1] == spec.state_dim and w["W2"].shape[0] == spec.action_dim
        assert all(v.dtype == np.float64 and np.isfinite(v).all() for v in w.values())
    assert calls == [False, False, False]
    assert (resources.files("ddp") / "assets" / "adroit" / "NOTICE").read_text().count("Apache") >= 1
    with pytest.raises(ValueError, match="no Adroit expert for task 'relocate'"):
        load_expert_weights("relocate")


@pytest.mark.parametrize("path", sorted(RECIPES.glob("adroit/*.yaml")), ids=lambda p: p.name)
def test_recipes_match_their_env(path):
    """Task dims equal the env's; the paper's Adroit protocols; no tracker (no displacement on Adroit)."""
    from ddp.recipe import load_recipe

    rec, parts, _ = validate(*load_recipe(path))
    env = parts["env"].config
    assert parts["env"].plugin.name == "adroit" and parts["data"].plugin.name == "adroit_expert"
    assert rec.task.action_dim == env.task_spec.action_dim and rec.task.agent_pos_dim == env.agent_pos_dim
    assert rec.task.num_points == env.num_points
    assert rec.eval.protocols == ["id", "imagination_10", "imagination_50", "imagination_100"]
    assert rec.controller.tracker is None and parts["controller.detector"].plugin.name == "discrepancy"
    assert parts["data"].config.episodes == 10
    if path.name.startswith("cpu_"):
        assert rec.policy.denoiser["down_dims"] == [64, 128, 256] and rec.task.num_points == 128
        assert rec.world_model.target_gradient is False and rec.train.max_steps <= 3000


def test_cpu_recipe_builds():
    import ddp

    exp = ddp.build(RECIPES / "adroit" / "cpu_pen.yaml")
    td = exp.model(_fake_obs(exp, batch=1))
    assert td["action"].shape == (1, 8, 24) and td["latent"].shape == (1, 2, 128)


def _fake_obs(exp, batch):
    from tensordict import TensorDict

    t = exp.recipe.task
    return TensorDict({"point_cloud": torch.rand(batch, 2, t.num_points, 3), "agent_pos": torch.rand(batch, 2, 24)},
                      batch_size=[batch])  # fmt: skip


# ------------------------------------------------------------------ env (simulator)
@pytest.mark.parametrize("task", TASKS)
def test_check_env_specs(make_env, task):
    from torchrl.envs.utils import check_env_specs

    env = make_env(task=task, **SMALL)
    check_env_specs(env, seed=0)
    td = env.reset(seed=0)
    spec = ADROIT_TASKS[task]
    assert td["point_cloud"].shape == (64, 3) and td["agent_pos"].shape == (24,)
    assert td["privileged", "state"].shape == (spec.state_dim,) and env.action_spec.shape == (spec.action_dim,)
    # the cloud lies above the table, inside the crop box, around the hand
    pc = td["point_cloud"]
    assert pc[:, 2].min() > 0.0 and pc[:, 2].max() < 1.0 and pc.std(0).min() > 0.01


def test_state_only_env_and_arm_hand_agent_pos(make_env):
    from torchrl.envs.utils import check_env_specs

    env = make_env(task="door", render_point_cloud=False, agent_pos="arm_hand")
    check_env_specs(env, seed=0)
    td = env.reset(seed=0)
    assert "point_cloud" not in td.keys() and td["agent_pos"].shape == (28,)
    # arm_hand agent_pos = the actuated joints; the hand part equals the default agent_pos (and state[3:27])
    assert torch.allclose(td["agent_pos"][4:], td["privileged", "state"][3:27])


def test_render_rgb_for_videos(make_env):
    env = make_env(task="hammer", render_point_cloud=False)
    env.reset(seed=0)
    frame = env.render_rgb(48, 32)
    assert frame.shape == (32, 48, 3) and frame.dtype == np.uint8 and frame.std() > 10
    assert env.render_rgb(48, 32, camera="fixed").shape == (32, 48, 3)
    with pytest.raises(ValueError, match="video camera must be one of .*'vil_camera'"):
        env.render_rgb(48, 32, camera="vil_cam")


def test_seeding_is_reproducible(make_env):
    env = make_env(task="hammer", **SMALL)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(5, 26))

    def run(seed):
        out = [env.reset(seed=seed)]
        for a in actions:
            out.append(_step(env, out[-1], a))
        return out

    a, b, c = run(3), run(3), run(4)
    for x, y in zip(a, b):
        assert torch.equal(x["point_cloud"], y["point_cloud"])
        assert torch.equal(x["privileged", "state"], y["privileged", "state"])
    assert not torch.equal(a[0]["privileged", "state"], c[0]["privileged", "state"])  # another board height
    assert int(a[0]["privileged", "seed"]) == 3
    # resets without a seed continue from the last seed + 1
    assert torch.equal(env.reset()["privileged", "state"], run(5)[0]["privileged", "state"])
    env.set_seed(3)
    assert torch.equal(env.reset()["point_cloud"], a[0]["point_cloud"])


def test_renders_only_the_consumed_frames_and_truncates(make_env):
    env = make_env(task="pen", obs_every=8, obs_history=2, max_episode_steps=20, **SMALL)
    rendered = []
    original = env._render_cloud
    env._render_cloud = lambda: (rendered.append(env.steps_done), original())[1]
    td = env.reset(seed=0)
    steps = 0
    while not bool(td.get("done", torch.zeros(1, dtype=torch.bool))):
        td = _step(env, td, np.zeros(24))
        steps += 1
    assert steps == 20 and bool(td["truncated"]) and not bool(td["terminated"])
    assert rendered == [0, 7, 8, 15, 16]


def test_occlusion_blinds_the_scheduled_chunks(make_env):
    env = make_env(task="door", occlusion_chunk=1, occlusion_chunks=1, chunk_len=4, **SMALL)
    td = env.reset(seed=0)
    flags = []
    for _ in range(10):
        td = _step(env, td, np.zeros(28))
        flags.append(bool(td["privileged", "occluded"]))
        if flags[-1]:
            assert torch.count_nonzero(td["point_cloud"]) == 0
    assert flags == [False] * 4 + [True] * 4 + [False] * 2
    with pytest.raises(DDPError, match="no end-effector shift"):
        env.shift_end_effector(np.zeros(3))


@pytest.mark.parametrize("task,seeds", [("door", (0, 1)), ("hammer", (0, 1))])
def test_packaged_expert_succeeds_and_idle_hand_does_not(make_env, task, seeds):
    from ddp.data.sources.adroit_expert import AdroitExpert
    from ddp.data.sources.metaworld_expert import expert_succeeds

    env = make_env(task=task, render_point_cloud=False, terminate_on_success=True)
    expert = AdroitExpert(task)
    assert all(expert_succeeds(env, expert, s) for s in seeds)
    assert not expert_succeeds(env, lambda td: np.zeros(ADROIT_TASKS[task].action_dim, np.float32), seeds[0])


def test_chunked_env_with_render_schedule(make_env):
    """What evaluation runs: ChunkedEnv over the env, rendering only the M frames read per chunk.

    (torchrl's check_env_specs would send random ``ee_shift`` values, which Adroit refuses: no tracking.)
    """
    from ddp.envs.adroit import AdroitEnv
    from ddp.envs.chunked import ChunkedEnv, chunk_render_config

    cfg = chunk_render_config(AdroitEnvConfig(task="pen", max_episode_steps=24, **SMALL), 8, 2)
    assert (cfg.obs_every, cfg.obs_history) == (8, 2)
    env = ChunkedEnv(AdroitEnv(cfg), action_steps=8, obs_steps=2)
    try:
        def policy(td):
            td["action"] = env.full_action_spec["action"].rand()
            td["ee_shift"] = torch.zeros(3)
            return td

        traj = env.rollout(10, policy, break_when_any_done=True)
        assert traj.batch_size == (3,) and bool(traj["next", "truncated"][-1])
        assert traj["next", "point_cloud"].shape == (3, 2, 64, 3) and traj["next", "agent_pos"].shape == (3, 2, 24)
        assert env.observation_spec.is_in(traj[-1]["next"].select(*env.observation_spec.keys(True, True)))
    finally:
        env.close()


# ------------------------------------------------------------------ demos
def _adroit_recipe(cache, **data):
    return {"name": "adroit_demo", "task": {"action_dim": 28, "agent_pos_dim": 24, "num_points": 64},
            "env": {"name": "adroit", "task": "door", **SMALL},
            "data": {"name": "adroit_expert", "episodes": 2, "stop_after_success": 0, "path": str(cache / "{task}"),
                     **data}}  # fmt: skip


def test_demos_are_successful_cached_and_reused(tmp_path, monkeypatch):
    pytest.importorskip("gymnasium_robotics")
    from ddp.data.sources.adroit_expert import AdroitExpertDemos

    source = _source(_adroit_recipe(tmp_path))
    assert source.cfg.max_steps == 200 and source.env_config.max_episode_steps == 200
    demos = source.load()
    steps = demos.steps
    assert demos.num_episodes == 2
    assert steps["point_cloud"].shape[1:] == (64, 3) and steps["agent_pos"].shape[1:] == (24,)
    assert steps["action"].shape[1:] == (28,) and steps["full_state"].shape[1:] == (39,)
    assert steps["action"].abs().max() <= 1.0
    assert source.stats["seeds"] == [0, 1] and source.stats["successes"] == 2
    assert demos.num_steps < 2 * 100  # stop_after_success=0: each episode ends at its first success (~50 steps)
    # the cache is reused: no generation on the second load, same arrays
    monkeypatch.setattr(AdroitExpertDemos, "generate", lambda self, progress=True: 1 / 0)
    again = _source(_adroit_recipe(tmp_path)).load()
    assert torch.equal(again.steps["point_cloud"], steps["point_cloud"])
    assert torch.equal(again.episode_ends, demos.episode_ends)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".door.lock", "door"]  # the cache and its generation lock
    # another env config does not match the cache: it would regenerate
    assert _source(_adroit_recipe(tmp_path, max_steps=150)).cached_meta() is None


def test_demo_source_checks_the_recipe():
    with pytest.raises(RecipeError, match="data 'adroit_expert' needs a adroit env section"):
        _source({"name": "x", "data": {"name": "adroit_expert"}})
    bad = {"name": "x", "task": {"action_dim": 26, "agent_pos_dim": 24}, "env": {"name": "adroit", "task": "door"},
           "data": {"name": "adroit_expert"}}  # fmt: skip
    with pytest.raises(RecipeError, match="task: adroit door demos .* have action_dim 28, agent_pos_dim 24"):
        _source(bad)
    pen_env = {"name": "adroit", "task": "pen", "occlusion_chunk": 2, "terminate_on_success": True, "obs_every": 8,
               "obs_history": 2}  # fmt: skip
    rec, parts, _ = validate({**bad, "task": {"action_dim": 24, "agent_pos_dim": 24}, "env": pen_env}, "<test>")
    src = parts["data"].build(task=rec.task, seed=rec.seed, env=parts["env"])
    assert src.cfg.max_steps == 100 and src.env_config.max_episode_steps == 100  # pen's horizon
    # evaluation-only options are neutralised for the demos, every frame is rendered
    ec = src.env_config
    assert (ec.occlusion_chunk, ec.terminate_on_success, ec.obs_every, ec.obs_history) == (None, False, 1, 1)
    # the recipe's env part keeps its evaluation options (the demos' config is a copy)
    kept = parts["env"].config
    assert ec is not kept and (kept.occlusion_chunk, kept.terminate_on_success, kept.obs_every) == (2, True, 8)


# ------------------------------------------------------------------ evaluation protocols
def test_paper_protocols_run_and_displacement_is_refused(tmp_path):
    """id and open-loop imagination run through ddp.evaluate on an (untrained) CPU recipe; ood_* fail clearly."""
    pytest.importorskip("gymnasium_robotics")
    import ddp

    exp = ddp.build(RECIPES / "adroit" / "cpu_pen.yaml",
                    ["env.image_size=32", "eval.max_steps=16", "policy.scheduler.num_inference_steps=2",
                     "world_model.scheduler.num_inference_steps=2"])  # fmt: skip
    report = exp.evaluate(["id", "imagination_100"], episodes=1, output_dir=tmp_path, progress=False)
    for name in ("id", "imagination_100"):
        assert report["protocols"][name]["episodes"] == 1
    # open loop: real latents at the first chunk only, imagined ones after it; the id protocol never imagines
    imagined = report["protocols"]["imagination_100"]["per_episode"][0]["imagined"]
    assert len(imagined) > 1 and not imagined[0] and all(imagined[1:])
    assert not any(report["protocols"]["id"]["per_episode"][0]["imagined"])
    with pytest.raises(RecipeError, match="env 'adroit' does not support displacement"):
        exp.evaluate(["ood_ddp"], episodes=1, output_dir=tmp_path, progress=False)


def test_nonfinite_actions_are_refused(make_env):
    from ddp.safety import NonFiniteError

    env = make_env(task="pen", image_size=32, num_points=64)
    td = env.reset()
    action = torch.zeros(env.action_spec.shape)
    action[5] = float("nan")
    with pytest.raises(NonFiniteError, match="adroit env: refused a non-finite action"):
        _step(env, td, action)


def test_occlusion_noise_is_not_the_stream_that_drew_the_layout():
    """gymnasium seeds np_random with PCG64(SeedSequence(seed)), which is np.random.default_rng(seed): the
    occlusion noise drawn from the env's default episode stream was a function of the door's placement."""
    import numpy as np
    from gymnasium.utils import seeding

    from ddp.envs.adroit import AdroitEnv

    layout, _ = seeding.np_random(5)
    ours = AdroitEnv._episode_rng(None, 5)
    assert not np.allclose(layout.uniform(size=4), ours.uniform(size=4))
    assert np.allclose(AdroitEnv._episode_rng(None, 5).uniform(size=4), AdroitEnv._episode_rng(None, 5).uniform(size=4))
