"""The period of a cancelled periodic disturbance, re-estimated from the loop's own command.

Resonant terms (leveler.loop.resonant) cancel a disturbance at the harmonics of the period
they were designed for; a cooler whose period drifts by more than about half a per cent
walks out from under them (docs/replay.md). While the loop holds the table level it
drives the piezo against the disturbance, so the command carries the disturbance's lines
at their true period even where the terms have taken them out of the reading. The period
is where the summed power of the command's first harmonics peaks, searched within a few
per cent of the designed one, on the last closed-loop stretch of a log.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SPAN_REL = 0.05  # searched: the designed period +-5 %
GRID = 2001  # periods on that span (0.005 % apart), then a parabola through the peak
HARMONICS = 5
MIN_PEAK = 10.0  # the peak's summed power over that well off it: a line, not noise
MIN_CYCLES = 10  # of the period in the stretch, for a period to within a fraction of 1 %
BLOCK_S = 1.0  # the command is averaged over blocks this long first (lines are at mHz)


@dataclass(frozen=True)
class Track:
    """The period found [s], how far its fundamental stands above the power well off it,
    what the record spanned [s] and how many harmonics were summed."""

    period_s: float
    peak_over_floor: float  # the fundamental's power there over its power well off it
    record_s: float
    harmonics: int
    at_edge: bool = False  # the peak is the span's end: the period moved further, or no line

    @property
    def clear(self) -> bool:
        return self.peak_over_floor >= MIN_PEAK


def _blocks(t_s: np.ndarray, u: np.ndarray, block_s: float) -> tuple[np.ndarray, np.ndarray]:
    dt = float(np.median(np.diff(t_s)))
    k = max(round(block_s / dt), 1)
    n = len(u) // k * k
    return t_s[:n].reshape(-1, k).mean(axis=1), u[:n].reshape(-1, k).mean(axis=1)


def _power(t: np.ndarray, x: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """|sum x e^(-2 pi i f t)|^2 at each of `freqs`, a few hundred at a time."""
    out = np.empty(len(freqs))
    for i in range(0, len(freqs), 200):
        f = freqs[i:i + 200]
        out[i:i + 200] = np.abs(np.exp(-2j * np.pi * np.outer(f, t)) @ x) ** 2
    return out


def estimate_period(t_s: np.ndarray, command_v: np.ndarray, period0_s: float, *,
                    harmonics: int = HARMONICS) -> Track:
    """The period near `period0_s` at which the command's first harmonics peak (module doc).
    ValueError for a stretch shorter than MIN_CYCLES periods."""
    record = float(t_s[-1] - t_s[0])
    if record < MIN_CYCLES * period0_s:
        raise ValueError(f"{record:.0f} s of closed loop is under {MIN_CYCLES} periods of "
                         f"{period0_s:g} s: too short to place the period to a fraction of "
                         "a per cent")
    t, u = _blocks(np.asarray(t_s, float), np.asarray(command_v, float), BLOCK_S)
    t = t - t[0]
    u = u - np.polyval(np.polyfit(t, u, 1), t)  # the slow thermal push is not a line
    # and a Hann window keeps its leakage (a random walk's power falls as 1 / f^2) from
    # leaning the fundamental's peak toward longer periods: +0.17 % without it
    u = u * np.hanning(len(u))
    nyquist = 0.5 / BLOCK_S
    hs = [h for h in range(1, harmonics + 1) if h / period0_s < nyquist * 0.8]
    periods = period0_s * np.linspace(1 - SPAN_REL, 1 + SPAN_REL, GRID)
    each = [_power(t, u, h / periods) for h in hs]
    power = np.sum(each, axis=0)
    i = int(np.argmax(power))
    period = float(periods[i])
    if 0 < i < GRID - 1:  # a parabola through the peak and its neighbours
        a, b, c = power[i - 1:i + 2]
        den = a - 2 * b + c
        if den < 0:
            period += 0.5 * (a - c) / den * float(periods[1] - periods[0])
    # The floor the fundamental stands on: its power at periods well off it (a median, so
    # the odd period that meets another line does not count). The fundamental, not the
    # sum: a harmonic of another periodic disturbance in the span (the 6th of a 300 s
    # cooler is the 5th of 250 s) peaks the sum too.
    away = period0_s * np.concatenate([np.linspace(0.7, 0.88, 200), np.linspace(1.12, 1.3, 200)])
    floor = float(np.median(_power(t, u, 1.0 / away)))
    edge = i in (0, GRID - 1)
    return Track(float(period), 0.0 if edge else float(each[0][i] / floor), record, len(hs),
                 edge)


def last_engaged(state: np.ndarray) -> slice:
    """The log's last closed-loop stretch, from the sample after the loop engaged."""
    engaged = np.asarray(state) == "engaged"
    if not engaged.any():
        return slice(0, 0)
    end = int(np.nonzero(engaged)[0][-1]) + 1
    off = np.nonzero(~engaged[:end])[0]
    return slice(int(off[-1]) + 1 if len(off) else 0, end)


def drift_rel(track: Track, period0_s: float) -> float:
    return track.period_s / period0_s - 1.0


def describe(track: Track, period0_s: float) -> str:
    resolution = period0_s ** 2 / track.record_s / track.harmonics / 10
    return (f"the command's lines put the period at {track.period_s:.4g} s (+-{resolution:.2g} "
            f"s: a tenth of {track.record_s / 3600:.3g} h's resolution over {track.harmonics} "
            f"harmonics), {drift_rel(track, period0_s) * 100:+.2f} % from the terms' "
            f"{period0_s:g} s; its line stands {track.peak_over_floor:.3g}x over the power "
            f"well off it{'' if track.clear else f' (under {MIN_PEAK:g}x: no clear line)'}"
            + (f"; at the edge of the +-{SPAN_REL:.0%} searched: the period moved further, or "
               "the line is not there (diagnose a recent log)" if track.at_edge else ""))


