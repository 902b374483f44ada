"""Episode seeds of the simulated envs: seed i is layout i, and each reset without a seed takes the next.

``EpisodeSeeds`` is listed before ``EnvBase``: ``_init_seeds(seed)`` in the
constructor, TorchRL's ``set_seed`` lands in ``_set_seed``, and ``_reset``
calls ``_episode_seed(seed)`` for the seed of the episode it starts (kept as
``_seed`` for the ``privileged/seed`` output).
"""

from __future__ import annotations

__all__ = ["EpisodeSeeds"]


class EpisodeSeeds:
    """The seed counter shared by the metaworld, adroit and franka envs."""

    def _init_seeds(self, seed: int | None) -> None:
        self._next_seed = 0 if seed is None else int(seed)
        self._seed = self._next_seed

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._next_seed = int(seed)

    def _episode_seed(self, seed: int | None) -> int:
        """The seed of the episode a reset starts: ``seed`` if given, else the next one; then count on."""
        seed = self._next_seed if seed is None else int(seed)
        if seed < 0:  # the envs' streams read |seed|: -5 replayed episode 5
            raise ValueError(f"episode seeds must be >= 0; got {seed}")
        self._next_seed = seed + 1
        self._seed = seed
        return seed
