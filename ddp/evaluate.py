"""Evaluation: the protocols of :mod:`ddp.protocols` (the paper's Table 1 conditions) run through
TorchRL collectors; results.json, table.md and plots written per run."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ddp.envs.chunked import ChunkedEnv, chunk_render_config
from ddp.errors import RecipeError
from ddp import results_json
from ddp.contracts import Calibratable
from ddp.protocols.base import EvalProtocol, check_protocols, get_protocol
from ddp.video import VideoSettings


def _env_overrides(exp, protocol: EvalProtocol, max_steps: int | None) -> dict:
    fields = {f.name for f in dataclasses.fields(exp.parts["env"].config)}
    over = dict(exp.recipe.eval.env)
    over.update(protocol.env)
    over.update({k: v for k, v in protocol.env_if_supported.items() if k in fields})
    if protocol.env_tracking and exp.recipe.eval.env_oracle_tracking:
        over["oracle_tracking"] = True
    if protocol.occlusion:
        over.update(occlusion_chunk=exp.recipe.eval.occlusion_chunk, occlusion_chunks=exp.recipe.eval.occlusion_chunks)
    if max_steps is not None:
        over["max_episode_steps"] = max_steps
    missing = sorted(set(over) - fields)
    if missing:
        raise RecipeError(
            f"env '{exp.parts['env'].plugin.name}' does not support {', '.join(missing)} needed by this protocol",
            source=exp.source, key="env",
        )
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
        base = registry.get("env", self.plugin).factory(cfg, seed=self.seed)
        return ChunkedEnv(base, self.action_steps, self.obs_steps, safe_lift=self.safe_lift, video=self.video)


def env_factory(exp, seed: int, overrides: dict | None = None, video: VideoSettings | None = None) -> ChunkedEnvFactory:
    pol, part = exp.recipe.policy, exp.parts["env"]
    return ChunkedEnvFactory(
        plugin=part.plugin.name, config=dataclasses.replace(part.config, **(overrides or {})),
        action_steps=pol.action_steps, obs_steps=pol.obs_steps, safe_lift=exp.recipe.controller.safe_lift,
        seed=seed, video=video, plugin_modules=exp.plugin_modules,
    )


def make_chunked_env(exp, seed: int, overrides: dict | None = None, video: VideoSettings | None = None) -> ChunkedEnv:
    return env_factory(exp, seed, overrides, video)()


def _chunks_per_episode(exp, overrides: dict) -> int:
    cfg = dataclasses.replace(exp.parts["env"].config, **overrides)
    steps = getattr(cfg, "max_episode_steps", None)
    if steps is None:
        raise RecipeError("the env config has no max_episode_steps; set eval.max_steps", source=exp.source, key="eval")
    return math.ceil(steps / exp.recipe.policy.action_steps)


def rollout_episodes(exp, controller, *, episodes: int, seed: int, overrides: dict, num_envs: int = 1,
                     desc: str = "", progress: bool = True, parallel: bool = False,
                     video: VideoSettings | None = None) -> list[dict]:
    """Run ``episodes`` seeded episodes with a torchrl Collector; one dict of results per episode.

    ``num_envs > 1`` steps several envs as one batch: in this process (``SerialEnv``) or, with
    ``parallel=True``, each in its own worker process (``ParallelEnv``). Env ``i`` runs the
    seeds ``seed + i * ceil(episodes / num_envs) + 0, 1, ...``. ``video`` records each env's
    first ``video.episodes`` episodes.
    """
    from torchrl.collectors import Collector
    from torchrl.envs import ParallelEnv, SerialEnv

    chunks = _chunks_per_episode(exp, overrides)
    num_envs = max(1, min(num_envs, episodes))
    per_env = math.ceil(episodes / num_envs)

    def factory(i: int) -> ChunkedEnvFactory:
        first = seed + i * per_env
        vid = None if video is None else dataclasses.replace(video, first_seed=first)
        return env_factory(exp, first, overrides, vid)

    if num_envs == 1:
        env = factory(0)()
    else:
        batched = ParallelEnv if parallel else SerialEnv
        env = batched(num_envs, [factory(i) for i in range(num_envs)])
    controller.reset()
    collector = Collector(
        env, controller, frames_per_batch=chunks * num_envs, total_frames=chunks * num_envs * per_env,
        reset_when_done=True, trust_policy=True, auto_register_policy_transforms=False,
    )
    results: list[dict] = []
    bar = tqdm(total=episodes, desc=desc, disable=not progress, unit="ep")
    try:
        for batch in collector:
            batch = batch.reshape(num_envs, chunks) if batch.batch_dims == 1 else batch
            for i in range(num_envs):
                traj = batch[i]
                if len(results) >= episodes:
                    break
                ep = i * per_env + len([r for r in results if r["env"] == i])
                results.append(_summarise(traj, env_index=i, seed=seed + ep))
                bar.update(1)
                bar.set_postfix(success=f"{np.mean([r['success'] for r in results]):.2f}")
            if len(results) >= episodes:
                break
    finally:
        bar.close()
        collector.shutdown()
        env.close(raise_if_closed=False)
    return sorted(results, key=lambda r: r["seed"])


def _summarise(traj, env_index: int, seed: int) -> dict:
    success = traj.get(("next", "success")).reshape(-1)
    out = {
        "seed": seed,
        "env": env_index,
        "success": bool(success.any()),
        "chunks": int(traj.batch_size[0]),
        "first_success_chunk": int(success.nonzero()[0]) if bool(success.any()) else None,
    }
    for key in ("mode", "imagined", "discrepancy"):
        if ("ddp", key) in traj.keys(True):
            out[key] = traj.get(("ddp", key)).reshape(-1).float().tolist()
    return out


def calibration_values(exp, *, episodes: int, seed: int, num_envs: int = 1, progress: bool = True,
                       parallel: bool = False) -> tuple[list[float], list[int]]:
    """D_R-I values observed in ID rollouts of the base policy, and the chunk index of each."""
    # the base policy, with the world model's forecast made every cycle so that D_R-I is measured
    ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True)
    res = rollout_episodes(exp, ctrl, episodes=episodes, seed=seed, overrides=dict(exp.recipe.eval.env), num_envs=num_envs,
                           desc="calibrate tau", progress=progress, parallel=parallel)
    pairs = [(v, c) for r in res for c, v in enumerate(r.get("discrepancy", [])) if not math.isnan(v)]
    return [v for v, _ in pairs], [c for _, c in pairs]


def calibrate_tau(exp, detector, *, episodes: int, seed: int, num_envs: int = 1, progress: bool = True,
                  parallel: bool = False) -> float:
    """Set a discrepancy detector's tau (and per-chunk thresholds) from D_R-I in ID rollouts; return tau."""
    values, chunks = calibration_values(exp, episodes=episodes, seed=seed, num_envs=num_envs, progress=progress,
                                        parallel=parallel)
    return detector.calibrate(values, chunks=chunks)


def evaluate(exp, protocols=None, *, episodes: int | None = None, output_dir: str | Path | None = None,
             progress: bool = True, num_envs: int | None = None, seed: int | None = None,
             video: bool | None = None, parallel: bool | None = None) -> dict:
    """Run the named protocols; write results.json, table.md and plots under ``output_dir``.

    With ``video`` (default ``eval.video``) the first ``eval.video_episodes`` episodes of each
    env are recorded under ``output_dir/videos/<protocol>/seed<N>.mp4`` (GIF without the
    ``video`` extra), labelled with the controller's mode.
    """
    cfg = exp.recipe.eval
    if exp.parts.get("env") is None:
        raise RecipeError("evaluation needs an env section", source=exp.source, key="env")
    if protocols is None:
        protocols = list(cfg.protocols)
    else:
        protocols = list(protocols)
        check_protocols(protocols, source="--protocols")
        if not protocols:
            raise RecipeError("no protocol given", source="--protocols")
    episodes = cfg.episodes if episodes is None else episodes
    num_envs = cfg.num_envs if num_envs is None else num_envs
    for flag, value in (("--episodes", episodes), ("--num-envs", num_envs)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise RecipeError(f"must be a whole number >= 1; got {value!r}", source=flag)
    seed = cfg.seed if seed is None else seed
    video = cfg.video if video is None else video
    parallel = cfg.parallel if parallel is None else parallel
    out_dir = Path(output_dir or cfg.output_dir.format(name=exp.recipe.name))
    out_dir.mkdir(parents=True, exist_ok=True)
    from ddp.train import resolve_device

    exp.model.to(resolve_device(cfg.device, source=exp.source, key="eval.device"))  # the envs stay on the CPU; the controller moves tensors
    report = {"recipe": exp.recipe.name, "episodes": episodes, "seed": seed, "protocols": {}}
    calibration = None  # thresholds calibrated once, on ID rollouts, for every protocol that needs them
    for name in protocols:
        proto = get_protocol(name)
        overrides = _env_overrides(exp, proto, cfg.max_steps)
        ctrl = exp.make_controller(detector=proto.detector, imagine=proto.imagine, tracker=proto.tracker)
        if isinstance(ctrl.detector, Calibratable) and ctrl.detector.needs_calibration:
            if calibration is None:
                calibrate_tau(exp, ctrl.detector, episodes=cfg.calibration_episodes, seed=seed + 100_000,
                              num_envs=num_envs, progress=progress, parallel=parallel)
                calibration = ctrl.detector.calibration()
            ctrl.detector.load_calibration(calibration)
        vid = None
        if video:
            vid = VideoSettings(str(out_dir / "videos" / name), episodes=cfg.video_episodes, size=cfg.video_size,
                                fps=cfg.video_fps, camera=cfg.video_camera)
        t0 = time.perf_counter()
        res = rollout_episodes(exp, ctrl, episodes=episodes, seed=seed, overrides=overrides, num_envs=num_envs,
                               desc=name, progress=progress, parallel=parallel, video=vid)
        rate = float(np.mean([r["success"] for r in res]))
        thresholds = ctrl.detector.calibration() if isinstance(ctrl.detector, Calibratable) else {}
        report["protocols"][name] = {
            "success_rate": rate,
            "successes": int(sum(r["success"] for r in res)),
            "episodes": len(res),
            "seconds": time.perf_counter() - t0,
            "tau": thresholds.get("tau"),
            "tau_per_chunk": thresholds.get("tau_per_chunk"),
            "per_episode": res,
        }
        if vid is not None:
            files = sorted(p for p in Path(vid.directory).glob("seed*") if p.suffix in (".mp4", ".gif"))
            report["protocols"][name]["videos"] = [str(p) for p in files]
    (out_dir / "results.json").write_text(results_json.dumps(report))  # strict JSON: NaN -> null
    (out_dir / "table.md").write_text(markdown_table({exp.recipe.name: report}))
    from ddp.plots import plot_report

    report["plots"] = [str(p) for p in plot_report(report, out_dir)]
    return report


def markdown_table(reports: dict[str, dict]) -> str:
    """Success rates (%) laid out like the paper's Table 1: one row per method / condition."""
    protocols = list(dict.fromkeys(p for r in reports.values() for p in r["protocols"]))  # first-seen order
    lines = ["| method | " + " | ".join(protocols) + " |", "|---|" + "---|" * len(protocols)]
    for name, rep in reports.items():
        cells = []
        for p in protocols:
            r = rep["protocols"].get(p)
            cells.append("-" if r is None else f"{100 * r['success_rate']:.0f} ({r['successes']}/{r['episodes']})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
