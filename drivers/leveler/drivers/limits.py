"""The piezo range and slew limit that actuator drivers enforce themselves, whatever they drive.

One definition, so the Modbus and NI-DAQ actuators cannot disagree about what a safe command
is: the range always wins, slew narrows it around the voltage the piezo last saw, and time
that has not advanced (first write, NaN, time running backwards) allows no change at all.
"""

from __future__ import annotations

import math


def slew_window(last_v: float, dt_s: float, min_v: float, max_v: float,
                slew_v_per_s: float) -> tuple[float, float]:
    """[lo, hi] a command may take now: [min_v, max_v] within slew_v_per_s x dt_s of last_v.

    A dt_s that is NaN, zero or negative holds last_v. If last_v lies outside the range
    (an output left there by someone else), the range comes first: [min_v, max_v].
    """
    max_dv = slew_v_per_s * dt_s if dt_s > 0 else 0.0
    lo, hi = max(min_v, last_v - max_dv), min(max_v, last_v + max_dv)
    return (min_v, max_v) if lo > hi else (lo, hi)


def limit_command(command_v: float, last_v: float, dt_s: float, min_v: float, max_v: float,
                  slew_v_per_s: float) -> float:
    """The voltage to apply for command_v: NaN holds last_v, anything else (+-inf too) is
    clamped into `slew_window`. For outputs that need no quantization (a DAQ's AO)."""
    lo, hi = slew_window(last_v, dt_s, min_v, max_v, slew_v_per_s)
    return min(max(last_v if math.isnan(command_v) else command_v, lo), hi)
