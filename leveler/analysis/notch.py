"""A notch against a named mode, chosen through the plant model and checked over its tolerances.

A mode the model names (`[plant.effects.extra_resonance]`, what diagnose fits) reaches the
loop two ways. Rung by the piezo (a gain), it is part of the plant: its peak adds to |L|
near its frequency and may eat the gain margin, or close an unstable loop on a corner of
the tolerances. Rung by the floor (only a noise drive), it is in the reading alone, and the
loop copies |T| = |L / (1 + L)| of it onto the table as true tilt. Either way the loop's
gain at the mode is what matters: a loop with |L| << 1 there (MIN_LOOP_AT_MODE) neither
rings the mode nor passes its reading on, and a notch would buy nothing but phase lag.

Otherwise a notch on the reading (leveler.loop.notch) at the mode's frequency is chosen
from a small grid of widths and depths: the one whose worst margins over every corner of
the model's tolerances (periodic.check: the sensor and actuator paths, the pendulum's
frequency and Q, and the mode's frequency and gain) sit furthest above the goals, in units
of the goals. Wide notches protect against a mode that moves; narrow ones cost less phase
at the crossover below it; the corners decide.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from leveler.analysis.periodic import (
    MIN_GAIN_MARGIN_DB,
    MIN_PHASE_MARGIN_DEG,
    LoopCheck,
    Predicted,
    check,
    controller_parts,
    margin_rows,
    notch_tf,
    predicted_rows,
)
from leveler.analysis.suggest import _response, _toml_float, plant_tf
from leveler.loop.pid import ControllerConfig
from leveler.sim.effects import ExtraResonance
from leveler.sim.params import PlantParams

MIN_LOOP_AT_MODE = 0.1  # |L| at the mode under which a notch is not worth its phase
WIDTHS_Q = (0.7, 1.0, 1.5, 2.0, 3.0, 5.0)
DEPTHS = (0.0, 0.1, 0.3)
GAIN_SCALES = (1.0, 0.8, 0.63, 0.5)  # the PID's gains, when the notch's lag needs room
GAINS = ("kp_v_per_m", "ki_v_per_m_s", "kd_v_s_per_m")
FULL_CHECKS = 3  # of each scale's shapes, ranked on the nominal model, checked on every corner


def named_mode(params: PlantParams) -> ExtraResonance | None:
    """The model's extra resonance (rung by the piezo, by its own noise, or both), or None."""
    fx = params.effects.extra_resonance
    if fx is None or not (fx.gain or fx.noise_rms_m):
        return None
    return fx


def loop_at(params: PlantParams, rate_hz: float, c: ControllerConfig, f_hz: float) -> complex:
    """L = C P at f_hz on the model (the notch and any resonant terms included)."""
    parts = controller_parts(c, rate_hz)
    loop = sum(complex(_response(p, f_hz)) for p in parts) * complex(
        _response(plant_tf(params, rate_hz), f_hz))
    notch = notch_tf(c, rate_hz)
    return loop if notch is None else loop * complex(_response(notch, f_hz))


def with_notch(c: ControllerConfig, frequency_hz: float, q: float, depth: float,
               gain_scale: float = 1.0) -> ControllerConfig:
    """`c` with this notch, and its PID gains times `gain_scale`."""
    return dataclasses.replace(
        c, notch_frequency_hz=frequency_hz, notch_q=q, notch_depth=depth,
        kp_v_per_m=c.kp_v_per_m * gain_scale, ki_v_per_m_s=c.ki_v_per_m_s * gain_scale,
        kd_v_s_per_m=c.kd_v_s_per_m * gain_scale)


def _score(x: LoopCheck) -> float:
    """The worst margin in units of its goal (1: both goals just met); -inf if unstable."""
    if not x.stable:
        return -math.inf
    return min(x.gain_margin_db / MIN_GAIN_MARGIN_DB, x.phase_margin_deg / MIN_PHASE_MARGIN_DEG)


@dataclass(frozen=True)
class Design:
    """The chosen notch (and gain scale) on top of `c`, and the checks of the loop with and
    without it."""

    mode: ExtraResonance
    controller: ControllerConfig  # with the notch
    gain_scale: float
    ours: LoopCheck
    theirs: LoopCheck
    loop_at_mode: complex  # the current loop's L at the mode, nominal model
    tried: int


def design(params: PlantParams, rate_hz: float, c: ControllerConfig) -> Design:
    """The notch at the named mode with the best worst-case margins (module doc), with the
    PID's gains as they are if that meets the goals, else scaled down by the least of
    GAIN_SCALES that does (or, when none does, the best there is). ValueError when the
    model names no mode, or one at or above the Nyquist frequency."""
    mode = named_mode(params)
    if mode is None:
        raise ValueError("the model names no extra resonance ([plant.effects.extra_resonance] "
                         "with a gain or a noise_rms_m)")
    f = mode.frequency_hz
    if not f < rate_hz / 2:
        raise ValueError(f"the mode at {f:g} Hz is at or above the loop's Nyquist frequency "
                         f"({rate_hz / 2:g} Hz): the loop sees it aliased; a notch cannot "
                         "reach it (an analog filter before the ADC can)")
    theirs = check(params, rate_hz, c)
    best: tuple[float, float, ControllerConfig, LoopCheck] | None = None
    tried = 0
    for scale in GAIN_SCALES:
        shapes = [with_notch(c, f, q, depth, scale) for q in WIDTHS_Q for depth in DEPTHS]
        shapes.sort(key=lambda x: -_score(check(params, rate_hz, x, nominal_only=True)))
        for cand in shapes[:FULL_CHECKS]:
            ours = check(params, rate_hz, cand)
            tried += 1
            if best is None or _score(ours) > best[0]:
                best = (_score(ours), scale, cand, ours)
        if best[0] >= 1.0:  # the goals met at the highest gain that meets them
            break
    assert best is not None
    return Design(mode, best[2], best[1], best[3], theirs, loop_at(params, rate_hz, c, f),
                  tried)


def mode_text(m: ExtraResonance) -> str:
    drive = []
    if m.gain:
        drive.append(f"rung by the piezo at {abs(m.gain) * 100:.3g} % of the static response")
    if m.noise_rms_m:
        drive.append(f"by its own noise, {m.noise_rms_m * 1e9:.3g} nm rms at the sensor")
    return f"extra resonance at {m.frequency_hz:.4g} Hz, Q {m.q:.3g}, " + " and ".join(drive)


def values(d: Design) -> dict[str, float]:
    """The suggestion as tune values: the notch, and the gains when they are scaled."""
    keys = ("notch_frequency_hz", "notch_q", "notch_depth")
    if d.gain_scale != 1:
        keys = (*GAINS, *keys)
    return {k: getattr(d.controller, k) for k in keys}


def not_needed(d: Design) -> str:
    """Why no notch is suggested ('' when one is): the current loop meets the goals on every
    model and has too little gain at the mode to ring it or copy it onto the table."""
    lm = abs(d.loop_at_mode)
    if d.theirs.ok and lm < MIN_LOOP_AT_MODE:
        return (f"No notch suggested: the loop's gain at {d.mode.frequency_hz:.4g} Hz is "
                f"|L| = {lm:.3g} ({20 * math.log10(lm):.0f} dB), under {MIN_LOOP_AT_MODE:g}: "
                f"it neither rings the mode nor puts more than {lm / max(1 - lm, 1e-9):.2g} of "
                "its reading onto the table, and it meets the margins on every model "
                f"({d.theirs.gain_margin_db:.1f} dB, {d.theirs.phase_margin_deg:.1f} deg "
                "at the worst); a notch would only cost phase.")
    return ""


def report(d: Design, pred: Predicted | None) -> str:
    """The notch as config lines, its margins beside the current loop's and what the model
    predicts it does to the true tilt."""
    c = d.controller
    lines = [
        f"The model names a mode: {mode_text(d.mode)}.",
        f"The current loop there: |L| = {abs(d.loop_at_mode):.3g}, |L / (1 + L)| = "
        f"{abs(d.loop_at_mode / (1 + d.loop_at_mode)):.3g} (the share of the mode's reading it "
        "puts onto the table).",
        f"Suggested: a notch on the reading at {c.notch_frequency_hz:.4g} Hz, Q {c.notch_q:g}, "
        f"depth {c.notch_depth:g}"
        + ("" if d.gain_scale == 1 else
           f", and the PID's gains x{d.gain_scale:g} to give its phase lag room below the "
           f"mode (x{d.gain_scale:g} the loop gain, so the suppression, at low frequency)")
        + f" (the best of {d.tried} checked on every model):",
        "[controller]",
        *([] if d.gain_scale == 1 else [f"{k} = {_toml_float(getattr(c, k))}" for k in GAINS]),
        f"notch_frequency_hz = {_toml_float(c.notch_frequency_hz)}",
        f"notch_q = {_toml_float(c.notch_q)}",
        f"notch_depth = {_toml_float(c.notch_depth)}",
    ]
    lines += margin_rows(d.ours, d.theirs)
    if pred is not None:
        lines += predicted_rows(pred, [f"ASD at {f:.4g} Hz (the mode)"
                                       for f in pred.freqs_hz[:pred.lines]])
    return "\n".join(lines)
