"""Exceptions with one-line messages that name the recipe file and dotted key."""

from __future__ import annotations

import difflib
from typing import Iterable


class DDPError(Exception):
    """Base class of every error ddp raises on bad user input."""


class RecipeError(DDPError):
    """A recipe (or an override) is invalid.

    The message reads ``<file>: <dotted.key>: <what is wrong>`` on one line.
    """

    def __init__(self, message: str, *, source: str | None = None, key: str | None = None):
        self.source = source
        self.key = key
        self.reason = message
        parts = [p for p in (source, key) if p]
        super().__init__(": ".join(parts + [message]))


class PluginError(DDPError):
    """A plugin is unknown, registered twice, or failed to import."""


class CheckpointError(DDPError):
    """A checkpoint file is missing, truncated or not a ddp checkpoint."""


def closest(name: str, candidates: Iterable[str], n: int = 3) -> list[str]:
    """The candidates closest to ``name`` (best first)."""
    return difflib.get_close_matches(str(name), list(candidates), n=n, cutoff=0.5)


def suggest(name: str, candidates: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` or an empty string."""
    near = closest(name, candidates, n=1)
    return f"; did you mean '{near[0]}'?" if near else ""
