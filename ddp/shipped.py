"""The repository's recipes and suites, shipped inside the package.

``recipes/`` and ``suites/`` live at the repository's root; ``ddp/recipes`` and ``ddp/suites`` link to them, so
a wheel carries copies (package data). :func:`locate` lets a relative path such as ``recipes/quickstart.yaml``
name a file of the working directory first and the shipped copy otherwise: ``build("recipes/quickstart.yaml")``
and ``ddp suite suites/metaworld_smoke.yaml`` work from any folder, after ``pip install`` too. Data caches
(``data/...``) and run folders (``runs/...``) stay relative to the working directory.
"""

from __future__ import annotations

import os
from importlib.resources import files
from pathlib import Path

#: the folders shipped with the package (their paths are read relative to the working directory first)
SHIPPED = ("recipes", "suites")


def locate(path: str | os.PathLike) -> Path:
    """``path`` where it exists or is absolute; else, for a path under ``recipes/`` or ``suites/``, the copy
    shipped with the package when there is one; else ``path`` (its reader reports it missing)."""
    p = Path(path)
    if p.is_absolute() or p.exists() or not p.parts or p.parts[0] not in SHIPPED:
        return p
    shipped = Path(str(files("ddp"))) / p
    return shipped if shipped.exists() else p
