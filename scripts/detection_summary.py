"""One table of several `ddp detect` runs: per statistic and (task, disturbance), the episodes detected
within one chunk of the first visible chunk, and the ID test episodes with a false alarm.

    python3 scripts/detection_summary.py results/detection/*_cpu*.json
"""
import argparse
import json

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("files", nargs="+", help="ddp detect reports (detect.json, or a copy named after its run)")
files = parser.parse_args().files
def label(f):  # the file's name, or its folder's for ddp detect's own detect.json
    parts = f.split('/')
    return parts[-2] if parts[-1] == 'detect.json' and len(parts) > 1 else parts[-1].replace('.json', '')
reps = [(label(f), json.load(open(f))) for f in files]
reps = [(n, rep) for n, rep in reps if "rows" in rep and "disturbances" in rep]  # ddp detect reports only
scores = list(dict.fromkeys(r["score"] for _, rep in reps for r in rep["rows"] if "error" not in r))
head = "| score | " + " | ".join(f"{n} / {d}" for n, rep in reps for d in rep["disturbances"]) + " |"
lines = [head, "|---|" + "---|" * (len(head.split("|")) - 3)]
for sc in scores:
    cells = []
    for n, rep in reps:
        row = next((r for r in rep["rows"] if r["score"] == sc), None)
        for d in rep["disturbances"]:
            if row is None or "error" in row:
                cells.append("-"); continue
            x = row[d]
            cells.append(f"{x['detected_within_1']}/{x['episodes']} ({row['id_false_alarm_episodes']} FA)")
    lines.append(f"| {sc} | " + " | ".join(cells) + " |")
print("\n".join(lines))
