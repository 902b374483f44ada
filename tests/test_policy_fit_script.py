"""scripts/policy_fit.py: a trained policy reproduces its demos far better than an untrained one."""

from __future__ import annotations

import copy
import importlib.util
import shutil

from conftest import ROOT, TINY


def _script():
    spec = importlib.util.spec_from_file_location("policy_fit", ROOT / "scripts" / "policy_fit.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_policy_fit_separates_a_trained_policy_from_an_untrained_one(tmp_path, capsys):
    from ddp import build

    fit = _script()
    recipe = copy.deepcopy(TINY)
    recipe["train"].update(max_steps=1, epochs=1000, output_dir=str(tmp_path / "run"))
    first = build(recipe).train(progress=False).checkpoint
    shutil.copy(first, tmp_path / "untrained.pt")
    recipe["train"]["max_steps"] = 150  # resumes the same run
    trained = build(recipe).train(progress=False).checkpoint

    before = fit.fit(str(tmp_path / "untrained.pt"), 32, 0)
    after = fit.fit(str(trained), 32, 0)
    assert after["variance"] == before["variance"] > 0  # the same demo windows
    assert after["mse"] / after["variance"] < 0.5 < before["mse"] / before["variance"]
    assert fit.main([str(trained), "--windows", "8"]) == 0
    assert f"| {trained} | 16 x 4 |" in capsys.readouterr().out
    # a bad path: one line naming it, before any table
    assert fit.main([str(trained), str(tmp_path / "missing.pt")]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.strip() == f"ddp: error: {tmp_path / 'missing.pt'}: checkpoint not found"
