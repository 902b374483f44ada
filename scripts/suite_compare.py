"""Per task, one method's stored suite results before and after a change of its settings: successes per
protocol and, for the protocols with a detector, displacements flagged within one chunk, missed, and episodes
with a false alarm.

    python3 scripts/suite_compare.py results/suites/metaworld_cpu/history/v3_ddp_window2 \\
        results/suites/metaworld_cpu --method ddp --seed 0 --protocols id,id_ddp,ood_ddp,ood_ddp_oracle

Reads only the run JSONs ``<task>__<method>__seed<k>.json`` in both folders (what ``ddp suite`` stores);
a task missing on either side, or stored "after" under the same recipe hash as "before" (not run again yet),
is shown with a dash there and left out of the averages.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def _runs(folder: Path, method: str, seed: int) -> dict[str, dict]:
    out = {}
    for f in sorted(folder.glob(f"*__{method}__seed{seed}.json")):
        run = json.loads(f.read_text())
        if run.get("complete", True):
            out[run["task"]] = run
    return out


def _cell(run: dict | None, protocol: str) -> str:
    if run is None or protocol not in run["protocols"]:
        return "-"
    p = run["protocols"][protocol]
    cell = f"{p['successes']}/{p['episodes']}"
    det = p.get("detection")
    if det and det.get("disturbed_episodes"):
        cell += f" ({det['detected_within_1']} on time, {det['missed']} missed)"
    elif det and det.get("clean_episodes"):
        cell += f" ({det['episodes_with_false_alarm']} FA)"
    return cell


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path, help="folder of the stored results before the change")
    parser.add_argument("after", type=Path, help="folder of the stored results after it")
    parser.add_argument("--method", default="ddp")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--protocols", default="id_ddp,ood_ddp", help="comma-separated")
    args = parser.parse_args(argv)
    for folder in (args.before, args.after):
        if not folder.is_dir():
            parser.error(f"no such folder: {folder}")
    before, after = (_runs(f, args.method, args.seed) for f in (args.before, args.after))
    after = {t: r for t, r in after.items() if t not in before or r["recipe_hash"] != before[t]["recipe_hash"]}
    protocols = args.protocols.split(",")
    print("| task | " + " | ".join(f"{p} before | {p} after" for p in protocols) + " |")
    print("|---|" + "---|---|" * len(protocols))
    totals = {p: [0, 0, 0, 0] for p in protocols}  # successes before, episodes before, after, after
    for task in sorted(set(before) | set(after)):
        b, a = before.get(task), after.get(task)
        cells = []
        for p in protocols:
            cells += [_cell(b, p), _cell(a, p)]
            if b is not None and a is not None and p in b["protocols"] and p in a["protocols"]:
                t = totals[p]
                t[0] += b["protocols"][p]["successes"]; t[1] += b["protocols"][p]["episodes"]
                t[2] += a["protocols"][p]["successes"]; t[3] += a["protocols"][p]["episodes"]
        print(f"| {task} | " + " | ".join(cells) + " |")
    cells = []
    for p in protocols:
        sb, nb, sa, na = totals[p]
        cells += [f"{100 * sb / nb:.1f} %" if nb else "-", f"{100 * sa / na:.1f} %" if na else "-"]
    print("| tasks on both sides | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
