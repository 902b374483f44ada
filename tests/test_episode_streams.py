"""Per-episode random streams: an episode draws the same noise whatever --num-envs runs it; seeds draw apart."""

import numpy as np
import pytest
import torch

from conftest import fit_normalizer
from ddp import build
from ddp.rng import mix
from ddp.schedulers.base import rand, randint, randn


def test_mix_separates_its_inputs_and_fits_an_int64():
    seeds = {mix(a, b) for a in range(-3, 20) for b in range(20)}
    assert len(seeds) == 23 * 20
    assert mix(0, 1) != mix(1, 0) and mix(5) != mix(5, 0)
    assert all(0 <= s < 2**63 for s in seeds)
    torch.tensor(sorted(seeds), dtype=torch.int64)  # no overflow


@pytest.mark.parametrize("draw", [
    lambda shape, g: randn(shape, generator=g, device="cpu", dtype=torch.float32),
    lambda shape, g: rand(shape, generator=g, device="cpu", dtype=torch.float64),
    lambda shape, g: randint(7, shape, generator=g, device="cpu"),
])
def test_one_generator_per_row_draws_each_row_from_its_own_stream(draw):
    rows = draw((3, 4, 2), [torch.Generator().manual_seed(s) for s in (5, 6, 7)])
    for i, s in enumerate((5, 6, 7)):
        assert torch.equal(rows[i], draw((4, 2), torch.Generator().manual_seed(s)))
    assert not torch.equal(rows[0], rows[1])
    with pytest.raises(ValueError, match="2 generators for a batch of 3 rows"):
        draw((3, 4), [torch.Generator(), torch.Generator()])


def _rollouts(exp, monkeypatch, *, num_envs, seed=0, detector=None, episodes=4):
    """Per episode seed: (actions [chunks, N, A], imagined per chunk) from ``rollout_episodes``."""
    import ddp.eval_runner as runner

    seen = {}
    orig = runner._summarise

    def recording(traj, env_index, seed, **kwargs):
        seen[seed] = traj.get("action").clone()
        return orig(traj, env_index=env_index, seed=seed, **kwargs)

    monkeypatch.setattr(runner, "_summarise", recording)
    ctrl = exp.make_controller(detector=detector or {"name": "substitution", "p": 0.5}, tracker=False, seed=seed,
                               forecast_every_cycle=True)
    runs = runner.rollout_episodes(exp, ctrl, episodes=episodes, seed=1000, overrides={"max_episode_steps": 48},
                                   num_envs=num_envs, progress=False)
    monkeypatch.setattr(runner, "_summarise", orig)
    return {r["seed"]: (seen[r["seed"]], r["imagined"], r["discrepancy"]) for r in runs}


STREAM_PATHS = {
    "async forecast, DDIM eta 0": {},
    "inline forecast": {"controller": {"async_forecast": False}},
    "3 forecast samples": {"controller": {"forecast_samples": 3}},
    "step noise (DDIM eta 1)": {"policy": {"scheduler": {"eta": 1.0}}, "world_model": {"scheduler": {"eta": 1.0}}},
}


@pytest.mark.parametrize("path", list(STREAM_PATHS))
def test_an_episode_draws_the_same_noise_whatever_num_envs(tiny_recipe, monkeypatch, path):
    """Sampling noise (initial and per step), forecast noise (K samples too) and substitution draws follow the
    episode, not the env row or the batch."""
    for section, values in STREAM_PATHS[path].items():
        for key, value in values.items():
            if isinstance(value, dict):
                tiny_recipe.setdefault(section, {}).setdefault(key, {}).update(value)
            else:
                tiny_recipe.setdefault(section, {})[key] = value
    exp = fit_normalizer(build(tiny_recipe))
    one = _rollouts(exp, monkeypatch, num_envs=1, episodes=3)
    for num_envs in (2, 3) if path == "async forecast, DDIM eta 0" else (3,):
        many = _rollouts(exp, monkeypatch, num_envs=num_envs, episodes=3)
        assert sorted(many) == sorted(one) == [1000, 1001, 1002]
        for seed, (actions, imagined, discrepancy) in one.items():
            assert many[seed][1] == imagined, (num_envs, seed)
            assert torch.allclose(many[seed][0], actions, atol=1e-4), (num_envs, seed)
            assert np.allclose(many[seed][2], discrepancy, atol=1e-4, equal_nan=True), (num_envs, seed)
    # the check can tell episodes apart: two episodes draw different substitutions or actions
    assert any(one[1000][1] != one[s][1] or not torch.allclose(one[1000][0], one[s][0]) for s in (1001, 1002))


def test_training_seeds_and_the_detector_seed_draw_other_substitutions(tiny_recipe, monkeypatch):
    exp = fit_normalizer(build(tiny_recipe))
    base = _rollouts(exp, monkeypatch, num_envs=2)
    again = _rollouts(exp, monkeypatch, num_envs=2)
    other_seed = _rollouts(exp, monkeypatch, num_envs=2, seed=1)
    other_detector = _rollouts(exp, monkeypatch, num_envs=2, detector={"name": "substitution", "p": 0.5, "seed": 3})
    pattern = lambda runs: [runs[s][1] for s in sorted(runs)]  # noqa: E731
    assert pattern(again) == pattern(base)  # deterministic
    assert pattern(other_seed) != pattern(base)
    assert pattern(other_detector) != pattern(base)
    # p = 0.5 after the first chunk: both choices occur
    flags = [f for run in pattern(base) for f in run[1:]]
    assert 0 < sum(flags) < len(flags)


def test_without_an_episode_seed_episodes_are_numbered_in_the_order_they_start(tiny_recipe):
    """An env that does not tell its episode's seed: each new episode still gets its own streams (numbered as
    they start), so two episodes in one batch do not draw the same noise, and a reset starts the count again."""
    from tensordict import TensorDict

    exp = fit_normalizer(build(tiny_recipe))
    ctrl = exp.make_controller(detector={"name": "never"}, tracker=False)
    obs = exp.make_env(seed=0).reset()
    batch = TensorDict({"point_cloud": obs["point_cloud"].expand(2, 2, *obs["point_cloud"].shape).clone(),
                        "agent_pos": obs["agent_pos"].expand(2, 2, *obs["agent_pos"].shape).clone(),
                        "chunk_index": torch.zeros(2, 1, dtype=torch.int64)}, batch_size=[2])
    first = ctrl(batch.clone())
    keys = first["ddp", "episode_key"].tolist()
    assert keys[0] != keys[1] and not torch.allclose(first["action"][0], first["action"][1])  # same input, own noise
    ctrl.reset()
    again = ctrl(batch.clone())
    assert again["ddp", "episode_key"].tolist() == keys and torch.equal(again["action"], first["action"])
    told = batch.clone()
    told["episode_seed"] = torch.tensor([[7], [7]])
    same = ctrl(told)  # an env telling both rows the same episode seed: the same streams
    assert torch.equal(same["action"][0], same["action"][1])
