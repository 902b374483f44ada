"""Evaluation reporter: episode results in, results.json, table.md and plots out."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ddp import results_json


def protocol_result(episodes: list[dict], *, seconds: float, thresholds: dict, videos: list[str] | None = None) -> dict:
    """One protocol's entry in results.json: success rate and counts, time, thresholds, every episode."""
    out = {
        "success_rate": float(np.mean([r["success"] for r in episodes])),
        "successes": int(sum(r["success"] for r in episodes)),
        "episodes": len(episodes),
        "seconds": seconds,
        "tau": thresholds.get("tau"),
        "tau_per_chunk": thresholds.get("tau_per_chunk"),
        "per_episode": episodes,
    }
    if videos is not None:
        out["videos"] = videos
    return out


def write_report(report: dict, out_dir: Path) -> list[Path]:
    """results.json (strict JSON: NaN -> null), table.md and the plots; returns the plot paths."""
    from ddp.plots import plot_report

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "results.json").write_text(results_json.dumps(report))
    (out_dir / "table.md").write_text(markdown_table({report["recipe"]: report}))
    return plot_report(report, out_dir)


def markdown_table(reports: dict[str, dict]) -> str:
    """Success rates (%) laid out like the paper's Table 1: one row per method / condition."""
    protocols = list(dict.fromkeys(p for r in reports.values() for p in r["protocols"]))  # first-seen order
    lines = ["| method | " + " | ".join(protocols) + " |", "|---|" + "---|" * len(protocols)]
    for name, rep in reports.items():
        cells = []
        for p in protocols:
            r = rep["protocols"].get(p)
            cells.append("-" if r is None else f"{100 * r['success_rate']:.0f} ({r['successes']}/{r['episodes']})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
