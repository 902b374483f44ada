"""Automatic OOD detection: statistics, conformal calibration, detection metrics, ``ddp detect``, the controller."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from conftest import displaced_exp
from ddp import results_json
from ddp.calibration_file import calibration_path, load_calibration, model_digest, save_calibration
from ddp.detection import alarmed_before_visible, auroc, detection_metrics, first_above
from ddp.detectors.discrepancy import DiscrepancyConfig, DiscrepancyDetector
from ddp.detectors.scores import ScoreSpec, conformal_threshold, episode_statistic, fit_calibration, residual_score


def episodes_from_scores(scores: np.ndarray, m: int = 2, d: int = 4, success=None) -> list[dict]:
    """Latent windows whose paper D_R-I is exactly ``scores[e, c]`` (NaN: no forecast); every episode
    successful unless ``success`` says otherwise (one flag per episode)."""
    out = []
    rows = np.atleast_2d(scores)
    flags = [True] * len(rows) if success is None else list(success)
    for row, ok in zip(rows, flags):
        pred = np.sqrt(row)[:, None, None] * np.ones((1, m, d))
        out.append({"latent_real": np.zeros_like(pred), "latent_pred": pred, "success": bool(ok)})
    return out


# ----------------------------------------------------------------------------------------- statistics
def test_scores_follow_their_definitions():
    real = torch.zeros(3, 2, 6)
    pred = torch.arange(36, dtype=torch.float64).reshape(3, 2, 6) / 10
    r2 = pred**2
    assert torch.allclose(residual_score(real, pred, ScoreSpec()), r2.mean((-1, -2)))
    assert torch.allclose(residual_score(real, pred, ScoreSpec(frames="newest")), r2[:, -1].mean(-1))
    assert torch.allclose(residual_score(real, pred, ScoreSpec(frames="max")), r2.mean(-1).amax(-1))
    assert torch.allclose(residual_score(real, pred, ScoreSpec(dims="point"), point_dims=4), r2[..., :4].mean((-1, -2)))
    assert torch.allclose(residual_score(real, pred, ScoreSpec(dims="state"), point_dims=4), r2[..., 4:].mean((-1, -2)))
    center, scale = torch.full((6,), 0.5, dtype=torch.float64), torch.full((6,), 2.0, dtype=torch.float64)
    white = residual_score(real, pred, ScoreSpec(whiten=True), center=center, scale=scale)
    assert torch.allclose(white, (((0 - pred) - 0.5) / 2.0).pow(2).mean((-1, -2)))
    assert math.isnan(residual_score(real[:1], torch.full((1, 2, 6), float("nan")), ScoreSpec()).item())
    with pytest.raises(ValueError, match="point-cloud and state parts"):
        residual_score(real, pred, ScoreSpec(dims="point"), point_dims=0)


def test_per_chunk_normalisation_and_cusum():
    from ddp.detectors.scores import ScoreCalibration

    cal = ScoreCalibration(median=2.0, chunk_scale=[1.0, 1.0, 4.0])
    s = np.array([np.nan, 2.0, 4.0, 6.0])
    assert episode_statistic(s, ScoreSpec(per_chunk=True), cal)[1:].tolist() == [2.0, 1.0, 3.0]  # chunk 3: median
    cusum = episode_statistic(s, ScoreSpec(per_chunk=True, cusum=True, drift=1.0), cal)
    assert math.isnan(cusum[0]) and cusum[1:].tolist() == [1.0, 1.0, 3.0]  # max(0, S + s - drift)


def test_per_chunk_scale_is_the_chosen_id_quantile_of_each_phase():
    rng = np.random.default_rng(1)
    scores = rng.gamma(2.0, 1.0, size=(20, 5)) * np.array([1.0, 1.0, 8.0, 8.0, 1.0])
    scores[:, 0] = np.nan
    eps = episodes_from_scores(scores)
    for q in (0.5, 0.9):
        spec = ScoreSpec(per_chunk=True, window=0, chunk_quantile=q)
        cal = fit_calibration(eps, spec, alpha=0.2, fit_fraction=0.5)
        fitting = scores[1::2, 1:]  # the 10 fitting episodes (every second one), chunk by chunk
        assert np.allclose(cal.chunk_scale[1:], np.quantile(fitting, q, axis=0))
        # a chunk past the longest fitting episode is scaled by the same quantile over all chunks
        assert cal.scale_at(99) == pytest.approx(np.quantile(fitting, q))
    assert DiscrepancyConfig(per_chunk=True, chunk_quantile=0.9).spec.chunk_quantile == 0.9
    for bad in (1.0, 0.0, float("nan")):
        with pytest.raises(ValueError, match="chunk_quantile"):
            DiscrepancyConfig(per_chunk=True, chunk_quantile=bad)


def test_tau_is_set_on_successful_held_out_episodes_and_more_are_asked_for():
    """threshold_on: successful ignores failing ID episodes (here the ones with huge residuals) when
    setting tau, and asks for more episodes while too few held-out ones succeeded; the fit / threshold
    split is by index, so episodes added later never move an earlier one across it."""
    from ddp.contracts import NeedMoreEpisodes
    from ddp.detectors.scores import split_fit

    assert split_fit(6, 0.5) == [False, True, False, True, False, True]
    assert split_fit(40, 0.5)[:6] == split_fit(6, 0.5) and sum(split_fit(40, 0.25)) == 10
    rng = np.random.default_rng(0)
    n = 60
    scores = rng.gamma(2.0, 0.5, size=(n, 6))
    failing = np.arange(n) % 5 == 4  # every fifth episode fails, its residual wandering far
    scores[failing, 3:] *= 50
    scores[:, 0] = np.nan
    eps = episodes_from_scores(scores, success=~failing)
    spec = ScoreSpec(per_chunk=True)  # fitted on half the episodes, tau on the other half
    everything = fit_calibration(eps, spec, alpha=0.05)
    nominal = fit_calibration(eps, spec, alpha=0.05, threshold_on="successful")
    held = ~np.array(split_fit(n, 0.5))
    assert everything.chunk_scale == nominal.chunk_scale  # the same fit: only tau's episodes differ
    # the reference (the ID side of AUROC) is every held-out episode, the failing ones too; tau comes from
    # the successful ones' maxima
    assert len(nominal.reference) == everything.threshold_episodes == 30
    ok = ~failing[held]
    maxima = [np.nanmax(r) for r, k in zip(nominal.reference, ok) if k]
    assert len(maxima) == nominal.threshold_episodes == int((held & ~failing).sum()) == 24
    assert nominal.tau == pytest.approx(conformal_threshold(maxima, 0.05))
    assert everything.threshold_episodes == 30 and nominal.tau < everything.tau / 10
    assert nominal.threshold_on == "successful" and everything.threshold_on == "all"
    # 40 episodes: 16 successful held out, alpha 0.05 needs 19: about 3 / (0.5 x 0.8) more
    with pytest.raises(NeedMoreEpisodes, match="needs 19 successful held-out") as short:
        fit_calibration(eps[:40], spec, alpha=0.05, threshold_on="successful")
    assert 6 <= short.value.more <= 12
    with pytest.raises(ValueError, match="none of the 20 held-out ID calibration episodes succeeded"):
        fit_calibration(episodes_from_scores(scores[:40], success=[False] * 40), spec, alpha=0.05,
                        threshold_on="successful")
    with pytest.raises(ValueError, match="record their success"):
        fit_calibration([{k: v for k, v in e.items() if k != "success"} for e in eps], spec, alpha=0.05,
                        threshold_on="successful")
    with pytest.raises(ValueError, match="threshold_on must be one of"):
        DiscrepancyConfig(threshold_on="succesful")


def test_the_per_chunk_scale_pools_the_chunks_around_each_one():
    """The default window (1): the phase scale at chunk c is the ID median over chunks c-1 .. c+1 of the fitting
    episodes (every value-checking test used window 0, where pooling is never exercised)."""
    from ddp.detectors.scores import split_fit

    scores = np.random.default_rng(3).gamma(2.0, 0.5, size=(20, 6))
    cal = fit_calibration(episodes_from_scores(scores), ScoreSpec(per_chunk=True), alpha=0.2)
    fit = scores[np.array(split_fit(20, 0.5))]
    assert cal.chunk_scale == pytest.approx([float(np.median(fit[:, max(0, c - 1):c + 2])) for c in range(6)],
                                            rel=1e-6)


def test_unjudged_calibration_episodes_fail_at_once_under_successful_selection():
    """A real robot's episodes carry success None: threshold_on: successful took them as failures, asked for
    150 more episodes (each an operator's reset) and then failed, or said the policy does not solve its task."""
    eps = episodes_from_scores(np.ones((20, 4)), success=np.ones(20, bool))
    for e in eps:
        e["success"] = None
    spec = ScoreSpec(per_chunk=True, window=0, chunk_quantile=0.9)
    with pytest.raises(ValueError, match=r"not judged .*threshold_on: successful cannot select .*"
                                         r"set controller.detector.threshold_on: all"):
        fit_calibration(eps, spec, alpha=0.1, threshold_on="successful")
    with pytest.raises(ValueError, match=r"fit_on: successful cannot select"):
        fit_calibration(eps, spec, alpha=0.1, fit_on="successful")
    with pytest.raises(ValueError, match=r"fit_on: successful cannot select"):  # tau given: still a fit
        fit_calibration(eps, spec, alpha=0.1, tau=2.0, fit_on="successful")
    assert fit_calibration(eps, spec, alpha=0.1).threshold_episodes == 10  # all / all: nothing to select


def test_a_given_tau_reports_the_episodes_its_reference_was_fitted_on():
    """With tau in the recipe, a per-chunk statistic still fits its reference, on every ID episode: it reported
    fit_episodes 0, so results.json's calibration read null, as if nothing had been fitted."""
    eps = episodes_from_scores(np.random.default_rng(0).gamma(2.0, 0.5, size=(12, 4)), success=np.ones(12, bool))
    cal = fit_calibration(eps, ScoreSpec(per_chunk=True, window=0, chunk_quantile=0.9), alpha=0.1, tau=2.0)
    assert cal.chunk_scale is not None and cal.fit_episodes == 12 and cal.threshold_episodes == 0
    assert fit_calibration(eps, ScoreSpec(), alpha=0.1, tau=2.0).fit_episodes == 0  # plain D_R-I: nothing fitted


def test_fit_on_successful_fits_the_phase_scale_on_nominal_episodes_only():
    """fit_on: successful: a failing fitting episode's wandering residual does not raise its phase's scale (the
    default fits on every fitting episode)."""
    from ddp.detectors.scores import split_fit

    rng = np.random.default_rng(1)
    n = 40
    scores = rng.gamma(2.0, 0.5, size=(n, 6))
    failing = np.arange(n) % 4 == 1  # fitting episodes (odd indices) among them
    scores[failing, 3:] *= 50
    eps = episodes_from_scores(scores, success=~failing)
    spec = ScoreSpec(per_chunk=True, window=0, chunk_quantile=0.9)
    every = fit_calibration(eps, spec, alpha=0.1, threshold_on="successful")
    nominal = fit_calibration(eps, spec, alpha=0.1, threshold_on="successful", fit_on="successful")
    fits = np.array(split_fit(n, 0.5))
    assert nominal.fit_episodes == int((fits & ~failing).sum()) == 10 and every.fit_episodes == 20
    ok = scores[fits & ~failing]
    assert nominal.chunk_scale == pytest.approx([np.quantile(ok[:, c], 0.9) for c in range(6)])
    assert all(a > 10 * b for a, b in zip(every.chunk_scale[3:], nominal.chunk_scale[3:]))
    assert nominal.fit_on == "successful" and every.fit_on == "all"
    with pytest.raises(ValueError, match="none of the 20 fitting ID calibration episodes succeeded"):
        fit_calibration(episodes_from_scores(scores, success=[False] * n), spec, alpha=0.1, fit_on="successful")
    # with tau in the recipe the reference is still fitted: fit_on selects its episodes there too (it was
    # ignored, every episode fitted, while results.json said "successful")
    given = fit_calibration(eps, spec, alpha=0.1, tau=2.0, fit_on="successful")
    assert given.fit_episodes == int((~failing).sum()) == 30 and given.fit_on == "successful"
    assert given.chunk_scale == pytest.approx([np.quantile(scores[~failing][:, c], 0.9) for c in range(6)])
    with pytest.raises(ValueError, match="fit_on must be one of"):
        DiscrepancyConfig(fit_on="ok")


def test_eval_rolls_out_more_calibration_episodes_until_enough_succeeded(tiny_recipe, monkeypatch):
    """ddp eval's calibration asks the detector; while it wants more, more ID episodes are rolled out on
    fresh seeds (up to eval.max_calibration_episodes, then one line says so)."""
    from ddp import build
    from ddp import eval_runner

    rng = np.random.default_rng(1)
    calls = []

    def fake_rollouts(exp, *, episodes, seed, **kw):
        calls.append((seed, episodes))
        seeds = range(seed, seed + episodes)
        eps = episodes_from_scores(rng.gamma(2.0, 0.5, size=(episodes, 5)), success=[(s // 2) % 2 == 0 for s in seeds])
        return [{**e, "seed": s} for e, s in zip(eps, seeds)]

    monkeypatch.setattr(eval_runner, "calibration_episodes", fake_rollouts)
    exp = build(tiny_recipe)
    det = DiscrepancyDetector(DiscrepancyConfig(alpha=0.05, per_chunk=True))
    tau = eval_runner.calibrate_detector(exp, det, episodes=40, seed=100, max_episodes=200)
    assert calls[0] == (100, 40) and all(s == calls[i][0] + calls[i][1] for i, (s, _) in enumerate(calls[1:]))
    assert tau > 0 and det.calibration()["threshold_episodes"] >= 19 and len(calls) >= 2
    calls.clear()
    with pytest.raises(ValueError, match="after 50 ID calibration episodes, the most eval.max_calibration_episodes"):
        eval_runner.calibrate_detector(exp, DiscrepancyDetector(DiscrepancyConfig(alpha=0.05, per_chunk=True)), episodes=40,
                                       seed=100, max_episodes=50)
    assert calls == [(100, 40), (140, 10)]


def test_detect_rolls_out_more_calibration_episodes_once_for_every_statistic(tiny_recipe, monkeypatch):
    """ddp detect: when a statistic lacks successful held-out episodes, more ID episodes come from the
    same helper ddp eval uses, on fresh seeds, and every statistic is calibrated on all of them."""
    from ddp import build
    from ddp import detection, eval_runner

    rng = np.random.default_rng(2)

    def make(n, seed, disturbed=False):
        seeds = list(range(seed, seed + n))
        eps = episodes_from_scores(rng.gamma(2.0, 0.5, size=(n, 5)), success=[(s // 2) % 2 == 0 for s in seeds])
        return [{**e, "seed": s, "disturbed": [disturbed and c >= 2 for c in range(5)]} for e, s in zip(eps, seeds)]

    extra = []

    def calibration(exp, *, episodes: int, seed: int, **kw):
        extra.append((seed, episodes))
        return make(episodes, seed)

    monkeypatch.setattr(detection, "_rollouts",
                        lambda exp, name, *, episodes, seed, env, **kw: make(episodes, seed, disturbed=name != "id"))
    monkeypatch.setattr(eval_runner, "calibration_episodes", calibration)
    exp = build(tiny_recipe)
    variants = {"per_chunk": {"per_chunk": True}, "per_chunk_all": {"per_chunk": True, "threshold_on": "all"}}
    rep = detection.detect(exp, episodes=4, calibration_episodes=40, variants=variants, progress=False)
    first = 100_000 + exp.recipe.eval.seed
    assert extra[0] == (first, 40)  # the calibration rollouts ddp eval makes (held-out initial states)
    assert len(extra) > 1 and extra[1][0] == first + 40  # then more, from the next unused seed
    n_cal = rep["calibration_episodes"]
    assert n_cal == sum(n for _, n in extra) and len(rep["rollouts"]["calibration"]) == n_cal
    rows = {r["score"]: r for r in rep["rows"]}
    assert rows["per_chunk"]["threshold_on"] == "successful" and rows["per_chunk"]["threshold_episodes"] >= 19
    assert rows["per_chunk_all"]["threshold_episodes"] == n_cal // 2  # the same episodes, every held-out one
    # --samples applies to that call: the experiment's recipe was left with it (a later evaluate() sampled so)
    before = exp.recipe.controller.forecast_samples
    rep = detection.detect(exp, episodes=4, calibration_episodes=40, variants=variants, progress=False, samples=3)
    assert rep["forecast_samples"] == 3 and exp.recipe.controller.forecast_samples == before


def test_conformal_threshold_rule():
    assert conformal_threshold([3.0, 1.0, 2.0], 0.5) == 2.0  # ceil(4 x 0.5) = 2nd smallest
    assert conformal_threshold(list(range(1, 20)), 0.05) == 19.0  # n = 19: the largest
    with pytest.raises(ValueError, match="needs at least 19 held-out"):
        conformal_threshold(list(range(18)), 0.05)


def test_a_cusum_restarts_after_its_alarm_with_a_head_start_so_a_persisting_change_is_seen_again():
    """The controller re-checks one cycle after an alarm: a CUSUM restarted at 0 needed a single chunk above
    tau to say OOD again, so the re-check read ID while the scene stayed changed. With the tau / 2 head start
    a persisting change reads OOD on the next chunk, an ID chunk reads ID."""
    det = DiscrepancyDetector(DiscrepancyConfig(cusum=True, drift=1.0, tau=4.0))
    det.cal.median = 1.0  # scores normalised by an ID median of 1

    from tensordict import TensorDict

    def step(score: float, chunk: int) -> bool:
        pred = torch.full((1, 2, 4), math.sqrt(score))  # a window whose paper D_R-I is ``score``
        td = TensorDict({("ddp", "latent_real"): torch.zeros(1, 2, 4), ("ddp", "latent_pred"): pred,
                         "chunk_index": torch.tensor([[chunk]])}, batch_size=[1])
        return bool(det(td)["ddp", "ood"].item())

    assert [step(v, c) for c, v in enumerate([1.0, 1.0, 3.5, 3.5])] == [False, False, False, True]  # 2.5 + 2.5
    assert step(3.5, 4)  # the move persists: 2 + 2.5 > 4, OOD on the re-check
    assert not step(1.0, 5)  # a quiet chunk after the next alarm: 2 + 0 <= 4, ID
    det.reset()
    assert [step(v, c) for c, v in enumerate([1.0, 6.0])] == [False, True]
    assert not step(1.0, 2)  # ID right after an alarm: back to reality at the re-check


@pytest.mark.parametrize("options", [{}, {"per_chunk": True, "cusum": True}, {"whiten": True, "per_chunk": True}])
def test_conformal_false_alarm_rate_is_alpha_on_fresh_id_episodes(options):
    """Split conformal: over calibrations, P(fresh ID episode alarms) lies in [alpha - 1/(n+1), alpha]."""
    rng = np.random.default_rng(0)
    alpha, n_cal, chunks, fresh = 0.2, 18, 12, 400
    phase = 1.0 + 3.0 * (np.arange(chunks) >= 6)  # a contact phase with larger ID errors

    def id_episodes(n):
        scores = phase * rng.gamma(2.0, 0.5, size=(n, chunks))
        scores[:, 0] = np.nan  # no forecast at the first chunk
        return episodes_from_scores(scores)

    spec = DiscrepancyConfig(alpha=alpha, **options).spec
    rates = []
    for _ in range(40):
        cal = fit_calibration(id_episodes(n_cal), spec, alpha=alpha)
        new = id_episodes(fresh)
        stats = [episode_statistic(residual_score(torch.as_tensor(e["latent_real"]), torch.as_tensor(e["latent_pred"]),
                                                  spec, center=cal.tensors()[0], scale=cal.tensors()[1]).numpy(),
                                   spec, cal) for e in new]
        rates.append(np.mean([first_above(list(s), cal.tau) is not None for s in stats]))
    held = n_cal - cal.fit_episodes
    mean = float(np.mean(rates))
    sem = float(np.std(rates) / np.sqrt(len(rates)))
    assert alpha - 1 / (held + 1) - 3 * sem <= mean <= alpha + 3 * sem, (mean, sem, held)


def test_detector_calibrates_then_flags_above_tau_and_never_at_the_first_chunk():
    from tensordict import TensorDict

    det = DiscrepancyDetector(DiscrepancyConfig(alpha=0.5))
    assert det.needs_calibration
    det.calibrate(episodes_from_scores(np.array([[np.nan, 0.1, 0.2], [np.nan, 0.3, 0.1], [np.nan, 0.2, 0.4]])))
    assert det.tau == pytest.approx(0.3) and not det.needs_calibration  # maxima 0.2, 0.3, 0.4: the 2nd
    real = torch.zeros(3, 2, 4)
    pred = torch.stack([torch.full((2, 4), float("nan")), torch.full((2, 4), 0.7), torch.full((2, 4), 0.5)])
    td = TensorDict({("ddp", "latent_real"): real, ("ddp", "latent_pred"): pred,
                     "chunk_index": torch.tensor([[0], [3], [3]])}, batch_size=[3])
    out = det(td)
    assert out["ddp", "ood"].tolist() == [False, True, False]  # 0.49 > 0.3, 0.25 is not; no forecast: never
    assert math.isnan(out["ddp", "score"][0]) and out["ddp", "score"][1] == pytest.approx(0.49)
    other = DiscrepancyDetector(DiscrepancyConfig(alpha=0.5))
    other.load_calibration(json.loads(json.dumps(det.calibration())))
    assert other(td)["ddp", "ood"].tolist() == [False, True, False]


def test_saved_rollouts_keep_a_success_nobody_judged(tmp_path):
    """ddp detect on a real robot (franky-sim included): success is None; saving its rollouts crashed on
    int(None), and a None read back must stay None, not become a failure."""
    from ddp.detection import load_rollouts, save_rollouts

    eps = [{"seed": 3, "success": None, "disturbed": [0, 1]}, {"seed": 4, "success": True, "disturbed": []}]
    save_rollouts({"id": eps}, tmp_path / "r.npz")
    back = load_rollouts(tmp_path / "r.npz")["id"]
    assert [(e["seed"], e["success"]) for e in back] == [(3, None), (4, True)]


def test_rollouts_killed_mid_write_leave_the_earlier_file_whole(tmp_path, monkeypatch):
    """detect_rollouts.npz was written in place: a kill mid-write left a truncated file that the next
    ``ddp detect --rollouts`` refused, the rollouts lost."""
    import numpy as np

    import ddp.detection as detection

    path = tmp_path / "detect_rollouts.npz"
    detection.save_rollouts({"id": [{"seed": 3, "success": True, "disturbed": []}]}, path)

    def killed(file, **arrays):
        file.write(b"PK\x03\x04 half a zip")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez_compressed", killed)
    with pytest.raises(KeyboardInterrupt):
        detection.save_rollouts({"id": [{"seed": 4, "success": False, "disturbed": []}]}, path)
    assert [e["seed"] for e in detection.load_rollouts(path)["id"]] == [3]
    assert [p.name for p in tmp_path.iterdir()] == ["detect_rollouts.npz"]  # no temp file left


def test_a_threshold_the_episode_cap_can_never_reach_fails_before_rolling_out_more(tiny_recipe, monkeypatch):
    """alpha 0.01 with tau set on successful held-out episodes needs 99 of them, i.e. at least 197 episodes
    (every second one held out, the first included): above eval.max_calibration_episodes (160) it fails at
    once, not after 160 rollouts."""
    from ddp import build, eval_runner

    calls = []

    def fake(exp, *, episodes, seed, **kw):
        calls.append(episodes)
        return [{**e, "seed": seed + i} for i, e in enumerate(episodes_from_scores(np.full((episodes, 4), 0.1)))]

    monkeypatch.setattr(eval_runner, "calibration_episodes", fake)
    exp = build(tiny_recipe)
    strict = DiscrepancyDetector(DiscrepancyConfig(alpha=0.01, per_chunk=True))
    from ddp.detectors.scores import _fewest_holding_out, split_fit

    assert _fewest_holding_out(19, 0.5) == 37 and 37 - sum(split_fit(37, 0.5)) == 19  # not 38
    with pytest.raises(ValueError, match=r"needs 99 successful.*at least 197 ID calibration episodes, more than "
                                         r"eval.max_calibration_episodes \(160\)"):
        eval_runner.calibrate_detector(exp, strict, episodes=40, seed=0, progress=False)
    assert calls == [40]  # no further rollouts
    calls.clear()
    eval_runner.calibrate_detector(exp, DiscrepancyDetector(DiscrepancyConfig(alpha=0.05, per_chunk=True)),
                                   episodes=20, seed=0, progress=False)
    assert calls == [20, 20]  # reachable: more episodes are rolled out as before


def test_whitening_floors_a_dim_without_id_variance_relative_to_the_others():
    from ddp.detectors.scores import fit_calibration

    rng = np.random.default_rng(0)
    eps = []
    for _ in range(40):
        real = rng.normal(size=(5, 2, 4))
        real[..., 3] = 0.0  # a latent dim that never varies in ID
        eps.append({"latent_real": real, "latent_pred": np.zeros_like(real), "success": True})
    cal = fit_calibration(eps, ScoreSpec(whiten=True), alpha=0.1)
    assert cal.scale[3] == pytest.approx(1e-3 * np.median(cal.scale[:3] + [0.0]), rel=1e-6)  # not 1e-8


def test_calibration_file_round_trips_and_is_bound_to_model_detector_and_env(tmp_path, tiny_recipe):
    from ddp import build

    exp = build(tiny_recipe)
    det = DiscrepancyDetector(DiscrepancyConfig(alpha=0.5, per_chunk=True))
    det.calibrate(episodes_from_scores(np.array([[np.nan, 0.1, 0.2], [np.nan, 0.3, 0.1], [np.nan, 0.2, 0.4],
                                                 [np.nan, 0.1, 0.3]])))
    key = dict(model_hash=model_digest(exp.model), detector={"name": "discrepancy", "alpha": 0.5}, id_env={"a": 1},
               episodes=4, seed=7, sampling={"policy": {"num_inference_steps": 10}, "forecast_samples": 1})
    path = save_calibration(calibration_path(tmp_path / "last.pt"), det.calibration(), **key)
    assert path.name == "last.calibration.json"
    again = DiscrepancyDetector(DiscrepancyConfig(alpha=0.5, per_chunk=True))
    again.load_calibration(load_calibration(path, **key))
    assert results_json.dumps(again.calibration()) == results_json.dumps(det.calibration())
    assert math.isnan(again.calibration()["reference"][0][0])  # stored as null, read back as NaN
    assert not again.needs_calibration
    for change in ({"seed": 8}, {"id_env": {"a": 2}}, {"detector": {"name": "discrepancy", "alpha": 0.1}},
                   {"model_hash": "0" * 16}, {"sampling": {"policy": {"num_inference_steps": 5}, "forecast_samples": 1}},
                   {"device": "cuda"}):
        assert load_calibration(path, **{**key, **change}) is None, change
    # a file from another version of the calibration code (what the statistic or its episodes mean) is refitted
    import ddp.calibration_file as calibration_file

    old = json.loads(path.read_text())
    old["valid_for"]["version"] = calibration_file.VERSION - 1
    path.write_text(json.dumps(old))
    assert load_calibration(path, **key) is None
    del old["valid_for"]["version"]  # files written before the version existed
    path.write_text(json.dumps(old))
    assert load_calibration(path, **key) is None
    with torch.no_grad():
        next(exp.model.parameters()).add_(1.0)
    assert model_digest(exp.model) != key["model_hash"]


# ----------------------------------------------------------------------------------------- metrics
def test_detection_metrics_count_delays_misses_and_false_alarms():
    eps = [
        {"seed": 0, "mode": [0, 0, 0, 1, 1], "disturbed": [0, 0, 1, 1, 1], "score": [math.nan, 0.1, 0.2, 0.9, 0.9]},
        {"seed": 1, "mode": [0, 0, 1, 1, 1], "disturbed": [0, 0, 1, 1, 1], "score": [math.nan, 0.1, 0.8, 0.9, 0.9]},
        {"seed": 2, "mode": [0, 0, 0, 0, 0], "disturbed": [0, 0, 1, 1, 1], "score": [math.nan, 0.1, 0.1, 0.1, 0.1]},
        {"seed": 3, "mode": [0, 1, 0, 0, 0], "disturbed": [0, 0, 0, 0, 0], "score": [math.nan, 0.6, 0.1, 0.1, 0.1]},
        {"seed": 4, "mode": [0, 1, 1, 1, 1], "disturbed": [0, 0, 0, 1, 1], "score": [math.nan, 0.6, 0.1, 0.1, 0.1]},
    ]
    m = detection_metrics(eps, reference=[[math.nan, 0.1, 0.1, 0.1, 0.1], [math.nan, 0.2, 0.2, 0.2, 0.2]])
    assert m["disturbed_episodes"] == 4 and m["clean_episodes"] == 1
    # seed 0: delay 1; seed 1: delay 0; seed 2: missed; seed 4: OOD since chunk 1 (a false alarm) and still on when
    # the move shows: the controller acts on it, not a miss
    assert m["detected"] == 2 and m["missed"] == 1 and m["alarm_before_visible"] == 1
    assert m["detected_within_1"] == 2 and m["median_delay"] == 0.5
    # an early alarm that ended before the move showed, and nothing after: a miss
    ended = {"seed": 5, "mode": [0, 1, 0, 0, 0], "disturbed": [0, 0, 0, 1, 1], "score": [math.nan] * 5}
    assert not alarmed_before_visible(ended) and detection_metrics([ended])["missed"] == 1
    assert alarmed_before_visible({"first_visible": 3, "mode": "01111"})  # a suite result's trace
    assert [e["delay"] for e in m["per_episode"]] == [1, 0, None, None, None]
    assert m["episodes_with_false_alarm"] == 2  # seed 3 (clean) and seed 4 (before its disturbance)
    late = {"seed": 6, "mode": [0, 0, 0, 0, 0, 1], "disturbed": [0, 0, 1, 1, 1, 1], "score": [math.nan] * 6}
    skewed = detection_metrics([eps[1], eps[1], late])  # delays 0, 0, 3
    assert skewed["median_delay"] == 0.0 and skewed["mean_delay"] == 1.0
    assert m["false_alarms_per_id_chunk"] == pytest.approx(2 / (5 + 2 + 2 + 2 + 3))
    # at first visibility: disturbed scores 0.2, 0.8, 0.1, 0.1 against ID 0.1 / 0.2 at those chunks
    assert m["auroc_after_visible"][0] == pytest.approx(auroc([0.1, 0.2] * 3 + [0.1, 0.2], [0.2, 0.8, 0.1, 0.1]))
    # moves first seen at different chunks are each compared with the ID statistic at their own chunk, each
    # (disturbed, ID) pair once: chunk 1 (ID 0.1, 0.2) and chunk 3 (ID 0.9, 1.0)
    staggered = [{"seed": 0, "mode": [0] * 4, "disturbed": [0, 1, 1, 1], "score": [math.nan, 0.95, 0.95, 0.95]},
                 {"seed": 1, "mode": [0] * 4, "disturbed": [0, 0, 0, 1], "score": [math.nan, 0.5, 0.5, 0.5]}]
    m = detection_metrics(staggered, reference=[[math.nan, 0.1, 0.5, 0.9], [math.nan, 0.2, 0.5, 1.0]], horizon=1)
    assert m["auroc_after_visible"][0] == pytest.approx(0.5)  # (2 + 0) of 4 pairs (pooled over chunks: 5 / 8)
    # after an alarm the controller forecasts from its imagination: those chunks' statistic (many steps open
    # loop) has no peer among 1-step ID forecasts, and inflated the AUROC at visible + k
    alarmed = [{"seed": 0, "mode": [0, 0, 1, 1, 1], "imagined": [0, 0, 1, 1, 1], "disturbed": [0, 0, 1, 1, 1],
                "score": [math.nan, 0.1, 0.15, 5.0, 5.0]},
               {"seed": 1, "mode": [0, 0, 0, 0, 0], "imagined": [0] * 5, "disturbed": [0, 0, 1, 1, 1],
                "score": [math.nan, 0.1, 0.15, 0.15, 0.15]}]
    m = detection_metrics(alarmed, reference=[[math.nan, 0.1, 0.2, 0.2, 0.2], [math.nan, 0.2, 0.1, 0.1, 0.1]])
    assert m["auroc_after_visible"][:3] == pytest.approx([0.5, 0.5, 0.5])  # seed 0 counts at chunk 2 only


# ----------------------------------------------------------------------------------------- controller
def test_controller_never_leaves_id_on_the_forecast_less_first_chunk(tiny_recipe):
    from ddp.evaluate import make_chunked_env

    exp = displaced_exp(tiny_recipe)
    ctrl = exp.make_controller(detector={"name": "discrepancy", "tau": 1e-30})  # anything finite is above it
    env = make_chunked_env(exp, seed=0, overrides={})
    ctrl.reset()
    r = env.rollout(3, ctrl, break_when_any_done=False)
    assert r["ddp", "mode"].tolist() == [0, 1, 1]
    assert torch.isnan(r["ddp", "latent_pred"][0]).all() and torch.isfinite(r["ddp", "latent_pred"][1]).all()


def test_the_default_detector_flags_a_displacement_at_its_first_observable_chunk(tiny_recipe):
    """The whole detection path on the synthetic env, with a world model that forecasts the ID scene (its real
    latents, recorded, plus small noise): the controller pairs each observation with the forecast made for
    it, the recipes' default statistic (point dims, newest frame, per-chunk scale) is calibrated on ID
    episodes at alpha 0.05, and the cube moved at the start of chunk 1 is flagged at chunk 2, the first
    observation that shows it; nothing is flagged before, nor in fresh ID runs. A forecast paired with the
    wrong cycle, or a score off the point-cloud dims, fails this."""
    from ddp.evaluate import make_chunked_env

    detector = {"name": "discrepancy", "alpha": 0.05, "dims": "point", "frames": "newest", "per_chunk": True}
    exp = displaced_exp(tiny_recipe, detector=detector)
    chunks, m, n = 8, exp.model.obs_steps, exp.model.action_steps
    # the ID scene's real latent windows, chunk by chunk (the base policy, forecasting every cycle)
    ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True)
    ctrl.reset()
    r = make_chunked_env(exp, seed=0, overrides={"displacement": False}).rollout(chunks, ctrl, break_when_any_done=False)
    ctrl.close()
    id_windows = r["ddp", "latent_real"].double()  # [chunks, M, L]
    noise = torch.Generator().manual_seed(0)
    sigma = 1e-3 * float(id_windows.std())

    def forecast_of(chunk):  # what an exact ID world model forecasts for ``chunk``, up to small noise
        return id_windows[min(chunk, chunks - 1)] + sigma * torch.randn(m, id_windows.shape[-1], generator=noise,
                                                                         dtype=torch.float64)

    calibration = []
    for _ in range(40):
        pred = torch.stack([torch.full_like(id_windows[0], float("nan"))] + [forecast_of(c) for c in range(1, chunks)])
        calibration.append({"latent_real": id_windows.numpy(), "latent_pred": pred.numpy(), "success": True})

    def rollout(displaced: bool):
        ctrl = exp.make_controller()
        ctrl.detector.calibrate(calibration, point_dims=exp.model.point_dims)
        made = []  # forecasts made so far: the one made at cycle t is for cycle t + 1

        def imagine(history, actions, generator=None):
            made.append(history.shape[0])
            future = torch.zeros(history.shape[0], n, history.shape[-1], dtype=history.dtype)
            future[:, -m:] = forecast_of(len(made)).to(history.dtype)
            return future

        ctrl.model.imagine = imagine
        ctrl.reset()
        env = make_chunked_env(exp, seed=0, overrides={} if displaced else {"displacement": False})
        try:
            out = env.rollout(chunks, ctrl, break_when_any_done=False)
        finally:
            ctrl.close()
            del ctrl.model.imagine
        return out

    assert rollout(displaced=False)["ddp", "mode"].tolist() == [0] * chunks
    out = rollout(displaced=True)
    assert out["ddp", "mode"].tolist()[:3] == [0, 0, 1]  # seen at chunk 2, flagged at chunk 2
    score = out["ddp", "score"].tolist()
    assert math.isnan(score[0]) and score[2] > 100 * score[1]  # the move dwarfs the ID residual


def test_nan_latents_flag_ood_and_a_false_alarm_returns_to_reality(tiny_recipe):
    from ddp.evaluate import make_chunked_env

    exp = displaced_exp(tiny_recipe)
    ctrl = exp.make_controller(detector={"name": "discrepancy", "tau": 1e9})
    env = make_chunked_env(exp, seed=0, overrides={"displacement": False})
    ctrl.reset()
    td = env.reset()
    td = ctrl(td)
    td = env.step(td)["next"]
    td = ctrl(td)  # a forecast exists now
    # the encoder's latents come out NaN for one cycle: OOD, acting from the forecast
    enc = exp.model.encode
    exp.model.encode = lambda pc, pos: enc(pc, pos) * float("nan")
    td = ctrl(env.step(td)["next"])
    exp.model.encode = enc
    assert td["ddp", "mode"].item() == 1 and td["ddp", "imagined"].item()
    # nothing displaced to track or recover: the next cycle re-checks the statistic and returns to reality
    td = ctrl(env.step(td)["next"])
    assert td["ddp", "mode"].item() == 0 and not td["ddp", "imagined"].item()
    # a false alarm in ID (the statistic above tau once, nothing displaced): one cycle of imagination, then back
    ctrl.detector.cal.tau = 1e-30
    td = ctrl(env.step(td)["next"])
    assert td["ddp", "mode"].item() == 1 and td["ddp", "imagined"].item()
    assert torch.equal(td["ee_shift"], torch.zeros(3))  # nothing tracked
    ctrl.detector.cal.tau = 1e9
    td = ctrl(env.step(td)["next"])
    assert td["ddp", "mode"].item() == 0


# ----------------------------------------------------------------------------------------- ddp detect
def test_ddp_detect_cli_writes_the_comparison(tiny_recipe, tmp_path):
    from ddp import build
    from ddp.cli import main

    tiny_recipe["env"].update(displacement_chunk=1, displacement_delta=[0.2, 0.0, 0.0], max_episode_steps=32)
    tiny_recipe["train"].update(max_steps=2, epochs=1, output_dir=str(tmp_path / "run"))
    exp = build(tiny_recipe)
    exp.train(progress=False)
    out = tmp_path / "detect"
    # an untrained policy never succeeds: tau from every held-out episode, failing ones too
    code = main(["detect", "--checkpoint", str(tmp_path / "run" / "last.pt"), "--episodes", "2",
                 "--calibration-episodes", "4", "--alpha", "0.5", "--scores", "paper,per_chunk_cusum",
                 "--threshold-on", "all",
                 "--env", "displacement_chunk=2", "--output-dir", str(out), "--quiet"])
    assert code == 0
    rep = json.loads((out / "detect.json").read_text())
    assert [r["score"] for r in rep["rows"]] == ["paper", "per_chunk_cusum"] and rep["env"] == {"displacement_chunk": 2}
    assert rep["first_visible"]["ood_base"] == [3, 3]  # displaced before chunk 2's actions, seen at chunk 3
    row = rep["rows"][0]
    assert row["ood_base"]["episodes"] == 2 and row["id_episodes"] == 2 and row["tau"] > 0
    # alpha's own count, over the successful ID test episodes: none of the untrained policy's
    assert row["id_successful"] == sum(rep["success"]["id"]) == 0 and row["id_false_alarm_successful"] == 0
    assert "| paper | ood_base |" in (out / "detect.md").read_text()
    assert (out / "detect_paper.png").stat().st_size > 0
    assert main(["detect", "--checkpoint", str(tmp_path / "run" / "last.pt"), "--scores", "papr"]) == 2
    # the saved rollouts score other statistics without rolling out: the same numbers for the same statistic
    again, ckpt, saved = tmp_path / "again", str(tmp_path / "run" / "last.pt"), str(out / "detect_rollouts.npz")
    assert main(["detect", "--checkpoint", ckpt, "--rollouts", saved, "--alpha", "0.5", "--threshold-on", "all",
                 "--scores", "paper,point_newest", "--disturbances", "ood_base",
                 "--output-dir", str(again), "--quiet"]) == 0
    rep2 = json.loads((again / "detect.json").read_text())
    assert rep2["rows"][0]["tau"] == row["tau"] and rep2["rows"][0]["ood_base"] == row["ood_base"]
    assert rep2["first_visible"] == {"ood_base": [3, 3]}
    # the header tells how the scored rollouts were made, not what this command's flags say (it said seed 0
    # and no env overrides here), and rollouts of other weights are refused (nothing checked they matched)
    from ddp.detection import load_rollouts, read_rollouts, rollouts_provenance, save_rollouts

    assert (rep2["seed"], rep2["env"]) == (rep["seed"], {"displacement_chunk": 2})
    made = rollouts_provenance(saved)
    read, read_made = read_rollouts(saved)  # one open: the same rollouts and provenance as the two readers
    assert read_made == made and made["seed"] == rep["seed"]
    assert [e["seed"] for e in read["ood_base"]] == [e["seed"] for e in load_rollouts(saved)["ood_base"]]
    other = str(tmp_path / "other.npz")
    save_rollouts(load_rollouts(saved), other, provenance={**made, "model": "0" * 16})
    assert main(["detect", "--checkpoint", ckpt, "--rollouts", other, "--alpha", "0.5", "--threshold-on", "all",
                 "--scores", "paper", "--disturbances", "ood_base", "--output-dir", str(again), "--quiet"]) == 2
    assert main(["detect", "--checkpoint", ckpt, "--rollouts", saved, "--disturbances", "occlusion",
                 "--quiet"]) == 2  # not in the saved rollouts: one line


def test_detect_table_counts_false_alarms_over_the_episodes_alpha_bounds():
    """With tau set on the successful held-out episodes, alpha bounds false alarms over successful ID
    episodes: the table's one count over every ID test episode read a failing episode's alarm as a breach."""
    from ddp.detection import format_detect

    row = {"score": "paper", "tau": 1.0, "threshold_on": "successful", "id_false_alarm_episodes": 3,
           "id_episodes": 10, "id_false_alarm_successful": 1, "id_successful": 8,
           "ood_base": {"episodes": 10, "detected": 9, "detected_within_1": 9, "median_delay": 0.0, "missed": 1,
                        "alarm_before_visible": 0, "auroc_after_visible": [1.0, 1.0, 1.0]}}
    rep = {"recipe": "r", "alpha": 0.1, "calibration_episodes": 40, "episodes": 10, "seed": 0, "env": {},
           "disturbances": ["ood_base"], "rows": [row]}
    assert "| 3/10 (1/8 successful) |" in format_detect(rep)
    row["threshold_on"] = "all"  # alpha over every episode: one count
    assert "| 3/10 |" in format_detect(rep)


def test_forecast_samples_give_a_mean_forecast_and_its_spread(tiny_recipe):
    from ddp.evaluate import make_chunked_env

    tiny_recipe["controller"] = {"detector": {"name": "never"}, "forecast_samples": 3, "forecast_every_cycle": True}
    tiny_recipe["env"]["max_episode_steps"] = 32
    from ddp import build
    from conftest import fit_normalizer

    exp = fit_normalizer(build(tiny_recipe))
    ctrl = exp.make_controller()
    calls = []
    imagine = exp.model.imagine
    exp.model.imagine = lambda h, a, generator=None: calls.append(h.shape[0]) or imagine(h, a, generator=generator)
    env = make_chunked_env(exp, seed=0, overrides={})
    r = env.rollout(3, ctrl, break_when_any_done=False)
    ctrl.wait_forecast()  # the last chunk's forecast runs in the background (async_forecast)
    assert calls == [3, 3, 3]  # K = 3 samples per forecast, one batched call, made right after each chunk
    std = r["ddp", "latent_pred_std"]
    assert torch.isnan(std[0]).all() and (std[1:] > 0).all()  # no forecast at chunk 0; samples differ
    # a spread-scaled detector calibrates on such rollouts and reads the spread online
    det = DiscrepancyDetector(DiscrepancyConfig(alpha=0.5, spread=True))
    latents = {k: r["ddp", k].double().numpy() for k in ("latent_real", "latent_pred", "latent_pred_std")}
    eps = [{**latents, "success": True}] * 2
    det.calibrate(eps)
    assert len(det.calibration()["scale"]) == std.shape[-1] and det.tau > 0
    out = det(r.select(("ddp", "latent_real"), ("ddp", "latent_pred"), ("ddp", "latent_pred_std"), "chunk_index"))
    assert out["ddp", "score"][1:].isfinite().all()
    with pytest.raises(ValueError, match="forecast_samples > 1"):
        DiscrepancyDetector(DiscrepancyConfig(alpha=0.5, spread=True)).calibrate(
            [{k: v for k, v in e.items() if k != "latent_pred_std"} for e in eps])
    with pytest.raises(ValueError, match="alternative normalisations"):
        DiscrepancyConfig(whiten=True, spread=True)


def test_detect_rollouts_take_the_next_draw_of_initial_states_past_one(tiny_recipe, monkeypatch):
    """ddp detect's test episodes past one draw of the env's initial states (MetaWorld: 50) come from the next
    draw, as ddp eval's do: seeds 50 apart started from one layout, twice in the ID and disturbed sets."""
    from ddp import build
    from ddp import detection, eval_runner

    calls = []
    monkeypatch.setattr(eval_runner, "evaluation_blocks",
                        lambda exp, over, seed, episodes: [(over, seed, 3), ({**over, "draw": 1}, seed + 3, episodes - 3)])
    monkeypatch.setattr(eval_runner, "rollout_episodes",
                        lambda exp, ctrl, *, episodes, seed, overrides, **kw: calls.append(
                            (seed, episodes, overrides.get("draw"))) or [{"seed": seed + i} for i in range(episodes)])
    exp = build(tiny_recipe)
    got = detection._rollouts(exp, "id", episodes=5, seed=10, env={}, progress=False, num_envs=1, parallel=False)
    assert calls == [(10, 3, None), (13, 2, 1)] and [e["seed"] for e in got] == [10, 11, 12, 13, 14]
