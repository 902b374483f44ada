"""results.json as strict JSON: NaN and infinities (e.g. D_R-I before the first forecast) become null.

Python's ``json`` writes bare ``NaN`` / ``Infinity`` by default, which JSON parsers in other
languages (and ``jq``) reject. Results go through :func:`dumps` instead.
"""

from __future__ import annotations

import json
import math
from typing import Any


def strict(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (containers copied, not mutated)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict(v) for v in value]
    return value


def dumps(value: Any, indent: int | None = 1) -> str:
    return json.dumps(strict(value), indent=indent, allow_nan=False)
