"""The DDP controller (Algorithm 2) on the synthetic env: modes, tracking, imagination, recovery."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from conftest import DELTA, displaced_exp, fit_normalizer
from ddp import build
from ddp.errors import RecipeError
from ddp.calibration_file import calibration_path, model_digest
from ddp.envs.chunked import ChunkedEnv
from ddp.envs.synthetic_reach import SyntheticReachEnv, SyntheticReachEnvConfig
from ddp.evaluate import make_chunked_env



@pytest.fixture
def exp(tiny_recipe):
    return displaced_exp(tiny_recipe)


def rollout(exp, ctrl, chunks=8, **env_over):
    env = make_chunked_env(exp, seed=0, overrides=env_over)
    ctrl.reset()
    return env.rollout(chunks, ctrl, break_when_any_done=False)


def test_chunked_env_specs_and_stacking():
    base = SyntheticReachEnv(SyntheticReachEnvConfig(num_points=32), seed=3)
    env = ChunkedEnv(base, action_steps=8, obs_steps=2)
    check_env_specs(env)
    td = env.reset()
    assert td["point_cloud"].shape == (2, 32, 3) and td["chunk_index"].item() == 0
    td["action"] = torch.zeros(8, 4)
    td["action"][:, 2] = 1.0  # up 2 cm per step
    td["ee_shift"] = torch.tensor([0.05, 0.0, 0.0])
    nxt = env.step(td)["next"]
    assert nxt["chunk_index"].item() == 1 and base._steps == 8
    z = nxt["agent_pos"][:, 2]
    assert torch.allclose(z[1] - z[0], torch.tensor(0.02), atol=1e-5)  # the last two frames, one step apart
    assert torch.allclose(nxt["privileged", "ee_offset"], torch.tensor([0.05, 0.0, 0.0]))


def test_never_detector_acts_from_reality(exp):
    r = rollout(exp, exp.make_controller(detector={"name": "never"}, tracker=False))
    assert (r["ddp", "mode"] == 0).all() and not r["ddp", "imagined"].any()
    assert (r["ee_shift"] == 0).all()
    assert torch.isnan(r["ddp", "discrepancy"]).all()  # nothing needs a forecast: the world model never runs
    exp.recipe.controller.forecast_every_cycle = True  # D_R-I diagnostics with any detector
    r = rollout(exp, exp.make_controller(detector={"name": "never"}, tracker=False))
    assert torch.isnan(r["ddp", "discrepancy"][0]) and not torch.isnan(r["ddp", "discrepancy"][1:]).any()
    assert (r["ddp", "mode"] == 0).all()


def test_a_non_finite_forecast_is_ood_not_a_silent_detector(exp, monkeypatch):
    """A world model whose forecast came out NaN made D_R-I NaN, which the discrepancy detector reads as "no
    forecast yet": detection was off for the rest of the episode, without a word. Now such a cycle is OOD
    (D_R-I inf, a warning) and acts from the real latents; nothing non-finite reaches the env."""
    ctrl = exp.make_controller(detector={"name": "discrepancy", "tau": 1e30})  # no finite D_R-I reaches it
    imagine = ctrl.model.imagine
    monkeypatch.setattr(ctrl.model, "imagine", lambda *a, **k: torch.full_like(imagine(*a, **k), float("nan")))
    with pytest.warns(RuntimeWarning, match="environment 0: the world model's forecast is not finite"):
        r = rollout(exp, ctrl, chunks=4)
    assert r["ddp", "mode"].tolist() == [0, 1, 1, 1] and not r["ddp", "imagined"].any()
    assert torch.isinf(r["ddp", "discrepancy"][1:]).all() and torch.isfinite(r["action"]).all()
    monkeypatch.setattr(ctrl.model, "imagine", imagine)  # a finite forecast: ID under this tau
    assert rollout(exp, ctrl, chunks=4)["ddp", "mode"].tolist() == [0, 0, 0, 0]


def test_open_loop_imagination_after_the_first_chunk(exp):
    r = rollout(exp, exp.make_controller(detector={"name": "substitution", "p": 1.0}, tracker=False))
    assert r["ddp", "imagined"].tolist() == [False] + [True] * 7


def test_oracle_track_imagine_recover_and_return_to_reality(exp):
    r = rollout(exp, exp.make_controller())
    mode, imagined, shift = r["ddp", "mode"].tolist(), r["ddp", "imagined"].tolist(), r["ee_shift"]
    # displaced at the start of chunk 1 -> seen at cycle 2: OOD, tracking shift = +delta, imagination
    assert mode[:2] == [0, 0] and mode[2] == 1 and imagined[2]
    assert torch.allclose(shift[2], torch.tensor(DELTA))
    # subtask 0 ends at chunk 4 -> recovery shift -delta; re-check at cycle 5 -> back to reality
    assert torch.allclose(shift[4], -torch.tensor(DELTA))
    assert mode[3:5] == [1, 1] and mode[5:] == [0, 0, 0] and not any(imagined[5:])
    assert r["ddp", "subtask"].tolist()[4] == 1
    offsets = r["next", "privileged", "ee_offset"]
    assert torch.allclose(offsets[2], torch.tensor(DELTA)) and torch.allclose(offsets[4], torch.zeros(3), atol=1e-6)


def test_tracking_ablation_does_not_imagine(exp):
    r = rollout(exp, exp.make_controller(imagine=False))
    assert r["ddp", "mode"][2] == 1 and not r["ddp", "imagined"].any()
    assert torch.allclose(r["ee_shift"][2], torch.tensor(DELTA))


def test_discrepancy_detector_threshold_and_calibration(exp):
    ctrl = exp.make_controller(detector={"name": "discrepancy", "tau": 1e9})
    r = rollout(exp, ctrl)
    assert (r["ddp", "mode"] == 0).all()
    ctrl = exp.make_controller(detector={"name": "discrepancy", "tau": 1e-12})
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"][1] == 1  # any discrepancy exceeds a tiny tau
    assert r["ddp", "mode"][0] == 0  # but nothing can flag the first chunk: there is no forecast yet
    assert torch.allclose(r["ddp", "score"][1:].double(), r["ddp", "discrepancy"][1:].double(), rtol=1e-5)
    with pytest.raises(RuntimeError, match="no threshold"):
        rollout(exp, exp.make_controller(detector={"name": "discrepancy"}), chunks=3)


def test_per_chunk_calibration_reaches_every_protocol(exp, tmp_path):
    from ddp.schema import resolve_part

    exp.parts["controller.detector"] = resolve_part(
        "detector", {"name": "discrepancy", "tau": None, "per_chunk": True, "threshold_on": "all"},
        key="controller.detector", source="<test>",  # an untrained policy: no ID episode succeeds
    )
    exp.parts["controller.detector"].config.alpha = 0.5  # 2 held-out episodes suffice for alpha 0.5
    exp.recipe.eval.calibration_episodes = 4
    exp.checkpoint_path = tmp_path / "last.pt"  # the calibration is saved beside it
    rep = exp.evaluate(["ood_ddp", "occlusion"], episodes=1, output_dir=tmp_path, progress=False)
    first, second = rep["protocols"]["ood_ddp"], rep["protocols"]["occlusion"]
    cal = json.loads(calibration_path(exp.checkpoint_path).read_text())["calibration"]
    assert cal["chunk_scale"] and all(t > 0 for t in cal["chunk_scale"])
    assert first["tau"] == second["tau"] == cal["tau"] and cal["fit_episodes"] == cal["threshold_episodes"] == 2
    assert len(cal["chunk_scale"]) == first["per_episode"][0]["chunks"]  # one per chunk index seen
    assert (tmp_path / "discrepancy_ood_ddp.png").exists()
    assert "detection" in first and "Detection" in (tmp_path / "table.md").read_text()
    # results.json says how tau was calibrated: with a tau the recipe gives, the per-chunk reference is still
    # fitted, on every calibration episode; nothing at all for the plain D_R-I
    stored = json.loads((tmp_path / "results.json").read_text())["protocols"]["ood_ddp"]["calibration"]
    assert stored["fit_episodes"] == stored["threshold_episodes"] == 2 and stored["threshold_on"] == "all"
    exp.parts["controller.detector"].config.tau = 1.0
    rep = exp.evaluate(["ood_ddp"], episodes=1, output_dir=tmp_path / "fixed", progress=False)
    fixed = rep["protocols"]["ood_ddp"]
    assert fixed["tau"] == 1.0 and (fixed["calibration"]["fit_episodes"], fixed["calibration"]["threshold_episodes"]) == (4, 0)
    exp.parts["controller.detector"].config.per_chunk = False
    rep = exp.evaluate(["ood_ddp"], episodes=1, output_dir=tmp_path / "plain", progress=False)
    assert rep["protocols"]["ood_ddp"]["calibration"] is None and rep["protocols"]["ood_ddp"]["tau"] == 1.0


def test_a_saved_calibration_serves_only_the_env_it_was_made_in(exp, tmp_path, monkeypatch):
    """Reused for the same model, detector and ID env; a changed env setting (here the cloud size, as
    ``ddp eval --set env.num_points=...`` changes it) calibrates again."""
    import ddp.evaluate as evaluate
    from ddp.schema import resolve_part

    calls, real = [], evaluate.calibrate_detector
    monkeypatch.setattr(evaluate, "calibrate_detector", lambda *a, **k: (calls.append(1), real(*a, **k))[1])
    exp.parts["controller.detector"] = resolve_part(
        "detector", {"name": "discrepancy", "tau": None, "alpha": 0.5, "threshold_on": "all"},
        key="controller.detector", source="<test>")
    exp.recipe.eval.calibration_episodes = 2
    exp.checkpoint_path = tmp_path / "last.pt"

    def evaluate_once():
        exp.evaluate(["ood_ddp"], episodes=1, output_dir=tmp_path, progress=False)

    import ddp.calibration_file as calibration_file

    digests, real_digest = [], calibration_file.model_digest
    monkeypatch.setattr(calibration_file, "model_digest", lambda m: digests.append(1) or real_digest(m))
    evaluate_once()
    assert len(digests) == 1  # the weights are hashed once per evaluation (results.json and the calibration key)
    evaluate_once()
    assert len(calls) == 1  # the second evaluation read the saved calibration
    with torch.no_grad():  # other weights: calibrated again
        next(exp.model.parameters()).add_(0.01)
    evaluate_once()
    assert len(calls) == 2
    calls.pop()
    exp.resolved["env"]["num_points"] = exp.resolved["env"]["num_points"] + 1
    evaluate_once()
    assert len(calls) == 2
    evaluate_once()
    assert len(calls) == 2  # saved again, for the new env
    exp.recipe.eval.max_calibration_episodes += 1  # a cap that may change how many episodes it takes
    evaluate_once()
    assert len(calls) == 3
    exp.recipe.eval.calibration_env = {"cube_x": [-0.1, 0.0]}  # calibrated on other initial states
    evaluate_once()
    assert len(calls) == 4
    exp.recipe.seed += 1  # ddp eval --set seed=1: other policy and forecast noise in the calibration rollouts
    evaluate_once()
    assert len(calls) == 5


def test_imagination_protocols_need_a_world_model_and_imagine_whatever_the_recipe(tiny_recipe, tmp_path):

    tiny_recipe["controller"] = {**tiny_recipe.get("controller", {}), "imagine": False}
    e = build(tiny_recipe)
    fit_normalizer(e)
    rep = e.evaluate(["imagination_100"], episodes=1, output_dir=tmp_path, progress=False)
    imagined = rep["protocols"]["imagination_100"]["per_episode"][0]["imagined"]
    assert imagined[0] == 0 and all(imagined[1:])  # real latents at the first chunk only
    tiny_recipe["world_model"]["enabled"] = False
    e = build(tiny_recipe)
    with pytest.raises(RecipeError, match="protocol imagination_50 acts on imagined latents: it needs a world model") as err:
        e.evaluate(["id", "imagination_50"], episodes=1, output_dir=tmp_path, progress=False)
    assert str(err.value).startswith("--protocols:")  # the names came from the caller, not the recipe
    e.recipe.eval.protocols = ["id", "imagination_50"]
    with pytest.raises(RecipeError, match="eval.protocols: protocol imagination_50 acts on imagined latents"):
        e.evaluate(episodes=1, output_dir=tmp_path, progress=False)
    # DDP's other conditions ran without one under DDP's name (ood_ddp_oracle was ood_tracking)
    for name in ("id_ddp", "ood_ddp", "ood_ddp_oracle"):
        with pytest.raises(RecipeError, match=f"--protocols: protocol {name} is DDP's .* it needs a world model"):
            e.evaluate([name], episodes=1, output_dir=tmp_path, progress=False)
    with pytest.raises(RecipeError, match="--protocols: protocol id is named twice"):
        e.evaluate(["id", "ood_base", "id"], episodes=1, output_dir=tmp_path, progress=False)


def test_discrepancy_needs_a_world_model(tiny_recipe):
    tiny_recipe["world_model"]["enabled"] = False
    e = build(tiny_recipe)
    with pytest.raises(ValueError, match="needs a world model"):
        e.make_controller(detector={"name": "discrepancy", "tau": 1.0})


def test_state_is_per_environment(exp):
    """Two envs in one batch: each keeps its own mode; a new episode resets only its own state."""
    ctrl = exp.make_controller()
    envs = [make_chunked_env(exp, seed=0), make_chunked_env(exp, seed=0, overrides={"displacement": False})]
    keys = ["point_cloud", "agent_pos", "chunk_index", "privileged"]
    obs = [e.reset().select(*keys) for e in envs]
    modes = []
    for cycle in range(4):
        if cycle == 3:
            obs[1] = envs[1].reset().select(*keys)  # env 1 starts a new episode
        out = ctrl(torch.stack(obs))
        modes.append(out["ddp", "mode"].tolist())
        obs = [envs[i].step(out[i].select("action", "ee_shift"))["next"].select(*keys) for i in range(2)]
    assert modes == [[0, 0], [0, 0], [1, 0], [1, 0]]
    assert out["ddp", "imagined"].tolist() == [True, False]


def test_evaluate_writes_results_table_and_plots(exp, tmp_path, monkeypatch):
    exp.recipe.controller.forecast_every_cycle = True  # D_R-I traces for the plot
    rep = exp.evaluate(["id", "ood_ddp", "imagination_100"], episodes=2, output_dir=tmp_path, progress=False)
    assert set(rep["protocols"]) == {"id", "ood_ddp", "imagination_100"}
    for res in rep["protocols"].values():
        assert res["episodes"] == 2 and len(res["per_episode"]) == 2
        assert [e["seed"] for e in res["per_episode"]] == [1000, 1001]
    assert (tmp_path / "results.json").exists() and (tmp_path / "table.md").read_text().startswith("| method |")
    assert (tmp_path / "success.png").exists() and (tmp_path / "discrepancy_ood_ddp.png").exists()
    # what reproduces it: batching, device, calibration seed, the weights' digest, the code, the resolved recipe
    stored = json.loads((tmp_path / "results.json").read_text())
    assert stored["num_envs"] == 1 and stored["parallel"] is False and stored["device"] == "cpu"
    assert stored["calibration_seed"] == 1000 + 100_000 and stored["checkpoint"] is None
    assert stored["model_digest"] == model_digest(exp.model) and stored["code"]["ddp"]
    assert stored["settings"]["controller"]["forecast_every_cycle"] is True
    assert stored["parts"]["controller.detector"]["name"] == exp.parts["controller.detector"].plugin.name
    assert not list(tmp_path.glob(".*.tmp"))  # nothing left beside
    # numpy values a Python caller sets (accepted by the option checks) reach results.json as numbers, and
    # both report files go through the atomic writer
    import ddp.atomic_file as atomic_file

    written, real = [], atomic_file.atomic_write
    monkeypatch.setattr(atomic_file, "atomic_write", lambda path, *a, **k: written.append(path.name) or real(path, *a, **k))
    exp.recipe.eval.env = {"max_episode_steps": np.int64(64)}
    exp.evaluate(["id"], episodes=1, output_dir=tmp_path / "np", progress=False)
    assert json.loads((tmp_path / "np" / "results.json").read_text())["settings"]["eval"]["env"] == {
        "max_episode_steps": 64}
    assert sorted(set(written)) == ["results.json", "table.md"]  # results.json again once the plots exist
    first = rep["protocols"]["ood_ddp"]["per_episode"][0]
    assert first["mode"][2] == 1.0
    # each chunk's subtask and the controller's shifts: tracked when flagged (chunk 2), recovered at chunk 4
    assert first["subtask"] == [0.0] * 4 + [1.0] * 4
    shifts = [[0.0] * 3] * 8
    shifts[2], shifts[4] = DELTA, [-d for d in DELTA]
    assert first["ee_shift"] == shifts


def test_video_frames_are_labelled_with_the_controller_mode(tmp_path):
    from ddp.video import ID_COLOUR, IMAGINED_COLOUR, SHIFT_COLOUR, VideoSettings

    base = SyntheticReachEnv(SyntheticReachEnvConfig(num_points=32, max_episode_steps=16), seed=0)
    env = ChunkedEnv(base, action_steps=8, obs_steps=2, video=VideoSettings(str(tmp_path), episodes=1, size=64))
    td = env.reset()
    frames = env.recorder.frames
    assert len(frames) == 1 and frames[0].shape == (64, 64, 3)
    td["action"] = torch.zeros(8, 4)
    td["ddp", "mode"], td["ddp", "imagined"] = torch.tensor(0), torch.tensor(False)
    td = env.step(td)["next"]
    assert len(frames) == 9 and tuple(frames[-1][0, 0]) == ID_COLOUR
    td["action"] = torch.zeros(8, 4)
    td["ee_shift"] = torch.tensor([0.05, 0.0, 0.0])
    td["ddp", "mode"], td["ddp", "imagined"] = torch.tensor(1), torch.tensor(True)
    env.step(td)  # the episode ends: the video is written and the frames dropped
    assert env.recorder.frames == [] and len(env.recorder.written) == 1
    video = env.recorder.written[0]
    assert video.name.startswith("seed0.") and video.stat().st_size > 0
    # the contact sheet: the last frame of each of the two chunks, side by side, labelled as in the video
    from PIL import Image

    sheet = np.asarray(Image.open(tmp_path / "seed0_sheet.png"))
    assert sheet.shape == (160, 320, 3)
    assert tuple(sheet[1, 1]) == ID_COLOUR and tuple(sheet[1, 161]) == IMAGINED_COLOUR
    env.reset()  # the second episode is not recorded (episodes=1)
    assert not env.recorder.recording and env.recorder.frames == []
    # the imagined chunk is red with a blue (tracking shift) ring, whatever the file format
    from ddp.video import ChunkLabel, annotate

    label = ChunkLabel(chunk=1, mode=1, imagined=True, shifted=True)
    img = annotate(np.zeros((64, 64, 3), np.uint8), label.caption(), label.colour(), flash=SHIFT_COLOUR)
    assert tuple(img[0, 0]) == IMAGINED_COLOUR and tuple(img[5, 5]) == SHIFT_COLOUR
    assert label.caption().startswith("chunk 1  OOD: imagining")


def test_chunked_env_without_render_rgb_refuses_video(tmp_path):
    from ddp.video import VideoSettings

    base = SyntheticReachEnv(SyntheticReachEnvConfig(num_points=32), seed=0)
    base.render_rgb = None
    with pytest.raises(ValueError, match="cannot record videos"):
        ChunkedEnv(base, action_steps=8, obs_steps=2, video=VideoSettings(str(tmp_path)))


def test_evaluate_videos_and_parallel_envs_match_serial(exp, tmp_path):
    exp.recipe.eval.video_episodes = 1
    exp.recipe.eval.video_size = 32
    serial = exp.evaluate(["ood_ddp"], episodes=4, num_envs=2, output_dir=tmp_path / "s", progress=False, video=True)
    videos = serial["protocols"]["ood_ddp"]["videos"]
    assert [Path(v).stem for v in videos] == ["seed1000", "seed1002"]  # env i starts at seed + 2 i
    parallel = exp.evaluate(["ood_ddp"], episodes=4, num_envs=2, output_dir=tmp_path / "p", progress=False,
                            parallel=True)
    for key in ("seed", "success", "mode", "chunks"):
        got = [e[key] for e in parallel["protocols"]["ood_ddp"]["per_episode"]]
        assert got == [e[key] for e in serial["protocols"]["ood_ddp"]["per_episode"]], key
    # those are alike for every episode here (the oracle's schedule, an untrained policy): the D_R-I traces,
    # which follow each episode's observations, say whether the workers ran the same episodes
    exp.recipe.controller.forecast_every_cycle = True
    traces = [[e["discrepancy"] for e in exp.evaluate(["ood_ddp"], episodes=4, num_envs=2, output_dir=tmp_path / d,
                                                      progress=False, parallel=d == "p2")["protocols"]["ood_ddp"]
               ["per_episode"]] for d in ("s2", "p2")]
    assert np.isfinite(np.asarray(traces[0], dtype=float)[:, 1:]).all()
    assert len({tuple(t) for t in traces[0]}) == 4  # the episodes differ
    np.testing.assert_allclose(np.asarray(traces[1], dtype=float), np.asarray(traces[0], dtype=float), rtol=1e-5,
                               equal_nan=True)


def test_an_evaluation_leaves_torch_s_thread_count_as_it_found_it(exp, tmp_path):
    """torchrl's batched envs set torch's thread count when they close (SerialEnv: to min(the count at import,
    count + envs)): after one evaluation a suite run with --threads 1 trained and evaluated on two OpenMP
    threads for the rest of its process, beside another run on a 2-core machine (its evaluations 10-16x slower)."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        exp.evaluate(["id"], episodes=2, num_envs=2, output_dir=tmp_path / "s", progress=False)
        assert torch.get_num_threads() == 1
        exp.evaluate(["id"], episodes=2, num_envs=2, output_dir=tmp_path / "p", progress=False, parallel=True)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_an_env_that_fails_its_first_reset_is_closed_and_the_thread_count_kept(exp, tmp_path, monkeypatch):
    """The collector resets the envs when it is built: an env failing there (a renderer, a robot that does not
    answer) left the batched env open (closed later by the garbage collector, which then raised torch's thread
    count) because the env and collector were made before the ``try`` that closes them."""
    import gc

    from torchrl.envs import SerialEnv

    from ddp.envs.chunked import ChunkedEnv

    closed = []
    close = SerialEnv.close

    def record(self, *args, **kwargs):
        closed.append(self)
        return close(self, *args, **kwargs)

    def fail(self, *args, **kwargs):
        raise RuntimeError("camera did not answer")

    monkeypatch.setattr(SerialEnv, "close", record)
    monkeypatch.setattr(ChunkedEnv, "_reset", fail)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with pytest.raises(RuntimeError, match="camera did not answer"):
            exp.evaluate(["id"], episodes=2, num_envs=2, output_dir=tmp_path / "s", progress=False)
        assert len(closed) == 1  # closed by the evaluation, not left to the garbage collector
        gc.collect()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_a_failing_close_after_a_failed_evaluation_keeps_the_first_error_and_every_cleanup(exp, tmp_path,
                                                                                          monkeypatch):
    """The evaluation's cleanup (bar, collector, env, thread count, background forecast) ran one step after
    another: a close failing on a dead worker's broken pipe replaced the worker's own error and skipped the
    thread-count restore and the close of the controller (its last forecast)."""
    from torchrl.envs import SerialEnv

    from ddp.envs.chunked import ChunkedEnv

    close = SerialEnv.close
    waited = []

    def broken_close(self, *args, **kwargs):
        close(self, *args, **kwargs)
        torch.set_num_threads(3)  # as torchrl's close does
        raise BrokenPipeError("worker pipe closed")

    def fail(self, *args, **kwargs):
        raise RuntimeError("camera did not answer")

    monkeypatch.setattr(SerialEnv, "close", broken_close)
    monkeypatch.setattr(ChunkedEnv, "_reset", fail)
    ctrl = exp.make_controller()
    monkeypatch.setattr(ctrl, "close", lambda: waited.append(True))
    from ddp.eval_runner import rollout_episodes

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with pytest.warns(RuntimeWarning, match="evaluation cleanup: BrokenPipeError"), \
                pytest.raises(RuntimeError, match="camera did not answer"):
            rollout_episodes(exp, ctrl, episodes=2, seed=0, overrides={"max_episode_steps": 24}, num_envs=2,
                             progress=False)
        assert torch.get_num_threads() == 1 and waited == [True]
    finally:
        torch.set_num_threads(before)


def test_env_section_oracle_tracking_turns_the_controllers_tracker_off(exp, monkeypatch):
    """A recipe whose env section sets oracle_tracking: the env tracks in ood_tracking and ood_ddp_oracle,
    so the controller must not shift the end-effector too (it read only the protocol's overrides)."""
    made = []

    def record(**kwargs):
        made.append(kwargs["tracker"])
        raise KeyboardInterrupt  # stop before any rollout

    exp.resolved["env"]["oracle_tracking"] = True
    monkeypatch.setattr(exp, "make_controller", record)
    with pytest.raises(KeyboardInterrupt):
        exp.evaluate(["ood_tracking"], episodes=1, progress=False)
    assert made == [False]
    exp.resolved["env"]["oracle_tracking"] = False
    with pytest.raises(KeyboardInterrupt):
        exp.evaluate(["ood_tracking"], episodes=1, progress=False)
    assert made == [False, True]


def test_videos_are_the_evaluated_episodes_whole_whatever_num_envs(exp, tmp_path):
    """An env whose share is smaller than eval.video_episodes, and the collector's reset after the last batch,
    started recordings that were written as 1-frame videos over the next env's real ones (and listed seeds
    that were never evaluated); a rerun into the same folder listed the earlier run's files."""
    from PIL import Image

    exp.recipe.eval.video_episodes = 2
    exp.recipe.eval.video_size = 32
    rep = exp.evaluate(["id"], episodes=3, num_envs=3, output_dir=tmp_path, progress=False, video=True)
    videos = [Path(v) for v in rep["protocols"]["id"]["videos"]]
    assert [v.stem for v in videos] == ["seed1000", "seed1001", "seed1002"]
    folder = tmp_path / "videos" / "id"
    assert sorted(p.stem for p in folder.iterdir() if p.suffix in (".mp4", ".gif")) == [v.stem for v in videos]
    chunks = rep["protocols"]["id"]["per_episode"][0]["chunks"]
    for v in videos:  # the contact sheet holds one tile per chunk: a whole episode, not its reset frame
        sheet = Image.open(folder / f"{v.stem}_sheet.png")
        assert sheet.width == min(chunks, 8) * 160, v.stem
    again = exp.evaluate(["id"], episodes=1, seed=2000, output_dir=tmp_path, progress=False, video=True)
    assert [Path(v).stem for v in again["protocols"]["id"]["videos"]] == ["seed2000"]


def test_a_video_camera_the_env_lacks_is_one_line_before_any_rollout(exp, tmp_path, monkeypatch):
    """eval.video_camera naming a camera the env does not have was a ValueError traceback at the first recorded
    frame (after the detector's calibration); now a RecipeError naming the key, before any rollout."""
    import ddp.evaluate as evaluate_module
    from ddp.errors import RecipeError

    def no_rollouts(*args, **kwargs):
        raise AssertionError("an episode ran before the camera was checked")

    exp.recipe.eval.video_camera = "side"
    monkeypatch.setattr(evaluate_module, "rollout_episodes", no_rollouts)
    with pytest.raises(RecipeError, match=r"eval.video_camera: .*one video camera, 'top'; got 'side'"):
        exp.evaluate(["id", "id_ddp"], episodes=1, output_dir=tmp_path, progress=False, video=True)
    exp.recipe.eval.video_camera = "top"
    with pytest.raises(AssertionError, match="before the camera was checked"):  # the env's camera passes
        exp.evaluate(["id"], episodes=1, output_dir=tmp_path, progress=False, video=True)
    exp.recipe.eval.video_camera = "side"
    with pytest.raises(AssertionError, match="before the camera was checked"):  # no video: not checked
        exp.evaluate(["id"], episodes=1, output_dir=tmp_path, progress=False, video=False)
    from ddp.envs.synthetic_reach import SyntheticReachEnv

    monkeypatch.delattr(SyntheticReachEnv, "render_rgb")  # an env plugin that cannot render
    with pytest.raises(RecipeError, match=r"eval.video_camera: env 'synthetic_reach' cannot record videos"):
        exp.evaluate(["id"], episodes=1, output_dir=tmp_path, progress=False, video=True)
    exp.recipe.eval.video_camera = None  # the default camera: refused all the same, before any rollout
    with pytest.raises(RecipeError, match=r"eval.video_camera: env 'synthetic_reach' cannot record videos"):
        exp.evaluate(["id", "id_ddp"], episodes=1, output_dir=tmp_path, progress=False, video=True)


def test_object_hidden_at_ood_entry_is_tracked_once_seen(exp):
    """A tracker that cannot see the object when OOD begins (zero offset) and sees it one cycle later."""

    class LateTracker(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.calls = 0

        def forward(self, td):
            self.calls += 1
            offsets = td.get(("privileged", "displacement")).clone()
            if self.calls <= 3:  # cycles 0-2: hidden (OOD is detected at cycle 2)
                offsets.zero_()
            td.set(("ddp", "offsets"), offsets)
            return td

        def reset(self):
            self.calls = 0

        def key(self, role):
            return ("ddp", role)

    ctrl = exp.make_controller()
    ctrl.tracker = LateTracker()
    r = rollout(exp, ctrl)
    mode, shift = r["ddp", "mode"].tolist(), r["ee_shift"]
    assert mode[2] == 1 and torch.allclose(shift[2], torch.zeros(3))  # OOD, but nothing seen to track yet
    assert torch.allclose(shift[3], torch.tensor(DELTA))  # seen at cycle 3: tracked then
    assert torch.allclose(shift[4], -torch.tensor(DELTA))  # and recovered at the end of its subtask


def test_tau_calibrated_from_id_rollouts_without_forecast_every_cycle(exp, tmp_path):
    assert not exp.recipe.controller.forecast_every_cycle
    from ddp.schema import resolve_part

    exp.parts["controller.detector"] = resolve_part(
        "detector", {"name": "discrepancy", "tau": None, "alpha": 0.5, "threshold_on": "all"},
        key="controller.detector", source="<test>",  # an untrained policy: no ID episode succeeds
    )
    exp.recipe.eval.calibration_episodes = 1
    exp.parts["controller.detector"].config.alpha = 0.05  # needs 19 held-out ID episodes: one line says so
    with pytest.raises(RecipeError, match="alpha 0.05 needs at least 19 held-out ID calibration episodes"):
        exp.evaluate(["ood_ddp"], episodes=1, output_dir=tmp_path, progress=False)
    exp.parts["controller.detector"].config.alpha = 0.5
    rep = exp.evaluate(["ood_ddp"], episodes=1, output_dir=tmp_path, progress=False)
    tau = rep["protocols"]["ood_ddp"]["tau"]
    assert tau is not None and tau > 0


@pytest.mark.parametrize("samples, threads", [(1, 1), (3, 1), (1, 2)])
def test_async_forecast_equals_the_inline_one(exp, samples, threads):
    """async_forecast makes the next forecast in a background thread while the chunk executes: two envs,
    one of which starts a new episode mid-way, give the same actions, forecasts and modes as the inline
    forecast_every_cycle path (own noise stream), with the D_R-I detector and imagination in play; also
    with two torch threads, where the background forecast runs single-threaded and the inline one not."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        outs = _inline_and_async(exp, samples)
    finally:
        torch.set_num_threads(previous)
    assert outs["inline"]["ddp", "imagined"].any()  # the comparison covers imagination
    pred = outs["inline"]["ddp", "latent_pred"]  # [cycle, env, M, D]: NaN only before an episode's first forecast
    assert torch.isnan(pred).flatten(2).all(-1).tolist() == [[True, True]] + [[False, False]] * 3 + [
        [False, True]] + [[False, False]] * 2
    for key in ("action", "ee_shift", ("ddp", "latent_pred"), ("ddp", "mode"), ("ddp", "imagined")):
        torch.testing.assert_close(outs["async"][key], outs["inline"][key], rtol=0, atol=0, equal_nan=True)


def _inline_and_async(exp, samples: int) -> dict:
    """Seven cycles of two envs (one resets at cycle 4) with the inline and with the background forecast."""
    exp.recipe.controller.forecast_samples = samples
    keys = ["point_cloud", "agent_pos", "chunk_index", "privileged"]
    outs = {}
    for mode in ("inline", "async"):
        ctrl = exp.make_controller(detector={"name": "discrepancy", "tau": 0.05}, forecast_every_cycle=True,
                                   async_forecast=mode == "async")
        envs = [make_chunked_env(exp, seed=0), make_chunked_env(exp, seed=1, overrides={"displacement": False})]
        obs = [e.reset().select(*keys) for e in envs]
        steps = []
        for cycle in range(7):
            if cycle == 4:
                obs[1] = envs[1].reset().select(*keys)
            out = ctrl(torch.stack(obs))
            if mode == "async":
                assert ctrl._job is not None  # the next forecast runs while the envs step
            steps.append(out.select("action", "ee_shift", ("ddp", "latent_pred"), ("ddp", "mode"),
                                    ("ddp", "imagined")).clone())
            obs = [envs[i].step(out[i].select("action", "ee_shift"))["next"].select(*keys) for i in range(2)]
        ctrl.close()
        outs[mode] = torch.stack(steps)
    return outs


def test_background_forecast_keeps_the_thread_count_copies_and_follows_a_swapped_detector(exp):
    import copy
    import threading

    threads, before = 2, torch.get_num_threads()  # the tests run single-threaded: the forecast drops to 1
    torch.set_num_threads(threads)
    try:
        ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True)
        during = []  # the forecast itself runs single-threaded (a second OpenMP team slows the main thread)
        imagine = ctrl.model.imagine
        ctrl.model.imagine = lambda *a, **k: during.append(torch.get_num_threads()) or imagine(*a, **k)
        env = make_chunked_env(exp, seed=0)
        td = ctrl(env.reset())
        ctrl.wait_forecast()
        assert during == [1]
        ctrl.model.imagine = imagine
        seen = []  # single-threaded only while the forecast ran: here, and in threads started later
        later = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
        later.start()
        later.join()
        assert torch.get_num_threads() == threads and seen == [threads]
    finally:
        torch.set_num_threads(before)
    clone = copy.deepcopy(ctrl)  # e.g. a collector moving the policy: the thread stays behind
    assert clone._pool is None and clone._job is None
    # the forecast the original was making is stored first: the copy's next cycle has a D_R-I to score
    out = clone(env.step(td)["next"])
    assert not torch.isnan(out["ddp", "latent_pred"]).any()
    clone.close()
    ctrl.close()
    # forecasting every cycle is read each cycle: a D_R-I detector swapped in later gets its forecasts
    lazy = exp.make_controller(detector={"name": "never"}, tracker=False)
    assert not lazy.forecast_every_cycle and not lazy.async_forecast
    lazy.detector = exp.make_controller(detector={"name": "discrepancy", "tau": 1.0}).detector
    assert lazy.forecast_every_cycle and lazy.async_forecast
    td = lazy(env.reset())
    td = lazy(env.step(td)["next"])
    assert not torch.isnan(td["ddp", "latent_pred"]).any()
    lazy.close()


def test_async_forecast_error_surfaces_on_the_next_cycle(exp):
    ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True, async_forecast=True)
    env = make_chunked_env(exp, seed=0)
    td = ctrl(env.reset())

    def broken(*args, **kwargs):
        raise RuntimeError("world model exploded")

    ctrl.wait_forecast()
    ctrl.model.imagine = broken  # the forecast already ran; break the next one
    td = env.step(td)["next"]
    td = ctrl(td)  # collects the good forecast, launches the broken one
    with pytest.raises(RuntimeError, match="world model exploded"):
        ctrl(env.step(td)["next"])
    td = ctrl(env.reset())  # launches another broken forecast; a reset says it drops it
    with pytest.warns(RuntimeWarning, match="forecast failed and was dropped at reset"):
        ctrl.reset()
    ctrl(env.reset())  # and a close: no cycle is left to raise its error
    with pytest.warns(RuntimeWarning, match="forecast failed and was dropped at close"):
        ctrl.close()
    del ctrl.model.imagine


def test_an_evaluation_without_an_episode_length_names_what_to_set(exp):
    """"set eval.max_steps" was the advice for an env config without a max_episode_steps field too, where
    eval.max_steps is refused (it sets that field); and it named the section, not the key."""
    import dataclasses

    from ddp.errors import RecipeError
    from ddp.eval_runner import _chunks_per_episode
    from ddp.schema import Part

    with pytest.raises(ValueError, match=r"max_episode_steps must be a number >= 1; got None"):
        _chunks_per_episode(exp, {"max_episode_steps": None})  # the shipped envs' configs refuse it

    @dataclasses.dataclass
    class UnsetLength:  # a plugin's config that leaves it unset
        max_episode_steps: int | None = None

    @dataclasses.dataclass
    class NoLength:
        seed: int = 0

    exp.parts["env"] = Part(exp.parts["env"].plugin, UnsetLength())
    with pytest.raises(RecipeError, match=r"eval.max_steps: the episode length is not set"):
        _chunks_per_episode(exp, {})
    exp.parts["env"] = Part(exp.parts["env"].plugin, NoLength())
    with pytest.raises(RecipeError, match=r"env: env 'synthetic_reach' has no max_episode_steps option"):
        _chunks_per_episode(exp, {})


def test_an_evaluation_reports_the_last_background_forecast_s_error(exp):
    """The forecast launched by an episode's last cycle is collected by no cycle: rollout_episodes waited for
    it and dropped its error silently (and left the controller's thread running)."""
    from ddp.eval_runner import rollout_episodes

    ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True, async_forecast=True)
    calls, imagine, fail_at = [], exp.model.imagine, []

    def counted(*args, **kwargs):
        calls.append(1)
        if len(calls) in fail_at:  # the forecast the last cycle launches
            raise RuntimeError("world model exploded")
        return imagine(*args, **kwargs)

    exp.model.imagine = counted
    try:
        rollout_episodes(exp, ctrl, episodes=1, seed=0, overrides={}, progress=False)
        assert ctrl._pool is None  # the thread is stopped; a controller used again starts another
        fail_at.append(len(calls))
        calls.clear()
        with pytest.warns(RuntimeWarning, match="forecast failed and was dropped at close: .*world model exploded"):
            rollout_episodes(exp, ctrl, episodes=1, seed=0, overrides={}, progress=False)
    finally:
        del exp.model.imagine
    assert len(calls) == fail_at[0] and ctrl._pool is None


def test_detection_metrics_follow_the_detector_s_decides_flag_not_its_name(tiny_recipe, tmp_path):
    """Evaluation listed the built-in non-deciding detectors by name: a plugin detector that decides nothing
    got detection metrics (and a deciding one named 'never' would have lost them)."""
    from ddp.detectors.never import NeverConfig, NeverDetector
    from ddp.registry import register, unregister

    @register("detector", "quiet_plugin", config=NeverConfig)
    class Quiet(NeverDetector):
        """Decides nothing (as never does), under another name."""

    try:
        recipe = dict(tiny_recipe, controller={"detector": {"name": "quiet_plugin"}, "tracker": None})
        exp = fit_normalizer(build(recipe))
        rep = exp.evaluate(["id_ddp"], episodes=1, output_dir=tmp_path, progress=False)
        assert "detection" not in rep["protocols"]["id_ddp"]
        Quiet.decides = True
        rep = exp.evaluate(["id_ddp"], episodes=1, output_dir=tmp_path, progress=False)
        assert "detection" in rep["protocols"]["id_ddp"]
    finally:
        unregister("detector", "quiet_plugin")
