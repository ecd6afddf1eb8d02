"""Tilt modulation by the piezo, a square or a triangle wave: the wave the loop drives.

The paper modulates the platform tilt with the piezo to see how strongly the torsion pendulum
couples to it: a square holds the piezo between its edges, so the pendulum's steps read the
lever arm. A triangle sweeps it through its range at a steady rate, so a response that
depends on the direction of travel (a piezo's hysteresis, a lag) shows as an opening between
the up and the down sweeps, which a square's held levels cannot show. The daemon runs the
wave as a procedure of the loop (state `modulating`, loop open, every sample logged);
leveler.procedures.tilt_modulation reads the response back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SHAPES = ("square", "triangle")


@dataclass(frozen=True, slots=True)
class Wave:
    """`cycles` periods from start_t_s about center_v, then center_v again. A square is
    center_v + amplitude_v for the first half of each period and center_v - amplitude_v for
    the second; a triangle rises from center_v to + amplitude_v at a quarter period, falls
    to - amplitude_v at three quarters and rises back to center_v, so it starts and ends
    without a step."""

    center_v: float
    amplitude_v: float
    period_s: float
    cycles: int
    start_t_s: float = 0.0
    shape: str = "square"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amplitude_v) and self.amplitude_v > 0):
            raise ValueError(f"amplitude_v must be > 0, got {self.amplitude_v!r}")
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"period_s must be > 0, got {self.period_s!r}")
        if self.cycles < 1:
            raise ValueError(f"cycles must be >= 1, got {self.cycles!r}")
        if self.shape not in SHAPES:
            raise ValueError(f"shape must be one of {', '.join(SHAPES)}, got {self.shape!r}")

    def check_fits(self, min_v: float, max_v: float, dt_s: float) -> None:
        """Refuse a wave the output range would clip or the loop rate could not draw."""
        lo, hi = self.center_v - self.amplitude_v, self.center_v + self.amplitude_v
        if lo < min_v or hi > max_v:
            raise ValueError(f"{self.center_v:.3f} V +- {self.amplitude_v:g} V leaves the "
                             f"output range {min_v:g}..{max_v:g} V")
        if self.period_s < 4 * dt_s:
            raise ValueError(f"period_s {self.period_s:g} s is under 4 loop periods "
                             f"({4 * dt_s:g} s)")

    @property
    def end_t_s(self) -> float:
        return self.start_t_s + self.cycles * self.period_s

    def command_v(self, t_s: float) -> float | None:
        """The piezo voltage at loop time t_s, or None once the last cycle is over."""
        phase = (t_s - self.start_t_s) / self.period_s
        if phase >= self.cycles - 1e-9:
            return None
        return self.center_v + self.amplitude_v * unit(self.shape, phase % 1.0)


def unit(shape: str, phase: float) -> float:
    """The wave at this phase of its period (0..1), in units of its amplitude."""
    if shape == "square":
        return 1.0 if phase < 0.5 - 1e-9 else -1.0
    if phase < 0.25:
        return 4.0 * phase
    if phase < 0.75:
        return 2.0 - 4.0 * phase
    return 4.0 * phase - 4.0
