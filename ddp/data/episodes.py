"""Episodes stored back to back, DP3 replay-buffer style, memory-mapped on disk.

``steps`` is a TensorDict with batch size [total_steps] (keys such as
``point_cloud`` [T, P, 3], ``agent_pos`` [T, D], ``action`` [T, A]);
``episode_ends`` holds the exclusive end index of each episode.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict

from ddp.atomic_file import atomic_directory
from ddp.errors import DDPError

FORMAT = "ddp-episodes"
VERSION = 1


@dataclass
class Episodes:
    steps: TensorDict
    episode_ends: torch.Tensor  # long [num_episodes], exclusive ends

    def __post_init__(self):
        ends = torch.as_tensor(self.episode_ends, dtype=torch.long)
        if ends.numel() == 0:
            raise ValueError("no episodes")
        if (ends[1:] <= ends[:-1]).any() or ends[0] <= 0 or int(ends[-1]) != self.steps.batch_size[0]:
            raise ValueError("episode_ends must be strictly increasing and end at the number of steps")
        self.episode_ends = ends

    @property
    def num_episodes(self) -> int:
        return int(self.episode_ends.numel())

    @property
    def num_steps(self) -> int:
        return int(self.steps.batch_size[0])

    def episode_starts(self) -> torch.Tensor:
        return torch.cat([torch.zeros(1, dtype=torch.long), self.episode_ends[:-1]])

    def locate(self, step: int) -> tuple[int, int]:
        """(episode, step within it) of a global step index."""
        ep = int(torch.searchsorted(self.episode_ends, torch.tensor(step), right=True))
        return ep, step - (0 if ep == 0 else int(self.episode_ends[ep - 1]))

    def first_nonfinite(self, keys, block: int = 4096) -> tuple[str, int, int] | None:
        """The first ``(key, episode, step within it)`` whose floating-point value holds NaN or inf, else None;
        read ``block`` steps at a time (the data may be memory-mapped)."""
        for key in keys:
            x = self.steps[key]
            if not (x.is_floating_point() or x.is_complex()):
                continue
            for start in range(0, self.num_steps, block):
                part = x[start : start + block]
                bad = ~torch.isfinite(part.reshape(part.shape[0], -1)).all(1)
                if bool(bad.any()):
                    return (key, *self.locate(start + int(bad.nonzero()[0, 0])))
        return None

    def episode(self, i: int) -> TensorDict:
        start = 0 if i == 0 else int(self.episode_ends[i - 1])
        return self.steps[start : int(self.episode_ends[i])]

    @classmethod
    def from_list(cls, episodes: list[TensorDict]) -> "Episodes":
        lengths = torch.tensor([ep.batch_size[0] for ep in episodes], dtype=torch.long)
        return cls(torch.cat(episodes, 0), torch.cumsum(lengths, 0))

    def subset(self, indices) -> "Episodes":
        return Episodes.from_list([self.episode(int(i)) for i in indices])

    def save(self, path: str | Path) -> Path:
        """Write a memory-mappable directory (TensorDict memmap + meta.json), atomically: written beside
        ``path`` and then moved onto it, so an interrupted save leaves what was there (``atomic_directory``).
        ``path`` must be new, empty or an episode directory (it is replaced whole)."""
        target = Path(path)
        if target.is_dir() and any(target.iterdir()) and not (target / "meta.json").is_file():
            raise DDPError(f"{target}: exists and is not an episode directory (no meta.json); saving would replace "
                           f"everything in it: choose a new or empty directory")

        def write(tmp: Path) -> None:
            self.steps.memmap(tmp / "steps", num_threads=0)
            torch.save(self.episode_ends, tmp / "episode_ends.pt")
            (tmp / "meta.json").write_text(
                json.dumps({"format": FORMAT, "version": VERSION, "num_episodes": self.num_episodes})
            )

        return atomic_directory(path, write)

    @classmethod
    def load(cls, path: str | Path) -> "Episodes":
        """Open a directory written by :meth:`save` (memory-mapped, no pickle)."""
        path = Path(path)
        meta_file = path / "meta.json"
        if not meta_file.exists():
            raise DDPError(f"{path}: not a ddp episode directory (no meta.json)")
        meta = _read_json(meta_file)
        found = meta.get("format") if isinstance(meta, dict) else None
        if found != FORMAT:
            raise DDPError(f"{path}: meta.json format is {found!r}, expected {FORMAT!r}")
        _check_leaf_files(path / "steps")  # a truncated file would map as zeros (and be extended on disk)
        try:  # tensors only: a pickled leaf (tensordict's other.pickle) would run code when loaded
            steps = TensorDict.load_memmap(path / "steps", allow_pickle=False)
        except RuntimeError as err:
            raise DDPError(f"{path}: the episode data holds something other than tensors (refused: loading "
                           f"it could run code): {str(err).splitlines()[0]}") from None
        steps = steps.apply(_copy_on_write)
        ends_file = path / "episode_ends.pt"
        if not ends_file.exists():
            raise DDPError(f"{ends_file}: missing (the episode boundaries)")
        try:
            ends = torch.load(ends_file, weights_only=True)
        except Exception as err:  # a pickled object or a damaged file: torch's several-line message, first line
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise DDPError(f"{ends_file}: not a tensor file this loader reads (refused: {first})") from None
        if not isinstance(ends, torch.Tensor):
            raise DDPError(f"{ends_file}: holds a {type(ends).__name__}, expected a 1-D integer tensor of episode ends")
        if ends.dim() != 1 or ends.is_floating_point() or ends.is_complex():
            raise DDPError(f"{ends_file}: holds a {ends.dtype} tensor of shape {tuple(ends.shape)}, expected a 1-D "
                           f"integer tensor of episode ends")
        try:
            return cls(steps, ends)
        except ValueError as err:
            raise DDPError(f"{path}: {err} (episode_ends.pt against the {steps.batch_size[0]} stored steps)") from None


def _copy_on_write(leaf: torch.Tensor) -> torch.Tensor:
    """A private mapping of a memory-mapped leaf: pages are read from disk as they are touched, as before,
    but an in-place edit (user code normalising ``episodes.steps`` in place) stays in this process instead
    of rewriting the cache or dataset on disk (tensordict maps a writable file shared)."""
    filename = getattr(leaf, "filename", None)
    if filename is None or leaf.numel() == 0:
        return leaf
    try:
        return torch.from_file(str(filename), shared=False, size=leaf.numel(), dtype=leaf.dtype).view(leaf.shape)
    except RuntimeError as err:  # a private writable mapping is charged its whole size (vm.overcommit_memory=2)
        warnings.warn(f"{filename}: mapped shared, not copy-on-write ({str(err).splitlines()[0]}): an in-place "
                      "edit of the loaded episodes would reach this file", RuntimeWarning, stacklevel=2)
        return leaf


def _read_json(file: Path):
    """``file``'s JSON value; a file that is not readable JSON is one DDPError line naming it."""
    try:
        return json.loads(file.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as err:  # (JSONDecodeError is a ValueError)
        raise DDPError(f"{file}: not valid JSON ({str(err).splitlines()[0] if str(err) else err!r})") from None


def _check_leaf_files(steps: Path) -> None:
    """Each memory-mapped leaf file holds exactly the bytes its shape and dtype in the TensorDict's
    meta.json need: a file cut short (an interrupted copy, a full disk) is a one-line error, where
    mapping it would read zeros past its end and grow the file to fit."""
    meta_file = steps / "meta.json"
    if not meta_file.is_file():
        raise DDPError(f"{meta_file}: missing (the episode data's layout): a damaged or partly copied episode "
                       "directory")
    meta = _read_json(meta_file)
    if not isinstance(meta, dict):
        raise DDPError(f"{meta_file}: holds a {type(meta).__name__}, expected the episode data's layout (a mapping)")
    for key, leaf in meta.items():
        if isinstance(leaf, dict) and "shape" in leaf and isinstance(leaf.get("dtype"), str):
            file = steps / f"{key}.memmap"
            dtype = getattr(torch, leaf["dtype"].removeprefix("torch."), None)
            if not isinstance(dtype, torch.dtype):
                continue  # not a plain memory-mapped leaf: the loader decides
            numel = 1
            for n in leaf["shape"]:
                numel *= int(n)
            if not file.is_file():
                if numel:  # tensordict skips a leaf without its file: the episodes would load without that key
                    raise DDPError(f"{file}: missing (the episode data's '{key}', {list(leaf['shape'])}): a damaged "
                                   f"or partly copied episode directory")
                continue
            need, size = numel * dtype.itemsize, file.stat().st_size
            if size != need:
                raise DDPError(f"{file}: holds {size} bytes where its shape {list(leaf['shape'])} "
                               f"({leaf['dtype']}) needs {need}: a damaged or cut-short episode file")
        elif (steps / key).is_dir():
            _check_leaf_files(steps / key)
