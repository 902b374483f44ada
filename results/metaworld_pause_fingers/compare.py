"""Pausing the fingers during a tracking shift: the budget suite's checkpoints re-evaluated with
``env.pause_fingers=true``, paired by initial state with the same checkpoints without the pause (same 20
held-out initial states, same calibration; only the pause differs).

    python results/metaworld_pause_fingers/compare.py WITH_ROOT WITHOUT_ROOT OUT_DIR METHOD [SEED]

Run from the repository root. WITH_ROOT/<task>/results.json are `ddp eval` outputs of METHOD's (ddp, dp3)
checkpoints with the pause (any protocols: ood_ddp and ood_ddp_oracle for DDP, ood_tracking for DP3);
WITHOUT_ROOT/<task>/results.json the same protocols without it, for the protocols whose per-episode
outcomes the suite's store lacks (it keeps them for ood_ddp only). The "without" counts are the suite's
stored ones (results/suites/metaworld_budget/<task>__<METHOD>__seed<SEED>.json); a re-evaluation that does
not reproduce them is reported. OUT_DIR gets <task>_<METHOD>_seed<SEED>.json (per protocol the successes
with and without the pause, episodes gained and lost and, per episode, both outcomes and the first chunk
the controller left ID) and table_<METHOD>_seed<SEED>.md. SEED: 0 by default.
"""
import json
import sys
from pathlib import Path

with_root, without_root, out = (Path(a) for a in sys.argv[1:4])
method = sys.argv[4]
seed = int(sys.argv[5]) if len(sys.argv) > 5 else 0
suite = Path("results/suites/metaworld_budget")


def outcomes(protocol: dict) -> list[bool]:
    return [bool(e["success"]) for e in protocol.get("traces") or protocol.get("per_episode") or []]


rows, totals = [], {}
for results in sorted(with_root.glob("*/results.json")):
    task = results.parent.name
    stored = json.loads((suite / f"{task}__{method}__seed{seed}.json").read_text())["protocols"]
    after = json.loads(results.read_text())["protocols"]
    rerun_file = without_root / task / "results.json"
    rerun = json.loads(rerun_file.read_text())["protocols"] if rerun_file.exists() else {}
    summary = {"task": task, "method": method, "seed": seed,
               "source": "results/suites/metaworld_budget checkpoint, env.pause_fingers=true vs false",
               "protocols": {}}
    cells = []
    for name, p in after.items():
        before = outcomes(stored[name]) or outcomes(rerun.get(name, {}))
        if name in rerun and rerun[name]["successes"] != stored[name]["successes"]:
            print(f"{task} {name}: the unpaused re-evaluation gives {rerun[name]['successes']}, "
                  f"the suite stored {stored[name]['successes']}")
        episodes = [{"seed": e["seed"], "success": e["success"],
                     "success_without_pause": before[i] if before else None,
                     "first_ood_chunk": next((c for c, m in enumerate(e.get("mode") or []) if m), None)}
                    for i, e in enumerate(p["per_episode"])]
        gained = sum(1 for e in episodes if e["success"] and e["success_without_pause"] is False)
        lost = sum(1 for e in episodes if not e["success"] and e["success_without_pause"] is True)
        summary["protocols"][name] = {"successes": p["successes"], "episodes": p["episodes"],
                                      "successes_without_pause": stored[name]["successes"],
                                      "paired": bool(before), "gained": gained, "lost": lost,
                                      "per_episode": episodes}
        total = totals.setdefault(name, {"without": 0, "with": 0, "episodes": 0, "gained": 0, "lost": 0})
        for key, value in (("without", stored[name]["successes"]), ("with", p["successes"]),
                           ("episodes", p["episodes"]), ("gained", gained), ("lost", lost)):
            total[key] += value
        pairing = f" (+{gained} -{lost})" if before else " (unpaired)"
        cells.append(f"{stored[name]['successes']} -> {p['successes']}{pairing}")
    (out / f"{task}_{method}_seed{seed}.json").write_text(json.dumps(summary, indent=1))
    rows.append(f"| {task} | " + " | ".join(cells) + " |")
avg = [f"{100 * t['without'] / t['episodes']:.1f} -> {100 * t['with'] / t['episodes']:.1f} "
       f"(+{t['gained']} -{t['lost']})" for t in totals.values()]
table = [f"| {method} seed {seed}: successes of 20 without -> with the pause (episodes gained, lost) | "
         + " | ".join(totals) + " |",
         "|---" * (len(totals) + 1) + "|", *rows,
         f"| average % over {len(rows)} tasks | " + " | ".join(avg) + " |"]
(out / f"table_{method}_seed{seed}.md").write_text("\n".join(table) + "\n")
print("\n".join(table))
