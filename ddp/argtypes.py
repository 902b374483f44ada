"""argparse types shared by the scripts (``benchmarks/``, ``scripts/``): a value outside its range is a one-line
usage error naming the flag (argparse adds the flag's name to the message). The ``ddp`` command checks its counts
after parsing instead (``cli._at_least_one``: flags whose unset default is None)."""

from __future__ import annotations

import argparse

__all__ = ["positive_int"]


def positive_int(text: str) -> int:
    """A whole number >= 1 (episode counts, step counts)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1; got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1; got {text}")
    return value
