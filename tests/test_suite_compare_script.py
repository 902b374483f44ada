"""scripts/suite_compare.py: per task, a method's stored results before and after a settings change; a run
stored under the same recipe hash on both sides has not been run again and counts on neither."""

from __future__ import annotations

import importlib.util
import json

from conftest import ROOT

from ddp.suite.store import FORMAT


def _script():
    spec = importlib.util.spec_from_file_location("suite_compare", ROOT / "scripts" / "suite_compare.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _store(folder, task, recipe_hash, successes, on_time, **protocols):
    folder.mkdir(exist_ok=True)
    detection = {"disturbed_episodes": 20, "clean_episodes": 0, "detected_within_1": on_time, "missed": 20 - on_time}
    run = {"format": FORMAT, "task": task, "method": "ddp", "seed": 0, "complete": True, "recipe_hash": recipe_hash,
           "protocols": {"ood_ddp": {"successes": successes, "episodes": 20, "detection": detection, "tau": 0.5},
                         **protocols}}
    (folder / f"{task}__ddp__seed0.json").write_text(json.dumps(run))


def test_rows_and_averages_count_only_runs_made_again(tmp_path, capsys):
    before, after = tmp_path / "before", tmp_path / "after"
    _store(before, "push", "h1", 4, 10)
    _store(after, "push", "h2", 12, 15)  # run again under the new settings
    _store(before, "sweep", "h1", 2, 5)
    _store(after, "sweep", "h1", 2, 5)  # still the old result: not compared
    assert _script().main([str(before), str(after), "--protocols", "ood_ddp"]) == 0
    out = capsys.readouterr().out
    assert "| push | 4/20 (10 on time, 10 missed) | 12/20 (15 on time, 5 missed) |" in out
    assert "| sweep | 2/20 (5 on time, 15 missed) | - |" in out
    assert "| tasks on both sides | 20.0 % | 60.0 % |" in out


def test_an_alarm_still_on_when_the_move_shows_is_not_a_miss(tmp_path, capsys):
    """Results stored before detection_metrics split them counted such episodes as missed: the script reads the
    stored traces."""
    before, after = tmp_path / "before", tmp_path / "after"
    for folder, h in ((before, "h1"), (after, "h2")):
        _store(folder, "push", h, 10, 17)  # 3 "missed" as stored
        run = json.loads((folder / "push__ddp__seed0.json").read_text())
        run["protocols"]["ood_ddp"]["traces"] = (
            [{"success": True, "first_visible": 3, "mode": "00011111", "score": []}] * 17
            + [{"success": False, "first_visible": 3, "mode": "01111111", "score": []}] * 2  # on since chunk 1
            + [{"success": False, "first_visible": 3, "mode": "00000000", "score": []}])  # never flagged
        (folder / "push__ddp__seed0.json").write_text(json.dumps(run))
    assert _script().main([str(before), str(after), "--protocols", "ood_ddp"]) == 0
    assert "| push | 10/20 (17 on time, 1 missed, 2 alarmed before) |" in capsys.readouterr().out


def test_detection_counts_only_where_a_detector_decided(tmp_path, capsys):
    """Under the oracle schedule (tau None) the mode follows the env: no on-time / missed counts there; a
    stored alarm_before_visible count is taken as stored."""
    before, after = tmp_path / "before", tmp_path / "after"
    oracle = {"successes": 17, "episodes": 20, "tau": None,
              "detection": {"disturbed_episodes": 20, "clean_episodes": 0, "detected_within_1": 20, "missed": 0}}
    _store(before, "push", "h1", 10, 15, ood_ddp_oracle=oracle)
    _store(after, "push", "h2", 12, 15, ood_ddp_oracle=oracle)
    run = json.loads((after / "push__ddp__seed0.json").read_text())
    run["protocols"]["ood_ddp"]["detection"].update(missed=2, alarm_before_visible=3)
    (after / "push__ddp__seed0.json").write_text(json.dumps(run))
    assert _script().main([str(before), str(after), "--protocols", "ood_ddp,ood_ddp_oracle"]) == 0
    out = capsys.readouterr().out
    assert "| push | 10/20 (15 on time, 5 missed) | 12/20 (15 on time, 2 missed, 3 alarmed before) | 17/20 | 17/20 |" in out


def test_bad_arguments_and_damaged_files_are_named(tmp_path, capsys):
    import pytest

    before, after = tmp_path / "before", tmp_path / "after"
    _store(before, "push", "h1", 4, 10)
    _store(after, "push", "h2", 12, 15)
    (after / "sweep__ddp__seed0.json").write_text('{"format": "half')  # half-written
    for argv, message in (([ "--method", "DDP"], "before: no stored run *__DDP__seed0.json (--method, --seed)"),
                          (["--seed", "3"], "no stored run *__ddp__seed3.json"),
                          (["--protocols", "ood_ddp,nosuch"], "--protocols: no stored run has protocol 'nosuch'")):
        with pytest.raises(SystemExit):
            _script().main([str(before), str(after), *argv])
        assert message in capsys.readouterr().err
    assert _script().main([str(before), str(after), "--protocols", "ood_ddp"]) == 0
    err = capsys.readouterr().err
    assert "sweep__ddp__seed0.json: not a whole stored result" in err
