"""Compact summary of a `ddp eval` results.json: per protocol its successes, tau, detection metrics and,
per episode, success, the chunk the detector first flagged and the scores of chunks 1-6.

    python results/metaworld_pickplace/summarize.py RESULTS_JSON OUT_JSON
"""
import json
import sys

src, dst = sys.argv[1], sys.argv[2]
report = json.load(open(src))
out = {"source": src, "recipe": report.get("recipe"), "seed": report.get("seed"), "protocols": {}}
for name, p in report["protocols"].items():
    det = p.get("detection") or {}
    keep = {k: det.get(k) for k in ("detected", "detected_within_1", "missed", "median_delay",
                                    "episodes_with_false_alarm", "auroc_after_visible") if k in det}
    episodes = []
    for e in p["per_episode"]:
        row = {"seed": e["seed"], "success": e["success"]}
        if e.get("mode"):
            row["first_ood_chunk"] = next((c for c, m in enumerate(e["mode"]) if m), None)
        if e.get("score") and any(x is not None for x in e["score"]):
            row["score_chunks_1_6"] = [None if x is None else round(x, 3) for x in e["score"][1:7]]
        episodes.append(row)
    out["protocols"][name] = {"successes": p["successes"], "episodes": p["episodes"], "tau": p.get("tau"),
                              "detection": keep, "per_episode": episodes}
json.dump(out, open(dst, "w"), indent=1)
print(dst, {k: f"{v['successes']}/{v['episodes']}" for k, v in out["protocols"].items()})
