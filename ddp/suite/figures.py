"""A suite report's figures: success per task beside the paper's numbers, and the detector's traces per task.

* :func:`plot_table` (``table.png``): one small panel per task and per benchmark average, one bar
  per method x protocol (a hue per method, a shade per protocol, the same in every panel, labelled
  under the bottom row). A task's error bar is the 95 % Wilson interval over all its episodes (every
  seed pooled), an average's the std over seeds (clipped to 0-100 %), and each seed's own rate is a
  dot where there are several; a black tick marks the published number. Written on the bars: "n/a"
  where a cell was not run (a missing bar is not 0 %), "k/n" for an average over k of its n tasks,
  "†" for an average whose tasks have different seeds (no spread).
* :func:`plot_detection` (``detection.png``): one panel per task and method whose runs stored
  detector traces. Each episode's statistic per control cycle on a log axis: in distribution
  (``id_ddp``) grey, disturbed (``ood_ddp``, or any other protocol with a detector statistic) green
  when the episode succeeded and red when it failed, a dot where the controller switched to OOD in a
  disturbed episode and a cross where it did in an ID one (a false alarm), each seed's threshold tau in
  its own line style (its traces share it), and the median first chunk at which the disturbance was
  visible dotted; the title counts the episodes per disturbance protocol. Where
  a task's automatic detection lags its oracle schedule, this shows whether the alarm came late, too
  early or never.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ddp.plots import save_figure

__all__ = ["plot_table", "plot_detection"]


def _grid(n: int, cols: int = 5) -> tuple[int, int]:
    cols = max(1, min(cols, n))
    return math.ceil(n / cols), cols


def _errors(cell: dict | None) -> tuple[float, float | None, float | None]:
    """(mean, lower, upper) error-bar lengths in percent; NaN mean for a missing cell, None lengths for a cell
    with no spread to draw.

    A task's cell (successes of episodes) gets the 95 % Wilson interval of all its episodes pooled over seeds:
    with two or three seeds a std says little, and one kind of bar for every task keeps methods with one
    and with several seeds comparable (the spread between seeds shows as their dots). Seeds with unequal
    episode counts, and averages, get the std of their per-seed rates, clipped to 0-100 %; an average with
    no std (one seed, or tasks with different seeds) gets the 95 % interval its episodes allow."""
    if cell is None:
        return float("nan"), None, None
    from ddp.suite.report import wilson  # (the report module imports this one)

    mean = 100 * cell["mean"]
    lo = hi = None
    if cell.get("episodes") and cell.get("successes") is not None:
        # the pooled interval sits around the bar's top (the seeds' mean rate) only where that is the pooled
        # rate: equal episodes per seed; with unequal ones the std below
        if abs(cell["successes"] / cell["episodes"] - cell["mean"]) < 1e-9:
            lo, hi = wilson(cell["successes"], cell["episodes"])
    elif "wilson95" in cell:
        lo, hi = cell["wilson95"]
    if lo is not None:  # clipped at 0 where the interval's end rounds to a hair inside the rate
        return mean, max(0.0, mean - 100 * lo), max(0.0, 100 * hi - mean)
    if "std" in cell:
        std = 100 * cell["std"]
        return mean, min(std, mean), min(std, 100 - mean)
    if "ci95" in cell:
        lo, hi = cell["ci95"]
        return mean, max(0.0, mean - 100 * lo), max(0.0, 100 * hi - mean)
    return mean, None, None


def _bar_note(cell: dict | None) -> str:
    """What a bar cannot show: "n/a" (not run), "k/n" (an average over k of its n tasks), "†" (an average
    whose tasks have different seeds)."""
    from ddp.suite.report import _coverage  # (imported here: the report module imports this one)

    if cell is None:
        return "n/a"
    note = _coverage(cell) if cell.get("missing_tasks") else ""
    return note + ("†" if cell.get("uneven_seeds") else "")


def _colours(plt, rows) -> list:
    """A hue per method, lighter shades for its later protocols: bars of one method read as a group."""
    methods = list(dict.fromkeys(m for m, _ in rows))
    hues = plt.get_cmap("tab10")
    out = []
    for m, p in rows:
        own = [q for n, q in rows if n == m]
        shade = 0.6 * own.index(p) / max(1, len(own) - 1) if len(own) > 1 else 0.0  # 0: the full hue
        r, g, b, _ = hues(methods.index(m) % hues.N)
        out.append((r + (1 - r) * shade, g + (1 - g) * shade, b + (1 - b) * shade))
    return out


def _finish(plt, fig, handles, labels, title: str, path: Path) -> Path:
    """The shared legend beside the panels, the title, and the file."""
    fig.legend(handles, labels, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(plt, fig, path, dpi=110, bbox_inches="tight")


def plot_table(table: dict, columns: list[str], path: Path, title: str, reference: dict[str, float] | None = None,
               reference_label: str = "paper") -> Path:
    """Small multiples of the success table, a panel per column (tasks, then ``avg:<benchmark>``);
    ``reference`` maps ``method|protocol|column`` to a rate in [0, 1]."""
    from ddp.plots import _pyplot

    plt = _pyplot()
    reference = reference or {}
    rows = table["rows"]
    colours = _colours(plt, rows)
    n_rows, n_cols = _grid(len(columns))
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(2.2 + 2.4 * n_cols, 1.4 + 2.3 * n_rows),
                             sharey=True, squeeze=False)
    xs = np.arange(len(rows))
    several_seeds = False
    for ax, column in zip(axes.flat, columns):
        for i, (m, p) in enumerate(rows):
            cell = table["cells"].get(f"{m}|{p}|{column}")
            mean, lo, hi = _errors(cell)
            if not math.isnan(mean):
                bars = {} if lo is None else {"yerr": [[lo], [hi]], "capsize": 1.5, "error_kw": {"lw": 0.8}}
                ax.bar(i, mean, 0.8, color=colours[i], hatch="//" if cell.get("missing_tasks") else None,
                       edgecolor="white" if cell.get("missing_tasks") else None, lw=0, **bars)
                per_seed = cell.get("per_seed") or []
                if len(per_seed) > 1 and not cell.get("uneven_seeds"):  # (there: only the seeds all tasks share)
                    several_seeds = True
                    ax.plot([i] * len(per_seed), [100 * v for v in per_seed], "o", ms=2, color="black", zorder=4)
            note = _bar_note(cell)
            if note:  # at the bar's foot, inside it: a note above a bar near 100 % would leave the panel
                ax.text(i, 2.0, note, rotation=90 if len(note) > 1 else 0, ha="center", va="bottom", fontsize=6,
                        color="0.15", zorder=6)
            ref = reference.get(f"{m}|{p}|{column}")
            if ref is not None:  # drawn over the axis line at 0 %, not clipped by it
                ax.plot([i - 0.4, i + 0.4], [100 * ref] * 2, color="black", lw=1.6, clip_on=False, zorder=5)
        ax.set_title(column.replace("avg:", "average, "), fontsize=9)
        ax.set_xticks(xs, [])
        ax.set_xlim(-0.6, len(rows) - 0.4)  # the same slots in every panel, whichever cells were run
        ax.set_ylim(-4, 105)  # 0 % bars and published zeros stay visible above the frame
        ax.set_yticks(range(0, 101, 20))
        ax.axhline(0, color="0.4", lw=0.6)
        ax.grid(axis="y", lw=0.3, alpha=0.5)
    for ax in axes.flat[len(columns):]:
        ax.axis("off")
    for c in range(min(n_cols, len(columns))):  # the bottom panel of each column names its bars
        r = (len(columns) - 1 - c) // n_cols
        axes[r, c].set_xticks(xs, [f"{m} / {p}" for m, p in rows], rotation=90, fontsize=6)
    for ax in axes[:, 0]:
        ax.set_ylabel("success rate (%)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[i]) for i in range(len(rows))]
    labels = [f"{m} / {p}" for m, p in rows]
    handles.append(plt.Line2D([], [], color="black", lw=0.8, marker="_", ms=6))
    labels.append("error bar: task, 95 % Wilson interval over its episodes (seeds pooled;\n"
                  "std over seeds where their episode counts differ); average, std over\n"
                  "seeds (one seed: 95 % interval from its episodes)")
    if several_seeds:
        handles.append(plt.Line2D([], [], color="black", marker="o", ls="", ms=3))
        labels.append("one seed's rate")
    if reference:
        handles.append(plt.Line2D([], [], color="black", lw=1.6))
        labels.append(f"{reference_label} (published)")
    handles.append(plt.Rectangle((0, 0), 1, 1, facecolor="0.7", hatch="//", edgecolor="white"))
    labels.append('average over only some tasks ("k/n");\n"†": tasks with different seeds; "n/a": not run')
    return _finish(plt, fig, handles, labels, title, path)


#: how the detection figure's titles name each seed's line style
STYLE_NAMES = ["solid", "dashed", "dotted", "dash-dot-dot", "long dash"]


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
    all_seeds: dict[tuple[str, str], set[int]] = {}
    for r in results:
        all_seeds.setdefault((r["task"], r["method"]), set()).add(r["seed"])
    plt = _pyplot()
    n_rows, n_cols = _grid(len(panels))
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(1.0 + 3.0 * n_cols, 0.8 + 2.4 * n_rows), squeeze=False)
    from matplotlib.ticker import MaxNLocator

    floor = 1e-3  # a log axis: statistics at or below zero are drawn at this floor
    # a run's traces and its tau share a line style (seeds in order; the first seed's tau dash-dot)
    seed_styles = ["-", "--", ":", (0, (5, 1, 1, 1, 1, 1)), (0, (8, 2))]
    for ax, ((task, method), runs) in zip(axes.flat, panels.items()):
        id_count, disturbed = 0, {}  # disturbed: protocol -> [succeeded, failed]
        visible = []
        for k, run in enumerate(runs):
            style = seed_styles[k % len(seed_styles)]
            for name, protocol in run["protocols"].items():
                for ep in protocol.get("traces") or []:
                    ys = [float("nan") if v is None else max(v, floor) for v in ep["score"]]
                    if ep["first_visible"] is None:
                        colour, z = "0.6", 1
                        id_count += 1
                    else:
                        colour, z = ("tab:green", 2) if ep["success"] else ("tab:red", 3)
                        disturbed.setdefault(name, [0, 0])[0 if ep["success"] else 1] += 1
                        visible.append(ep["first_visible"])
                    ax.plot(range(len(ys)), ys, color=colour, lw=0.7, alpha=0.6, zorder=z, ls=style)
                    switch = (ep.get("mode") or "").find("1")
                    if 0 <= switch < len(ys) and not math.isnan(ys[switch]):
                        # a switch in an ID episode is a false alarm: a cross
                        marker = "o" if ep["first_visible"] is not None else "x"
                        ax.plot(switch, ys[switch], marker, ms=3, color=colour if marker == "o" else "0.2",
                                zorder=z + 1)
            taus = {p["tau"] for p in run["protocols"].values() if p.get("traces") and p.get("tau") is not None}
            for tau in taus:  # one calibration per run: its protocols share it
                ax.axhline(max(floor, tau), color="black", ls="-." if style == "-" else style, lw=0.9)
        if visible:
            ax.axvline(float(np.median(visible)), color="tab:blue", ls=":", lw=1.0)
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        seeds = ", ".join(f"seed {r['seed']}" + (f" {STYLE_NAMES[k % len(STYLE_NAMES)]}" if len(runs) > 1 else "")
                          for k, r in enumerate(runs))  # (a sixth seed repeats the first style)
        untraced = sorted(all_seeds.get((task, method), set()) - {r["seed"] for r in runs})
        if untraced:
            seeds += f"; seed {', '.join(map(str, untraced))}: no traces"
        kinds = ", ".join(f"{name} {ok}/{ok + bad} ok" for name, (ok, bad) in disturbed.items())
        ax.set_title(f"{task} / {method} ({seeds})\n{id_count} ID; {kinds or 'none disturbed'}", fontsize=8)
        ax.tick_params(labelsize=8)
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    for ax in axes[-1, :]:
        ax.set_xlabel("control cycle (action chunk)", fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel("D_R-I statistic (log axis)", fontsize=8)
    handles = [plt.Line2D([], [], color="0.6"), plt.Line2D([], [], color="tab:green"),
               plt.Line2D([], [], color="tab:red"), plt.Line2D([], [], color="tab:green", marker="o", ls="", ms=3),
               plt.Line2D([], [], color="0.2", marker="x", ls="", ms=3),
               plt.Line2D([], [], color="black", ls="-."), plt.Line2D([], [], color="tab:blue", ls=":"),
               plt.Line2D([], [], ls="")]
    labels = ["undisturbed (id_ddp, or the disturbance never showed)", "disturbed, succeeded", "disturbed, failed",
              "switch to OOD (disturbed episode)", "switch to OOD in an ID episode (false alarm)",
              "tau: dash-dot for the first seed (its traces\nsolid); later seeds' tau in their traces' style",
              "first visible chunk (median)", f"(statistics <= {floor:g} are drawn at {floor:g})"]
    return _finish(plt, fig, handles, labels, title, path)
