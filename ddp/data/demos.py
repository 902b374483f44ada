"""Scripted-expert demonstrations: roll an expert through a TorchRL env and keep the good episodes.

DP3's recipe for simulated demonstrations, which the paper follows ("a fixed
dataset of 50 demonstrations per task"): run a scripted expert, record at
every step the observation *before* the action together with that action,
and keep only the episodes that succeed.

Reproducibility: attempt ``i`` resets the env with seed ``seed + i`` (the
env's ``set_seed`` then ``reset``), and the expert is deterministic, so the
same arguments give identical arrays. Because attempts run in order, the
first ``k`` episodes of a run with ``episodes=n >= k`` are the episodes of a
run with ``episodes=k``.

Episode ends: DP3 records ``max_steps`` steps whatever happens.
``stop_after_success=N`` instead ends the episode ``N`` steps after the
action that first reached success (``N=0``: that action is the last one).
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping

import numpy as np
import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from ddp.data.episodes import Episodes
from ddp.errors import DDPError

__all__ = ["DEFAULT_RECORD_KEYS", "DemoGenerationError", "generate_demos", "prepare_demos"]

#: name in the episodes -> key read from the env's observation
DEFAULT_RECORD_KEYS: dict[str, NestedKey] = {"point_cloud": "point_cloud", "agent_pos": "agent_pos"}


class DemoGenerationError(DDPError):
    """The expert did not produce enough successful episodes."""


def _as_action(value: Any, spec) -> torch.Tensor:
    action = torch.as_tensor(np.asarray(value) if not isinstance(value, torch.Tensor) else value)
    action = action.detach().to("cpu", torch.float32).reshape(spec.shape)
    low, high = getattr(spec, "low", None), getattr(spec, "high", None)
    if low is not None and high is not None:  # record what the env executes (it clips too)
        action = torch.minimum(torch.maximum(action, low.to(action)), high.to(action))
    return action


def _rollout(
    env, expert: Callable, seed: int, max_steps: int, stop_after_success: int | None, keys: Mapping[str, NestedKey]
) -> tuple[dict[str, np.ndarray], bool, int | None]:
    """One episode: per-step observations (before the action) and actions; success; first success step."""
    reset = getattr(expert, "reset", None)
    if callable(reset):
        reset()
    env.set_seed(seed)
    td: TensorDictBase = env.reset()
    rows: dict[str, list[np.ndarray]] = {name: [] for name in keys}
    rows["action"] = []
    first_success: int | None = None
    for t in range(max_steps):
        for name, key in keys.items():
            rows[name].append(td.get(key).detach().cpu().numpy().copy())
        action = _as_action(expert(td), env.action_spec)
        rows["action"].append(action.numpy())
        td.set("action", action)
        td = env.step(td).get("next")
        if bool(td.get("failed", torch.zeros(1, dtype=torch.bool)).any()):  # failed for good (an over-press)
            return {name: np.stack(v) for name, v in rows.items()}, False, first_success
        if first_success is None and bool(td.get("success", torch.zeros(1, dtype=torch.bool)).any()):
            first_success = t
        if stop_after_success is not None and first_success is not None and t >= first_success + stop_after_success:
            break
        if bool(td.get("done").any()):
            break
    return {name: np.stack(v) for name, v in rows.items()}, first_success is not None, first_success


def generate_demos(
    make_env: Callable[[], Any],
    expert: Callable[[TensorDictBase], Any],
    *,
    episodes: int,
    seed: int,
    max_steps: int,
    keep_only_success: bool = True,
    progress: bool = True,
    stop_after_success: int | None = None,
    max_attempts: int | None = None,
    record_keys: Mapping[str, NestedKey] | None = None,
    desc: str = "demos",
    states_per_draw: int | None = None,
    make_block_env: Callable[[int], Any] | None = None,
) -> tuple[Episodes, dict]:
    """Roll ``expert`` out in an env until ``episodes`` episodes are kept.

    Args:
        make_env: builds the TorchRL env (called once; the env is closed at the end).
            Its observations must hold the ``record_keys`` and a boolean ``"success"``.
        expert: ``tensordict -> action`` (tensor or array); an optional ``reset()``
            method is called before every episode.
        episodes: episodes to keep.
        seed: attempt ``i`` uses env seed ``seed + i``.
        max_steps: actions per episode at most (DP3: 200).
        keep_only_success: drop failed episodes (DP3). False keeps the first ``episodes`` attempts.
        progress: show a tqdm bar with the running success rate.
        stop_after_success: end an episode this many steps after the first success (None: full length).
        max_attempts: give up after this many episodes (default ``2 * episodes + 10``).
        record_keys: episode key -> observation key (default point_cloud and agent_pos);
            ``"action"`` is always recorded.
        desc: progress bar label.
        states_per_draw: for an env whose seeds repeat an initial state this many seeds apart (MetaWorld:
            50): attempt ``i`` then runs in ``make_block_env(i // states_per_draw)`` (block 0: ``make_env``),
            an env drawing other initial states, so that no two attempts start from one state (an expert
            that failed on some states would otherwise record the first states' demos twice).
        make_block_env: ``block -> env`` for those further blocks (needed with ``states_per_draw``).

    Returns:
        ``(Episodes, stats)``: steps with the ``record_keys`` and ``"action"``; stats
        ``attempts, successes, success_rate, episodes, steps, mean_length,
        mean_first_success, failed_seeds, seeds, simulated_steps, seconds, seconds_per_episode,
        seconds_per_step`` (per simulated step, failed attempts included), and with ``states_per_draw``
        ``states_per_draw`` and ``blocks`` (each kept episode's block).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1; got {episodes}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1; got {max_steps}")
    if stop_after_success is not None and stop_after_success < 0:
        raise ValueError(f"stop_after_success must be >= 0 or None; got {stop_after_success}")
    limit = max_attempts if max_attempts is not None else 2 * episodes + 10
    if limit < episodes:
        raise ValueError(f"max_attempts ({limit}) must be >= episodes ({episodes})")
    if states_per_draw is not None and (states_per_draw < 1 or make_block_env is None):
        raise ValueError(f"states_per_draw ({states_per_draw}) needs to be >= 1 and a make_block_env")
    keys = dict(DEFAULT_RECORD_KEYS if record_keys is None else record_keys)
    if "action" in keys:
        raise ValueError("record_keys must not contain 'action' (actions are always recorded)")

    from tqdm.auto import tqdm

    start = time.perf_counter()
    kept: list[TensorDict] = []
    seeds, failed, first_success, blocks = [], [], [], []
    attempts = successes = simulated = block = 0
    env = make_env()
    bar = tqdm(total=episodes, desc=desc, unit="ep", disable=not progress, dynamic_ncols=True)
    try:
        while len(kept) < episodes:
            if attempts >= limit:
                raise DemoGenerationError(
                    f"{desc}: only {len(kept)} of {episodes} episodes after {attempts} attempts "
                    f"({successes} successful, seeds {seed}..{seed + attempts - 1}); the expert fails too often "
                    f"in this env (failed seeds: {failed[:10]}{' ...' if len(failed) > 10 else ''})"
                )
            ep_seed = seed + attempts
            if states_per_draw is not None and attempts // states_per_draw != block:
                block = attempts // states_per_draw  # every state of the last draw was tried: the next draw
                env.close()
                env = None  # (a failing make_block_env leaves nothing to close twice)
                env = make_block_env(block)
            arrays, ok, first = _rollout(env, expert, ep_seed, max_steps, stop_after_success, keys)
            attempts += 1
            simulated += arrays["action"].shape[0]
            if ok:
                successes += 1
                first_success.append(first)
            else:
                failed.append(ep_seed)
            if ok or not keep_only_success:
                length = arrays["action"].shape[0]
                kept.append(TensorDict({k: torch.from_numpy(v) for k, v in arrays.items()}, batch_size=[length]))
                seeds.append(ep_seed)
                blocks.append(block)
                bar.update(1)
            bar.set_postfix(attempts=attempts, success=f"{successes / attempts:.0%}")
    finally:
        bar.close()
        if env is not None:
            env.close()
    demos = Episodes.from_list(kept)
    seconds = time.perf_counter() - start
    lengths = [td.batch_size[0] for td in kept]
    stats = {
        "attempts": attempts,
        "successes": successes,
        "success_rate": successes / attempts,
        "episodes": len(kept),
        "steps": demos.num_steps,
        "mean_length": float(np.mean(lengths)),
        "mean_first_success": float(np.mean(first_success)) if first_success else None,
        "failed_seeds": failed,
        "seeds": seeds,
        "seconds": seconds,
        "seconds_per_episode": seconds / attempts,
        "simulated_steps": simulated,
        "seconds_per_step": seconds / max(1, simulated),
    }
    if states_per_draw is not None:
        stats.update(states_per_draw=states_per_draw, blocks=blocks)
    return demos, stats


def prepare_demos(
    recipe,
    overrides=(),
    *,
    episodes: int | None = None,
    regenerate: bool = False,
    progress: bool = True,
) -> dict:
    """Make a recipe's demonstrations ready on disk (what ``ddp demos RECIPE --episodes N`` runs).

    Builds only the recipe's ``data`` source (not the model). Sources with a
    cache (``metaworld_expert``) generate and save their demos unless a
    matching cache exists (``regenerate=True`` forces a new run); other
    sources are just loaded. ``episodes`` overrides ``data.episodes``.

    Returns ``{"path", "generated", "episodes", "stats"}``: the cache
    directory (None for sources without one), whether demos were generated
    now, how many episodes the source holds, and the generation stats
    (:func:`generate_demos`; None when unknown).
    """
    from ddp.recipe import load_recipe
    from ddp.schema import validate

    overrides = list(overrides)
    if episodes is not None:
        overrides.append(f"data.episodes={int(episodes)}")
    data, source = load_recipe(recipe, overrides)
    rec, parts, _ = validate(data, source)
    if parts.get("data") is None:
        from ddp.errors import RecipeError

        raise RecipeError("this recipe has no data section (ddp list dataset)", source=source, key="data")
    src = parts["data"].build(task=rec.task, seed=rec.seed, env=parts.get("env"))
    if callable(getattr(src, "prepare", None)):
        return src.prepare(progress=progress, regenerate=regenerate)
    start = time.perf_counter()
    demos = src.load()
    return {
        "path": getattr(src, "path", None),
        "generated": False,
        "episodes": demos.num_episodes,
        "stats": {"steps": demos.num_steps, "seconds": time.perf_counter() - start},
    }
