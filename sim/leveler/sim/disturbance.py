"""Disturbances and noise, generated ahead in seeded blocks with numpy.

Everything that does not depend on the controller (plate temperature, thermal and cooler
tilt, sensor noise and zero drift) is drawn here, vectorized, so the per-sample loop only
indexes lists; the same seed gives the same realization whatever the controller does,
which is what makes an open-loop vs closed-loop comparison fair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from leveler.sim.effects import Signals
from leveler.sim.params import PlantParams

DAY_S = 86400.0


@dataclass(slots=True)
class Block:
    """Disturbance values for samples [start, start + len) as plain lists (fast indexing),
    and the same as numpy arrays by field name (for leveler.loop.kernel)."""

    start: int
    temperature_k: list[float]
    thermal_tilt_rad: list[float]
    cooler_tilt_rad: list[float]
    noise_m: list[float]
    drift_m: list[float]
    effect_tilt_rad: list[float]
    arrays: dict[str, np.ndarray]


class Disturbances:
    """Block generator; state (random walks, thermal lag) carries across blocks."""

    def __init__(self, params: PlantParams, dt_s: float, seed: int, block_len: int = 8192):
        self._p = params
        self._dt = dt_s
        self._len = block_len
        temp_ss, noise_ss, drift_ss = np.random.SeedSequence(seed).spawn(3)
        self._rng_temp = np.random.default_rng(temp_ss)
        self._rng_noise = np.random.default_rng(noise_ss)
        self._rng_drift = np.random.default_rng(drift_ss)
        self._start = 0
        self._walk_k = 0.0
        self._drift_m = 0.0
        self._lag_state: float | None = None
        self._tilt_effects = [(fx, {}) for fx in params.effects.of("tilt")]

    def next_block(self) -> Block:
        th, co, se = self._p.thermal, self._p.cooler, self._p.sensor
        n, dt, start = self._len, self._dt, self._start
        t = (start + np.arange(n)) * dt

        steps = self._rng_temp.standard_normal(n) * (th.random_walk_k_per_sqrt_s * math.sqrt(dt))
        walk = self._walk_k + np.cumsum(steps)
        self._walk_k = float(walk[-1])
        temp = th.mean_k + walk + th.daily_amplitude_k * np.sin(
            2 * math.pi * t / DAY_S + th.daily_phase_rad
        )
        lagged = self._lag(temp)
        thermal_tilt = th.tilt_per_kelvin_rad_per_k * (lagged - th.mean_k)

        frac = np.mod((t + co.phase_s) / co.period_s, 1.0)
        rise = 1.0 - co.fall_fraction
        shape = np.where(frac < rise, frac / rise, (1.0 - frac) / co.fall_fraction)
        cooler = co.peak_to_peak_rad * (shape - 0.5)

        noise = self._rng_noise.standard_normal(n) * (se.noise_m_per_rthz * math.sqrt(0.5 / dt))
        dsteps = self._rng_drift.standard_normal(n) * (se.drift_m_per_sqrt_s * math.sqrt(dt))
        drift = self._drift_m + np.cumsum(dsteps)
        self._drift_m = float(drift[-1])

        extra = np.zeros(n)
        sig = Signals(t, dt, temp)
        for fx, state in self._tilt_effects:
            extra += fx.tilt(sig, state)  # type: ignore[attr-defined]

        self._start += n
        arrays = {"temperature_k": temp, "thermal_tilt_rad": thermal_tilt,
                  "cooler_tilt_rad": cooler, "noise_m": noise, "drift_m": drift,
                  "effect_tilt_rad": extra}
        return Block(start, *(a.tolist() for a in arrays.values()), arrays)

    def _lag(self, temp: np.ndarray) -> np.ndarray:
        """First-order thermal lag, exact for a signal held over each sample."""
        lag_s = self._p.thermal.lag_s
        if lag_s == 0:
            return temp
        a = math.exp(-self._dt / lag_s)
        if self._lag_state is None:  # start settled at the first temperature
            self._lag_state = a * float(temp[0])
        out, self._lag_state = first_order_lag(temp, a, self._lag_state, lag_s / self._dt)
        return out


def first_order_lag(x: np.ndarray, a: float, z: float, lag_samples: float
                    ) -> tuple[np.ndarray, float]:
    """y[n] = (1 - a) x[n] + a y[n-1], from state z = a y[-1]; returns y and the next state.

    scipy's lfilter([1 - a], [1, -a], x, zi=[z]) in numpy alone: importing scipy.signal for
    it cost every simulated stand (a `leveler run` on the sim backend, `leveler sim`) about a
    second at start. In closed form per chunk, y[n] = a^n (z + (1 - a) sum_k<=n a^-k x[k]),
    the chunks at most four lags long so a^-k stays within e^4 and the sums keep their digits.
    """
    out = np.empty(len(x))
    step = max(1, int(4 * lag_samples))
    k = np.arange(min(step, len(x)))
    down, up = a ** k, a ** -k.astype(float)  # a^k and a^-k over one chunk
    for i in range(0, len(x), step):
        n = min(step, len(x) - i)
        y = down[:n] * (z + (1 - a) * np.cumsum(x[i:i + n] * up[:n]))
        out[i:i + n] = y
        z = a * float(y[-1])
    return out, z
