"""A notch on the controller's reading: the loop stops acting on one frequency.

A mode the plant model lacks (a table top, a mount) that the piezo rings shows up in the
reading at its frequency; a loop that acts on it either rings it further (the mode eats the
gain margin) or, when the mode is rung by the floor, turns its reading into true tilt.
Filtering the reading before the PID removes the loop's gain there and nowhere else:

    H(s) = (s^2 + depth (w / Q) s + w^2) / (s^2 + (w / Q) s + w^2),   w = 2 pi f

unity at 0 Hz and at high frequency, `depth` at f (0: a full notch), half-power width
f / Q for depth 0. Discretized by the bilinear transform prewarped at f, so the notch
sits at f at any loop rate below 2 f. leveler.analysis.notch chooses f, Q and depth from
a fitted model and checks the margins; leveler.analysis.stability holds its states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Notch:
    """Where [Hz], how wide (Q) and how deep (gain at the centre, 0 to 1) the notch is."""

    frequency_hz: float
    q: float = 2.0
    depth: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.frequency_hz) and self.frequency_hz > 0):
            raise ValueError(f"notch frequency_hz must be finite and > 0, got "
                             f"{self.frequency_hz!r}")
        if not (math.isfinite(self.q) and self.q > 0):
            raise ValueError(f"notch q must be finite and > 0, got {self.q!r}")
        if not 0.0 <= self.depth < 1.0:
            raise ValueError(f"notch depth must be in [0, 1), got {self.depth!r}")

    def coefficients(self, dt_s: float) -> tuple[tuple[float, float, float], tuple[float, float]]:
        """((b0, b1, b2), (a1, a2)) of the biquad at this sample time, a0 = 1.
        ValueError at or above the Nyquist frequency, where no discrete notch exists."""
        if not self.frequency_hz < 0.5 / dt_s:
            raise ValueError(f"a notch at {self.frequency_hz:g} Hz needs a loop rate above "
                             f"{2 * self.frequency_hz:g} Hz (Nyquist); the loop runs at "
                             f"{1 / dt_s:g} Hz")
        w = 2.0 * math.pi * self.frequency_hz
        k = w / math.tan(w * dt_s / 2.0)  # prewarped: the analog w maps onto itself
        bw = w / self.q
        a0 = k * k + bw * k + w * w
        b = ((k * k + self.depth * bw * k + w * w) / a0, 2.0 * (w * w - k * k) / a0,
             (k * k - self.depth * bw * k + w * w) / a0)
        return b, (2.0 * (w * w - k * k) / a0, (k * k - bw * k + w * w) / a0)


class NotchFilter:
    """The notch running sample by sample (direct form II transposed)."""

    __slots__ = ("_a1", "_a2", "_b0", "_b1", "_b2", "_dt", "_z1", "_z2", "notch")

    def __init__(self, notch: Notch, dt_s: float) -> None:
        self.notch = notch
        self._dt = math.nan
        self._coefficients(dt_s)
        self._z1 = self._z2 = 0.0

    def _coefficients(self, dt_s: float) -> None:
        (self._b0, self._b1, self._b2), (self._a1, self._a2) = self.notch.coefficients(dt_s)
        self._dt = dt_s

    def seed(self, x: float) -> None:
        """The state of a filter that has seen x forever: its next output for x is x (unity
        at 0 Hz), so switching the notch in does not move the reading the PID sees."""
        self._z1 = x * (1.0 - self._b0)
        self._z2 = x * (self._b2 - self._a2)

    def state(self) -> tuple[float, float]:
        return self._z1, self._z2

    def restore(self, state: tuple[float, float]) -> None:
        """Back to a `state()`: a caller that refuses a sample undoes its step."""
        self._z1, self._z2 = state

    def step(self, x: float, dt_s: float) -> float:
        if dt_s != self._dt:
            self._coefficients(dt_s)
        y = self._b0 * x + self._z1
        self._z1 = self._b1 * x + self._z2 - self._a1 * y
        self._z2 = self._b2 * x - self._a2 * y
        return y
