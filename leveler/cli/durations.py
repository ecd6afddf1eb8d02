"""Human durations for the command line: '90s', '90m', '6h', '1.5d'; always with a unit.

A bare number is refused: `sim --duration 24` meant 24 s to the parser and a day to the
person typing it, and a day's analysis of 24 s of data fails far from the cause.
"""

from __future__ import annotations

import math
import re

_UNITS = {"s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0, "d": 86400.0}
_PATTERN = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(s|min|m|h|d)?\s*$")


def parse_duration(text: str) -> float:
    """Seconds in `text`; raises ValueError with the accepted forms."""
    match = _PATTERN.match(text)
    if not match:
        raise ValueError(f"bad duration {text!r}: use e.g. 90s, 90m, 6h or 1d")
    if match.group(2) is None:
        n = match.group(1)
        raise ValueError(f"bad duration {text!r}: give its unit, e.g. {n}s, {n}m or {n}h "
                         "(s, m or min, h, d)")
    seconds = float(match.group(1)) * _UNITS[match.group(2)]
    if not math.isfinite(seconds) or seconds <= 0:
        raise ValueError(f"bad duration {text!r}: must be positive")
    return seconds
