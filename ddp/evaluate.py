"""``evaluate()``: run a recipe's evaluation protocols and report them, top to bottom.

1. settle the settings (the recipe's ``eval`` section, overridden by arguments, checked);
2. for each protocol: its env overrides and controller, a discrepancy threshold calibrated
   once on ID rollouts when the detector needs one, the episodes (:mod:`ddp.eval_runner`);
3. write results.json, table.md and plots (:mod:`ddp.eval_report`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from ddp.contracts import Calibratable
from ddp.errors import RecipeError
from ddp.eval_report import markdown_table, protocol_result, write_report  # noqa: F401 (re-exported)
from ddp.eval_runner import (  # noqa: F401 (re-exported: the runner's public names)
    ChunkedEnvFactory, calibrate_tau, calibration_values, env_factory, env_overrides, make_chunked_env,
    rollout_episodes,
)
from ddp.protocols.base import check_protocols, get_protocol
from ddp.video import VideoSettings

_env_overrides = env_overrides  # the name earlier code used

__all__ = [
    "evaluate", "settle", "EvalSettings", "markdown_table", "protocol_result", "write_report", "ChunkedEnvFactory",
    "calibrate_tau", "calibration_values", "env_factory", "env_overrides", "make_chunked_env", "rollout_episodes",
]


@dataclass
class EvalSettings:
    protocols: list[str]
    episodes: int
    num_envs: int
    seed: int
    video: bool
    parallel: bool
    out_dir: Path


def settle(exp, protocols, *, episodes, output_dir, num_envs, seed, video, parallel) -> EvalSettings:
    """The recipe's ``eval`` section with the arguments that override it, each checked."""
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
    return EvalSettings(
        protocols=protocols, episodes=episodes, num_envs=num_envs, seed=cfg.seed if seed is None else seed,
        video=cfg.video if video is None else video, parallel=cfg.parallel if parallel is None else parallel,
        out_dir=Path(output_dir or cfg.output_dir.format(name=exp.recipe.name)),
    )


def evaluate(exp, protocols=None, *, episodes: int | None = None, output_dir: str | Path | None = None,
             progress: bool = True, num_envs: int | None = None, seed: int | None = None,
             video: bool | None = None, parallel: bool | None = None) -> dict:
    """Run the named protocols; write results.json, table.md and plots under ``output_dir``.

    With ``video`` (default ``eval.video``) the first ``eval.video_episodes`` episodes of each
    env are recorded under ``output_dir/videos/<protocol>/seed<N>.mp4`` (GIF without the
    ``video`` extra), labelled with the controller's mode.
    """
    from ddp.train import resolve_device

    s = settle(exp, protocols, episodes=episodes, output_dir=output_dir, num_envs=num_envs, seed=seed, video=video,
               parallel=parallel)
    cfg = exp.recipe.eval
    exp.model.to(resolve_device(cfg.device, source=exp.source, key="eval.device"))  # envs stay on the CPU
    runs = dict(num_envs=s.num_envs, progress=progress, parallel=s.parallel)
    report = {"recipe": exp.recipe.name, "episodes": s.episodes, "seed": s.seed, "protocols": {}}
    calibration = None  # thresholds calibrated once, on ID rollouts, for every protocol that needs them
    for name in s.protocols:
        protocol = get_protocol(name)
        overrides = env_overrides(exp, protocol, cfg.max_steps)
        ctrl = exp.make_controller(detector=protocol.detector, imagine=protocol.imagine, tracker=protocol.tracker)
        if not isinstance(ctrl.detector, Calibratable) and callable(getattr(ctrl.detector, "calibrate", None)):
            import warnings

            warnings.warn(f"detector {type(ctrl.detector).__name__} has calibrate() but not the whole Calibratable "
                          "contract (needs_calibration, calibration, load_calibration): it is not calibrated",
                          stacklevel=2)
        if isinstance(ctrl.detector, Calibratable) and ctrl.detector.needs_calibration:
            if calibration is None:
                calibrate_tau(exp, ctrl.detector, episodes=cfg.calibration_episodes, seed=s.seed + 100_000, **runs)
                calibration = ctrl.detector.calibration()
            ctrl.detector.load_calibration(calibration)
        vid = None
        if s.video:
            vid = VideoSettings(str(s.out_dir / "videos" / name), episodes=cfg.video_episodes, size=cfg.video_size,
                                fps=cfg.video_fps, camera=cfg.video_camera)
        t0 = time.perf_counter()
        episodes_run = rollout_episodes(exp, ctrl, episodes=s.episodes, seed=s.seed, overrides=overrides, desc=name,
                                        video=vid, **runs)
        videos = None
        if vid is not None:
            videos = [str(p) for p in sorted(Path(vid.directory).glob("seed*")) if p.suffix in (".mp4", ".gif")]
        thresholds = ctrl.detector.calibration() if isinstance(ctrl.detector, Calibratable) else {}
        report["protocols"][name] = protocol_result(episodes_run, seconds=time.perf_counter() - t0,
                                                    thresholds=thresholds, videos=videos)
    report["plots"] = [str(p) for p in write_report(report, s.out_dir)]
    return report
