"""D_R-I separability report: AUROC, first crossing, and the report on the synthetic env."""

import math

import numpy as np
import pytest

from conftest import fit_normalizer
from ddp import build
from ddp.separability import auroc, first_above, format_report, plot_separability, separability


def test_auroc_counts_pairs_and_ties():
    assert auroc([0.1, 0.2], [0.3, 0.4]) == 1.0
    assert auroc([0.3, 0.4], [0.1, 0.2]) == 0.0
    assert auroc([0.1, 0.3], [0.2]) == 0.5  # one pair above, one below
    assert auroc([0.2], [0.2]) == 0.5  # a tie counts half
    assert auroc([0.1, float("nan")], [0.2]) == 1.0  # NaN (no forecast yet) dropped
    assert math.isnan(auroc([], [0.2]))
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=300), rng.normal(1.0, size=300)
    # against the rank formula (Mann-Whitney U / n m)
    ranks = np.argsort(np.argsort(np.concatenate([x, y]))) + 1
    u = ranks[300:].sum() - 300 * 301 / 2
    assert auroc(x, y) == pytest.approx(u / (300 * 300))


def test_first_above_skips_nan():
    assert first_above([float("nan"), 0.1, 0.5, 0.9], 0.4) == 2
    assert first_above([float("nan"), 0.1], 0.4) is None
    # one threshold per index, the last one repeated past the list
    assert first_above([0.3, 0.3, 0.3], [0.5, 0.2]) == 1
    assert first_above([0.3, 0.1, 0.6], [0.5, 0.5]) == 2
    assert first_above([0.3, 0.1, 0.4], [0.5, 0.5]) is None


def test_report_on_the_synthetic_env(tiny_recipe, tmp_path):
    tiny_recipe["env"].update(displacement_chunk=1, displacement_delta=[0.2, 0.0, 0.0], max_episode_steps=32)
    exp = build(tiny_recipe)
    fit_normalizer(exp)
    rep = separability(exp, episodes=2, tau=0.5, progress=False)
    assert rep["tau"] == 0.5 and not rep["tau_calibrated"]
    assert len(rep["discrepancy"]["id"]) == 2 and len(rep["discrepancy"]["ood_base"]) == 2
    chunks = len(rep["discrepancy"]["id"][0])
    assert [r["chunk"] for r in rep["chunks"]] == list(range(1, chunks))  # chunk 0 has no forecast
    # same seeds, same actions until the displacement: identical D_R-I before it is observed
    assert rep["discrepancy"]["id"][0][1] == rep["discrepancy"]["ood_base"][0][1]
    assert rep["discrepancy"]["id"][0][2:] != rep["discrepancy"]["ood_base"][0][2:]
    for r, vals in zip(rep["detection_chunk"], rep["discrepancy"]["ood_base"]):
        assert r == first_above(vals, 0.5)
    text = format_report(rep)
    assert "AUROC" in text and f"tau 0.5 (recipe)" in text
    plot_separability(rep, tmp_path / "s.png")
    assert (tmp_path / "s.png").stat().st_size > 0
    # no tau given and none in the recipe's detector: calibrated on ID rollouts
    exp.recipe.eval.calibration_episodes = 1
    rep = separability(exp, episodes=1, progress=False)
    assert rep["tau_calibrated"] and rep["tau"] > 0
    per = rep["tau_per_chunk"]
    assert per[-1] == rep["tau"] and all(t > 0 for t in per)
    assert rep["detection_chunk_per_chunk"] == [first_above(d, per) for d in rep["discrepancy"]["ood_base"]]
    assert "per-chunk thresholds" in format_report(rep)
    plot_separability(rep, tmp_path / "s2.png")
