"""Resonant (internal-model) terms: the PID's integral, for a disturbance that repeats.

An integrator is the internal model of a constant: infinite gain at 0 Hz, so a constant
disturbance leaves no error. A resonator at w is the internal model of a sinusoid at w:
infinite gain there, so a periodic disturbance of period T (a water cooler's sawtooth)
leaves none at w = 2 pi h / T for each harmonic h given one. Each term is a complex state
rotated by w dt every sample and fed the error times dt (so its gain is in V/(m s), as the
integral's), and its output is the state's projection at a phase `phase_rad` that makes
it add to the loop as an integrator would near w (leveler.analysis.periodic chooses gains
and phases from the plant model, and checks the margins).

Like the integral it is accumulated forward (the output uses the state before this
sample's error) and frozen while the command sits on the rail it would push further into.
`radius` < 1 makes each resonance finite (peak gain ~ gain / (2 (1 - radius) / dt)) and
wider: tolerance to a drifting period, bought with suppression at the exact line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class PeriodicTerms:
    """Resonators at harmonics 1..len(gains) of `period_s`: gains [V/(m s)], phases [rad]."""

    period_s: float
    gains_v_per_m_s: tuple[float, ...]
    phases_rad: tuple[float, ...]
    radius: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"period_s must be finite and > 0, got {self.period_s!r}")
        if len(self.gains_v_per_m_s) != len(self.phases_rad):
            raise ValueError(f"one phase per gain: {len(self.gains_v_per_m_s)} gains, "
                             f"{len(self.phases_rad)} phases")
        if not all(math.isfinite(v) for v in (*self.gains_v_per_m_s, *self.phases_rad)):
            raise ValueError("gains and phases must be finite")
        if not 0.0 < self.radius <= 1.0:
            raise ValueError(f"radius must be in (0, 1], got {self.radius!r}")


class Resonators:
    """The running terms: `output_v` now, `advance(error, dt)` after the command is known."""

    __slots__ = ("_c", "_cos_out", "_dt", "_im", "_re", "_s", "_sin_out", "terms")

    def __init__(self, terms: PeriodicTerms) -> None:
        self.terms = terms
        n = len(terms.gains_v_per_m_s)
        k, ph = terms.gains_v_per_m_s, terms.phases_rad
        self._cos_out = [g * math.cos(p) for g, p in zip(k, ph, strict=True)]
        self._sin_out = [g * math.sin(p) for g, p in zip(k, ph, strict=True)]
        self._re = [0.0] * n
        self._im = [0.0] * n
        self._dt = math.nan
        self._c: list[float] = []
        self._s: list[float] = []

    def output_v(self) -> float:
        """Sum over harmonics of k Re(e^(j phase) z): what the terms add to the command."""
        out = 0.0
        for co, so, re, im in zip(self._cos_out, self._sin_out, self._re, self._im,
                                  strict=True):
            out += co * re - so * im
        return out

    def rotation(self, dt_s: float) -> tuple[list[float], list[float]]:
        """r cos(w_h dt) and r sin(w_h dt) of every term, for this sample time."""
        if dt_s != self._dt:
            w1, r = 2.0 * math.pi / self.terms.period_s, self.terms.radius
            n = len(self._re)
            self._c = [r * math.cos(w1 * h * dt_s) for h in range(1, n + 1)]
            self._s = [r * math.sin(w1 * h * dt_s) for h in range(1, n + 1)]
            self._dt = dt_s
        return self._c, self._s

    def advance(self, error_m: float, dt_s: float, feed: bool = True) -> None:
        """Rotate every state one sample of dt_s and (if `feed`) add error x dt to it."""
        self.rotation(dt_s)
        x = error_m * dt_s if feed else 0.0
        re, im = self._re, self._im
        for j, (c, s) in enumerate(zip(self._c, self._s, strict=True)):
            a, b = re[j], im[j]
            re[j] = c * a - s * b + x
            im[j] = s * a + c * b
