"""``evaluate()``: run a recipe's evaluation protocols and report them, top to bottom.

1. settle the settings (the recipe's ``eval`` section, overridden by arguments, checked);
2. for each protocol: its env overrides and controller, the detector's statistic and threshold
   calibrated once on ID rollouts when it needs them (or read from the calibration saved beside
   the checkpoint, ``ddp.calibration_file``), the episodes (:mod:`ddp.eval_runner`), and the
   detection metrics of every protocol whose detector decides (:mod:`ddp.detection`);
3. write results.json, table.md and plots (:mod:`ddp.eval_report`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from ddp import results_json
from ddp.contracts import Calibratable
from ddp.detection import detection_metrics
from ddp.errors import DDPError, RecipeError
from ddp.eval_report import markdown_table, protocol_result, write_report  # noqa: F401 (re-exported)
from ddp.eval_runner import (  # noqa: F401 (re-exported: the runner's public names)
    ChunkedEnvFactory, calibrate_detector, calibration_env, calibration_episodes, env_factory, env_overrides, make_chunked_env,
    evaluation_blocks, rollout_episodes, check_video_camera,
)
from ddp.protocols.base import check_protocols, check_protocols_for_model, get_protocol
from ddp.video import VideoSettings

_env_overrides = env_overrides  # the name earlier code used

__all__ = [
    "evaluate", "settle", "EvalSettings", "markdown_table", "protocol_result", "write_report", "ChunkedEnvFactory",
    "calibrate_detector", "calibration_episodes", "env_factory", "env_overrides", "make_chunked_env", "rollout_episodes",
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
    named = {"source": exp.source, "key": "eval.protocols"}  # where the names came from, for the errors below
    if protocols is None:
        protocols = list(cfg.protocols)
    else:
        named = {"source": "--protocols"}
        protocols = [protocols] if isinstance(protocols, str) else list(protocols)  # evaluate("id"): one name
        check_protocols(protocols, source="--protocols")
        if not protocols:
            raise RecipeError("no protocol given", source="--protocols")
    check_protocols_for_model(protocols, has_world_model=exp.model.has_world_model, **named)
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
    device = resolve_device(cfg.device, source=exp.source, key="eval.device")
    exp.model.to(device)  # envs stay on the CPU
    runs = dict(num_envs=s.num_envs, progress=progress, parallel=s.parallel)
    report = {"recipe": exp.recipe.name, "episodes": s.episodes, "seed": s.seed, "protocols": {},
              **provenance(exp, s, device)}
    calibrations: dict[str, dict] = {}  # per detector section: calibrated once, on ID rollouts
    # every protocol's controller is built before any rollout: a part the env cannot serve (e.g. an oracle on
    # a real robot) is refused before the first episode runs
    plan = []
    for name in s.protocols:
        protocol = get_protocol(name)
        overrides = env_overrides(exp, protocol, cfg.max_steps)
        # where the env's own oracle tracks (this protocol's overrides, else the recipe's env section), the
        # controller does not track too
        env_tracks = overrides.get("oracle_tracking", (exp.resolved.get("env") or {}).get("oracle_tracking", False))
        tracker = protocol.tracker and not env_tracks
        plan.append((name, protocol, overrides,
                     exp.make_controller(detector=protocol.detector, imagine=protocol.imagine, tracker=tracker,
                                         env=overrides)))
    if s.video:
        check_video_camera(exp, plan[0][2], cfg.video_camera)
    for name, protocol, overrides, ctrl in plan:
        section = _detector_section(exp, protocol)
        if not isinstance(ctrl.detector, Calibratable) and callable(getattr(ctrl.detector, "calibrate", None)):
            import warnings

            warnings.warn(f"detector {type(ctrl.detector).__name__} has calibrate() but not the whole Calibratable "
                          "contract (needs_calibration, calibration, load_calibration): it is not calibrated",
                          stacklevel=2)
        if isinstance(ctrl.detector, Calibratable) and ctrl.detector.needs_calibration:
            key = results_json.dumps(section)
            if key not in calibrations:
                calibrations[key] = _calibration(exp, ctrl.detector, section, seed=report["calibration_seed"],
                                                 model_hash=report["model_digest"], runs=runs)
            ctrl.detector.load_calibration(calibrations[key])
        vid = None
        if s.video:
            vid = VideoSettings(str(s.out_dir / "videos" / name), episodes=cfg.video_episodes, size=cfg.video_size,
                                fps=cfg.video_fps, camera=cfg.video_camera)
        t0, started = time.perf_counter(), time.time()
        episodes_run = []
        for i, (block, first, n) in enumerate(evaluation_blocks(exp, overrides, s.seed, s.episodes)):
            episodes_run += rollout_episodes(exp, ctrl, episodes=n, seed=first, overrides=block, desc=name,
                                             video=vid if i == 0 else None, **runs)
        videos = None
        if vid is not None:
            # this evaluation's own: an earlier run's files in the same folder (other seeds, more episodes) are not
            names = {f"{vid.prefix}{e['seed']}" for e in episodes_run}
            videos = [str(p) for p in sorted(Path(vid.directory).glob(f"{vid.prefix}*"))
                      if p.suffix in (".mp4", ".gif") and p.stem in names and p.stat().st_mtime >= started - 1]
        thresholds = ctrl.detector.calibration() if isinstance(ctrl.detector, Calibratable) else {}
        detection = None
        if getattr(ctrl.detector, "decides", True):  # (the contract's optional flag)
            detection = detection_metrics(episodes_run, reference=thresholds.get("reference"))
        report["protocols"][name] = protocol_result(episodes_run, seconds=time.perf_counter() - t0,
                                                    thresholds=thresholds, videos=videos, detection=detection,
                                                    detector=section)
    write_report(report, s.out_dir)  # sets report["plots"]
    return report


def provenance(exp, s: EvalSettings, device) -> dict:
    """What reproduces an evaluation beside its seeds: the code, the weights, the recipe as run (every --set
    and Python change) and its parts with their defaults, how episodes were batched and where the model ran,
    the detector calibration's seed."""
    from ddp.calibration_file import model_digest
    from ddp.config import to_dict
    from ddp.suite.provenance import code_version

    weights = None
    if exp.checkpoint_path is not None:
        weights = {"path": str(exp.checkpoint_path), "weights": exp.checkpoint_weights}
    return {"num_envs": s.num_envs, "parallel": s.parallel, "device": str(device),
            "calibration_seed": s.seed + 100_000, "checkpoint": weights, "model_digest": model_digest(exp.model),
            "code": code_version(), "settings": to_dict(exp.recipe),  # as run: changes made in Python included
            "parts": {key: part.as_dict() for key, part in exp.parts.items() if part is not None}}  # with defaults


def _detector_section(exp, protocol) -> dict:
    """The detector section a protocol runs: its own, or the recipe's (resolved, defaults filled)."""
    from ddp.schema import resolve_part

    if protocol.detector is not None:
        return resolve_part("detector", protocol.detector, key="controller.detector", source="<protocol>").as_dict()
    return exp.parts["controller.detector"].as_dict()


def _calibration(exp, detector, section: dict, *, seed: int, model_hash: str, runs: dict) -> dict:
    """The detector's calibration: read from beside the checkpoint when it was made for this model
    (``model_hash``: its weights' digest, computed once per evaluation), detector, ID env and sampling setup,
    else fitted on ``eval.calibration_episodes`` ID rollouts and saved there."""
    from ddp.calibration_file import calibration_path, load_calibration, save_calibration

    cfg = exp.recipe.eval
    # the ID env the scores come from: the recipe's env section (cloud size, camera, noise, ...), the
    # evaluation's overrides of it, and the chunking (a chunk's actions and the stacked observations)
    id_env = {"env": exp.resolved["env"], "overrides": calibration_env(exp),
              "obs_steps": exp.model.obs_steps, "action_steps": exp.model.action_steps}
    # (the controller's seed too: it seeds the calibration rollouts' policy and forecast noise)
    sampling = {"policy": exp.resolved["policy"]["scheduler"], "world_model": exp.resolved["world_model"]["scheduler"],
                "forecast_samples": exp.recipe.controller.forecast_samples, "controller_seed": exp.recipe.seed}
    key = dict(model_hash=model_hash, detector=section, id_env=id_env,
               episodes=cfg.calibration_episodes, max_episodes=cfg.max_calibration_episodes, seed=seed,
               sampling=sampling, device=next(exp.model.parameters()).device.type)
    path = calibration_path(exp.checkpoint_path) if exp.checkpoint_path is not None else None
    saved = load_calibration(path, **key) if path is not None else None
    if saved is not None:
        return saved
    try:
        calibrate_detector(exp, detector, episodes=cfg.calibration_episodes, seed=seed, **runs)
    except DDPError:  # already one line naming its own key or file (e.g. a camera calibration file)
        raise
    except ValueError as err:  # e.g. too few ID episodes for alpha
        raise RecipeError(str(err), source=exp.source, key="controller.detector") from None
    calibration = detector.calibration()
    if path is not None:
        save_calibration(path, calibration, checkpoint=str(exp.checkpoint_path), **key)
    return calibration
