"""A detector's calibration saved beside its checkpoint, so it is fitted once and can ship to the robot.

``ddp eval`` writes ``<checkpoint stem>.calibration.json`` next to the
checkpoint: the fitted statistic and threshold (the detector's ``calibration()``), the target
false-alarm rate, how many ID episodes and which seeds produced it, and what it is valid for: a
digest of the model's weights, the detector section, the ID env (the recipe's env section, the
calibration's overrides of it, the chunking), the episode count and its cap, the sampling setup (both
schedulers' sections, the forecast samples, the controller's seed), the device type and the calibration code's ``VERSION``. A later evaluation with the same reuses it; anything else calibrates again and overwrites it. The file is plain
JSON (written atomically); loading it runs no code.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch

from ddp import results_json
from ddp.atomic_file import atomic_write

__all__ = ["calibration_path", "model_digest", "load_calibration", "save_calibration"]

FORMAT = "ddp-detector-calibration"
#: bumped whenever the code changes what a calibration means (the statistic, how tau is set, which ID
#: episodes it comes from); a file of another version is fitted again. 2: calibration seeds past one draw of
#: MetaWorld's initial states go to the next draw (they replayed its 50 layouts); 3: a task's failure for good
#: revokes an episode's success (Franka press: an over-press after a good press), which selects tau's episodes
VERSION = 3


def calibration_path(checkpoint) -> Path:
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(f"{checkpoint.stem}.calibration.json")


def model_digest(model: torch.nn.Module) -> str:
    """sha256 (16 hex digits) of the model's parameters and buffers, in state_dict order."""
    h = hashlib.sha256()
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _key(model_hash: str, detector: dict, id_env: dict, episodes: int, seed: int, sampling: dict | None,
         max_episodes: int | None, device: str | None = None) -> dict:
    key = {"version": VERSION, "model": model_hash, "detector": detector, "id_env": id_env, "episodes": episodes,
           "seed": seed, "sampling": sampling}
    if device is not None:  # the forecasts' device type: another one's kernels give other scores (e.g. TF32 on CUDA)
        key["device"] = device
    if max_episodes is not None:  # the cap on the ID episodes a detector may ask for (the count can grow to it)
        key["max_episodes"] = max_episodes
    return key


def load_calibration(path, *, model_hash: str, detector: dict, id_env: dict, episodes: int, seed: int,
                     sampling: dict | None = None, max_episodes: int | None = None,
                     device: str | None = None) -> dict | None:
    """The saved calibration if ``path`` holds one made for exactly this model, detector, ID env, sampling
    setup (the schedulers' sections, the forecast samples: fewer denoising steps change the scores), device
    type and calibration code (``VERSION``); else None."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        return None
    want = json.loads(results_json.dumps(_key(model_hash, detector, id_env, episodes, seed, sampling, max_episodes,
                                              device)))
    if data.get("valid_for") != want:
        return None
    return data.get("calibration")


def save_calibration(path, calibration: dict, *, model_hash: str, detector: dict, id_env: dict, episodes: int,
                     seed: int, sampling: dict | None = None, checkpoint: str | None = None,
                     max_episodes: int | None = None, device: str | None = None) -> Path:
    """Write the calibration atomically (temp file, fsync, rename)."""
    payload = {"format": FORMAT, "checkpoint": checkpoint,
               "valid_for": _key(model_hash, detector, id_env, episodes, seed, sampling, max_episodes, device),
               "calibration": calibration}
    text = results_json.dumps(payload)
    return atomic_write(path, lambda f: f.write(text), binary=False)
