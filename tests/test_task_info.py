"""The task diagnostics an env reports (``("privileged", "task_info")``) reach each episode's and each
protocol's evaluation result, and a suite run's stored summary."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from ddp.eval_report import protocol_result, task_info_mean
from ddp.eval_runner import _summarise
from ddp.suite.runner import _summary


def _trajectory(max_depth: list[float]) -> TensorDict:
    """A 3-chunk episode whose env reports press-like diagnostics after each chunk."""
    n = len(max_depth)
    info = TensorDict({"max_depth": torch.tensor(max_depth).reshape(n, 1),
                       "over_pressed": (torch.tensor(max_depth) > 0.014).float().reshape(n, 1)}, batch_size=[n])
    nxt = TensorDict({"success": torch.tensor([False, True, True]).reshape(n, 1),
                      "privileged": TensorDict({"task_info": info}, batch_size=[n])}, batch_size=[n])
    return TensorDict({"next": nxt}, batch_size=[n])


def test_episode_reports_the_diagnostics_at_its_end():
    out = _summarise(_trajectory([0.002, 0.009, 0.021]), env_index=0, seed=7)
    assert out["task_info"] == {"max_depth": torch.tensor(0.021).item(), "over_pressed": 1.0}
    plain = TensorDict({"next": TensorDict({"success": torch.zeros(2, 1, dtype=torch.bool)}, [2])}, [2])
    assert "task_info" not in _summarise(plain, env_index=0, seed=7)  # an env without diagnostics


def test_protocol_and_suite_summaries_average_them_leaving_out_nan():
    episodes = [{"success": True, "task_info": {"max_depth": 0.008, "over_pressed": 0.0}},
                {"success": False, "task_info": {"max_depth": 0.020, "over_pressed": 1.0}},
                {"success": False, "task_info": {"max_depth": math.nan, "over_pressed": math.nan}},  # hardware
                {"success": False}]
    mean = task_info_mean(episodes)
    assert mean["max_depth"] == 0.014 and mean["over_pressed"] == 0.5
    result = protocol_result(episodes, seconds=1.0, thresholds={})
    assert result["task_info"] == mean
    assert _summary(result)["task_info"] == mean  # what results/suites/<suite>/<run>.json keeps
    assert "task_info" not in protocol_result([{"success": True}], seconds=1.0, thresholds={})
    assert task_info_mean([{"success": True, "task_info": {"x": math.nan}}]) == {}


def test_a_task_failed_for_good_revokes_an_earlier_success(tiny_recipe):
    """A press past its depth after a good press: the env's "failed" flag revokes the episode's success in
    ChunkedEnv, for the rest of the episode, and an evaluation reads the episode's success after its last
    chunk (any chunk's success counted the good press)."""
    from ddp import build
    from ddp.evaluate import make_chunked_env

    env = make_chunked_env(build(tiny_recipe), seed=0)
    env.reset()

    def step(**flags):
        env._after_inner_step(TensorDict({k: torch.tensor([v]) for k, v in flags.items()}, batch_size=[]))
        return env._success

    assert step(success=True) and step(success=False)  # success so far
    assert not step(success=True, failed=True) and not step(success=True)  # revoked, for good
    env.reset()
    assert step(success=True)  # a new episode starts clean
    revoked = TensorDict({"next": TensorDict({"success": torch.tensor([False, True, False]).reshape(3, 1)}, [3])},
                         [3])
    out = _summarise(revoked, env_index=0, seed=1)
    assert out["success"] is False and out["first_success_chunk"] == 1
    env.close()
