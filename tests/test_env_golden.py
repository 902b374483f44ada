"""Golden observations: every env's outputs stay what they were when the env base was introduced.

Each case rolls one env (fixed seed, seeded random actions, disturbances and
occlusion on) through ``ChunkedEnv`` and fingerprints every leaf of every
output: its dtype, shape, the float64 sum and the sum of squares, and a
hash-free sample of values. ``tests/golden/env_observations.json`` holds
the fingerprints; regenerate it (only when an observation change is meant)
with ``python tests/test_env_golden.py --write``.

The comparison is exact on dtype, shape and integer/bool leaves, and at
``rtol=1e-6`` on float sums (MuJoCo's EGL depth may differ in the last bit
across CPUs; a behaviour change moves them by far more).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

GOLDEN = Path(__file__).parent / "golden" / "env_observations.json"
CHUNKS = 4

CASES = {
    "synthetic_displaced": ("synthetic_reach", dict(displacement=True, displacement_chunk=1)),
    "synthetic_occluded": ("synthetic_reach", dict(occlusion_chunk=1, occlusion_chunks=2)),
    "metaworld_oracle": (
        "metaworld",
        dict(task="drawer-open", image_size=48, num_points=128, displacement=True, displacement_chunk=1,
             oracle_tracking=True, settle_steps=2),
    ),
    "metaworld_occluded": (
        "metaworld", dict(task="button-press", image_size=48, num_points=128, occlusion_chunk=2, occlusion_mode="noise"),
    ),
    "adroit_occluded": ("adroit", dict(task="door", image_size=48, num_points=128, occlusion_chunk=1,
                                       occlusion_mode="drop")),
    "franka_oracle": (
        "franka",
        dict(task="stack", num_points=128, presample=512, image_height=48, image_width=64, displacement=True,
             displacement_chunks=[1, 2], oracle_tracking=True, settle_steps=5, occlusion_chunk=3,
             occlusion_mode="noise"),
    ),
}
NEEDS = {"metaworld": "metaworld", "adroit": "gymnasium_robotics", "franka": "robosuite"}


def _fingerprint(td) -> dict:
    out = {}
    for key in sorted(td.keys(include_nested=True, leaves_only=True), key=str):
        x = td.get(key)
        name = key if isinstance(key, str) else "/".join(key)
        a = x.detach().cpu().numpy()
        entry = {"dtype": str(a.dtype), "shape": list(a.shape)}
        if a.dtype.kind == "f":
            a64 = a.astype(np.float64)
            entry["sum"] = float(a64.sum())
            entry["sumsq"] = float((a64**2).sum())
            entry["first"] = [float(v) for v in a64.ravel()[:4]]
        else:
            entry["values"] = a.astype(np.int64).ravel()[:16].tolist()
            entry["sum"] = int(a.astype(np.int64).sum())
        out[name] = entry
    return out


def roll(case: str) -> list[dict]:
    """Fingerprints of the reset and ``CHUNKS`` chunk steps of ``case``."""
    from ddp import registry
    from ddp.envs.chunked import ChunkedEnv, chunk_render_config

    name, options = CASES[case]
    plugin = registry.get("env", name)
    config = chunk_render_config(plugin.config_cls(**options), 8, 2)
    base = plugin.factory(config, seed=3)
    env = ChunkedEnv(base, action_steps=8, obs_steps=2)
    try:
        gen = torch.Generator().manual_seed(0)
        td = env.reset()
        prints = [_fingerprint(td)]
        low, high = env.full_action_spec["action"].space.low, env.full_action_spec["action"].space.high
        for _ in range(CHUNKS):
            action = low + (high - low) * torch.rand(low.shape, generator=gen)
            td.set("action", action.to(torch.float32))
            td.set("ee_shift", torch.zeros(3))
            td = env.step(td)["next"]
            prints.append(_fingerprint(td))
            td = td.exclude("reward", "done", "terminated", "truncated")
        return prints
    finally:
        env.close()


def _compare(got, want, where: str) -> None:
    assert set(got) == set(want), f"{where}: keys differ: {sorted(set(got) ^ set(want))}"
    for key in want:
        g, w = got[key], want[key]
        assert g["dtype"] == w["dtype"] and g["shape"] == w["shape"], f"{where} {key}: {g} != {w}"
        if "values" in w:
            assert g["values"] == w["values"] and g["sum"] == w["sum"], f"{where} {key}: {g} != {w}"
        else:
            for field in ("sum", "sumsq", "first"):
                np.testing.assert_allclose(g[field], w[field], rtol=1e-6, atol=1e-9, err_msg=f"{where} {key} {field}")


@pytest.mark.parametrize("case", sorted(CASES))
def test_observations_match_the_golden_fingerprints(case):
    name = CASES[case][0]
    if name in NEEDS:
        pytest.importorskip(NEEDS[name])
    want = json.loads(GOLDEN.read_text())[case]
    got = roll(case)
    assert len(got) == len(want)
    for i, (g, w) in enumerate(zip(got, want)):
        _compare(g, w, f"{case} output {i}")


if __name__ == "__main__":  # python tests/test_env_golden.py --write
    os.environ.setdefault("MUJOCO_GL", "egl")
    if "--write" not in sys.argv:
        sys.exit("usage: python tests/test_env_golden.py --write   (regenerates tests/golden/env_observations.json)")
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps({case: roll(case) for case in sorted(CASES)}, indent=1) + "\n")
    print(f"wrote {GOLDEN}")
