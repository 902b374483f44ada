"""What a lower threshold would do to automatic detection, from the stored per-chunk detector traces.

For each stored DDP run (ten tasks x seeds 0, 1) the threshold tau of its `ood_ddp` / `id_ddp` evaluation is
scaled down and the stored traces are re-read: displaced episodes flagged within one chunk of the first chunk
that shows the move ("on time"), and ID episodes with an alarm. A lower tau crosses no later than the stored
one, and a trace is the controller's own up to its stored flag, so both counts are exact for the lower tau
(what the controller would have done after the earlier flag is not: no success rates here).

    python3 results/suites/metaworld_budget/tau_sweep.py > results/suites/metaworld_budget/tau_sweep.md
"""
import json
from pathlib import Path

HERE = Path(__file__).parent
TASKS = ["assembly", "button-press", "coffee-pull", "door-unlock", "drawer-open", "hammer", "pick-place", "push",
         "soccer", "sweep"]


def first_cross(scores, tau):
    return next((c for c, v in enumerate(scores) if v is not None and v > tau), None)


print("| tau scale | displaced episodes flagged on time | ID episodes with an alarm | per task and seed: on time / ID alarms |")
print("|---|---|---|---|")
for scale in (1.0, 0.8, 0.65, 0.5):
    on_all = fa_all = n = 0
    cells = []
    for task in TASKS:
        for seed in (0, 1):
            run = json.loads((HERE / f"{task}__ddp__seed{seed}.json").read_text())["protocols"]
            tau = run["ood_ddp"]["tau"] * scale
            on = sum(1 for tr in run["ood_ddp"]["traces"]
                     if (c := first_cross(tr["score"], tau)) is not None and tr["first_visible"] <= c <= tr["first_visible"] + 1)
            fa = sum(1 for tr in run["id_ddp"]["traces"] if first_cross(tr["score"], tau) is not None)
            on_all, fa_all, n = on_all + on, fa_all + fa, n + len(run["ood_ddp"]["traces"])
            cells.append(f"{task} s{seed} {on}/{fa}")
    print(f"| {scale:g} | {on_all}/{n} | {fa_all}/{n} | {', '.join(cells)} |")
