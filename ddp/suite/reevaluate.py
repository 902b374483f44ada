"""Bringing stale results up to date by re-evaluating some protocols from each run's checkpoint.

A suite file that changes only how runs are evaluated (a detector setting, a controller option) makes every
affected result stale, and ``ddp suite`` would train and evaluate those runs again. ``ddp suite SUITE
--reevaluate id_ddp,ood_ddp`` instead loads each stale run's ``last.pt``, evaluates only the named protocols,
keeps the stored values of the others and stores the result under the run's current recipe, with a
``reevaluated`` record (protocols, the recipe keys that changed since training, the previous success rates,
the code version, seconds). Which protocols a change touches is the caller's call (the detector's settings
reach ``id_ddp`` and ``ood_ddp`` only; ``ood_ddp_oracle`` and the imagination protocols use none of them).

Every stale run is checked before any starts, and one that cannot be brought up to date this way stops the
command with a one-line reason: no checkpoint, one that cannot serve the recipe (what it trains on or a
training setting changed, or it is not at the step its stored result came from), another episode count, a
stored result lacking a protocol of the current list that is not re-evaluated, or a named protocol the run
does not evaluate.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ddp.errors import DDPError
from ddp.suite.spec import RunSpec
from ddp.suite.store import ResultStore

__all__ = ["plan_reevaluation", "merge_reevaluation"]


#: keys ddp train lets a resumed run change (``ddp.train.RESUMABLE``) that still change the weights a finished
#: run's checkpoint would hold: the step budget. Every other train key is either resumable and operational
#: (threads, device, logging, ...) or refused by the resume rule itself.
SCHEDULE = ("train.max_steps", "train.epochs")


def _resolved(run: RunSpec) -> dict:
    from ddp.schema import validate

    return validate(run.recipe, run.run_id)[2]


def _protocols(run: RunSpec, resolved: dict | None = None) -> list[str]:
    if run.protocols is not None:
        return list(run.protocols)
    return list((resolved or _resolved(run))["eval"]["protocols"])


def plan_reevaluation(store: ResultStore, runs: list[RunSpec], protocols: list[str]) -> list[RunSpec]:
    """The stale runs among ``runs``, each to re-evaluate ``protocols`` (``RunSpec.reevaluate``); raises a
    one-line DDPError naming the first run that cannot be brought up to date this way."""
    from ddp.checkpoint import load_checkpoint, stored_recipe
    from ddp.recipe import recipe_changes
    from ddp.train import LAST, describe_changes, resume_conflicts

    if not protocols:
        raise DDPError("--reevaluate needs at least one protocol name")
    out = []
    for run in runs:
        if store.status(run) != "stale":
            continue
        stored, resolved = store._complete(run), _resolved(run)
        listed = _protocols(run, resolved)
        unknown = [p for p in protocols if p not in listed]
        if unknown:
            raise DDPError(f"--reevaluate: {run.run_id} does not evaluate {', '.join(unknown)} (its protocols: "
                           f"{', '.join(listed)}); choose the runs with --tasks / --methods / --seeds")
        lacking = [p for p in listed if p not in stored.get("protocols", {}) and p not in protocols]
        if lacking:
            raise DDPError(f"--reevaluate: the stored result of {run.run_id} lacks {', '.join(lacking)}; "
                           "add it to --reevaluate")
        episodes = run.episodes if run.episodes is not None else resolved["eval"]["episodes"]
        if stored.get("episodes") != episodes:
            raise DDPError(f"--reevaluate: {run.run_id} was evaluated on {stored.get('episodes')} episodes per "
                           f"protocol, the suite now asks {episodes}; run it again instead")
        run_dir = Path(run.recipe["train"]["output_dir"])
        ckpt = run_dir / LAST
        if not ckpt.is_file():
            raise DDPError(f"--reevaluate: {run.run_id} has no checkpoint ({ckpt})")
        state = load_checkpoint(ckpt, mmap=True)
        # what training could not continue from (ddp train's resume rule), and any train setting that shapes
        # the weights (a raised or lowered step budget included)
        conflicts = resume_conflicts(ckpt, state, resolved)
        trained = [k for k in recipe_changes(stored_recipe(ckpt, state), resolved) if k in SCHEDULE]
        if conflicts or trained:
            why = describe_changes(conflicts) if conflicts else ", ".join(trained) + " changed"
            raise DDPError(f"--reevaluate: the checkpoint of {run.run_id} cannot serve this recipe ({why}); "
                           "run it again instead")
        # the checkpoint must be the one the stored result was evaluated on (not a later, resumed training)
        steps = (stored.get("train") or {}).get("steps")
        if state.get("step") != steps:
            raise DDPError(f"--reevaluate: the checkpoint of {run.run_id} is at step {state.get('step')}, its "
                           f"stored result at {steps}: not the model the result came from; run it again instead")
        out.append(dataclasses.replace(run, reevaluate=tuple(protocols)))
    return out


def merge_reevaluation(store: ResultStore, run: RunSpec, result: dict) -> dict:
    """The stored (stale) result of ``run`` with ``result``'s re-evaluated protocols in place and a record of
    what was redone; what ``ResultStore.save`` then stores under the run's current recipe."""
    data = {k: v for k, v in store._complete(run).items() if k not in ("format", "complete", "recipe_hash")}
    previous = {p: data["protocols"].get(p, {}).get("success_rate") for p in result["protocols"]}
    data["protocols"] = {p: result["protocols"].get(p, data["protocols"].get(p)) for p in _protocols(run)
                         if p in result["protocols"] or p in data["protocols"]}
    history = data.get("reevaluated") or []
    history = [history] if isinstance(history, dict) else list(history)
    history.append({"protocols": list(result["protocols"]), "changed_since_training": result["changed"],
                    "previous": previous, "code": result["code"], "seconds": result["wall_seconds"]})
    data["reevaluated"] = history
    return data
