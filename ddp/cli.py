"""The ``ddp`` command line: ``ddp list | recipe | summary | train | bench | demos | eval | detect | suite | run``."""

from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import os
import sys
import zipfile
from pathlib import Path

from ddp.errors import DDPError
from ddp.preemption import Preempted, resume_hint, stop_signals


def _add_recipe_args(p: argparse.ArgumentParser, optional: bool = False) -> None:
    if optional:
        p.add_argument("recipe", nargs="?", help="path to a YAML recipe (default: the one stored in the checkpoint)")
    else:
        p.add_argument("recipe", help="path to a YAML recipe")
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a recipe value, e.g. --set policy.scheduler.num_inference_steps=5 (repeatable)",
    )


def _at_least_one(**flags) -> None:
    """One line for a count flag below 1 (instead of a silent default or a deep error)."""
    for name, value in flags.items():
        if value is not None and value < 1:
            raise DDPError(f"--{name.replace('_', '-')}: must be >= 1; got {value}")


def _names(value: str | None, flag: str) -> list[str] | None:
    """A comma-separated flag's names; None when the flag is not given. Given but empty (``--protocols ""``, an
    unset shell variable) is an error, not "all of them"."""
    if value is None:
        return None
    names = [n.strip() for n in value.split(",") if n.strip()]
    if not names:
        raise DDPError(f"{flag}: empty; name at least one (leave the flag out for the default)")
    return names


def cmd_list(args) -> int:
    from ddp import registry

    kinds = [args.kind] if args.kind else list(registry.KINDS)
    for kind in kinds:
        entries = [p for p in registry.plugins(kind) if fnmatch.fnmatch(p.name, args.pattern)]
        print(f"{kind}: {registry.KINDS[kind][1]}")
        if not entries:
            print("  (none registered yet)" if args.pattern == "*" else f"  (none matching {args.pattern!r})")
        for p in entries:
            print(f"  {p.name:<20} {p.summary}  [{p.module}]")
    return 0


def cmd_recipe(args) -> int:
    from ddp.experiment import build

    print(build(args.recipe, args.overrides).to_yaml(), end="")
    return 0


def cmd_summary(args) -> int:
    from ddp.experiment import build

    exp = build(args.recipe, args.overrides)
    r = exp.recipe
    print(f"recipe: {exp.source} ({r.name})")
    print(f"  encoder      {exp.parts['encoder'].plugin.name} -> latent {exp.model.latent_dim} per step")
    print(
        f"  policy       {exp.parts['policy.denoiser'].plugin.name} + {exp.parts['policy.scheduler'].plugin.name}"
        f"  H={r.policy.horizon} M={r.policy.obs_steps} N={r.policy.action_steps}"
    )
    if r.world_model.enabled:
        print(
            f"  world model  {exp.parts['world_model.denoiser'].plugin.name} + "
            f"{exp.parts['world_model.scheduler'].plugin.name}  lambda={r.world_model.weight}"
        )
    else:
        print("  world model  disabled (DP3 baseline)")
    print("parameters:")
    for part, n in exp.parameter_counts().items():
        print(f"  {part:<12} {n:>12,d}  ({n / 1e6:.2f} M)")
    return 0


def cmd_train(args) -> int:
    from ddp.experiment import build

    from ddp.distributed import env_ranks

    exp = build(args.recipe, args.overrides)
    res = exp.train(output_dir=args.output_dir, resume=not args.no_resume, progress=not args.quiet)
    ranks = env_ranks()
    if not ranks.main:  # under torchrun only rank 0 reports
        return 0
    print(
        (f"{ranks.world} processes (torch DistributedDataParallel): " if ranks.enabled else "") +
        f"trained {res.steps} steps ({res.epochs} epochs) in {res.seconds:.1f} s, {res.samples_per_second:.0f} samples/s; "
        f"loss {res.loss:.4f} (bc {res.loss_bc:.4f}, lambda*wm {res.loss_wm:.4f}, L_WM {res.wm_error:.4f}); "
        f"checkpoint {res.checkpoint}"
    )
    return 0


def _print_eval(report: dict, out_dir) -> None:
    from ddp.evaluate import markdown_table

    print(markdown_table({report["recipe"]: report}), end="")
    print(f"results: {out_dir}/results.json, table: {out_dir}/table.md, plots: {', '.join(report.get('plots', [])) or 'none'}")
    videos = [v for p in report["protocols"].values() for v in p.get("videos", [])]
    if videos:
        print(f"videos: {len(videos)} under {out_dir}/videos/")


def cmd_eval(args) -> int:
    with stop_signals():  # SIGTERM / SIGHUP end it like Ctrl-C: the envs close (a real robot stops) in finally
        return _eval(args)


def _eval(args) -> int:
    from pathlib import Path

    from ddp.experiment import build, experiment_from_checkpoint

    protocols = _names(args.protocols, "--protocols")
    if args.recipe is None:  # the recipe stored in the checkpoint; its plugin modules only on --trust-plugins
        exp = experiment_from_checkpoint(args.checkpoint, ema=not args.raw_weights, trust_plugins=args.trust_plugins,
                                         overrides=args.overrides)
    else:
        exp = build(args.recipe, args.overrides)
        exp.load_checkpoint(args.checkpoint, ema=not args.raw_weights)
    out_dir = Path(args.output_dir or exp.recipe.eval.output_dir.format(name=exp.recipe.name))
    report = exp.evaluate(protocols, episodes=args.episodes, output_dir=out_dir, num_envs=args.num_envs,
                          progress=not args.quiet, video=True if args.video else None,
                          parallel=True if args.parallel else None)
    _print_eval(report, out_dir)
    return 0


def _env_overrides(pairs: list[str]) -> dict:
    """``KEY=VALUE`` pairs (values parsed as YAML) -> a dict; one line for a malformed pair."""
    import yaml

    from ddp.recipe import load_yaml

    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise DDPError(f"--env: expected KEY=VALUE, e.g. --env displacement_chunk=4; got {pair!r}")
        try:  # the recipes' YAML (1.2 numbers: 1e-2 is a float)
            out[key.strip()] = load_yaml(value)
        except yaml.YAMLError as err:
            raise DDPError(f"--env: {key.strip()}: not a YAML value ({str(err).splitlines()[0]}): {value!r}") from None
    return out


def cmd_detect(args) -> int:
    with stop_signals():  # as ddp eval: SIGTERM / SIGHUP close the envs on the way out
        return _detect(args)


def _detect(args) -> int:
    from pathlib import Path

    from ddp import results_json
    from ddp.atomic_file import atomic_write
    from ddp.calibration_file import model_digest
    from ddp.detection import (
        SCORE_VARIANTS, detect, format_detect, plot_detect, read_rollouts, save_rollouts, summary_json,
    )
    from ddp.errors import suggest
    from ddp.experiment import build, experiment_from_checkpoint

    _at_least_one(episodes=args.episodes, calibration_episodes=args.calibration_episodes, samples=args.samples,
                  num_envs=args.num_envs)
    if args.alpha is not None and not 0.0 < args.alpha < 1.0:
        raise DDPError(f"--alpha: must be in (0, 1); got {args.alpha}")
    variants = SCORE_VARIANTS
    if args.scores:
        names = [n.strip() for n in args.scores.split(",") if n.strip()]
        for n in names:
            if n not in SCORE_VARIANTS:
                raise DDPError(f"--scores: unknown score {n!r}{suggest(n, SCORE_VARIANTS)} "
                               f"(known: {', '.join(SCORE_VARIANTS)})")
        variants = {n: SCORE_VARIANTS[n] for n in names}
    if args.recipe is None:
        exp = experiment_from_checkpoint(args.checkpoint, trust_plugins=args.trust_plugins, overrides=args.overrides)
    else:
        exp = build(args.recipe, args.overrides)
        exp.load_checkpoint(args.checkpoint)
    disturbances = tuple(d.strip() for d in args.disturbances.split(",") if d.strip())
    from ddp.protocols.base import check_protocols

    check_protocols(disturbances, source="--disturbances")
    rollouts = made_with = None
    if args.rollouts:
        # how the rollouts were made is the file's: a flag that would change them is refused, not ignored
        ignored = [flag for flag, value in (("--episodes", args.episodes), ("--calibration-episodes",
                   args.calibration_episodes), ("--env", args.env or None), ("--samples", args.samples),
                   ("--seed", args.seed), ("--num-envs", args.num_envs), ("--parallel", args.parallel or None))
                   if value is not None]
        if ignored:
            raise DDPError(f"--rollouts scores saved rollouts: {', '.join(ignored)} would change how they are made, "
                           f"which the file fixes (drop {'it' if len(ignored) == 1 else 'them'}, or --rollouts to roll "
                           "out again)")
        if not Path(args.rollouts).is_file():
            raise DDPError(f"--rollouts: no such file: {args.rollouts}")
        try:
            rollouts, made_with = read_rollouts(args.rollouts)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as err:  # a truncated or foreign .npz
            raise DDPError(f"--rollouts: {args.rollouts} is not a ddp detect rollouts file ({err})") from None
        digest = model_digest(exp.model)
        if made_with is not None and made_with.get("model") != digest:
            raise DDPError(f"--rollouts: {args.rollouts} was rolled out with other weights (digest "
                           f"{made_with.get('model')}; this checkpoint's {digest}): drop --rollouts to roll out "
                           f"this one")
    try:
        # the recipe detector's alpha (what its evaluations calibrate to), unless --alpha says otherwise
        alpha = args.alpha if args.alpha is not None else getattr(exp.parts["controller.detector"].config, "alpha", 0.05)
        rep = detect(exp, episodes=10 if args.episodes is None else args.episodes,
                     calibration_episodes=args.calibration_episodes, alpha=alpha,
                     seed=args.seed, disturbances=disturbances, env=_env_overrides(args.env), variants=variants,
                     progress=not args.quiet, num_envs=1 if args.num_envs is None else args.num_envs,
                     parallel=args.parallel,
                     samples=args.samples, rollouts=rollouts, threshold_on=args.threshold_on)
    except ValueError as err:
        raise DDPError(str(err)) from None
    made = ("seed", "env", "forecast_samples")
    if rollouts is not None and made_with is not None:  # the header says how the scored rollouts were made
        rep.update({k: made_with[k] for k in made if k in made_with})
    out = Path(args.output_dir or Path(args.checkpoint).parent / "detect")
    out.mkdir(parents=True, exist_ok=True)
    if rollouts is None:
        save_rollouts(rep["rollouts"], out / "detect_rollouts.npz",
                      provenance={"model": model_digest(exp.model), **{k: rep[k] for k in made}})
    for name, text in (("detect.json", results_json.dumps(summary_json(rep))),
                       ("detect_traces.json", results_json.dumps(rep["traces"], indent=None)),
                       ("detect.md", format_detect(rep))):
        atomic_write(out / name, lambda f: f.write(text), binary=False)
    for score in rep["traces"]:
        plot_detect(rep, score, out / f"detect_{score}.png")
    print(format_detect(rep))
    print(f"wrote {out}/detect.json, detect.md, detect_traces.json, one detect_<score>.png per score"
          + ("" if rollouts else " and detect_rollouts.npz (--rollouts scores new statistics without rolling out)"))
    return 0


def cmd_suite(args) -> int:
    from ddp.file_lock import exclusive_lock
    from ddp.suite import SuiteRunsFailed, load_suite, run_suite, select
    from ddp.suite.budget import SuiteTimeLimit, estimate_seconds, fmt_minutes, parse_duration, stored_results, total_expected
    from ddp.suite.reevaluate import plan_reevaluation
    from ddp.suite.store import ResultStore
    from ddp.suite.superseded import superseded

    _at_least_one(workers=args.workers, threads=args.threads)
    if args.ray is not None and args.workers is not None:
        raise DDPError("--workers and --ray are alternatives: Ray places each run itself (leave out --workers)")
    if args.gpus_per_run and args.ray is None:
        raise DDPError(f"--gpus-per-run {args.gpus_per_run} needs --ray (the process pool does not place GPUs)")
    if args.gpus_per_run < 0:
        raise DDPError(f"--gpus-per-run: must be >= 0; got {args.gpus_per_run}")
    suite = load_suite(args.suite)
    try:
        seeds = [int(s) for s in args.seeds.split(",")] if args.seeds is not None else None
    except ValueError:
        raise DDPError(f"--seeds takes comma-separated integers, got {args.seeds!r}") from None
    chosen = select(suite, tasks=_names(args.tasks, "--tasks"), methods=_names(args.methods, "--methods"),
                    seeds=seeds)
    reevaluate = None
    if args.reevaluate is not None:
        from ddp.protocols.base import check_protocols

        reevaluate = list(dict.fromkeys(p.strip() for p in args.reevaluate.split(",") if p.strip()))
        if not reevaluate:
            raise DDPError("--reevaluate needs at least one protocol name, e.g. --reevaluate id_ddp,ood_ddp")
        if args.report:
            raise DDPError("--reevaluate runs protocols; --report only aggregates what is stored")
        check_protocols(reevaluate, source="--reevaluate")
    time_limit = parse_duration(args.time_limit) if args.time_limit is not None else None
    if time_limit is not None and args.report:
        raise DDPError("--time-limit limits the runs; --report only aggregates what is stored")
    if args.dry_run:
        store, counts = ResultStore(suite.results_dir, restamp=False), {"done": 0, "stale": 0, "missing": 0}
        again = {r.run_id for r in plan_reevaluation(store, chosen.runs, reevaluate)} if reevaluate else set()
        stored, expected = stored_results(suite.results_dir), []
        resumes = retrains = 0
        for run in chosen.runs:
            state = store.status(run)
            counts[state] += 1
            out = run.recipe["train"]["output_dir"]
            protocols = ",".join(run.protocols) if run.protocols else "the recipe's"
            what = f"{run.recipe['name']}, protocols {protocols}, -> {out}"
            if run.run_id in again:
                cost, why = estimate_seconds(dataclasses.replace(run, reevaluate=tuple(reevaluate)), stored)
                expected.append(cost)
                print(f"{run.run_id}: stale, re-evaluates {', '.join(reevaluate)} from {out}/last.pt (keeps the "
                      f"others); {what}; expected {fmt_minutes(cost)} ({why})")
                continue
            found = state != "done" and (Path(out) / "last.pt").is_file()
            changed = superseded(out, run.recipe, args.suite) if found else None
            resumes += found and not changed
            retrains += bool(changed)
            label = {"done": "done", "stale": "stale (its recipe changed: runs again)", "missing": "to run"}[state]
            if changed:
                label += (f", trains from scratch (its last.pt cannot continue this recipe: {changed}; the folder "
                          "will be set aside)")
            elif found:
                label += f", resumes {out}/last.pt"
            if state != "done":
                cost, why = estimate_seconds(run, stored)
                expected.append(cost)
                what += f"; expected {fmt_minutes(cost)} ({why})"
            print(f"{run.run_id}: {label}; {what}")
        cost = ""
        if expected:
            cost = (f"; expected {total_expected(expected)}"
                    + (f", time limit {fmt_minutes(time_limit)}" if time_limit is not None else ""))
        print(f"{len(chosen.runs)} runs: {counts['done']} done, {counts['stale'] + counts['missing']} to run "
              f"({counts['stale']} stale, {resumes} resuming a checkpoint, {retrains} setting one aside"
              + (f", {len(again)} re-evaluating" if reevaluate else "") + f"); results in {suite.results_dir}" + cost)
        return 0
    failed = None
    if not args.report:
        ray = (args.ray or True) if args.ray is not None else False
        try:
            run_suite(chosen, workers=args.workers or 1, threads=args.threads, progress=not args.quiet, ray=ray,
                      gpus_per_run=args.gpus_per_run, reevaluate=reevaluate, time_limit=time_limit)
        except (SuiteRunsFailed, SuiteTimeLimit) as err:  # the table still shows what finished
            failed = err
    if not Path(suite.results_dir).is_dir():  # nothing stored: nothing to lock (nor a folder to make)
        return _suite_report(suite, failed)
    with exclusive_lock(Path(suite.results_dir) / "report"):  # another suite process's report waits: the
        return _suite_report(suite, failed)  # last one written read the store last


def _suite_report(suite, failed) -> int:
    """The suite's report from every stored run (under the report lock), and the exit status."""
    from ddp.suite import write_suite_report
    from ddp.suite.budget import EXIT_TIME_LIMIT, SuiteTimeLimit
    from ddp.suite.store import ResultStore

    done = ResultStore(suite.results_dir).all(suite.runs)  # the table covers every stored run
    # labelled as the suite file labels them now (a task's benchmark is no part of a run's identity)
    results = [{**done[r.run_id], "task": r.task, "method": r.method, "seed": r.seed, "benchmark": r.benchmark}
               for r in suite.runs if r.run_id in done]
    if not results:
        if isinstance(failed, SuiteTimeLimit):
            print(f"ddp: {failed} (no finished run yet: no table)", file=sys.stderr)
            return EXIT_TIME_LIMIT
        if failed is not None:  # a failed run exits 1 (README), whether or not another run finished
            print(f"ddp: {failed}", file=sys.stderr)
            return 1
        raise DDPError(f"no finished runs of suite {suite.name!r} in {suite.results_dir} yet")
    paths = write_suite_report(results, suite.results_dir, f"suite {suite.name} ({len(results)}/{len(suite.runs)} runs)",
                               reference=suite.reference, tasks_of_suite=suite.tasks)
    print(paths[0].read_text(), end="")  # (no other process writes it while the lock is held)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    if isinstance(failed, SuiteTimeLimit):
        print(f"ddp: {failed}", file=sys.stderr)
        return EXIT_TIME_LIMIT
    if failed is not None:
        print(f"ddp: error: {failed}", file=sys.stderr)
        return 1
    return 0


def cmd_run(args) -> int:
    with stop_signals():  # SIGTERM / SIGHUP end it like Ctrl-C: a checkpoint is saved, envs close (a robot stops)
        return _run(args)


def _run(args) -> int:
    from pathlib import Path

    from ddp.evaluate import markdown_table
    from ddp.experiment import build

    _at_least_one(jobs=args.jobs, episodes=args.episodes)
    protocols = _names(args.protocols, "--protocols")
    if protocols is not None:  # a misspelt name is found now, not after the training
        from ddp.protocols.base import check_protocols

        check_protocols(protocols, source="--protocols")
    from ddp.evaluate import settle

    # every recipe built and its evaluation settled before any trains (side by side too): a typo in the second
    # recipe, or a protocol the DP3 baseline cannot run, is found now, not after the first recipe's training
    # (each is built again before it trains: a build seeds torch, so a run trains as it would alone)
    for recipe in args.recipes:
        settle(build(recipe, args.overrides), protocols, episodes=args.episodes, output_dir=None, num_envs=None,
               seed=None, video=None, parallel=None)
    if args.jobs > 1 and len(args.recipes) > 1:
        return _run_jobs(args)
    reports = {}
    for recipe in args.recipes:
        exp = build(recipe, args.overrides)
        res = exp.train(resume=not args.no_resume, progress=not args.quiet)
        print(f"[{exp.recipe.name}] trained {res.steps} steps in {res.seconds:.0f} s; loss {res.loss:.4f}")
        exp.load_checkpoint(res.checkpoint)
        out_dir = Path(exp.recipe.eval.output_dir.format(name=exp.recipe.name))
        report = exp.evaluate(protocols, episodes=args.episodes, output_dir=out_dir, progress=not args.quiet)
        reports[exp.recipe.name] = report
        print(f"[{exp.recipe.name}] results in {out_dir}")
    print(markdown_table(reports), end="")
    return 0


def _run_jobs(args) -> int:
    """``ddp run --jobs N``: the recipes side by side in child processes (:mod:`ddp.run_jobs`)."""
    from ddp.evaluate import markdown_table
    from ddp.run_jobs import JobsFailed, plan_jobs, run_jobs, threads_per_job

    parallel = min(args.jobs, len(args.recipes))
    threads = threads_per_job(parallel)
    jobs = plan_jobs(args.recipes, args.overrides, threads=threads, protocols=args.protocols,
                     episodes=args.episodes, no_resume=args.no_resume, quiet=args.quiet)
    print(f"{len(jobs)} recipes, {parallel} at a time, {threads} thread(s) each")
    try:
        reports = run_jobs(jobs, parallel=parallel, threads=threads)
    except JobsFailed as err:
        if err.reports:
            print(markdown_table(err.reports), end="")
        print(f"ddp: error: {err}", file=sys.stderr)
        return 1
    print(markdown_table(reports), end="")
    return 0


def cmd_bench(args) -> int:
    import torch

    from ddp.bench import bench, compare
    from ddp.experiment import build

    _at_least_one(repeats=args.repeats, threads=args.threads)
    if args.threads:
        torch.set_num_threads(args.threads)
    exp = build(args.recipe, args.overrides)
    model = exp.model
    steps = f"policy {model.policy_scheduler.inference_steps}" + (
        f" / world model {model.world_model_scheduler.inference_steps}" if model.has_world_model else "")
    print(f"{exp.recipe.name}: batch 1, {steps} denoising steps, device {args.device}, {torch.get_num_threads()} threads")
    if args.no_baseline or not exp.recipe.world_model.enabled:
        for k, v in bench(exp, repeats=args.repeats, device=args.device).items():
            unit = "" if k.endswith("per_s") else " ms"
            print(f"  {k:<24} {v:10.1f}{unit}")
        return 0
    print(f"  {'stage':<24} {exp.recipe.name[:12]:>12} {'dp3_baseline':>12} {'ratio':>7}  (baseline: world model off, "
          "same process, alternating rounds; ratio: recipe's cost / baseline's)")
    for k, (v, b, ratio) in compare(exp, repeats=args.repeats, device=args.device).items():
        cells = f"{v:12.1f} " + (f"{b:12.1f} {ratio:6.2f}x" if b is not None else f"{'-':>12} {'-':>7}")
        print(f"  {k:<24} {cells}")
    return 0


def cmd_demos(args) -> int:
    from ddp.data.demos import prepare_demos

    _at_least_one(episodes=args.episodes)
    info = prepare_demos(args.recipe, args.overrides, episodes=args.episodes, regenerate=args.regenerate,
                         progress=not args.quiet)
    stats = info.get("stats") or {}
    what = "generated" if info.get("generated") else "ready (cached)"
    print(f"{info['episodes']} demonstrations {what}" + (f" in {info['path']}" if info.get("path") else ""))
    keys = ("attempts", "successes", "success_rate", "mean_length", "seconds", "seconds_per_episode")
    shown = [f"{k} {stats[k]:.3g}" if isinstance(stats[k], float) else f"{k} {stats[k]}" for k in keys if k in stats]
    if shown:
        print("  " + ", ".join(shown))
    return 0


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ddp", description="Dream Diffusion Policy: diffusion policies with a world model to dream with."
    )
    from ddp import __version__

    parser.add_argument("--version", action="version", version=f"ddp {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("list", help="list registered plugins", description="List registered plugins by kind.")
    p.add_argument("kind", nargs="?", help="only this kind (encoder, denoiser, scheduler, ...)")
    p.add_argument("--pattern", default="*", help="glob on plugin names, e.g. '*dd*'")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("recipe", help="print a recipe fully resolved", description="Print the resolved recipe (bases merged, overrides applied, defaults filled) as YAML.")
    _add_recipe_args(p)
    p.set_defaults(func=cmd_recipe)

    p = sub.add_parser("summary", help="parameter counts per part", description="Build a recipe's model and print its parts and parameter counts.")
    _add_recipe_args(p)
    p.set_defaults(func=cmd_summary)

    p = sub.add_parser("train", help="train a recipe", description="Train a recipe's model; resumes from <output_dir>/last.pt unless --no-resume. Several processes (CPU or one GPU each): torchrun --nproc-per-node K -m ddp train RECIPE, data-parallel with torch's DistributedDataParallel (not the Dream Diffusion Policy that DDP names elsewhere here); train.micro_batches must be a multiple of K, and the weights equal a 1-process run with the same micro_batches.")
    _add_recipe_args(p)
    p.add_argument("--output-dir", help="where checkpoints and logs go (default: the recipe's train.output_dir)")
    p.add_argument("--no-resume", action="store_true", help="start from scratch even if a checkpoint exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("bench", help="control-cycle latency and training throughput", description="Median latency at batch 1 of the encoder, policy sampling, world-model imagination, detector and the full control cycle; training samples/s.")
    _add_recipe_args(p)
    p.add_argument("--repeats", type=int, default=20, help="timed runs per stage (after warm-up)")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, help="torch CPU threads")
    p.add_argument("--no-baseline", action="store_true",
                   help="time the recipe only (default: also its DP3 baseline, world model off, in alternating rounds, with cost ratios)")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("demos", help="generate scripted-expert demonstrations", description="Roll out the recipe's scripted expert, keep successful episodes and store them (memory-mapped) where the recipe's data section says.")
    _add_recipe_args(p)
    p.add_argument("--episodes", type=int, help="successful episodes to keep (default: data.episodes)")
    p.add_argument("--regenerate", action="store_true", help="ignore a matching cache and generate anew")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_demos)

    p = sub.add_parser("eval", help="evaluate a checkpoint", description="Run evaluation protocols (id, id_ddp, ood_base, ood_tracking, ood_ddp, ood_ddp_oracle, imagination_10/50/100, occlusion, occlusion_oracle; see ddp list protocol) and write results.json, table.md and plots. Without RECIPE the checkpoint's stored recipe is used; its plugin modules are imported only with --trust-plugins.")
    _add_recipe_args(p, optional=True)
    p.add_argument("--trust-plugins", action="store_true",
                   help="without RECIPE: import the plugin modules the checkpoint's recipe lists (runs their code)")
    p.add_argument("--checkpoint", required=True, help="checkpoint written by ddp train (last.pt)")
    p.add_argument("--protocols", help="comma-separated protocols (default: the recipe's eval.protocols)")
    p.add_argument("--episodes", type=int, help="episodes per protocol (default: eval.episodes)")
    p.add_argument("--num-envs", type=int, help="environments stepped together (default: eval.num_envs)")
    p.add_argument("--parallel", action="store_true", help="one worker process per env (torchrl ParallelEnv; default: eval.parallel)")
    p.add_argument("--video", action="store_true", help="record the first eval.video_episodes episodes per env and protocol, labelled with the controller's mode")
    p.add_argument("--output-dir", help="default: the recipe's eval.output_dir")
    p.add_argument("--raw-weights", action="store_true", help="evaluate the raw weights instead of the EMA")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("detect", help="compare OOD detection statistics on a checkpoint", description="Roll out the base policy with the world model forecasting every cycle on ID calibration episodes, ID test episodes and disturbed episodes (displacement, occlusion), calibrate every detection statistic to the same false-alarm rate alpha (split conformal) and report, per statistic and disturbance: AUROC at the first chunk the disturbance is visible and after, detections within one chunk, median delay, misses, alarms before the disturbance and ID false alarms. Writes detect.json, detect.md, per-chunk traces and one plot per statistic.")
    _add_recipe_args(p, optional=True)
    p.add_argument("--trust-plugins", action="store_true",
                   help="without RECIPE: import the plugin modules the checkpoint's recipe lists (runs their code)")
    p.add_argument("--checkpoint", required=True, help="checkpoint written by ddp train (last.pt)")
    p.add_argument("--episodes", type=int, help="test episodes per condition (ID and each disturbance; default 10)")
    p.add_argument("--calibration-episodes", type=int, help="ID calibration episodes (default: eval.calibration_episodes; more are rolled out while too few succeed to set tau on)")
    p.add_argument("--threshold-on", choices=["successful", "all"], help="held-out ID episodes that set every statistic's tau (default: each statistic's own, successful unless it says all)")
    p.add_argument("--alpha", type=float, help="target false-alarm rate per ID episode (default: the recipe detector's "
                   "controller.detector.alpha, else 0.05)")
    p.add_argument("--disturbances", default="ood_base", help="comma-separated protocols that disturb the episodes, run with the base policy (default ood_base; e.g. ood_base,occlusion)")
    p.add_argument("--env", action="append", default=[], metavar="KEY=VALUE", help="env override for the disturbed episodes, e.g. --env displacement_chunk=4 --env 'displacement_delta=[0.1,0,0]' (repeatable)")
    p.add_argument("--scores", help="comma-separated statistics to compare (default: all of ddp.detection.SCORE_VARIANTS)")
    p.add_argument("--rollouts", help="score the rollouts a previous ddp detect saved (detect_rollouts.npz) instead of rolling out")
    p.add_argument("--samples", type=int, help="world-model samples per forecast (default: controller.forecast_samples); the spread statistics need > 1")
    p.add_argument("--seed", type=int, help="first test seed (default: eval.seed; calibration uses seed + 100000)")
    p.add_argument("--num-envs", type=int, help="environments stepped together (default 1)")
    p.add_argument("--parallel", action="store_true", help="one worker process per env")
    p.add_argument("--output-dir", help="default: <checkpoint dir>/detect")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("suite", help="train and evaluate tasks x methods x seeds, resumable, aggregated", description="Expand a suite file (tasks x methods x seeds; see ddp/suite/spec.py) into runs, train and evaluate each one (skipping those whose result is already stored under results/suites/<suite>/), then write the paper's Table 1 layout (mean ± std over seeds) as table.md / .json / .csv / .png, with cost.md (wall time per run), vs_reference.md and detection.png. Not to be confused with torch's DistributedDataParallel: DDP here is the Dream Diffusion Policy.")
    p.add_argument("suite", help="path to a suite YAML file (e.g. suites/metaworld_smoke.yaml)")
    p.add_argument("--workers", type=int, help="runs at once, each in its own process (default 1: sequential in this process); not with --ray")
    p.add_argument("--threads", type=int, help="torch threads per run (default: all cores / workers; 1 under --ray)")
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS", help="run each run as a Ray task: on a local Ray started here (--ray) or a cluster (--ray ADDRESS, e.g. ray://head:10001 or auto); needs the ray extra")
    p.add_argument("--gpus-per-run", type=float, default=0.0, help="with --ray: GPUs each run asks for (default 0)")
    p.add_argument("--report", action="store_true", help="only aggregate the stored results (run nothing)")
    p.add_argument("--tasks", help="comma-separated task labels to run (default: all; the table always covers every stored run)")
    p.add_argument("--methods", help="comma-separated method labels to run (default: all)")
    p.add_argument("--seeds", help="comma-separated seeds to run (default: all); runs go seed by seed")
    p.add_argument("--dry-run", action="store_true",
                   help="list the runs, which are stored, stale or to run (and which resume a checkpoint), and exit")
    p.add_argument("--reevaluate", metavar="PROTOCOLS",
                   help="bring stale runs up to date by re-evaluating only these comma-separated protocols from each "
                        "run's checkpoint, keeping the others (for a change in how runs are evaluated, e.g. the "
                        "detector: --reevaluate id_ddp,ood_ddp); missing runs still run in full")
    p.add_argument("--time-limit", metavar="DURATION",
                   help="wall-clock budget (e.g. 2h30m, 150m, 9000): start a run only if its expected time (from "
                        "this suite's stored runs; --dry-run shows it) fits in the time left, stop the runs still "
                        "going at the limit (a training run saves its checkpoint) and exit with status 75")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_suite)

    p = sub.add_parser("run", help="train then evaluate one or more recipes", description="Train each recipe (resuming if a checkpoint exists) and evaluate it; print one table for all.")
    p.add_argument("recipes", nargs="+", help="recipes to run in turn, or --jobs at once (e.g. DDP and its DP3 baseline)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override applied to every recipe (repeatable)")
    p.add_argument("--protocols", help="comma-separated protocols (default: each recipe's eval.protocols)")
    p.add_argument("--episodes", type=int, help="episodes per protocol")
    p.add_argument("--no-resume", action="store_true", help="train from scratch")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--jobs", "-j", type=int, default=1, metavar="N",
                   help="run up to N recipes at once, each in its own process with its share of the cores and its "
                        "output in <train.output_dir>/run.log (default 1: in turn, in this process)")
    p.set_defaults(func=cmd_run)
    return parser


def main(argv: list[str] | None = None) -> int:
    # OpenMP's default wait policy (workers spin briefly between parallel regions) is left alone: on this
    # 2-core CPU, OMP_WAIT_POLICY=PASSIVE made training 1.7x and batch-1 sampling 2x slower. Concurrent
    # suite workers get PASSIVE (ddp.suite.runner), where spinning threads would steal each other's cores.
    parser = make_parser()
    args = parser.parse_args(argv)
    if args.command == "list" and args.kind:
        from ddp import registry

        try:
            registry._check_kind(args.kind)
        except DDPError as err:
            parser.exit(2, f"ddp: error: {err}\n")
    try:
        return args.func(args)
    except DDPError as err:
        print(f"ddp: error: {err}", file=sys.stderr)
        return 2
    except Preempted as err:
        again = resume_hint(getattr(args, "no_resume", False))
        _say(f"ddp: {err} (a training run saved its checkpoint, an evaluation closed its envs; {again} training)")
        return 128 + err.signum
    except BrokenPipeError:  # `ddp list | head`: the reader left; no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except KeyboardInterrupt:
        again = resume_hint(getattr(args, "no_resume", False))
        _say(f"ddp: interrupted (a checkpoint was written where training was running; {again})")
        return 130


def _say(message: str) -> None:
    """The last line of a stopped command, on stderr; a hung-up terminal (SIGHUP) keeps the exit status."""
    try:
        print(message, file=sys.stderr)
    except OSError:
        pass


if __name__ == "__main__":
    sys.exit(main())
