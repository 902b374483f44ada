"""One table of several `ddp detect` runs: per statistic and (task, disturbance), the episodes detected
within one chunk of the first visible chunk, and the ID test episodes with a false alarm (of those run).

    python3 scripts/detection_summary.py results/detection/*_cpu*.json

Files that are not `ddp detect` reports (an evaluation's results.json, a rescoring) are named on stderr and
left out; the reports must share one alpha (the table's heading states it).
"""
import argparse
import json
import sys

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("files", nargs="+", help="ddp detect reports (detect.json, or a copy named after its run)")
files = parser.parse_args().files


def label(f):  # the file's name, or its folder's for ddp detect's own detect.json
    parts = f.split('/')
    return parts[-2] if parts[-1] == 'detect.json' and len(parts) > 1 else parts[-1].replace('.json', '')


reps = []
for f in files:
    try:
        with open(f) as stream:
            rep = json.load(stream)
    except (OSError, ValueError) as err:
        sys.exit(f"{f}: {getattr(err, 'strerror', None) or err}")
    if isinstance(rep, dict) and "rows" in rep and "disturbances" in rep:
        reps.append((label(f), rep))
    else:
        print(f"{f}: not a ddp detect report (no rows / disturbances): left out", file=sys.stderr)
if not reps:
    sys.exit("no ddp detect report among the files")
alphas = {rep.get("alpha") for _, rep in reps}
if len(alphas) > 1:
    sys.exit(f"the reports were calibrated at different alphas {sorted(alphas, key=str)}: one table per alpha")
scores = list(dict.fromkeys(r["score"] for _, rep in reps for r in rep["rows"] if "error" not in r))
print(f"alpha {alphas.pop()}, {len(reps)} reports", file=sys.stderr)
head = "| score | " + " | ".join(f"{n} / {d}" for n, rep in reps for d in rep["disturbances"]) + " |"
lines = [head, "|---|" + "---|" * (len(head.split("|")) - 3)]
for sc in scores:
    cells = []
    for n, rep in reps:
        row = next((r for r in rep["rows"] if r["score"] == sc), None)
        for d in rep["disturbances"]:
            if row is None or "error" in row:
                cells.append("-")
                continue
            x = row[d]
            clean = f"/{row['id_episodes']}" if "id_episodes" in row else ""
            # tau set on successful ID episodes bounds their false alarms (alpha): those, beside all episodes'
            nominal = (f", {row['id_false_alarm_successful']}/{row['id_successful']} successful"
                       if row.get("threshold_on") == "successful" and "id_successful" in row else "")
            cells.append(f"{x['detected_within_1']}/{x['episodes']} ({row['id_false_alarm_episodes']}{clean} FA"
                         f"{nominal})")
    lines.append(f"| {sc} | " + " | ".join(cells) + " |")
print("\n".join(lines))
