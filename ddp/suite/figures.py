"""A suite report's figures: success per task beside the paper's numbers, and the detector's traces per task.

* :func:`plot_table` (``table.png``): one small panel per task and per benchmark average, one bar
  per method x protocol (the same colour in every panel) with its error bar (std over seeds, or the
  95 % Wilson interval with one seed) and a black tick at the published number where there is one.
* :func:`plot_detection` (``detection.png``): one panel per task and method whose runs stored
  detector traces. Each episode's statistic per control cycle on a log axis: in distribution
  (``id_ddp``) grey, disturbed (``ood_ddp``, or any other protocol with a detector statistic) green
  when the episode succeeded and red when it failed, a dot where the controller switched to OOD, each
  seed's threshold tau dashed and the first chunk at which the disturbance was visible dotted. Where
  a task's automatic detection lags its oracle schedule, this shows whether the alarm came late, too
  early or never.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["plot_table", "plot_detection"]


def _grid(n: int, cols: int = 5) -> tuple[int, int]:
    cols = max(1, min(cols, n))
    return math.ceil(n / cols), cols


def _errors(cell: dict | None) -> tuple[float, float | None, float | None]:
    """(mean, lower, upper) error-bar lengths in percent; NaN mean for a missing cell, None lengths for a cell
    with neither a std nor an interval (an average over one seed, or over tasks with different seeds)."""
    if cell is None:
        return float("nan"), None, None
    mean = 100 * cell["mean"]
    if "std" in cell:
        return mean, 100 * cell["std"], 100 * cell["std"]
    if "wilson95" in cell:
        # clipped at 0: at a rate of 0 or 1 the interval's end can round to a hair inside the mean
        lo, hi = cell["wilson95"]
        return mean, max(0.0, mean - 100 * lo), max(0.0, 100 * hi - mean)
    return mean, None, None


def _coverage_mark(table: dict, rows, column: str) -> str:
    """" (k/n tasks)" for an average panel whose cells cover only k of its benchmark's n tasks, as the tables say."""
    from ddp.suite.report import _coverage  # (the report module imports this one)

    for m, p in rows:
        cell = table["cells"].get(f"{m}|{p}|{column}")
        if cell and cell.get("missing_tasks"):
            return f" ({_coverage(cell)} tasks)"
    return ""


def _finish(plt, fig, handles, labels, title: str, path: Path) -> Path:
    """The shared legend beside the panels, the title, and the file."""
    fig.legend(handles, labels, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_table(table: dict, columns: list[str], path: Path, title: str, reference: dict[str, float] | None = None,
               reference_label: str = "paper") -> Path:
    """Small multiples of the success table, a panel per column (tasks, then ``avg:<benchmark>``);
    ``reference`` maps ``method|protocol|column`` to a rate in [0, 1]."""
    from ddp.plots import _pyplot

    plt = _pyplot()
    reference = reference or {}
    rows = table["rows"]
    palette = plt.get_cmap("tab10" if len(rows) <= 10 else "tab20")
    colours = [palette(i % palette.N) for i in range(len(rows))]
    n_rows, n_cols = _grid(len(columns))
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(2.2 + 2.4 * n_cols, 0.6 + 2.3 * n_rows),
                             sharey=True, squeeze=False)
    xs = np.arange(len(rows))
    for ax, column in zip(axes.flat, columns):
        for i, (m, p) in enumerate(rows):
            mean, lo, hi = _errors(table["cells"].get(f"{m}|{p}|{column}"))
            if not math.isnan(mean):
                bars = {} if lo is None else {"yerr": [[lo], [hi]], "capsize": 1.5, "error_kw": {"lw": 0.8}}
                ax.bar(i, mean, 0.8, color=colours[i], **bars)
            ref = reference.get(f"{m}|{p}|{column}")
            if ref is not None:
                ax.plot([i - 0.4, i + 0.4], [100 * ref] * 2, color="black", lw=1.6)
        ax.set_title(column.replace("avg:", "average, ") + _coverage_mark(table, rows, column), fontsize=9)
        ax.set_xticks(xs, [])
        ax.set_ylim(0, 105)
        ax.grid(axis="y", lw=0.3, alpha=0.5)
    for ax in axes.flat[len(columns):]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("success rate (%)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[i]) for i in range(len(rows))]
    labels = [f"{m} / {p}" for m, p in rows]
    if reference:
        handles.append(plt.Line2D([], [], color="black", lw=1.6))
        labels.append(f"{reference_label} (published)")
    return _finish(plt, fig, handles, labels, title, path)


def _with_traces(results: list[dict]) -> dict[tuple[str, str], list[dict]]:
    """(task, method) -> the runs (sorted by seed) with at least one protocol that stored traces."""
    out: dict[tuple[str, str], list[dict]] = {}
    for r in sorted(results, key=lambda r: r["seed"]):
        if any(p.get("traces") for p in r["protocols"].values()):
            out.setdefault((r["task"], r["method"]), []).append(r)
    return out


def plot_detection(results: list[dict], path: Path, title: str) -> Path | None:
    """The detector's traces per task and method (see the module's docstring); None when no run stored any."""
    from ddp.plots import _pyplot

    panels = _with_traces(results)
    if not panels:
        return None
    plt = _pyplot()
    n_rows, n_cols = _grid(len(panels))
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(1.0 + 3.0 * n_cols, 0.8 + 2.4 * n_rows), squeeze=False)
    floor = 1e-3  # a log axis: statistics at or below zero are drawn at this floor
    for ax, ((task, method), runs) in zip(axes.flat, panels.items()):
        counts = {"id": 0, "ok": 0, "failed": 0}
        visible = []
        for k, run in enumerate(runs):
            for protocol in run["protocols"].values():
                for ep in protocol.get("traces") or []:
                    ys = [float("nan") if v is None else max(v, floor) for v in ep["score"]]
                    disturbed = ep["first_visible"] is not None
                    if not disturbed:
                        colour, kind, z = "0.6", "id", 1
                    else:
                        colour, kind, z = ("tab:green", "ok", 2) if ep["success"] else ("tab:red", "failed", 3)
                        visible.append(ep["first_visible"])
                    counts[kind] += 1
                    ax.plot(range(len(ys)), ys, color=colour, lw=0.7, alpha=0.6, zorder=z)
                    switch = ep["mode"].find("1")
                    if disturbed and switch >= 0 and switch < len(ys) and not math.isnan(ys[switch]):
                        ax.plot(switch, ys[switch], "o", ms=2.5, color=colour, zorder=z + 1)
            taus = {p["tau"] for p in run["protocols"].values() if p.get("traces") and p.get("tau") is not None}
            for tau in taus:  # one calibration per run: its protocols share it
                ax.axhline(max(floor, tau), color="black", ls="--", lw=0.9, alpha=1.0 if k == 0 else 0.6)
        if visible:
            ax.axvline(float(np.median(visible)), color="black", ls=":", lw=0.9)
        ax.set_yscale("log")
        seeds = ",".join(str(r["seed"]) for r in runs)
        ax.set_title(f"{task} / {method} (seed {seeds})\n{counts['id']} ID, {counts['ok']} disturbed ok, "
                     f"{counts['failed']} failed", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    for ax in axes[-1, :]:
        ax.set_xlabel("control cycle (action chunk)", fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel("detector statistic", fontsize=8)
    handles = [plt.Line2D([], [], color="0.6"), plt.Line2D([], [], color="tab:green"),
               plt.Line2D([], [], color="tab:red"), plt.Line2D([], [], color="black", marker="o", ls="", ms=3),
               plt.Line2D([], [], color="black", ls="--"), plt.Line2D([], [], color="black", ls=":")]
    labels = ["in distribution (id_ddp)", "disturbed, succeeded", "disturbed, failed", "switch to OOD",
              "tau (one per seed)", "first visible (median)"]
    return _finish(plt, fig, handles, labels, title, path)
