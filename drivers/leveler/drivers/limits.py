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


def check_piezo_range(min_v: float, max_v: float, safe_v: float, amplifier_gain: float,
                      out_lo_v: float, out_hi_v: float, out_name: str) -> None:
    """A piezo range [min_v, max_v] with safe_v inside it, reachable through an amplifier of
    `amplifier_gain` from an analog output spanning [out_lo_v, out_hi_v] (named `out_name`
    in the error). Checked when the config is built, so a lab learns it before the stand
    moves."""
    if not min_v < max_v:
        raise ValueError(f"min_v ({min_v} V) must be below max_v ({max_v} V)")
    if not min_v <= safe_v <= max_v:
        raise ValueError(f"safe_v ({safe_v} V) must lie in [min_v, max_v] = "
                         f"[{min_v}, {max_v}] V")
    need_lo, need_hi = min_v / amplifier_gain, max_v / amplifier_gain
    tol = 1e-9 * (out_hi_v - out_lo_v)
    if need_lo < out_lo_v - tol or need_hi > out_hi_v + tol:
        raise ValueError(
            f"piezo range [{min_v}, {max_v}] V needs the AO to span "
            f"[{need_lo:.4g}, {need_hi:.4g}] V at amplifier_gain {amplifier_gain}, "
            f"but {out_name} [{out_lo_v}, {out_hi_v}] V")
