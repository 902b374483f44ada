"""Reports write percentages with halves rounded up, the same in every table, plot and log line."""

import pytest

from ddp.percent import percent
from ddp.suite.figures import _bar_note, _errors
from ddp.suite.report import format_cell


@pytest.mark.parametrize("fraction,text", [(33 / 40, "83"), (39 / 40, "98"), (29 / 40, "73"), (5 / 40, "13"),
                                           (25 / 40, "63"), (17 / 20, "85"), (0.0, "0"), (1.0, "100"), (2 / 3, "67")])
def test_halves_round_up(fraction, text):
    assert percent(fraction) == text


def test_one_decimal_and_a_table_cell():
    assert percent(0.74255, 1) == "74.3" and percent(0.7425, 1) == "74.3" and percent(0.6, 1) == "60.0"
    # two seeds of 20 whose rates differ by an odd count: a half (push ood_ddp 15/20 and 10/20: 62.5 %)
    assert format_cell({"mean": 0.625, "std": 0.1767767, "episodes": 40}) == "63 ± 18 (n=40)"
    assert format_cell({"mean": 0.85, "wilson95": [0.6396, 0.9476], "episodes": 20}) == "85 [64, 95] (n=20)"


def test_an_average_without_spread_draws_no_error_bar_and_says_which_tasks_it_covers():
    one_seed_average = {"mean": 0.883, "tasks": ["a", "b"], "missing_tasks": ["c", "d", "e"]}
    assert _errors(one_seed_average) == (pytest.approx(88.3), None, None)  # no zero-length bar with caps
    assert _errors({"mean": 0.5, "std": 0.1})[1:] == (pytest.approx(10.0), pytest.approx(10.0))
    # a std past 0 or 100 % is clipped there (franka stack's 50 +- 71 ran off the axis)
    assert _errors({"mean": 0.5, "std": 0.71})[1:] == (pytest.approx(50.0), pytest.approx(50.0))
    assert _errors({"mean": 0.9, "std": 0.2})[1:] == (pytest.approx(20.0), pytest.approx(10.0))
    assert _bar_note(one_seed_average) == "2/5" and _bar_note({"mean": 1.0, "tasks": ["a"]}) == ""
    assert _bar_note(None) == "n/a" and _bar_note({"mean": 0.7, "uneven_seeds": True}) == "†"


def test_a_task_bar_is_the_wilson_interval_of_its_pooled_episodes_whatever_its_seeds():
    """Two seeds' std (85 +- 0 from 17/20 twice) looked certain beside one seed's Wilson interval."""
    from ddp.suite.report import wilson

    lo, hi = wilson(34, 40)
    two_seeds = {"mean": 0.85, "seeds": [0, 1], "episodes": 40, "successes": 34, "per_seed": [0.85, 0.85], "std": 0.0}
    assert _errors(two_seeds) == (pytest.approx(85.0), pytest.approx(85 - 100 * lo), pytest.approx(100 * hi - 85))
    lo, hi = wilson(0, 20)
    assert _errors({"mean": 0.0, "episodes": 20, "successes": 0, "wilson95": [lo, hi]}) == (0.0, 0.0, pytest.approx(100 * hi))


def test_an_evaluation_success_plot_carries_each_rate_s_wilson_interval(tmp_path, monkeypatch):
    """success.png: one seed's episodes are the only spread there is; the bars carry their 95 % interval."""
    import matplotlib.axes

    from ddp.plots import plot_success
    from ddp.suite.report import wilson

    seen, real = {}, matplotlib.axes.Axes.bar
    monkeypatch.setattr(matplotlib.axes.Axes, "bar", lambda self, *a, **k: seen.update(k) or real(self, *a, **k))
    report = {"recipe": "r", "episodes": 10, "protocols": {
        "id": {"success_rate": 1.0, "successes": 10, "episodes": 10},
        "ood_ddp": {"success_rate": 0.7, "successes": 7, "episodes": 10},
        "real": {"success_rate": None, "successes": None, "episodes": 10}}}  # not judged: no bar
    assert plot_success(report, tmp_path / "success.png").stat().st_size > 0
    (lo1, hi1), (lo7, hi7) = wilson(10, 10), wilson(7, 10)
    lower, upper = seen["yerr"]
    assert lower == [pytest.approx(100 - 100 * lo1), pytest.approx(70 - 100 * lo7)]
    assert upper == [pytest.approx(max(0.0, 100 * hi1 - 100)), pytest.approx(100 * hi7 - 70)]
