"""Scripted-expert demo generation (generic + MetaWorld cache) and the episodes_dir source.

The generic tests use a tiny 1-D TorchRL env; the MetaWorld tests skip
without metaworld and use small clouds (32 px, 64 points) to stay fast.
"""

import dataclasses

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

import ddp
from ddp.data.demos import DemoGenerationError, generate_demos
from ddp.data.episodes import Episodes
from ddp.errors import DDPError, RecipeError
from ddp.schema import TaskConfig, validate

# ----------------------------------------------------------------- a tiny env


class LineEnv(EnvBase):
    """Reach x = 1 from x0 = 0.1 * (seed % 5); seeds with seed % 5 == 4 start behind a wall (unreachable)."""

    def __init__(self):
        super().__init__(batch_size=torch.Size([]))
        self.observation_spec = Composite(
            point_cloud=Unbounded(shape=(2, 3)), agent_pos=Unbounded(shape=(1,)),
            success=Categorical(2, shape=(1,), dtype=torch.bool),
        )  # fmt: skip
        self.action_spec = Bounded(-1.0, 1.0, shape=(1,))
        self.reward_spec = Unbounded(shape=(1,))
        self.seed, self.x, self.t, self.closed = 0, 0.0, 0, False

    def _set_seed(self, seed):
        self.seed = int(seed)

    def _obs(self, success=False, done=False):
        pc = torch.tensor([[self.x, 0.0, 0.0], [1.0, 0.0, 0.0]])
        flag = lambda b: torch.tensor([b])  # noqa: E731
        return TensorDict(
            point_cloud=pc, agent_pos=torch.tensor([self.x]), success=flag(success),
            done=flag(done), terminated=flag(False), truncated=flag(done), reward=torch.zeros(1),
        )  # fmt: skip

    def _reset(self, td=None, **kwargs):
        self.x, self.t = 0.1 * (self.seed % 5), 0
        self.wall = self.seed % 5 == 4
        return self._obs()

    def _step(self, td):
        self.t += 1
        self.x = self.x + 0.1 * float(td["action"])
        if self.wall:
            self.x = min(self.x, 0.5)
        return self._obs(success=self.x >= 1.0 - 1e-6, done=self.t >= 30)

    def close(self, **kwargs):
        self.closed = True
        super().close(**kwargs)


def line_expert(td):
    return torch.tensor([2.0])  # clipped to 1 by the action spec: records must hold 1


def test_generate_demos_records_observation_before_action_and_cuts_after_success():
    envs = []

    def make():
        envs.append(LineEnv())
        return envs[-1]

    demos, stats = generate_demos(make, line_expert, episodes=3, seed=0, max_steps=25, progress=False,
                                  stop_after_success=2)  # fmt: skip
    assert envs[0].closed
    assert demos.num_episodes == 3 and stats["successes"] == 3 and stats["attempts"] == 3
    assert set(demos.steps.keys()) == {"point_cloud", "agent_pos", "action"}
    assert (demos.steps["action"] == 1.0).all()
    for i, x0 in enumerate([0.0, 0.1, 0.2]):
        ep = demos.episode(i)
        # the first recorded observation is the reset one; x grows 0.1 per action afterwards
        assert ep["agent_pos"][0, 0] == pytest.approx(x0)
        assert torch.allclose(ep["agent_pos"][1:, 0] - ep["agent_pos"][:-1, 0], torch.tensor(0.1), atol=1e-5)
        assert torch.equal(ep["point_cloud"][:, 0, 0], ep["agent_pos"][:, 0])
        first = round((1.0 - x0) / 0.1) - 1  # the action that reaches x = 1
        assert ep.batch_size[0] == first + 1 + 2
    assert stats["mean_first_success"] == pytest.approx(np.mean([9, 8, 7]))

    full, _ = generate_demos(LineEnv, line_expert, episodes=1, seed=0, max_steps=25, progress=False)
    assert full.num_steps == 25  # DP3 style: full length when stop_after_success is None


def test_generate_demos_skips_failures_and_is_reproducible():
    kwargs = dict(episodes=5, seed=2, max_steps=20, progress=False, stop_after_success=0)
    a, stats = generate_demos(LineEnv, line_expert, **kwargs)
    b, _ = generate_demos(LineEnv, line_expert, **kwargs)
    assert stats["failed_seeds"] == [4] and stats["attempts"] == 6
    assert stats["seeds"] == [2, 3, 5, 6, 7]
    assert stats["success_rate"] == pytest.approx(5 / 6)
    assert torch.equal(a.episode_ends, b.episode_ends)
    assert (a.steps == b.steps).all()
    kept_all, stats_all = generate_demos(LineEnv, line_expert, **{**kwargs, "episodes": 3}, keep_only_success=False)
    assert stats_all["seeds"] == [2, 3, 4] and kept_all.episode(2).batch_size[0] == 20


def test_generate_demos_gives_up_with_a_clear_error():
    always_fails = lambda td: torch.tensor([-1.0])  # noqa: E731
    with pytest.raises(DemoGenerationError, match=r"only 0 of 2 episodes after 6 attempts"):
        generate_demos(LineEnv, always_fails, episodes=2, seed=0, max_steps=5, progress=False, max_attempts=6)
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        generate_demos(LineEnv, line_expert, episodes=0, seed=0, max_steps=5)


class BlockLineEnv(LineEnv):
    """LineEnv whose 5 states (seed % 5) start 0.01 * block further along in block ``block``: another draw."""

    def __init__(self, block=0):
        super().__init__()
        self.block = block

    def _reset(self, td=None, **kwargs):
        out = super()._reset(td, **kwargs)
        self.x += 0.01 * self.block
        return self._obs()


def test_attempts_past_the_states_of_a_draw_move_to_another_draw():
    """5 states per draw, state 4 unreachable: 5 demos need 6 attempts; the 6th must not replay state 0."""
    kwargs = dict(episodes=5, seed=0, max_steps=20, progress=False, stop_after_success=0)
    old, old_stats = generate_demos(BlockLineEnv, line_expert, **kwargs)
    assert old_stats["seeds"] == [0, 1, 2, 3, 5]
    assert (old.episode(4) == old.episode(0)).all()  # what happened before: seed 5 replayed seed 0's demo
    built = []

    def block_env(block):
        built.append(block)
        return BlockLineEnv(block)

    demos, stats = generate_demos(BlockLineEnv, line_expert, **kwargs, states_per_draw=5, make_block_env=block_env)
    assert stats["seeds"] == [0, 1, 2, 3, 5] and stats["blocks"] == [0, 0, 0, 0, 1] and built == [1]
    assert stats["states_per_draw"] == 5
    starts = [float(demos.episode(i)["agent_pos"][0]) for i in range(5)]
    assert len(set(starts)) == 5 and starts[4] == pytest.approx(0.01)  # state 0 of draw 1
    with pytest.raises(ValueError, match="needs to be >= 1 and a make_block_env"):
        generate_demos(BlockLineEnv, line_expert, **kwargs, states_per_draw=5)


# ------------------------------------------------------------ episodes_dir


def _source(recipe: dict):
    """The recipe's data source, as ``Experiment.dataset()`` builds it (without building the model)."""
    rec, parts, _ = validate(recipe, "<test>")
    return parts["data"].build(task=rec.task, seed=rec.seed, env=parts.get("env"))


def _synthetic(episodes=3):
    recipe = {"name": "syn", "task": {"num_points": 32}, "data": {"name": "synthetic_reach", "episodes": episodes}}
    return _source(recipe).load()


def test_episodes_dir_round_trip(tmp_path):
    demos = _synthetic()
    demos.save(tmp_path / "mine")
    loaded = _source({"name": "mine", "task": {"num_points": 32},
                      "data": {"name": "episodes_dir", "path": str(tmp_path / "mine")}}).load()  # fmt: skip
    assert torch.equal(loaded.episode_ends, demos.episode_ends)
    assert (loaded.steps == demos.steps).all()

    # numpy's float64 default: training windows come out float32 (the model's layers refused float64 at the
    # first step), the data stay memory-mapped as stored
    from ddp.data.sequence import SequenceDataset

    wide = demos.steps.clone()
    for k in ("point_cloud", "agent_pos", "action"):
        wide[k] = wide[k].double()
    Episodes(wide, demos.episode_ends).save(tmp_path / "wide")
    back = _source({"name": "w", "task": {"num_points": 32},
                    "data": {"name": "episodes_dir", "path": str(tmp_path / "wide")}}).load()  # fmt: skip
    assert back.steps["action"].dtype == torch.float64
    windows = SequenceDataset(back, 4, keys=["point_cloud", "agent_pos", "action"])
    batch = windows.batch(torch.tensor([0, 2]))
    assert {batch[k].dtype for k in ("point_cloud", "agent_pos", "action")} == {torch.float32}
    assert windows[1]["action"].dtype == torch.float32
    assert torch.equal(batch["action"], SequenceDataset(demos, 4).batch(torch.tensor([0, 2]))["action"])

    missing = tmp_path / "nothing_here"
    with pytest.raises(DDPError, match=f"{missing}.*does not exist"):
        _source({"name": "x", "data": {"name": "episodes_dir", "path": str(missing)}}).load()
    recipe = {"name": "x", "task": {"action_dim": 7}, "data": {"name": "episodes_dir", "path": str(tmp_path / "mine")}}
    with pytest.raises(DDPError, match="task.action_dim is 7 but the data have 4"):
        _source(recipe).load()
    with pytest.raises(RecipeError, match="data.path: missing required option"):
        _source({"name": "x", "data": {"name": "episodes_dir"}})
    flat = demos.steps.clone()  # a 1-D action [T] read as action_dim T
    flat["action"] = flat["action"][:, 0]
    Episodes(flat, demos.episode_ends).save(tmp_path / "flat")
    recipe = {"name": "x", "task": {"num_points": 32, "action_dim": demos.num_steps},
              "data": {"name": "episodes_dir", "path": str(tmp_path / "flat")}}  # fmt: skip
    with pytest.raises(DDPError, match=r"action has shape \(\d+,\); expected 2 dimensions"):
        _source(recipe).load()


# -------------------------------------------------------------- MetaWorld

SMALL_ENV = {"name": "metaworld", "task": "button-press", "image_size": 32, "num_points": 64}
MW_DATA = {"name": "metaworld_expert", "episodes": 3, "max_steps": 150, "stop_after_success": 5}


def _mw_recipe(cache, env=None, **data):
    return {"name": "mw", "task": {"num_points": 64}, "env": dict(env or SMALL_ENV),
            "data": {**MW_DATA, "path": str(cache / "{task}"), **data}}  # fmt: skip


@pytest.fixture(scope="module")
def mw_cache(tmp_path_factory):
    """Three button-press demos generated once through the plugin's cache."""
    pytest.importorskip("metaworld")
    cache = tmp_path_factory.mktemp("demos")
    source = _source(_mw_recipe(cache))
    demos = source.load()
    return cache, source, demos


def test_metaworld_demos_are_successful_and_replayable(mw_cache):
    from ddp.envs.metaworld import MetaWorldEnv, MetaWorldEnvConfig

    cache, source, demos = mw_cache
    assert demos.num_episodes == 3
    assert demos.steps["point_cloud"].shape[1:] == (64, 3)
    assert demos.steps["agent_pos"].shape[1:] == (9,) and demos.steps["action"].shape[1:] == (4,)
    assert demos.steps["full_state"].shape[1:] == (39,)
    assert demos.steps["action"].abs().max() <= 1.0
    stats = source.stats
    assert stats["successes"] == stats["attempts"] == 3 and stats["seeds"] == [0, 1, 2]
    # replay the recorded actions in a state-only env: same states, and success 5 steps before the end
    env = MetaWorldEnv(MetaWorldEnvConfig(task="button-press", render_point_cloud=False))
    try:
        for i, seed in enumerate(stats["seeds"]):
            ep = demos.episode(i)
            td = env.reset(seed=seed)
            success_at = None
            for t in range(ep.batch_size[0]):
                assert torch.equal(td["agent_pos"], ep["agent_pos"][t])
                td["action"] = ep["action"][t].clone()
                td = env.step(td)["next"]
                if success_at is None and bool(td["success"]):
                    success_at = t
            assert success_at == ep.batch_size[0] - 1 - 5
    finally:
        env.close()
    # every frame was rendered (clouds differ from step to step as the arm moves)
    pc = demos.episode(0)["point_cloud"]
    assert all(not torch.equal(pc[t], pc[t + 1]) for t in range(0, 10))


def test_metaworld_demos_reproducible_and_cached(mw_cache, monkeypatch):
    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    cache, _, demos = mw_cache
    assert (cache / "button-press" / "generation.json").is_file()
    # same seed -> identical arrays (generated again, in memory; generation is sequential, so one
    # episode is the first of the three)
    again, _ = _source(_mw_recipe(cache, episodes=1)).generate(progress=False)
    assert again.num_episodes == 1
    assert (again.steps == demos.episode(0)).all()

    def fail(self, progress=True):
        raise AssertionError("regenerated although the cache matches")

    monkeypatch.setattr(MetaWorldExpertDemos, "generate", fail)
    # a matching cache is memory-mapped, not regenerated; training-only env options do not matter
    for recipe in (_mw_recipe(cache), _mw_recipe(cache, env={**SMALL_ENV, "obs_every": 8, "obs_history": 2}),
                   {**_mw_recipe(cache), "seed": 3}):  # fmt: skip
        loaded = _source(recipe).load()
        assert torch.equal(loaded.episode_ends, demos.episode_ends) and (loaded.steps == demos.steps).all()
    # fewer episodes: the first ones of the cache
    two = _source(_mw_recipe(cache, episodes=2)).load()
    assert torch.equal(two.episode_ends, demos.episode_ends[:2])
    assert torch.equal(two.steps["action"], demos.steps["action"][: int(demos.episode_ends[1])])


def test_metaworld_demos_regenerate_when_parameters_change(mw_cache, monkeypatch):
    """A copy of the module's cache, loaded with one setting changed, is regenerated; loaded unchanged, it
    is used as it is (each case loaded from a fresh folder had no cache to compare with, so it passed
    whatever the comparison did)."""
    import shutil

    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    cache, _, demos = mw_cache
    calls = []

    def fake_generate(self, progress=True):  # stands for a real run: record the call, return small demos
        calls.append(self)
        small = demos.subset(range(min(self.cfg.episodes, 3)))
        return small, {"attempts": small.num_episodes}

    monkeypatch.setattr(MetaWorldExpertDemos, "generate", fake_generate)
    changes = [
        dict(episodes=4), dict(max_steps=120), dict(stop_after_success=None), dict(seed=7),
        dict(env={**SMALL_ENV, "image_size": 40}), dict(env={**SMALL_ENV, "num_points": 32}), dict(regenerate=True),
    ]  # fmt: skip
    unchanged = cache / "unchanged"
    shutil.copytree(cache / "button-press", unchanged / "button-press")
    _source(_mw_recipe(unchanged)).load()
    assert calls == []  # the control: the copy matches as it is
    for i, change in enumerate(changes):
        env = change.pop("env", None)
        other = cache / f"other{i}"
        shutil.copytree(cache / "button-press", other / "button-press")  # a cache to compare with
        recipe = _mw_recipe(other, env=env, **change)
        recipe["task"]["num_points"] = recipe["env"]["num_points"]  # the env's clouds fit the model
        _source(recipe).load()
        assert (other / "button-press" / "generation.json").is_file()
        assert len(calls) == i + 1, change
    # the original cache was untouched by those runs and still matches
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: 1 / 0)
    _source(_mw_recipe(cache)).load()


def test_options_added_later_keep_older_demo_caches_at_their_default(mw_cache):
    """visible_sites came after caches existed: left at its default it is not part of the cache's hash (a
    cache written before it stays valid); set, it is (the clouds differ)."""
    _, source, _ = mw_cache
    params = source.generation_params()
    assert "visible_sites" not in params["env_config"]
    drawn = _source({**_mw_recipe(source.path.parent), "env": {**SMALL_ENV, "visible_sites": ["goal"]}})
    assert drawn.generation_params()["env_config"]["visible_sites"] == ["goal"]
    assert drawn.generation_params()["env_config_hash"] != params["env_config_hash"]


def test_eval_only_env_options_leave_the_demo_cache_alone(mw_cache):
    """pause_fingers only acts during tracking shifts, which demos never make: set or not, the same cache."""
    _, source, _ = mw_cache
    params = source.generation_params()
    assert "pause_fingers" not in params["env_config"]
    paused = _source({**_mw_recipe(source.path.parent), "env": {**SMALL_ENV, "pause_fingers": True}})
    assert paused.generation_params()["env_config_hash"] == params["env_config_hash"]


def test_metaworld_demo_caches_that_replayed_states_are_regenerated(mw_cache):
    import copy

    from ddp.envs.metaworld import MetaWorldEnv, MetaWorldEnvConfig

    _, source, _ = mw_cache
    meta = source.cached_meta()
    assert meta is not None and meta["stats"]["states_per_draw"] == 50 and meta["stats"]["blocks"] == [0, 0, 0]
    old = copy.deepcopy(meta)
    del old["stats"]["states_per_draw"]
    assert source._matches(old)  # written before the fix, every attempt within one draw: the same demos
    old["stats"]["seeds"] = [0, 1, 50]  # attempt 50 replayed state 0 (soccer's cache had seven such)
    assert not source._matches(old)
    fixed = copy.deepcopy(old)
    fixed["stats"]["states_per_draw"] = 50  # the present code drew seed 50 from another draw
    assert source._matches(fixed)
    # that draw's states are others: seed 50 there is not seed 0 here
    cfg = MetaWorldEnvConfig(task="button-press", render_point_cloud=False)
    states = []
    for config, seed in ((cfg, 0), (dataclasses.replace(cfg, **cfg.demo_initial_states(1)), 50)):
        env = MetaWorldEnv(config)
        states.append(env.reset(seed=seed)["privileged", "state"])
        env.close()
    assert not torch.allclose(states[0], states[1])
    assert cfg.demo_initial_states(1) == {"seed_tasks": 500}


def test_a_generation_file_of_another_shape_is_no_match(mw_cache, tmp_path):
    import json

    _, source, _ = mw_cache
    meta = source.cached_meta()
    other = _source(_mw_recipe(tmp_path))
    other.path.mkdir(parents=True)
    for bad in ([1, 2], "text", {**meta, "episodes": "many"}, {**meta, "stats": {"seeds": ["x"]}}):
        (other.path / "generation.json").write_text(json.dumps(bad))
        assert other.cached_meta() is None, bad  # regenerated, not a traceback


def test_a_cache_made_under_other_simulator_versions_is_used_with_a_warning(tmp_path, monkeypatch):
    import json
    import warnings

    pytest.importorskip("metaworld")
    from importlib.metadata import version

    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    fake = _synthetic(2)
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: (fake, {"attempts": 2}))
    _source(_mw_recipe(tmp_path, episodes=2)).load()
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: 1 / 0)  # never again
    meta_file = _source(_mw_recipe(tmp_path, episodes=2)).path / "generation.json"
    meta = json.loads(meta_file.read_text())
    assert meta["software"] == {"mujoco": version("mujoco"), "metaworld": version("metaworld")}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same versions: no warning
        _source(_mw_recipe(tmp_path, episodes=2)).load()
    meta_file.write_text(json.dumps({**meta, "software": {**meta["software"], "metaworld": "2.0.0"}}))
    with pytest.warns(RuntimeWarning, match=f"metaworld 2.0.0 \\(now {version('metaworld')}\\).*data.regenerate=true"):
        loaded = _source(_mw_recipe(tmp_path, episodes=2)).load()
    assert loaded.num_episodes == 2  # used, not regenerated
    del meta["software"]  # a cache written before versions were recorded: nothing to say
    meta_file.write_text(json.dumps(meta))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _source(_mw_recipe(tmp_path, episodes=2)).load()


def test_metaworld_cache_is_replaced_atomically(tmp_path, monkeypatch):
    pytest.importorskip("metaworld")
    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    fake = _synthetic(2)
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: (fake, {"attempts": 2}))
    src = _source(_mw_recipe(tmp_path, episodes=2))
    src.load()
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        _source(_mw_recipe(tmp_path, episodes=2, max_steps=99)).load()
    # the failed regeneration left the old cache in place and no temporary directories (only the lock file)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".button-press.lock", "button-press"]
    assert _source(_mw_recipe(tmp_path, episodes=2)).load().num_episodes == 2
    # a directory that is not a cache is never overwritten
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "data.txt").write_text("mine")
    with pytest.raises(DDPError, match="not a metaworld_expert demo cache"):
        _source(_mw_recipe(tmp_path, path=str(tmp_path / "foreign"))).load()


def test_runs_started_together_generate_a_cache_once(tmp_path, monkeypatch):
    """Two processes (here threads: flock locks conflict between open files) preparing the same cache at once:
    the second waits for the first one's demos instead of generating them again."""
    pytest.importorskip("metaworld")
    import threading
    import time

    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    fake, calls = _synthetic(2), []

    def slow_generate(self, progress=True):
        calls.append(threading.get_ident())
        time.sleep(0.5)
        return fake, {"attempts": 2}

    monkeypatch.setattr(MetaWorldExpertDemos, "generate", slow_generate)
    results = []
    threads = [threading.Thread(target=lambda: results.append(_source(_mw_recipe(tmp_path, episodes=2)).prepare(
        progress=False))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and sorted(r["generated"] for r in results) == [False, True]
    assert all(r["cache_episodes"] == 2 for r in results)


def test_a_cache_is_read_under_its_lock(tmp_path, monkeypatch):
    """load() maps the cache while holding its lock: a run with other settings on the same path waits
    instead of replacing the cache between this run's check and its read."""
    pytest.importorskip("metaworld")
    import fcntl
    import os

    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: (_synthetic(2), {"attempts": 2}))
    src = _source(_mw_recipe(tmp_path, episodes=2))
    src.prepare(progress=False)
    held, real_load = [], Episodes.load

    def probing_load(path):
        fd = os.open(tmp_path / ".button-press.lock", os.O_RDWR)
        try:  # another open file asking for the lock without waiting: refused while load() holds it
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held.append(False)
            fcntl.flock(fd, fcntl.LOCK_UN)
        except BlockingIOError:
            held.append(True)
        finally:
            os.close(fd)
        return real_load(path)

    monkeypatch.setattr(Episodes, "load", staticmethod(probing_load))
    assert src.load().num_episodes == 2 and held == [True]


def test_metaworld_expert_needs_a_metaworld_env(tmp_path):
    from ddp.data.sources.metaworld_expert import MetaWorldExpertConfig, MetaWorldExpertDemos

    with pytest.raises(RecipeError, match=r"^env: .*needs a metaworld env section.*got no env section"):
        MetaWorldExpertDemos(MetaWorldExpertConfig(), task=TaskConfig(), seed=0, env=None)
    recipe = {"name": "x", "env": {"name": "synthetic_reach"}, "data": {"name": "metaworld_expert"}}
    with pytest.raises(RecipeError, match="got env 'synthetic_reach'"):
        _source(recipe)
    with pytest.raises(RecipeError, match="data: episodes must be >= 1; got 0"):
        _source({**_mw_recipe(tmp_path), "data": {"name": "metaworld_expert", "episodes": 0}})


def test_demo_env_config_neutralises_evaluation_options():
    from ddp.data.sources.metaworld_expert import demo_env_config
    from ddp.envs.metaworld import MetaWorldEnvConfig

    cfg = MetaWorldEnvConfig(task="drawer-open", obs_every=8, obs_history=2, displacement=True, oracle_tracking=True,
                             occlusion_chunk=3, terminate_on_success=True, num_points=128)  # fmt: skip
    demo = demo_env_config(cfg, max_steps=180)
    assert (demo.obs_every, demo.obs_history, demo.displacement, demo.oracle_tracking) == (1, 1, False, False)
    assert demo.occlusion_chunk is None and not demo.terminate_on_success and demo.max_episode_steps == 180
    assert demo.num_points == 128 and demo.task == "drawer-open"
    # the recipe's config is not modified: a new object, and every evaluation option as the recipe set it
    assert demo is not cfg
    assert (cfg.obs_every, cfg.obs_history, cfg.displacement, cfg.oracle_tracking) == (8, 2, True, True)
    assert cfg.occlusion_chunk == 3 and cfg.terminate_on_success and cfg.max_episode_steps != 180


def test_build_trains_from_metaworld_demos(mw_cache, tiny_recipe, monkeypatch, tmp_path):
    """The recipe snippet for MetaWorld demos works through ddp.build: exp.episodes() comes from the cache."""
    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    cache, _, demos = mw_cache
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: 1 / 0)
    recipe = {**tiny_recipe, **_mw_recipe(cache), "name": "tiny_mw"}
    recipe["train"] = {**recipe["train"], "max_steps": 2, "epochs": 1}
    exp = ddp.build(recipe)
    episodes = exp.episodes()
    assert torch.equal(episodes.episode_ends, demos.episode_ends)
    assert exp.resolved["data"]["path"] == str(cache / "{task}")
    assert exp.resolved["env"]["task"] == "button-press"
    result = exp.train(output_dir=tmp_path / "run", progress=False)
    assert result.checkpoint.exists()


def test_prepare_demos_is_the_cli_entry_point(mw_cache, monkeypatch):
    from ddp.data.demos import prepare_demos
    from ddp.data.sources.metaworld_expert import MetaWorldExpertDemos

    cache, _, demos = mw_cache
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: 1 / 0)
    info = prepare_demos(_mw_recipe(cache), episodes=2, progress=False)
    assert info["generated"] is False and info["path"] == cache / "button-press"
    assert info["episodes"] == 2 and info["cache_episodes"] == 3
    assert info["stats"]["successes"] == 3
    fake = demos.subset([0])
    monkeypatch.setattr(MetaWorldExpertDemos, "generate", lambda self, progress=True: (fake, {"attempts": 1}))
    info = prepare_demos(_mw_recipe(cache / "new"), ["data.max_steps=99"], episodes=1, regenerate=True, progress=False)
    assert info["generated"] is True and info["episodes"] == 1
    other = prepare_demos({"name": "s", "task": {"num_points": 32}, "data": {"name": "synthetic_reach", "episodes": 2}})
    assert other["episodes"] == 2 and other["generated"] is False


def test_training_checks_demos_for_non_finite_values_and_short_episodes():
    """Finite demos only (a NaN made its dimension's normaliser scale NaN and every checkpoint after it), and
    episodes too short for a training window are counted in a warning (they were dropped silently)."""
    from ddp.models.normalizer import MinMaxNormalizer
    from ddp.train import check_training_episodes

    def demos(lengths):
        n = sum(lengths)
        steps = TensorDict({"action": torch.rand(n, 4), "agent_pos": torch.rand(n, 3)}, batch_size=[n])
        return Episodes(steps, torch.cumsum(torch.tensor(lengths), 0))

    eps = demos([20, 20])
    check_training_episodes(eps, ["action", "agent_pos"], 8, "<r>")  # nothing to say
    eps.steps["agent_pos"][27, 1] = float("inf")
    with pytest.raises(DDPError, match="'agent_pos' holds NaN or inf at episode 1, step 7"):
        check_training_episodes(eps, ["action", "agent_pos"], 8, "<r>")
    with pytest.warns(UserWarning, match="1 of 2 demonstration episodes are shorter than 8 steps"):
        check_training_episodes(demos([4, 20]), ["action"], 8, "<r>")
    with pytest.raises(ValueError, match="normalizer field 'action': the data hold NaN or inf"):
        MinMaxNormalizer({"action": 4}).fit({"action": torch.tensor([[0.0, 1.0, float("nan"), 2.0]])})


class OvershootEnv(LineEnv):
    """LineEnv whose task fails for good past x = 1.15 (a press past its depth), after its success at x = 1."""

    def __init__(self):
        super().__init__()
        self.observation_spec["failed"] = Categorical(2, shape=(1,), dtype=torch.bool)

    def _obs(self, success=False, done=False):
        return super()._obs(success, done).set("failed", torch.tensor([self.x >= 1.15]))


def test_demos_drop_an_episode_that_fails_for_good_after_its_success():
    """A demo that succeeds and then fails for good (an over-press) is not a successful demo, as evaluation
    judges it (it was kept: success was read at any step)."""
    with pytest.raises(DemoGenerationError):
        generate_demos(OvershootEnv, line_expert, episodes=1, seed=0, max_steps=25, progress=False,
                       stop_after_success=3, max_attempts=3)
    demos, _ = generate_demos(OvershootEnv, line_expert, episodes=1, seed=0, max_steps=25, progress=False,
                              stop_after_success=0)  # cut at the success: the overshoot never happens
    assert demos.num_episodes == 1
