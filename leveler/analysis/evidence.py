"""What a replay residual says about the model, in the terms effects ask for their guesses.

Each effect's `guesses` reads this: spectral lines standing out of the fitted noise
spectrum, the best phase or lag from a small grid with the amplitude solved linearly
(coherence with an input, in effect), how far the command moved (hysteresis needs
reversals), and whether the raw readings sit on a lattice coarser than the model's ADC.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from leveler.analysis.predict import Measured, Predictor
from leveler.analysis.whittle import Whitener
from leveler.sim.effects import Effect

_LINE_Z = 12.0  # a line must stand this far (in ln p-value) above the noise spectrum


class Evidence:
    def __init__(self, meas: Measured, pred: Predictor, whitener: Whitener) -> None:
        self.meas = meas
        self.sig = meas.sig
        self.pred = pred
        self.w = whitener
        self.residual = meas.y_m - pred.base.y_m
        self.white = whitener.whiten(self.residual)
        self._z = whitener.zscores(self.residual)

    def fmin_hz(self) -> float:
        """Lowest frequency with at least eight cycles in the span: fewer do not make a
        periodic disturbance, and the lowest bins are where unmodeled drift lives."""
        return 8.0 / (self.w.n * self.sig.dt_s)

    def peaks(self, fmin_hz: float, fmax_hz: float, most: int = 3) -> list[float]:
        """Frequencies of the strongest lines in [fmin, fmax], harmonics of a stronger line
        left out (a sawtooth is one disturbance, not ten)."""
        f, z = self.w.f_hz, self._z
        df = f[1] - f[0]
        threshold = math.log(len(z)) + _LINE_Z
        idx = np.flatnonzero((f >= fmin_hz) & (f <= fmax_hz) & (z > threshold))
        found: list[float] = []

        def harmonic(fx: float) -> bool:  # of a line already found (refined to ~df/10)
            return any(abs(fx - h * g) <= df * (2.0 + 0.1 * h)
                       for g in found for h in range(1, int(fx / g) + 2))

        for k in idx[np.argsort(z[idx])[::-1]]:
            if harmonic(float(f[k])):
                continue
            fk = self._refine(self._fundamental(int(k), threshold, fmin_hz))
            if harmonic(fk):
                continue
            found.append(fk)
            if len(found) >= most:
                break
        return sorted(set(found))

    def _fundamental(self, k: int, threshold: float, fmin_hz: float) -> int:
        """The lowest significant subharmonic of bin k: a sawtooth's second or third
        harmonic can stand out more than its fundamental."""
        z = self._z
        for div in (5, 4, 3, 2):
            j = round(k / div)
            if j < 4 or self.w.f_hz[j] < fmin_hz:
                continue
            lo = j - 1
            peak = lo + int(np.argmax(z[lo:j + 2]))
            around = np.median(z[max(peak - 12, 1):peak + 13])
            # A line, not the red noise a subharmonic of a line may sit in.
            if z[peak] > threshold and z[peak] > 30 * around:
                return peak
        return k

    def _refine(self, k: int) -> float:
        """Line frequency between bins: the centroid of the power around the peak."""
        lo, hi = max(k - 2, 1), min(k + 3, len(self._z))
        p = self._z[lo:hi]
        return float(np.sum(self.w.f_hz[lo:hi] * p) / np.sum(p))

    def contribution(self, fx: Effect) -> np.ndarray:
        return self.pred.with_candidate(fx) - self.pred.base.y_m

    def best_linear(self, starts: Sequence[Effect], amp_key: str | None, keep: int) -> list[Effect]:
        """Each start with its amplitude solved by whitened least squares (or as it is if
        amp_key is None); the `keep` that leave the smallest cost."""
        scored: list[tuple[float, Effect]] = []
        for fx in starts:
            if amp_key is None:
                e = self.w.whiten(self.meas.y_m - self.pred.with_candidate(fx))
                scored.append((float(e @ e), fx))
                continue
            unit = fx.scale(amp_key)
            c = self.w.whiten(self.contribution(fx.replace(**{amp_key: unit})))
            cc = float(c @ c)
            if not cc > 0 or not math.isfinite(cc):
                continue
            lo, hi = fx.bounds(amp_key)
            beta = min(max(float(c @ self.white) / cc * unit, lo), hi) / unit
            e = self.white - beta * c
            scored.append((float(e @ e), fx.replace(**{amp_key: beta * unit})))
        scored.sort(key=lambda s: s[0])
        return [fx for _, fx in scored[:keep]]

    def best_phase(self, template: Effect, phase_key: str, period_s: float,
                   amp_key: str, steps: int = 12) -> list[Effect]:
        starts = [template.replace(**{phase_key: period_s * k / steps}) for k in range(steps)]
        return self.best_linear(starts, amp_key, keep=1)

    def command_spread_v(self) -> float:
        """How far the actuator voltage moved (5th to 95th percentile) over the span."""
        u = self.meas.u_v[self.w.span]
        return float(np.percentile(u, 95) - np.percentile(u, 5))

    def command_v(self) -> np.ndarray:
        """The actuator voltage over the span."""
        return self.meas.u_v[self.w.span]

    def lattice(self) -> tuple[float, float] | None:
        """(step, offset) if the readings sit on a lattice clearly coarser than the model's
        ADC count; None otherwise. Seen in the changes between consecutive readings, which
        are whole multiples of the step (mostly one step) when the noise cannot dither."""
        y = self.meas.y_m[self.w.span]
        lsb = self.pred.params.sensor.lsb_m
        d = np.abs(np.diff(y))
        d = d[d > 0.5 * lsb]
        if len(d) < 50:
            return None
        step = float(np.median(d[d <= np.percentile(d, 25)]))
        if step < 3.0 * lsb:
            return None
        k = np.round(d / step)
        if np.mean(np.abs(d - k * step) < max(1.01 * lsb, 0.05 * step)) < 0.9:
            return None
        step = float(np.mean(d[k == 1]))
        phase = 2 * np.pi * y / step
        offset = float(np.angle(np.mean(np.exp(1j * phase)))) / (2 * np.pi) * step
        return step, offset

    def noise_std_m(self) -> float:
        """The model's white sensor noise per sample."""
        return self.pred.params.sensor.noise_m_per_rthz * math.sqrt(0.5 / self.sig.dt_s)

    def natural_frequency_hz(self) -> float:
        """The model pendulum's: a line near it means its frequency or Q is off."""
        return self.pred.params.pendulum.natural_frequency_hz
