"""Tilt modulation analysis (paper sec. 3.2): what the inverted pendulum made of the wave.

The response against what the piezo geometry of the model predicts checks the lever arm
(piezo stroke / support spacing) and the pendulum's amplification on the stand. With the
torsion pendulum's own step it gives the paper's ratio (3 um on the inverted pendulum went
with about 0.4 um on the torsion pendulum) and the roll/pitch split it implies: the inverted
pendulum senses pitch (its axis is taken as the torsion pendulum's pitch axis); the torsion
pendulum answers M g (pitch l_cm,y + roll l_cm,x) / K0 at its arm, so with its
centre-of-mass offsets known (`leveler calibrate-com`) the roll that went with the measured
pitch follows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from leveler.loop.modulation import SquareWave
from leveler.sim.torsion import TorsionParams

SETTLED_FRACTION = 0.5  # of each half period: the pendulum rings down in the first half


@dataclass(frozen=True, slots=True)
class Response:
    """Peak-to-peak step of a signal under the wave: mean and scatter over the half periods."""

    peak_to_peak: float
    scatter: float  # standard deviation of the single steps
    steps: int


def response(wave: SquareWave, t_s: np.ndarray, y: np.ndarray) -> Response:
    """The signal's step between the high and the low half periods.

    Each half period contributes the mean of its settled part (the last SETTLED_FRACTION);
    a step is a high mean minus the mean of the two lows around it (and the other way round),
    which cancels a linear drift. NaN samples (failed reads) are left out.
    """
    half = wave.period_s / 2
    means = []
    for k in range(2 * wave.cycles):
        a = wave.start_t_s + (k + 1 - SETTLED_FRACTION) * half
        b = wave.start_t_s + (k + 1) * half
        sel = (t_s >= a) & (t_s < b) & np.isfinite(y)
        if not sel.any():
            raise ValueError(f"no samples in half period {k} ({a:.3f}..{b:.3f} s): the run "
                             "is shorter than the wave, or every read failed")
        means.append(float(np.mean(y[sel])))
    m = np.asarray(means)
    if len(m) < 3:  # one cycle: one high, one low
        steps = np.array([m[0] - m[1]])
    else:
        sign = np.where(np.arange(1, len(m) - 1) % 2 == 0, 1.0, -1.0)  # k even: a high
        steps = sign * (m[1:-1] - 0.5 * (m[:-2] + m[2:]))
    return Response(float(np.mean(steps)), float(np.std(steps)), len(steps))


def analyze(wave: SquareWave, t: np.ndarray, y: np.ndarray, v: np.ndarray,
            model: dict[str, float], where: str) -> dict[str, Any]:
    """The inverted pendulum's and the piezo's steps under the wave, the tilt they mean,
    and that tilt against the model's piezo geometry (`model`: sensor_m_per_rad,
    tilt_rad_per_v)."""
    ip: Response = response(wave, t, y)
    piezo = response(wave, t, v)
    expected_tilt = piezo.peak_to_peak * model["tilt_rad_per_v"]
    tilt = ip.peak_to_peak / model["sensor_m_per_rad"]
    return {
        "where": where,
        "wave": {"center_v": wave.center_v, "amplitude_v": wave.amplitude_v,
                 "period_s": wave.period_s, "cycles": wave.cycles},
        "samples": len(t),
        "piezo_peak_to_peak_v": piezo.peak_to_peak,
        "ip_peak_to_peak_m": ip.peak_to_peak,
        "ip_scatter_m": ip.scatter,
        "ip_steps": ip.steps,
        "ip_m_per_v": ip.peak_to_peak / piezo.peak_to_peak,
        "tilt_peak_to_peak_rad": tilt,
        "model": model,
        "model_tilt_peak_to_peak_rad": expected_tilt,
        "measured_over_model": tilt / expected_tilt,
    }


def square_waves(t_s: np.ndarray, u_v: np.ndarray,
                 usable: np.ndarray | None = None) -> list[SquareWave]:
    """The square waves of a recorded command (`drive_lines`: a line with harmonics on its
    span), each as the `SquareWave` that ran: its whole cycles on the span, the start where
    its fundamental, (4 A / pi) sin(w (t - start)), rises through zero."""
    from leveler.procedures.drive_lines import drive_spans, measure

    spans = drive_spans(t_s, u_v, usable)
    squared = {(s.a, s.b) for s in spans if s.harmonic > 1}
    waves = []
    for line in measure(t_s, u_v, u_v, [s for s in spans if s.harmonic == 1
                                        and (s.a, s.b) in squared], settle_fraction=0.0):
        w, period = 2 * math.pi * line.frequency_hz, 1 / line.frequency_hz
        start = float(t_s[0]) - (math.atan2(line.command_v.imag, line.command_v.real)
                                 + math.pi / 2) / w
        start += math.ceil((line.start_s - start) / period) * period  # first whole cycle
        cycles = int((line.end_s - start) // period)
        if cycles < 1:
            continue
        sel = (t_s >= start) & (t_s < start + cycles * period)
        waves.append(SquareWave(float(np.mean(u_v[sel])), abs(line.command_v) * math.pi / 4,
                                period, cycles, start))
    return waves


def torsion_split(r: dict[str, Any], tp_pp_m: float, tp: TorsionParams) -> dict[str, Any]:
    """The IP/TP ratio, and the roll that the TP's step implies next to the IP's pitch."""
    pitch = r["tilt_peak_to_peak_rad"]
    per_rad = tp.arm_m * tp.mass_kg * tp.gravity_m_per_s2 / tp.stiffness_nm_per_rad
    out: dict[str, Any] = {"peak_to_peak_m": tp_pp_m, "ip_over_tp": r["ip_peak_to_peak_m"]
                           / tp_pp_m, "pitch_only_peak_to_peak_m": per_rad * pitch * tp.com_y_m,
                           "com_x_m": tp.com_x_m, "com_y_m": tp.com_y_m}
    if tp.com_x_m:
        roll = (tp_pp_m / per_rad - pitch * tp.com_y_m) / tp.com_x_m
        out |= {"roll_peak_to_peak_rad": roll, "roll_over_pitch": roll / pitch,
                "tilt_axis_deg": math.degrees(math.atan2(roll, pitch))}
    return out
