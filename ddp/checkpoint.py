"""Checkpoints: written atomically, loaded without executing pickled code.

A checkpoint is one file saved by ``torch.save`` holding only tensors,
numbers, strings and containers of them, and read back with
``torch.load(weights_only=True)``, which refuses anything else.
"""

from __future__ import annotations

import os
import pickle
import re
import warnings
from pathlib import Path
from typing import Any

import torch

from ddp.atomic_file import atomic_write
from ddp.errors import CheckpointError

FORMAT = "ddp-checkpoint"
VERSION = 1


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` to ``path`` atomically (temp file in the same folder, fsync, rename); a write the
    system refuses (disk full, no permission, a file where the folder should be) is a one-line
    :class:`CheckpointError`, and the file at ``path`` stays as it was."""
    data = {"format": FORMAT, "version": VERSION, **payload}
    try:
        return atomic_write(path, lambda f: torch.save(data, f))
    except OSError as err:
        raise CheckpointError(f"{path}: cannot write the checkpoint: {err.strerror or err}") from None
    except RuntimeError as err:  # torch.save reports a failed write of its zip stream as RuntimeError
        if "write" not in str(err).lower():
            raise
        raise CheckpointError(f"{path}: cannot write the checkpoint: {str(err).splitlines()[0]}") from None


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu", *,
                    mmap: bool = False) -> dict[str, Any]:
    """Read a checkpoint; a missing, truncated or foreign file raises :class:`CheckpointError`. ``mmap``
    maps the tensors instead of reading them (for a caller that only looks at the recipe or step)."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: is a directory, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols before refusing: the error says it
            warnings.simplefilter("ignore")
            data = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as err:
        text = " ".join(str(err).split())
        found = re.search(r"Unsupported global: GLOBAL (\S+)", text) or re.search(r"Trying to load [^.]*", text)
        if found is None:  # not a pickle of objects at all: damaged or foreign bytes
            op = re.search(r"Unsupported operand \d+", text)
            raise CheckpointError(f"{path}: not a readable checkpoint (truncated or foreign file?): "
                                  f"{op.group(0) if op else type(err).__name__}") from None
        what = found.group(1) if found.re.groups else found.group(0)
        raise CheckpointError(f"{path}: refused to load: it holds Python objects ({what}), not only tensors and "
                              "containers; loading never runs a checkpoint's code") from None
    except Exception as err:  # noqa: BLE001 - torch raises many types on damaged files
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or foreign file?): {first}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a ddp checkpoint (no '{FORMAT}' marker)")
    if data.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {data.get('version')} is not supported (expected {VERSION})")
    return data


def describe_mismatch(model: torch.nn.Module, weights: dict, limit: int = 3) -> str:
    """One line: which keys a state dict lacks or adds, and which shapes differ, against ``model``.

    Empty when the keys and shapes agree.
    """
    if not isinstance(weights, dict):
        return f"the weights are a {type(weights).__name__}, not a state dict"
    own = model.state_dict()
    missing = [k for k in own if k not in weights]
    unexpected = [k for k in weights if k not in own]
    shapes = [
        f"{k} {tuple(weights[k].shape)} vs {tuple(own[k].shape)}"
        for k in own
        if k in weights and hasattr(weights[k], "shape") and tuple(weights[k].shape) != tuple(own[k].shape)
    ]
    shapes += [f"{k} is a {type(weights[k]).__name__}, not a tensor" for k in own
               if k in weights and not isinstance(weights[k], torch.Tensor)]

    def part(label: str, items: list[str]) -> str:
        more = f" (+{len(items) - limit} more)" if len(items) > limit else ""
        return f"{len(items)} {label}: {', '.join(items[:limit])}{more}"

    parts = [part(label, items) for label, items in (("missing", missing), ("unexpected", unexpected),
                                                      ("shape mismatches (checkpoint vs model)", shapes)) if items]
    return "; ".join(parts)


def stored_recipe(path, state: dict) -> dict:
    """The recipe a checkpoint was trained with, as a mapping; one CheckpointError line if there is none."""
    from ddp.recipe import load_yaml

    if not isinstance(state.get("recipe"), str):
        raise CheckpointError(f"{path}: the checkpoint holds no recipe (it was not written by ddp train)")
    try:
        recipe = load_yaml(state["recipe"])
    except Exception:  # noqa: BLE001 - any unreadable stored recipe
        raise CheckpointError(f"{path}: the stored recipe is not readable YAML") from None
    if not isinstance(recipe, dict):
        raise CheckpointError(f"{path}: the stored recipe is not a mapping (got {type(recipe).__name__})")
    return recipe
