"""Collect the push DP3 ablation runs (runs/<name>/quickstart_dp3) into push_ablation.json (small; no checkpoints).

    .venv/bin/python results/metaworld_push/collect.py push512 push512g push512g3k push128g push512plain
"""

import json
import math
import sys
from pathlib import Path

import yaml

from ddp.checkpoint import load_checkpoint


def wilson(k: int, n: int, z: float = 1.96) -> list[float]:
    p, d = k / n, 1 + z * z / n
    c, h = (p + z * z / (2 * n)) / d, z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return [round(100 * (c - h), 1), round(100 * (c + h), 1)]


rows = []
for name in sys.argv[1:]:
    run = Path("runs") / name / "quickstart_dp3"
    res = json.loads((run / "eval" / "results.json").read_text())
    state = load_checkpoint(run / "last.pt")  # weights only; the recipe is stored as YAML text
    recipe = yaml.safe_load(state["recipe"])
    env = recipe["env"]
    rows.append({
        "run": name,
        "num_points": env["num_points"],
        "visible_sites": list(env.get("visible_sites", [])),
        "crop_min_z": env["crop_min"][2],
        "train_steps": int(state["step"]),
        "final_loss": round(float(state.get("losses", {}).get("loss", float("nan"))), 4),
        "eval_episodes": res["episodes"],
        "protocols": {p: {"successes": v["successes"], "episodes": v["episodes"],
                          "success_rate_pct": round(100 * v["success_rate"], 1),
                          "wilson95_pct": wilson(v["successes"], v["episodes"])}
                      for p, v in res["protocols"].items()},
    })
out = Path(__file__).with_name("push_ablation.json")
out.write_text(json.dumps({"task": "push", "method": "dp3 (recipes/metaworld/quickstart_dp3.yaml)", "seed": 0,
                           "demos": 20, "runs": rows}, indent=1))
for r in rows:
    print(r["run"], r["num_points"], r["visible_sites"], r["crop_min_z"], r["train_steps"],
          {p: f"{v['successes']}/{v['episodes']}" for p, v in r["protocols"].items()})
