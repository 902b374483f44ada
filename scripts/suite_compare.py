"""Per task, one method's stored suite results before and after a change of its settings: successes per
protocol and, for the protocols with a detector, displacements flagged within one chunk, missed, and episodes
with a false alarm.

    .venv/bin/python scripts/suite_compare.py results/suites/metaworld_cpu/history/v3_ddp_window2 \\
        results/suites/metaworld_cpu --method ddp --seed 0 --protocols id,id_ddp,ood_ddp,ood_ddp_oracle

Reads only the run JSONs ``<task>__<method>__seed<k>.json`` in both folders (what ``ddp suite`` stores;
one that is not whole by the store's own rule, ``ddp.suite.store.read_complete``, is left out);
a task missing on either side, or stored "after" under the same recipe hash as "before" (not run again yet),
is shown with a dash there and left out of the averages.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddp.detection import alarmed_before_visible
from ddp.percent import percent
from ddp.suite.store import read_complete


def _runs(folder: Path, method: str, seed: int) -> dict[str, dict]:
    runs = {}
    for f in sorted(folder.glob(f"*__{method}__seed{seed}.json")):
        run = read_complete(f)
        if run is None:
            print(f"{f}: not a whole stored result (half-written or damaged): left out", file=sys.stderr)
        else:
            runs[run["task"]] = run
    return runs


def _cell(run: dict | None, protocol: str) -> str:
    if run is None or protocol not in run["protocols"]:
        return "-"
    p = run["protocols"][protocol]
    cell = f"{p['successes']}/{p['episodes']}"
    # detection counts only where a detector decided (a tau): under the oracle schedule or the DP3 / FlowPolicy
    # tracking ablation the mode follows the env's schedule, and "on time" would say nothing
    det = p.get("detection") if p.get("tau") is not None else None
    if det and det.get("disturbed_episodes"):
        if "alarm_before_visible" in det:
            early, missed = det["alarm_before_visible"], det["missed"]
        else:  # stored before detection_metrics split them: counted from the traces, they were in "missed"
            early = sum(alarmed_before_visible(t) for t in p.get("traces") or [])
            missed = det["missed"] - early
        cell += f" ({det['detected_within_1']} on time, {missed} missed"
        cell += f", {early} alarmed before)" if early else ")"
    elif det and det.get("clean_episodes"):
        cell += f" ({det['episodes_with_false_alarm']} FA)"
    return cell


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("before", type=Path, help="folder of the stored results before the change")
    parser.add_argument("after", type=Path, help="folder of the stored results after it")
    parser.add_argument("--method", default="ddp", help="the suite's method label (default ddp)")
    parser.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    parser.add_argument("--protocols", default="id_ddp,ood_ddp", help="comma-separated (default id_ddp,ood_ddp)")
    args = parser.parse_args(argv)
    for folder in (args.before, args.after):
        if not folder.is_dir():
            parser.error(f"no such folder: {folder}")
    before, after = (_runs(f, args.method, args.seed) for f in (args.before, args.after))
    for folder, runs in ((args.before, before), (args.after, after)):
        if not runs:
            parser.error(f"{folder}: no stored run *__{args.method}__seed{args.seed}.json (--method, --seed)")
    protocols = args.protocols.split(",")
    stored = {p for runs in (before, after) for run in runs.values() for p in run["protocols"]}
    for p in protocols:
        if p not in stored:
            parser.error(f"--protocols: no stored run has protocol {p!r} (stored: {', '.join(sorted(stored))})")
    after = {t: r for t, r in after.items() if t not in before or r["recipe_hash"] != before[t]["recipe_hash"]}
    if not after:
        print(f"{args.after}: every run is stored under the same recipe hash as in {args.before} (the same "
              "settings): no 'after' to show", file=sys.stderr)
    print("| task | " + " | ".join(f"{p} before | {p} after" for p in protocols) + " |")
    print("|---|" + "---|---|" * len(protocols))
    both = {p: [] for p in protocols}  # per protocol: (before, after) of each task stored on both sides
    for task in sorted(set(before) | set(after)):
        b, a = before.get(task), after.get(task)
        print(f"| {task} | " + " | ".join(f"{_cell(b, p)} | {_cell(a, p)}" for p in protocols) + " |")
        for p in protocols:
            if b is not None and a is not None and p in b["protocols"] and p in a["protocols"]:
                both[p].append((b["protocols"][p], a["protocols"][p]))

    def rate(results) -> str:
        n = sum(r["episodes"] for r in results)
        return f"{percent(sum(r['successes'] for r in results) / n, 1)} %" if n else "-"

    print("| tasks on both sides | " + " | ".join(
        f"{rate([b for b, _ in both[p]])} | {rate([a for _, a in both[p]])}" for p in protocols) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
