"""Demonstrations already on disk as a ddp episodes directory (your own data).

Write one with :meth:`ddp.data.episodes.Episodes.save` (steps TensorDict with
``point_cloud`` [T, P, 3], ``agent_pos`` [T, D], ``action`` [T, A], plus
``episode_ends``); ``load()`` memory-maps it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ddp.data.episodes import Episodes
from ddp.errors import DDPError
from ddp.registry import register

__all__ = ["EpisodesDirConfig", "EpisodesDir", "check_task"]

REQUIRED_KEYS = ("point_cloud", "agent_pos", "action")


@dataclass
class EpisodesDirConfig:
    """Options of the ``episodes_dir`` data source.

    Attributes:
        path: directory written by ``Episodes.save`` (holds meta.json, steps/, episode_ends.pt).
    """

    path: str

    def __post_init__(self):
        if not self.path:
            raise ValueError("path must not be empty")


class EpisodesDir:
    """Episodes saved on disk by ddp (Episodes.save), memory-mapped."""

    def __init__(self, config: EpisodesDirConfig, *, task, seed: int = 0, env=None):
        self.cfg = config
        self.task = task
        self.path = Path(config.path).expanduser()

    def load(self) -> Episodes:
        path = self.path
        if not path.exists():
            raise DDPError(f"data.path: {path} does not exist (expected a directory written by Episodes.save)")
        if not path.is_dir():
            raise DDPError(f"data.path: {path} is not a directory (expected one written by Episodes.save)")
        episodes = Episodes.load(path)
        missing = [k for k in REQUIRED_KEYS if k not in episodes.steps.keys()]
        if missing:
            raise DDPError(
                f"{path}: episodes lack {', '.join(missing)} (have {', '.join(sorted(episodes.steps.keys()))})"
            )
        check_task(episodes, self.task, str(path))
        return episodes


def check_task(episodes: Episodes, task, where: str) -> None:
    """The stored shapes must fit the recipe's ``task`` section (``task=None``: no check)."""
    if task is None:
        return
    steps = episodes.steps
    for key, dims in (("action", 2), ("agent_pos", 2), ("point_cloud", 3)):
        if steps[key].dim() != dims:
            raise DDPError(f"{where}: {key} has shape {tuple(steps[key].shape)}; expected {dims} dimensions "
                           f"([steps{', points' if dims == 3 else ''}, channels])")
    got = {
        "action_dim": steps["action"].shape[-1],
        "agent_pos_dim": steps["agent_pos"].shape[-1],
        "point_dim": steps["point_cloud"].shape[-1],
        "num_points": steps["point_cloud"].shape[-2],
    }
    bad = [f"task.{k} is {getattr(task, k)} but the data have {v}" for k, v in got.items() if getattr(task, k) != v]
    if bad:
        raise DDPError(f"{where}: {'; '.join(bad)}")


register("dataset", "episodes_dir", config=EpisodesDirConfig)(EpisodesDir)
