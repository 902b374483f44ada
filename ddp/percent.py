"""How reports write a fraction as a percentage: halves rounded up (33/40 = 82.5 % reads "83"), the same in
every table and plot. Python's ``format(x, ".0f")`` rounds halves to even and a float product such as
``100 * 33 / 40`` may land a hair below the half, so the value is settled to 9 decimals first."""

from __future__ import annotations

from decimal import ROUND_HALF_UP, Decimal

__all__ = ["percent"]


def percent(fraction: float, digits: int = 0) -> str:
    """``fraction`` (0.825) as a percentage string ("83"), halves rounded up."""
    value = Decimal(repr(round(100 * float(fraction), 9)))
    return str(value.quantize(Decimal(1).scaleb(-digits), rounding=ROUND_HALF_UP))
