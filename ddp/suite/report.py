"""Aggregating a suite's results: the paper's Table 1 layout with the variance over seeds.

Rows are method x protocol (the paper's conditions: ``id``, ``ood_base``, ``ood_tracking``,
``ood_ddp`` with automatic detection, ``ood_ddp_oracle``, ``imagination_*``), columns are the tasks
and one average per benchmark. A cell is the mean success rate over seeds +/- its standard deviation
(sample std, ddof 1) with the seeds and episodes behind it; with a single seed it is the rate with
its 95 % Wilson interval instead. A benchmark average is the mean over its tasks, and its std is
that of the per-seed averages over tasks (seeds every task of the benchmark has).
:func:`write_suite_report` writes ``table.md``, ``table.json``, ``table.csv``, ``cost.md``, with a
reference ``vs_reference.md`` (the gaps to the published numbers), and the figures of
:mod:`ddp.suite.figures` (``table.png``; ``detection.png`` when runs stored detector traces).
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from pathlib import Path

import numpy as np

from ddp import results_json
from ddp.atomic_file import atomic_write
from ddp.percent import percent
from ddp.suite.figures import plot_detection, plot_table
from ddp.suite.store import evaluation_seconds

__all__ = ["aggregate", "wilson", "write_suite_report", "format_cell", "gaps_markdown"]


def wilson(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The 95 % Wilson score interval of a binomial proportion."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def average_interval(mean: float, episodes: list[int]) -> tuple[float, float]:
    """The 95 % interval of an average of task success rates that the episodes' own (binomial) noise
    allows, for tasks of ``episodes`` episodes each (over their seeds): the Wilson interval of ``mean``
    over the effective count ``tasks**2 / sum(1 / episodes)`` (the pooled episodes where every task has
    the same number; the average then is the pooled rate). Two seeds that agree give a std of 0; this says
    how far 20 episodes a task still leave the average."""
    if not episodes or min(episodes) <= 0:
        return (float("nan"), float("nan"))
    n = len(episodes) ** 2 / sum(1 / e for e in episodes)
    return wilson(mean * n, n)


def _cell(rates: list[float], successes: int, episodes: int, seeds: list[int]) -> dict:
    cell = {"mean": float(np.mean(rates)), "seeds": seeds, "episodes": episodes, "successes": successes,
            "per_seed": rates}
    if len(rates) > 1:
        cell["std"] = float(np.std(rates, ddof=1))
    else:
        cell["wilson95"] = list(wilson(successes, episodes))
    return cell


def reference_cells(table: dict, reference: dict | None) -> dict[str, float]:
    """``{"method|protocol|column": rate}`` from a suite's reference (percent) for the table's rows and columns.

    A task column reads ``values[method][protocol][benchmark][task]``, where a label ``<task>-<benchmark>``
    (e.g. ``hammer-adroit``, beside MetaWorld's ``hammer``) reads ``<task>``. ``avg:<benchmark>`` is the
    reference's own ``avg`` where the suite averages the very tasks it lists, else the mean of its numbers
    over the suite's tasks (absent unless it has them all): a suite of three tasks is not compared with a
    ten-task average.
    """
    if not reference:
        return {}
    bench_of = {t: b for b, names in table["benchmarks"].items() for t in names}
    out = {}
    for m, p in table["rows"]:
        by_bench = (reference["values"].get(m) or {}).get(p) or {}
        for t in table["tasks"]:
            bench = bench_of[t]
            name = t[: -len(bench) - 1] if t.endswith(f"-{bench}") else t
            value = (by_bench.get(bench) or {}).get(name)
            if value is not None:
                out[f"{m}|{p}|{t}"] = float(value) / 100
        for bench, names in table["benchmarks"].items():
            cell = table["cells"].get(f"{m}|{p}|avg:{bench}")
            have = cell["tasks"] if cell else names
            if not have or not all(f"{m}|{p}|{t}" in out for t in have):
                continue
            published = by_bench.get(bench) or {}
            tasks = {k for k in published if k != "avg"}
            named = {t[: -len(bench) - 1] if t.endswith(f"-{bench}") else t for t in have}
            if "avg" in published and named == tasks:  # the very tasks the paper averaged: its own number
                out[f"{m}|{p}|avg:{bench}"] = float(published["avg"]) / 100
            else:
                # to a tenth of a point, as the paper's own averages (it printed 0.1429 and 22.14)
                out[f"{m}|{p}|avg:{bench}"] = round(float(np.mean([out[f"{m}|{p}|{t}"] for t in have])), 3)
    return out


def aggregate(results: list[dict], tasks_of_suite: dict[str, str] | None = None) -> dict:
    """``{"rows": [(method, protocol)], "tasks": [...], "benchmarks": {name: [tasks]}, "cells": {...}}``.

    ``tasks_of_suite`` (label -> benchmark, the suite file's tasks) makes a benchmark's tasks those the suite
    lists, so that an average over the tasks with results so far says how many of them it covers
    ("missing_tasks"); without it a benchmark is the tasks that have results.
    """
    tasks = list(dict.fromkeys(r["task"] for r in results))
    methods = list(dict.fromkeys(r["method"] for r in results))
    benchmarks: dict[str, list[str]] = {}
    for label, bench in (tasks_of_suite or {}).items():
        benchmarks.setdefault(bench, []).append(label)
    for r in results:
        benchmarks.setdefault(r.get("benchmark", "all"), [])
        if r["task"] not in benchmarks[r.get("benchmark", "all")]:
            benchmarks[r.get("benchmark", "all")].append(r["task"])
    rows, cells = [], {}
    for m in methods:
        protocols = list(dict.fromkeys(p for r in results if r["method"] == m for p in r["protocols"]))
        for p in protocols:
            rows.append((m, p))
            per_task_seed: dict[str, dict[int, float]] = {}
            for t in tasks:
                runs = sorted((r for r in results if r["method"] == m and r["task"] == t and p in r["protocols"]),
                              key=lambda r: r["seed"])
                if not runs:
                    continue
                rates = [r["protocols"][p]["success_rate"] for r in runs]
                cells[f"{m}|{p}|{t}"] = _cell(rates, sum(r["protocols"][p]["successes"] for r in runs),
                                              sum(r["protocols"][p]["episodes"] for r in runs),
                                              [r["seed"] for r in runs])
                per_task_seed[t] = {r["seed"]: r["protocols"][p]["success_rate"] for r in runs}
            for bench, names in benchmarks.items():
                have = [t for t in names if t in per_task_seed]
                if not have:
                    continue
                seeds = sorted(set.intersection(*(set(per_task_seed[t]) for t in have)))
                per_seed = [float(np.mean([per_task_seed[t][s] for t in have])) for s in seeds]
                task_means = [float(np.mean(list(per_task_seed[t].values()))) for t in have]
                cell = {"mean": float(np.mean(task_means)), "tasks": have, "seeds": seeds, "per_seed": per_seed}
                counts = [cells[f"{m}|{p}|{t}"]["episodes"] for t in have]
                cell["episodes"] = sum(counts)
                cell["ci95"] = list(average_interval(cell["mean"], counts))
                uneven = any(set(per_task_seed[t]) != set(seeds) for t in have)
                if uneven:  # the mean uses every run, a std over the shared seeds would describe fewer: none
                    cell["uneven_seeds"] = True
                elif len(per_seed) > 1:
                    cell["std"] = float(np.std(per_seed, ddof=1))
                if len(have) < len(names):
                    cell["missing_tasks"] = [t for t in names if t not in have]
                cells[f"{m}|{p}|avg:{bench}"] = cell
    return {"rows": rows, "tasks": tasks, "benchmarks": benchmarks, "cells": cells}


def format_cell(cell: dict | None) -> str:
    if cell is None:
        return "-"
    text = percent(cell["mean"])
    if "std" in cell:
        text += f" ± {percent(cell['std'])}"
    elif "wilson95" in cell:
        lo, hi = cell["wilson95"]
        text += f" [{percent(lo)}, {percent(hi)}]"
    if "ci95" in cell:  # an average: the interval its episodes allow, beside any std over seeds
        lo, hi = cell["ci95"]
        text += f" [{percent(lo)}, {percent(hi)}]"
    if "episodes" in cell:
        text += f" (n={cell['episodes']})"
    if cell.get("uneven_seeds"):
        text += " †"
    if cell.get("missing_tasks"):
        text += f" ({_coverage(cell)} tasks)"
    return text


def _coverage(cell: dict) -> str:
    """``k/n``: an average over k of its benchmark's n tasks."""
    k = len(cell["tasks"])
    return f"{k}/{k + len(cell.get('missing_tasks', []))}"


def _columns(table: dict) -> list[str]:
    return [*table["tasks"], *(f"avg:{b}" for b in table["benchmarks"])]


def markdown(table: dict, title: str, reference: dict | None = None) -> str:
    """The table; with a reference, each row that has published numbers is followed by a row of them."""
    cols = _columns(table)
    ref = reference_cells(table, reference)
    label = reference["label"] if reference else ""
    lines = [f"{title}: success rate in %, mean ± std over seeds (one seed: [95 % Wilson interval]); "
             "n = episodes over all seeds; an average is the mean of its task means, ± std of the per-seed "
             "averages, [95 % interval from its episodes' binomial noise] (†: its tasks have "
             "different seeds, so no std; (k/n tasks): runs of only k tasks)"
             + (f"; rows marked ({label}) are the published numbers" if ref else ""),
             "", "| method | protocol | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for m, p in table["rows"]:
        cells = [format_cell(table["cells"].get(f"{m}|{p}|{c}")) for c in cols]
        lines.append(f"| {m} | {p} | " + " | ".join(cells) + " |")
        if any(f"{m}|{p}|{c}" in ref for c in cols):
            published = [f"{100 * ref[f'{m}|{p}|{c}']:.4g}" if f"{m}|{p}|{c}" in ref else "-" for c in cols]
            lines.append(f"| {m} | {p} ({label}) | " + " | ".join(published) + " |")
    return "\n".join(lines) + "\n"


def gaps_markdown(table: dict, reference: dict, title: str) -> str:
    """Where the results stand against the reference: every benchmark average with a published number (ours,
    theirs, the difference in percentage points, whether it is within the reference's ``tolerance``), then
    every task cell outside the tolerance, largest shortfall first."""
    ref, label = reference_cells(table, reference), reference["label"]
    tol = float(reference.get("tolerance", 10))

    def row(key: str) -> tuple[str, str, str, str, float]:
        m, p, c = key.split("|")
        ours = table["cells"][key]
        gap = 100 * (ours["mean"] - ref[key])
        spread = f" ± {100 * ours['std']:.1f}" if "std" in ours else ""
        return m, p, c, f"{100 * ours['mean']:.1f}{spread}", gap

    averages = [row(k) for k in ref if "|avg:" in k and k in table["cells"]]
    tasks = sorted((row(k) for k in ref if "|avg:" not in k and k in table["cells"]), key=lambda r: r[4])
    lines = [f"{title}: against the {label} numbers (percentage points; within ±{tol:g}: reproduced)", "",
             f"| method | protocol | benchmark | ours | {label} | ours - {label} | within ±{tol:g} |",
             "|---|---|---|---|---|---|---|"]
    for m, p, c, ours, gap in averages:
        cell = table["cells"][f"{m}|{p}|{c}"]  # an average over part of the benchmark is compared over that part
        part = f" ({_coverage(cell)} tasks)" if cell.get("missing_tasks") else ""
        lines.append(f"| {m} | {p} | {c[len('avg:'):]}{part} | {ours} | {100 * ref[f'{m}|{p}|{c}']:.4g} | {gap:+.1f} | "
                     f"{'yes' if abs(gap) <= tol + 1e-9 else 'no'} |")
    outside = [r for r in tasks if abs(r[4]) > tol + 1e-9]
    lines += ["", f"Task cells more than {tol:g} points from the {label}'s ({len(outside)} of {len(tasks)}), "
              "largest shortfall first:", "", f"| method | protocol | task | ours | {label} | ours - {label} |",
              "|---|---|---|---|---|---|"]
    for m, p, c, ours, gap in outside:
        lines.append(f"| {m} | {p} | {c} | {ours} | {100 * ref[f'{m}|{p}|{c}']:.4g} | {gap:+.1f} |")
    return "\n".join(lines) + "\n"


def _minutes(seconds: list[float]) -> str:
    return f"{statistics.median(seconds) / 60:.1f} [{min(seconds) / 60:.1f}, {max(seconds) / 60:.1f}]"


def run_wall_seconds(result: dict) -> float | None:
    """A run's wall time over all its attempts: the last start's ``wall_seconds`` plus the training that
    earlier attempts did (a resumed run's ``train.seconds`` counts every attempt, ``attempt_seconds`` the last)."""
    if result.get("wall_seconds") is None:
        return None
    train = result.get("train") or {}
    earlier = 0.0
    if train.get("seconds") is not None and train.get("attempt_seconds") is not None:
        earlier = max(float(train["seconds"]) - float(train["attempt_seconds"]), 0.0)
    return float(result["wall_seconds"]) + earlier


def cost_markdown(results: list[dict], title: str) -> str:
    """What the stored runs cost, per method: training time (all of it, across resumes), the evaluation
    protocols' time, and each run's wall time over all its attempts (:func:`run_wall_seconds`)."""
    lines = [f"{title}: compute per stored run, in minutes (median [min, max]); totals in hours; a resumed "
             "run's wall time adds the training its earlier attempts did", "",
             "| method | runs | training steps | training | evaluation protocols | wall time | total wall time |",
             "|---|---|---|---|---|---|---|"]
    for method in sorted({r["method"] for r in results}):
        runs = [r for r in results if r["method"] == method]
        train = [float(r["train"]["seconds"]) for r in runs if (r.get("train") or {}).get("seconds") is not None]
        evals = [evaluation_seconds(r) for r in runs]
        wall = [w for w in map(run_wall_seconds, runs) if w is not None]
        steps = sorted({int(r["train"]["steps"]) for r in runs if (r.get("train") or {}).get("steps") is not None})
        lines.append(f"| {method} | {len(runs)} | {', '.join(map(str, steps)) or '-'} | "
                     f"{_minutes(train) if train else '-'} | {_minutes(evals)} | {_minutes(wall) if wall else '-'} | "
                     f"{sum(wall) / 3600:.1f} |")
    return "\n".join(lines) + "\n"


def write_suite_report(results: list[dict], out_dir: str | Path, title: str,
                       reference: dict | None = None, tasks_of_suite: dict[str, str] | None = None) -> list[Path]:
    """table.md, table.json, table.csv, cost.md and table.png under ``out_dir``; returns their paths. A ``reference``
    (the suite's published numbers) adds rows to table.md, a ``reference`` entry to table.json and
    ``vs_reference.md`` (:func:`gaps_markdown`). ``tasks_of_suite``: see :func:`aggregate` (averages over part
    of a benchmark's tasks are marked "(k/n tasks)" in every file)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = aggregate(results, tasks_of_suite)

    def write(name: str, text: str) -> None:  # whole or not at all (a report is committed beside its results)
        atomic_write(out / name, lambda f: f.write(text), binary=False)

    write("table.md", markdown(table, title, reference))
    write("cost.md", cost_markdown(results, title))
    ref = reference_cells(table, reference)
    extra = {"reference": {"label": reference["label"], "cells": ref}} if reference else {}
    write("table.json", results_json.dumps({**table, "rows": [list(r) for r in table["rows"]], **extra}))
    cols = _columns(table)
    buffer = io.StringIO(newline="")
    w = csv.writer(buffer)
    # every cell: mean, std over seeds (empty with one), episodes, seeds, its 95 % interval (a task's Wilson
    # interval of its pooled episodes, an average's from its episodes' noise); an average also says which of
    # its benchmark's tasks it covers (k/n) and whether their seeds differ
    w.writerow(["method", "protocol", *(f"{c}_{k}" for c in cols
                                        for k in ("mean", "std", "n", "seeds", "lo95", "hi95",
                                                  *(("tasks", "uneven_seeds") if c.startswith("avg:") else ())))])
    for m, p in table["rows"]:
        row = [m, p]
        for c in cols:
            cell = table["cells"].get(f"{m}|{p}|{c}")
            if cell is None:
                row += [""] * (8 if c.startswith("avg:") else 6)
                continue
            if "ci95" in cell:
                lo, hi = cell["ci95"]
            elif cell.get("episodes"):
                lo, hi = wilson(cell["successes"], cell["episodes"])
            else:
                lo = hi = ""
            row += [cell["mean"], cell.get("std", ""), cell.get("episodes", ""),
                    " ".join(str(s) for s in cell["seeds"]), lo, hi]
            if c.startswith("avg:"):
                row += [_coverage(cell), bool(cell.get("uneven_seeds"))]
        w.writerow(row)
    write("table.csv", buffer.getvalue())
    paths = [out / "table.md", out / "table.json", out / "table.csv", out / "cost.md"]
    if ref:
        write("vs_reference.md", gaps_markdown(table, reference, title))
        paths.append(out / "vs_reference.md")
    else:  # an earlier report's, from when the suite named a reference
        (out / "vs_reference.md").unlink(missing_ok=True)
    try:
        paths.append(plot_table(table, cols, out / "table.png", title, ref,
                                reference["label"] if reference else "paper"))
        traces = plot_detection(results, out / "detection.png", f"{title}: the detector's statistic per episode")
        if traces is not None:
            paths.append(traces)
        else:  # no stored run has traces now: an earlier report's figure would describe other runs
            (out / "detection.png").unlink(missing_ok=True)
    except ImportError:  # no matplotlib: the tables alone (figures already there are left as they are)
        pass
    return paths
