"""Evaluation runner: a protocol and a trained experiment in, one result dict per episode out.

Builds the seeded evaluation envs (``ChunkedEnv`` around the recipe's env, in this process or one
worker each), runs the controller through a TorchRL collector, and summarises every episode
(seed, success, chunks, the controller's mode / imagination / D_R-I per chunk). Also the ID
rollouts that calibrate a discrepancy threshold. Writing results is :mod:`ddp.eval_report`'s job.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from ddp.config import coerce, field_types
from ddp.envs.chunked import ChunkedEnv, chunk_render_config
from ddp.errors import RecipeError, suggest
from ddp.protocols.base import EvalProtocol
from ddp.schema import Part
from ddp.video import VideoSettings


def check_env_options(exp, options: dict, *, source, key: str | None = None, needed_by: str | None = None,
                      values: bool = True) -> None:
    """Every key of ``options`` is an option of the recipe's env config and (``values``) the config accepts the
    values: else one line naming the env and the offending key (with the closest option name), or what the
    config refused. ``needed_by`` words the error for options a protocol needs ("... does not support X needed
    by ..."); otherwise an unknown key reads "has no option X"."""
    env = exp.parts["env"]
    fields = {f.name for f in dataclasses.fields(env.config)}
    missing = sorted(set(options) - fields)
    if missing and needed_by is not None:
        raise RecipeError(f"env '{env.plugin.name}' does not support {', '.join(missing)} needed by {needed_by}",
                          source=source, key=key)
    if missing:
        raise RecipeError(f"env '{env.plugin.name}' has no option {missing[0]!r}{suggest(missing[0], fields)}",
                          source=source, key=key)
    if not values:
        return
    types_ = field_types(type(env.config))  # options set here skip the recipe loader's type checks
    for name, value in options.items():
        coerce(_plain(value), types_[name], name if key is None else f"{key}.{name}", source)
    try:
        dataclasses.replace(env.config, **options)
    except (TypeError, ValueError) as err:
        raise RecipeError(str(err).splitlines()[0], source=source, key=key) from None


def _plain(value):
    """numpy scalars and arrays as Python numbers and lists (a caller's np.float32(0.1) is a float option)."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value)
    return value


def env_config(exp, overrides: dict | None = None):
    """The recipe's env config with ``overrides`` (``eval.env``, a protocol's, ``--env``) in place: the config
    of the env the episodes run in."""
    return dataclasses.replace(exp.parts["env"].config, **(overrides or {}))


def env_overrides(exp, protocol: EvalProtocol, max_steps: int | None, extra: dict | None = None,
                  extra_source: str = "--env") -> dict:
    """The env overrides a protocol runs with: ``eval.env``, the protocol's own, oracle tracking, occlusion and
    the episode length, then ``extra`` on top (e.g. ``ddp detect --env``). Checked against the env's config
    as a whole, so an extra option may complete the protocol's (a displacement chunk for its displacement);
    a refused value is reported under ``extra_source`` when there are extras, else under ``eval.env``."""
    fields = {f.name for f in dataclasses.fields(exp.parts["env"].config)}
    over = dict(exp.recipe.eval.env)
    # the recipe's own options first, under their key (a typo there is the recipe's, with the closest name)
    check_env_options(exp, over, source=exp.source, key="eval.env", values=False)
    over.update(protocol.env)
    over.update({k: v for k, v in protocol.env_if_supported.items() if k in fields})
    if protocol.env_tracking and exp.recipe.eval.env_oracle_tracking:
        over["oracle_tracking"] = True
    if protocol.occlusion:
        over.update(occlusion_chunk=exp.recipe.eval.occlusion_chunk, occlusion_chunks=exp.recipe.eval.occlusion_chunks)
    check_env_options(exp, over, source=exp.source, key="env", needed_by="this protocol", values=False)
    if max_steps is not None:
        check_env_options(exp, {"max_episode_steps": max_steps}, source=exp.source, key="eval.max_steps",
                          needed_by="eval.max_steps", values=False)
        over["max_episode_steps"] = max_steps
    if extra:
        check_env_options(exp, extra, source=extra_source, values=False)
        over.update(extra)
        check_env_options(exp, over, source=extra_source)
    else:
        check_env_options(exp, over, source=exp.source, key="eval.env")
    return over


@dataclass(frozen=True, eq=False)  # hashed by identity (torchrl puts factories in a set)
class ChunkedEnvFactory:
    """Builds one evaluation env (``ChunkedEnv`` around the recipe's env plugin); picklable, so
    ``ParallelEnv`` can call it in a worker process (it re-imports the recipe's ``plugins`` there)."""

    plugin: str
    config: object
    action_steps: int
    obs_steps: int
    safe_lift: float = 0.0
    seed: int = 0
    video: VideoSettings | None = None
    plugin_modules: tuple[str, ...] = ()

    def __call__(self) -> ChunkedEnv:
        from ddp import registry

        if self.plugin_modules:
            registry.import_plugin_modules(list(self.plugin_modules))
        cfg = chunk_render_config(self.config, self.action_steps, self.obs_steps)
        base = Part(registry.get("env", self.plugin), cfg).build(seed=self.seed)  # checked against the env contract
        try:
            return ChunkedEnv(base, self.action_steps, self.obs_steps, safe_lift=self.safe_lift, video=self.video)
        except BaseException:  # the base env holds a simulator, a renderer or a robot connection
            try:
                base.close()
            except Exception:  # noqa: BLE001 - the refusal is the error to report
                pass
            raise


def env_factory(exp, seed: int, overrides: dict | None = None, video: VideoSettings | None = None) -> ChunkedEnvFactory:
    pol, part = exp.recipe.policy, exp.parts["env"]
    return ChunkedEnvFactory(
        plugin=part.plugin.name, config=env_config(exp, overrides),
        action_steps=pol.action_steps, obs_steps=pol.obs_steps, safe_lift=exp.recipe.controller.safe_lift,
        seed=seed, video=video, plugin_modules=exp.plugin_modules,
    )


def make_chunked_env(exp, seed: int, overrides: dict | None = None, video: VideoSettings | None = None) -> ChunkedEnv:
    return env_factory(exp, seed, overrides, video)()


def judges_success(exp, overrides: dict | None = None) -> bool:
    """Whether the env the episodes run in (the recipe's config with ``overrides``: ``eval.env``, a protocol's,
    ``--env``) can tell a success (the env contract's optional ``judges_success()``; a real robot cannot: a
    person judges its episodes, and evaluations report none)."""
    cfg = env_config(exp, overrides)
    judges = getattr(cfg, "judges_success", None)
    return not callable(judges) or bool(judges())


def check_video_camera(exp, overrides: dict, camera: str | None) -> None:
    """For a video evaluation, an env that cannot render or a camera it does not have, refused before any
    rollout under ``eval.video_camera`` (each was a traceback at the first recorded frame, after the detector's
    calibration). Checked on one env (a camera by rendering one frame of it reset); only where the env judges
    success itself (a simulator: a real robot's reset moves the arm and waits for its operator)."""
    if not judges_success(exp, overrides):
        return
    env = make_chunked_env(exp, seed=0, overrides=overrides)
    try:
        if not callable(getattr(env.base, "render_rgb", None)):
            raise RecipeError(f"env '{exp.parts['env'].plugin.name}' cannot record videos (it has no "
                              f"render_rgb(width, height, camera)): set eval.video false", source=exp.source,
                              key="eval.video_camera")
        if camera is None:  # the env's default camera
            return
        env.reset()
        try:
            env.base.render_rgb(16, 16, camera=camera)
        except ValueError as err:  # the env contract's answer to a camera it lacks
            raise RecipeError(str(err).strip().splitlines()[0], source=exp.source, key="eval.video_camera") from err
    finally:
        env.close(raise_if_closed=False)


def _chunks_per_episode(exp, overrides: dict) -> int:
    cfg = env_config(exp, overrides)
    if not hasattr(cfg, "max_episode_steps"):  # eval.max_steps sets that field: nothing can be set here
        raise RecipeError(f"env '{exp.parts['env'].plugin.name}' has no max_episode_steps option: evaluation "
                          f"needs the episode length (the env plugin's config must have one)", source=exp.source,
                          key="env")
    steps = cfg.max_episode_steps
    if steps is None:
        raise RecipeError("the episode length is not set (env.max_episode_steps is null): set it", source=exp.source,
                          key="eval.max_steps")
    if getattr(cfg, "terminate_on_success", False):
        # episodes are cut from the collector's stream every `chunks` chunks: one that ended early would
        # run into the next (its seed, success and detector trace mixed with another episode's)
        raise RecipeError("must be false for evaluation: episodes run their full length and count success "
                          "at any step (DP3's protocol; a task's failure for good revokes it)", source=exp.source,
                          key="env.terminate_on_success")
    return math.ceil(steps / exp.recipe.policy.action_steps)


def rollout_episodes(exp, controller, *, episodes: int, seed: int, overrides: dict, num_envs: int = 1,
                     desc: str = "", progress: bool = True, parallel: bool = False,
                     video: VideoSettings | None = None, record_latents: bool = False) -> list[dict]:
    """Run ``episodes`` seeded episodes with a torchrl Collector; one dict of results per episode.

    ``num_envs > 1`` steps several envs as one batch: in this process (``SerialEnv``) or, with
    ``parallel=True``, each in its own worker process (``ParallelEnv``). The episodes are seeds
    ``seed, seed + 1, ..., seed + episodes - 1`` whatever ``num_envs``: env ``i`` runs a consecutive share of
    them (``episodes // num_envs``, one more for the first ``episodes % num_envs`` envs). ``video`` records each env's
    first ``video.episodes`` episodes. ``record_latents`` keeps each chunk's real and forecast latent
    windows (``latent_real`` / ``latent_pred`` arrays [chunks, M, D]) for detector calibration.
    """
    import torch
    from torchrl.collectors import Collector
    from torchrl.envs import ParallelEnv, SerialEnv

    chunks = _chunks_per_episode(exp, overrides)
    num_envs = max(1, min(num_envs, episodes))
    quota = [episodes // num_envs + (i < episodes % num_envs) for i in range(num_envs)]
    starts = [seed + sum(quota[:i]) for i in range(num_envs)]  # env i: seeds starts[i] ... + quota[i] - 1

    def factory(i: int) -> ChunkedEnvFactory:
        first = starts[i]
        # at most the env's share: past it the env runs idle episodes (the collector's batches), not evaluated ones
        vid = None if video is None else dataclasses.replace(video, first_seed=first,
                                                            episodes=min(video.episodes, quota[i]))
        return env_factory(exp, first, overrides, vid)

    # torchrl's batched envs set torch's thread count in this process (ParallelEnv lowers it while its workers
    # run; closing either raises it to min(the count at torchrl's import, count + envs)): restored below, or a
    # suite run with --threads 1 would train and evaluate on more OpenMP threads than it was given
    threads = torch.get_num_threads()
    results: list[dict] = []
    done = [0] * num_envs  # episodes kept per env (one per env and batch; an env past its share runs idle)
    judged = judges_success(exp, overrides)  # a real robot's env cannot: a person judges its episodes
    env = collector = bar = None
    finished = False
    try:  # from the env's construction on: the collector resets the envs when it is built, which may fail
        if num_envs == 1:
            env = factory(0)()
        else:
            batched = ParallelEnv if parallel else SerialEnv
            env = batched(num_envs, [factory(i) for i in range(num_envs)])
        controller.reset()
        collector = Collector(
            env, controller, frames_per_batch=chunks * num_envs, total_frames=chunks * num_envs * max(quota),
            reset_when_done=True, trust_policy=True, auto_register_policy_transforms=False,
        )
        bar = tqdm(total=episodes, desc=desc, disable=not progress, unit="ep")
        for batch in collector:
            batch = batch.reshape(num_envs, chunks) if batch.batch_dims == 1 else batch
            for i in range(num_envs):
                if done[i] >= quota[i]:
                    continue
                results.append(_summarise(batch[i], env_index=i, seed=starts[i] + done[i], latents=record_latents))
                if not judged:  # no success to report (not False: the table says "not judged", not 0 %)
                    results[-1].update(success=None, first_success_chunk=None)
                done[i] += 1
                bar.update(1)
                if judged:
                    bar.set_postfix(success=f"{np.mean([r['success'] for r in results]):.2f}")
            if len(results) >= episodes:
                break
        finished = True
    finally:
        # the last cycle's background forecast: waited for (nothing may run on the model after us), its thread
        # stopped, and its error a warning (no cycle is left to collect it); a controller used again restarts it
        wait = getattr(controller, "close", None) or getattr(controller, "wait_forecast", None)
        _clean_up([
            None if bar is None else bar.close,
            None if collector is None else collector.shutdown,
            None if env is None else (lambda: env.close(raise_if_closed=False)),
            lambda: _restore_threads(threads),  # after the env's close, which may raise the count
            wait,
        ], quiet=not finished)
    return sorted(results, key=lambda r: r["seed"])


def _restore_threads(threads: int) -> None:
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)


def _clean_up(steps: list, quiet: bool) -> None:
    """Run every cleanup step (None: nothing to do), whichever of them fails. ``quiet`` (the evaluation itself
    failed): a step's error is a warning, so the evaluation's own error is the one raised (a dead worker's, not
    the broken pipe its env's close then meets); otherwise the first step's error is raised once all have run."""
    error = None
    for step in steps:
        if step is None:
            continue
        try:
            step()
        except Exception as err:  # noqa: BLE001 - the others still run; reported below
            if quiet:
                import warnings

                warnings.warn(f"evaluation cleanup: {type(err).__name__}: {err}", RuntimeWarning, stacklevel=2)
            elif error is None:
                error = err
    if error is not None:
        raise error


def _disturbed(traj) -> list[bool] | None:
    """Per chunk, whether the observation the controller saw was disturbed: an object displaced (privileged
    ``displacement``) or the camera blind (``occluded``). None when the env reports neither."""
    keys = traj.keys(True)
    flags = None
    if ("privileged", "displacement") in keys:
        disp = traj.get(("privileged", "displacement"))
        flags = disp.reshape(disp.shape[0], -1, disp.shape[-1]).norm(dim=-1).amax(-1) > 1e-6  # any object moved
    if ("privileged", "occluded") in keys:
        occ = traj.get(("privileged", "occluded")).reshape(-1).bool()
        flags = occ if flags is None else flags | occ
    return None if flags is None else flags.tolist()


def _summarise(traj, env_index: int, seed: int, latents: bool = False) -> dict:
    success = traj.get(("next", "success")).reshape(-1)
    out = {
        "seed": seed,
        "env": env_index,
        # the episode's success so far after its last chunk (ChunkedEnv keeps it, and revokes it where the task
        # failed for good; equal to any chunk's success otherwise). first_success_chunk stays where a success
        # was revoked: when the good press came
        "success": bool(success[-1]),
        "chunks": int(traj.batch_size[0]),
        "first_success_chunk": int(success.nonzero()[0]) if bool(success.any()) else None,
    }
    for key in ("mode", "imagined", "discrepancy", "score", "subtask"):
        if ("ddp", key) in traj.keys(True):
            out[key] = traj.get(("ddp", key)).reshape(-1).float().tolist()
    if "ee_shift" in traj.keys():  # the controller's tracking (+Delta p) and recovery (-Delta p) shifts, per chunk
        shifts = traj.get("ee_shift").reshape(-1, 3)
        out["ee_shift"] = [[round(float(x), 4) for x in row] for row in shifts]
    disturbed = _disturbed(traj)
    if disturbed is not None:
        out["disturbed"] = disturbed
    info_key = ("next", "privileged", "task_info")
    if info_key in traj.keys(True):  # the task's diagnostics at the episode's end (e.g. press depth, balls poured)
        info = traj.get(info_key)
        out["task_info"] = {name: float(info.get(name).reshape(info.shape[0], -1)[-1, 0]) for name in info.keys()}
    if latents:
        out["latent_real"] = traj.get(("ddp", "latent_real")).double().numpy()
        out["latent_pred"] = traj.get(("ddp", "latent_pred")).double().numpy()
        if ("ddp", "latent_pred_std") in traj.keys(True):
            out["latent_pred_std"] = traj.get(("ddp", "latent_pred_std")).double().numpy()
    return out


def calibration_env(exp, block: int = 0) -> dict:
    """The env overrides of a detector's calibration rollouts: the ``id`` protocol's (``eval.env``,
    ``eval.max_steps``: episodes as long as evaluated ones) and ``eval.calibration_env``, or where that is
    unset, the env's own held-out draw of initial states (its config's ``held_out_initial_states(block)``,
    for envs whose initial states repeat across seeds, e.g. MetaWorld's 50 per MT1 draw): the calibration's
    ID episodes never replay an evaluated initial state."""
    overrides, config = _id_env(exp)
    extra = exp.recipe.eval.calibration_env
    if extra is None:
        held_out = getattr(config, "held_out_initial_states", None)
        extra = (held_out(block) if block else held_out()) if callable(held_out) else {}
    check_env_options(exp, {**overrides, **extra}, source=exp.source, key="eval.calibration_env")
    return {**overrides, **extra}


def _id_env(exp) -> tuple[dict, object]:
    """The ``id`` protocol's env overrides and the env config they make."""
    from ddp.protocols.base import get_protocol

    overrides = env_overrides(exp, get_protocol("id"), exp.recipe.eval.max_steps)
    return overrides, env_config(exp, overrides)


def calibration_blocks(exp, seed: int, episodes: int, first_seed: int) -> list[tuple[int, int, int]]:
    """``(block, first seed, episodes)`` for the calibration seeds ``seed .. seed + episodes - 1``: one block
    where the env's held-out states do not repeat (or ``eval.calibration_env`` is set), else a new block
    (:func:`calibration_env`'s ``block``, another draw of initial states) every ``initial_states_per_draw``
    seeds, counted from ``first_seed``'s, so that no two calibration episodes start from one state."""
    period = None
    if exp.recipe.eval.calibration_env is None:
        period = getattr(_id_env(exp)[1], "initial_states_per_draw", None)
    if not period:
        return [(0, seed, episodes)]
    return seed_blocks(seed, episodes, period, first=first_seed)


def seed_blocks(seed: int, episodes: int, period: int, *, anchor: int = 0,
                first: int | None = None) -> list[tuple[int, int, int]]:
    """``(block, first seed, episodes)``: the seeds ``seed .. seed + episodes - 1`` cut wherever ``seed -
    anchor`` is a multiple of ``period`` (so each piece's seeds are consecutive and fewer than ``period``:
    distinct initial states), each piece's block counted from the one ``first`` (default ``seed``) lies in."""
    first = seed if first is None else first
    out, s, end = [], seed, seed + episodes
    while s < end:
        stop = min(end, anchor + ((s - anchor) // period + 1) * period)
        out.append(((s - anchor) // period - (first - anchor) // period, s, stop - s))
        s = stop
    return out


def evaluation_blocks(exp, overrides: dict, seed: int, episodes: int) -> list[tuple[dict, int, int]]:
    """``(overrides, first seed, episodes)`` for evaluating seeds ``seed .. seed + episodes - 1``: the
    protocol's ``overrides`` for the first ``initial_states_per_draw`` seeds (all of them for an env whose
    states do not repeat), then, per further block of that many seeds, the env's ``more_initial_states(block)``
    on top (another draw of initial states: no two evaluated episodes start from one state)."""
    config = env_config(exp, overrides)
    period = getattr(config, "initial_states_per_draw", None)
    more = getattr(config, "more_initial_states", None)
    if not period or not callable(more) or episodes <= period:
        return [(overrides, seed, episodes)]
    out = []
    for block, start, n in seed_blocks(seed, episodes, period, anchor=seed):
        extra = more(block) if block else {}
        if extra:
            check_env_options(exp, {**overrides, **extra}, source=exp.source, key="eval.env")
        out.append(({**overrides, **extra}, start, n))
    return out


def calibration_episodes(exp, *, episodes: int, seed: int, num_envs: int = 1, progress: bool = True,
                         parallel: bool = False, first_seed: int | None = None) -> list[dict]:
    """ID rollouts of the base policy with the world model forecasting every cycle, each with its
    chunks' real and forecast latent windows (what a discrepancy detector is calibrated on), in the env
    of :func:`calibration_env` (its blocks: :func:`calibration_blocks`; ``first_seed``: the calibration's
    first seed, where these episodes continue it)."""
    ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True)
    out = []
    for block, start, n in calibration_blocks(exp, seed, episodes, seed if first_seed is None else first_seed):
        out += rollout_episodes(exp, ctrl, episodes=n, seed=start, overrides=calibration_env(exp, block),
                                num_envs=num_envs, desc="calibrate detector", progress=progress, parallel=parallel,
                                record_latents=True)
    return out


def calibrate_detector(exp, detector, *, episodes: int, seed: int, num_envs: int = 1, progress: bool = True,
                       parallel: bool = False, max_episodes: int | None = None) -> float:
    """Fit a calibratable detector (statistic and threshold) on ID rollouts; return its tau.

    ``episodes`` ID episodes first; while the detector asks for more (:class:`ddp.contracts.NeedMoreEpisodes`,
    e.g. too few successful ones to set tau on), as many more as it asks for, on the next unused seeds,
    up to ``max_episodes`` in all (default ``eval.max_calibration_episodes``)."""
    from ddp.contracts import NeedMoreEpisodes

    cap = max(episodes, max_episodes if max_episodes is not None else exp.recipe.eval.max_calibration_episodes)
    kw = dict(num_envs=num_envs, progress=progress, parallel=parallel)
    runs = calibration_episodes(exp, episodes=episodes, seed=seed, **kw)
    while True:
        try:
            return detector.calibrate(runs, point_dims=exp.model.point_dims)
        except NeedMoreEpisodes as short:
            if short.at_least is not None and short.at_least > cap:  # even if every episode succeeded
                raise ValueError(f"{short}: it takes at least {short.at_least} ID calibration episodes, more than "
                                 f"eval.max_calibration_episodes ({cap}) allows (raise it, or alpha)") from None
            if len(runs) >= cap:
                raise ValueError(f"{short} after {len(runs)} ID calibration episodes, the most "
                                 "eval.max_calibration_episodes allows (raise it, or alpha)") from None
            runs = more_calibration_episodes(exp, runs, short.more, cap=cap, **kw)


def more_calibration_episodes(exp, runs: list[dict], more: int, *, cap: int, **kw) -> list[dict]:
    """``runs`` and up to ``more`` further ID calibration episodes on the next unused seeds, ``cap`` in all
    (``kw``: :func:`calibration_episodes`' ``num_envs``, ``progress``, ``parallel``)."""
    return runs + calibration_episodes(exp, episodes=min(more, cap - len(runs)),
                                       seed=max(e["seed"] for e in runs) + 1,
                                       first_seed=min(e["seed"] for e in runs), **kw)
