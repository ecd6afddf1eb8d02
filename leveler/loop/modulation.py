"""Square-wave tilt modulation by the piezo: the wave the loop drives.

The paper modulates the platform tilt with the piezo to see how strongly the torsion pendulum
couples to it. The daemon runs the wave as a procedure of the loop (state `modulating`, loop
open, every sample logged); leveler.procedures.tilt_modulation reads the response back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class SquareWave:
    """center_v + amplitude_v for the first half of each period, center_v - amplitude_v for
    the second, `cycles` times from start_t_s; then center_v again."""

    center_v: float
    amplitude_v: float
    period_s: float
    cycles: int
    start_t_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amplitude_v) and self.amplitude_v > 0):
            raise ValueError(f"amplitude_v must be > 0, got {self.amplitude_v!r}")
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"period_s must be > 0, got {self.period_s!r}")
        if self.cycles < 1:
            raise ValueError(f"cycles must be >= 1, got {self.cycles!r}")

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
        up = (phase % 1.0) < 0.5 - 1e-9
        return self.center_v + (self.amplitude_v if up else -self.amplitude_v)

