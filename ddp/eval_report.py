"""Evaluation reporter: episode results in, results.json, table.md and plots out."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ddp import results_json
from ddp.percent import percent


def protocol_result(episodes: list[dict], *, seconds: float, thresholds: dict, videos: list[str] | None = None,
                    detection: dict | None = None, detector: dict | None = None) -> dict:
    """One protocol's entry in results.json: success rate and counts, time, the detector and its threshold,
    the detection metrics (``ddp.detection``), every episode."""
    judged = all(r["success"] is not None for r in episodes)  # an env that cannot judge (a real robot): None
    out = {
        "success_rate": float(np.mean([r["success"] for r in episodes])) if judged else None,
        "successes": int(sum(r["success"] for r in episodes)) if judged else None,
        "episodes": len(episodes),
        "seconds": seconds,
        "detector": detector,
        "tau": thresholds.get("tau"),
        "alpha": thresholds.get("alpha"),
        # how the threshold was calibrated (the per-chunk reference itself stays beside the checkpoint); None
        # where nothing was fitted (a tau given in the recipe for a statistic without a reference)
        "calibration": ({k: thresholds[k] for k in CALIBRATION_FIELDS if k in thresholds}
                        if thresholds.get("fit_episodes") or thresholds.get("threshold_episodes") else None),
        "per_episode": episodes,
    }
    info = task_info_mean(episodes)
    if info:
        out["task_info"] = info
    if detection is not None:
        out["detection"] = detection
    if videos is not None:
        out["videos"] = videos
    return out


#: the calibration's fields results.json keeps
CALIBRATION_FIELDS = ("fit_episodes", "threshold_episodes", "threshold_on", "fit_on", "chunk_fallback", "median")


def task_info_mean(episodes: list[dict]) -> dict[str, float]:
    """The mean over episodes of each task diagnostic the env reported at the episode's end (``task_info``:
    e.g. Franka press's ``max_depth`` and ``over_pressed``), NaN values left out; empty when there are none."""
    names = sorted({name for e in episodes for name in e.get("task_info") or {}})
    out = {}
    for name in names:
        values = [e["task_info"][name] for e in episodes if name in (e.get("task_info") or {})]
        values = [v for v in values if v is not None and np.isfinite(v)]
        if values:
            out[name] = float(np.mean(values))
    return out


def write_report(report: dict, out_dir: Path) -> list[Path]:
    """results.json (strict JSON: NaN -> null), table.md and the plots; returns the plot paths, which
    ``report["plots"]`` and results.json list (the JSON is written first and again once the plots exist,
    so a plotting failure still leaves the results)."""
    from ddp.plots import plot_report

    from ddp.atomic_file import atomic_write

    def write_json():
        atomic_write(out_dir / "results.json", lambda f: f.write(results_json.dumps(report)), binary=False)

    out_dir.mkdir(parents=True, exist_ok=True)  # written whole or not at all (a kill mid-write left half a JSON)
    report["plots"] = []
    write_json()
    table = markdown_table({report["recipe"]: report}) + detection_table(report)
    atomic_write(out_dir / "table.md", lambda f: f.write(table), binary=False)
    plots = plot_report(report, out_dir)
    report["plots"] = [str(p) for p in plots]
    write_json()
    return plots


def markdown_table(reports: dict[str, dict]) -> str:
    """Success rates (%) laid out like the paper's Table 1: one row per method / condition."""
    protocols = list(dict.fromkeys(p for r in reports.values() for p in r["protocols"]))  # first-seen order
    lines = ["| method | " + " | ".join(protocols) + " |", "|---|" + "---|" * len(protocols)]
    for name, rep in reports.items():
        cells = []
        for p in protocols:
            r = rep["protocols"].get(p)
            if r is None:
                cells.append("-")
            elif r["success_rate"] is None:  # a real robot's episodes: success is a person's call
                cells.append(f"not judged ({r['episodes']} episodes)")
            else:
                cells.append(f"{percent(r['success_rate'])} ({r['successes']}/{r['episodes']})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def detection_table(report: dict) -> str:
    """Markdown: per protocol whose detector decides, the detector and its detection metrics."""
    from ddp.detection import fmt_num

    rows = [(name, r) for name, r in report["protocols"].items() if "detection" in r]
    if not rows:
        return ""
    lines = ["", "Detection (first visible = first chunk whose observation shows the disturbance):", "",
             "| protocol | detector | detected (<= 1 chunk) | median delay | missed (OOD on before visible) | "
             "episodes with a false alarm | "
             "false alarms per ID chunk | AUROC at visible / +1 / +2 / +3 |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in rows:
        m, det = r["detection"], r.get("detector") or {}
        what = det.get("name", "?")
        if det.get("tau") is not None:  # a threshold the recipe set, or the calibration's alpha
            what += f" (tau {det['tau']})"
        elif r.get("alpha") is not None:
            what += f" (alpha {r['alpha']})"
        aurocs = [a for a in (m.get("auroc_after_visible") or []) if a is not None and a == a]
        au = "/".join(fmt_num(a, "{:.2f}") for a in m["auroc_after_visible"]) if aurocs else "-"
        n = m["disturbed_episodes"] + m["clean_episodes"]
        detected, missed = "-", "-"
        if m["disturbed_episodes"]:
            detected = f"{m['detected']}/{m['disturbed_episodes']} ({m['detected_within_1']})"
            early = m.get("alarm_before_visible")  # results stored before it counted these in missed
            missed = str(m["missed"]) if early is None else f"{m['missed']} ({early})"
        lines.append(
            f"| {name} | {what} | {detected} | {fmt_num(m['median_delay'], '{:.1f}')} | {missed} | "
            f"{m['episodes_with_false_alarm']}/{n} | {fmt_num(m['false_alarms_per_id_chunk'])} | {au} |"
        )
    return "\n".join(lines) + "\n"
