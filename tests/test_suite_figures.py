"""The suite report's figures: what each mark means (drawing calls checked, not pixels)."""

from __future__ import annotations

import pytest

from ddp.suite.figures import _errors, plot_detection, plot_table


def test_unequal_seed_episodes_draw_the_std_not_a_pooled_interval_around_another_rate():
    """1/1 and 0/9: the seeds' mean is 50 %, the pooled rate 10 %; a pooled interval [2, 40] around 50 lied."""
    cell = {"mean": 0.5, "seeds": [0, 1], "episodes": 10, "successes": 1, "per_seed": [1.0, 0.0], "std": 0.7071}
    assert _errors(cell) == (pytest.approx(50.0), pytest.approx(50.0), pytest.approx(50.0))  # clipped std


def test_an_average_without_a_std_draws_the_interval_its_episodes_allow():
    """One seed (or tasks with different seeds): no std, and the bar had no error bar at all."""
    from ddp.suite.report import aggregate

    runs = [{"task": t, "method": "ddp", "seed": 0, "benchmark": "mw", "protocols": {"id": {
        "success_rate": k / 20, "successes": k, "episodes": 20}}} for t, k in (("a", 15), ("b", 12))]
    avg = aggregate(runs)["cells"]["ddp|id|avg:mw"]
    mean, lower, upper = _errors(avg)
    assert "std" not in avg and mean == pytest.approx(67.5)
    assert (mean - lower, mean + upper) == (pytest.approx(100 * avg["ci95"][0]), pytest.approx(100 * avg["ci95"][1]))
    assert 10 < lower < 20 and 10 < upper < 20


def _capture(monkeypatch, method: str) -> list[tuple[tuple, dict]]:
    import matplotlib.axes

    calls, real = [], getattr(matplotlib.axes.Axes, method)
    monkeypatch.setattr(matplotlib.axes.Axes, method,
                        lambda self, *a, **k: calls.append((a, k)) or real(self, *a, **k))
    return calls


def _run(seed: int, traces: list[dict]) -> dict:
    return {"task": "push", "method": "ddp", "seed": seed,
            "protocols": {"id_ddp": {"tau": 1.0, "traces": [t for t in traces if t["first_visible"] is None]},
                          "ood_ddp": {"tau": 1.2, "traces": [t for t in traces if t["first_visible"] is not None]},
                          "occlusion": {"tau": 1.2, "traces": []}}}


def test_detection_figure_marks_false_alarms_and_counts_each_disturbance(tmp_path, monkeypatch):
    plots, titles = _capture(monkeypatch, "plot"), _capture(monkeypatch, "set_title")
    clean_alarm = {"first_visible": None, "success": True, "score": [0.5, 2.0, 0.5], "mode": "011"}
    clean = {"first_visible": None, "success": True, "score": [0.5, 0.4, 0.5], "mode": "000"}
    caught = {"first_visible": 1, "success": True, "score": [0.5, 3.0, 3.0], "mode": "011"}
    missed = {"first_visible": 1, "success": False, "score": [0.5, 0.6, 0.6]}  # no mode stored: no switch
    results = [_run(0, [clean_alarm, clean, caught, missed]), _run(1, [clean, caught]),
               {"task": "push", "method": "ddp", "seed": 2, "protocols": {"id": {"tau": None}}}]
    assert plot_detection(results, tmp_path / "detection.png", "t").stat().st_size > 0
    markers = [(a[2], a[0], a[1]) for a, _ in plots if len(a) == 3 and isinstance(a[2], str)]
    assert ("x", 1, 2.0) in markers  # the ID episode's switch: a false alarm, a cross
    assert [m for m in markers if m[0] == "o"] == [("o", 1, 3.0)] * 2  # the caught move, once per seed
    title = titles[0][0][0]
    assert "seed 0 solid, seed 1 dashed; seed 2: no traces" in title
    assert "3 ID; ood_ddp 2/3 ok" in title  # per disturbance protocol


def test_table_panels_share_their_slots_and_name_cells_not_run(tmp_path, monkeypatch):
    texts, limits = _capture(monkeypatch, "text"), _capture(monkeypatch, "set_xlim")
    table = {"rows": [["ddp", "id"], ["dp3", "id"], ["flowpolicy", "id"]], "cells": {
        "ddp|id|a": {"mean": 1.0, "episodes": 20, "successes": 20, "per_seed": [1.0], "wilson95": [0.84, 1.0]},
        "dp3|id|a": {"mean": 0.0, "episodes": 20, "successes": 0, "per_seed": [0.0], "wilson95": [0.0, 0.16]},
        "ddp|id|avg:mw": {"mean": 1.0, "tasks": ["a"], "missing_tasks": ["b"], "per_seed": [1.0]}}}
    plot_table(table, ["a", "avg:mw"], tmp_path / "table.png", "t")
    notes = [(a[0], a[2]) for a, _ in texts]
    assert (2, "n/a") in notes and (1, "n/a") in notes  # flowpolicy in a, dp3 and flowpolicy in the average
    assert (0, "1/2") in notes and (1, "n/a") in notes and not any(n == (1, "0") for n in notes)
    assert [a for a, _ in limits].count((-0.6, 2.6)) == 2  # both panels: three slots whichever cells ran
