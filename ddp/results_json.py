"""results.json as strict JSON: NaN and infinities (e.g. D_R-I before the first forecast) become null.

Python's ``json`` writes bare ``NaN`` / ``Infinity`` by default, which JSON parsers in other
languages (and ``jq``) reject. Results go through :func:`dumps` instead.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np


def strict(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (containers copied, not mutated); numpy scalars
    and arrays as Python numbers and lists (a recipe changed from Python may hold them)."""
    if isinstance(value, np.generic):
        value = value.item()
    elif isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict(v) for v in value]
    return value


_SCALAR = r"(?:-?\d[\d.eE+-]*|null|true|false)"
# an indented list of scalars only: json.dumps opens it with "[" and a newline (a newline inside a
# JSON string is always escaped, so this never matches text within a string)
_SCALAR_LIST = re.compile(r"\[\n\s*(" + _SCALAR + r"(?:,\n\s*" + _SCALAR + r")*)\n\s*\]")


def dumps(value: Any, indent: int | None = 1) -> str:
    """Strict JSON; indented, with each list of numbers (a per-chunk trace) kept on one line."""
    text = json.dumps(strict(value), indent=indent, allow_nan=False)
    if indent is None:
        return text
    return _SCALAR_LIST.sub(lambda m: "[" + re.sub(r",\n\s*", ", ", m.group(1)) + "]", text)
