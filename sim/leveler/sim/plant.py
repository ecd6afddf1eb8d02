"""The simulated stand: platform, piezo, inverted pendulum, capacitive sensor and ADC.

State advances in fixed steps of dt; over each step the amplifier slews the piezo to its
new voltage at its rate, and the pendulum follows that ramp exactly (`ramp_terms`); a
resonance feels the voltage's mean over the step (`slew_lag_v`). The
measurement at step n uses the pendulum state at t = n dt; the step from n to n+1 uses the
platform tilt at t = n dt. Driver, replay and discrepancy tools all use this one model.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from leveler.records import Truth
from leveler.sim.disturbance import Block, Disturbances
from leveler.sim.effects import ExtraResonance
from leveler.sim.params import PlantParams
from leveler.sim.pendulum import PendulumModel, delayed_slew, ramp_terms


def slew_lag_v(dv: float | np.ndarray, max_dv: float) -> float | np.ndarray:
    """How far below the new voltage the piezo's mean over a step sits, for a change dv
    within one step (|dv| <= max_dv = slew rate x dt).

    The amplifier slews continuously: a change of dv takes |dv| / slew of the step. A 6.8 V
    step of a square modulation at 100 V/s and 10 Hz sits 2.3 V short over its first
    step: held as a jump, it reads as a 27 ms actuator delay. A resonance is driven by
    this mean; the pendulum follows the ramp itself (`ramp_terms`)."""
    return dv * abs(dv) / (2.0 * max_dv)


class Plant:
    """One realization of the stand for a seed; `step` it, `measure` it, ask for `truth`."""

    def __init__(self, params: PlantParams, dt_s: float, seed: int = 0) -> None:
        self.params = params
        self.dt_s = dt_s
        self.n = 0
        pz, se = params.piezo, params.sensor
        self._tilt_per_v = pz.gain_m_per_v / params.platform.support_spacing_m
        self._v_ref = pz.ref_v
        self._v_min, self._v_max = pz.min_v, pz.max_v
        self._max_dv = pz.slew_v_per_s * dt_s
        self.v_applied = pz.ref_v
        self.v_target = pz.ref_v
        self.v_effective = pz.ref_v  # what moves the piezo after actuator effects
        self._lag_v = 0.0  # the slew's ramp: the step's mean below v_effective
        self._arm = params.pendulum.sensor_arm_m
        self._gain, self._offset = se.gain_v_per_m, se.offset_v
        self._adc_min, self._lsb = se.adc_min_v, se.lsb_v
        self._top = 2**se.adc_bits - 1
        self.samples_per_cycle = se.samples_per_cycle
        # The spread of the fast conversions about each cycle's noisy value; a stream of its
        # own, so oversampling leaves every other random draw of a seed unchanged.
        self._rng_sub = np.random.default_rng([seed, 0x5AB])
        self._sub_sigma_m = se.noise_m_per_rthz * math.sqrt(0.5 / dt_s * se.samples_per_cycle)
        self._offset_tilt = params.platform.initial_tilt_rad
        self._dist = Disturbances(params, dt_s, seed)
        self._block: Block = self._dist.next_block()
        self._i = 0
        self.pendulum = PendulumModel(params.pendulum, dt_s)
        # per unit dphi, [theta, omega] the slew adds at a step's end: Horner in its time
        self._ramp_k = tuple((float(a), float(b))
                             for a, b in ramp_terms(params.pendulum, dt_s)[::-1])
        self._slew_v_per_s = pz.slew_v_per_s
        self.pendulum.settle(params.pendulum, self.tilt_rad())
        fx = params.effects
        delay = fx.actuator_delay
        self._delay_s = 0.0 if delay is None else delay.delay_s
        self._actuator_fx = [e.stepper(dt_s) for e in fx.of("actuator") if e is not delay]
        # a delayed piezo's last end values and ramp times (`delayed_slew`), the oldest
        # first: the log's start is settled at the reference
        keep = int(self._delay_s // dt_s) + 3
        self._recent: tuple[deque[float], deque[float]] = (
            deque([pz.ref_v] * keep, maxlen=keep), deque([0.0] * keep, maxlen=keep))
        self._sensor_fx = [e.stepper(dt_s) for e in fx.of("sensor")]
        self._resonances = [_Resonance(e, dt_s, params.pendulum.sensor_arm_m
                                       * params.pendulum.amplification,
                                       np.random.default_rng([seed, 0x4E5, i]))
                            for i, e in enumerate(fx.of("response"))
                            if isinstance(e, ExtraResonance)]
        self._extra_m = 0.0
        # the plate thermometer's noise: a stream of its own, so reading it (or not) leaves
        # every other draw of a seed unchanged
        self._rng_thermometer = np.random.default_rng([seed, 0x7E3])
        self._thermometer_z: list[float] = []  # its draws to come, the next one last

    def tilt_rad(self) -> float:
        """True platform tilt now: piezo stroke / spacing + thermal + cooler + offset."""
        b, i = self._block, self._i
        return (self._tilt_per_v * (self.v_effective - self._v_ref) + b.thermal_tilt_rad[i]
                + b.cooler_tilt_rad[i] + b.effect_tilt_rad[i] + self._offset_tilt)

    def command(self, v: float) -> float:
        """Set the piezo target voltage; returns what the next step will apply (clamped, slewed)."""
        self.v_target = min(max(v, self._v_min), self._v_max)
        return self._slewed()

    def _slewed(self) -> float:
        dv = self.v_target - self.v_applied
        if dv > self._max_dv:
            dv = self._max_dv
        elif dv < -self._max_dv:
            dv = -self._max_dv
        return self.v_applied + dv

    def step(self) -> None:
        """Advance one dt."""
        before = self.v_applied
        self.v_applied = v = self._slewed()
        self._lag_v = float(slew_lag_v(v - before, self._max_dv))
        if self._actuator_fx:
            t_s = self.n * self.dt_s
            for f in self._actuator_fx:
                v = f(v, t_s)
        # The piezo got there by a ramp of |dv| / slew from the step's start, not a jump.
        tau = abs(self.v_applied - before) / self._slew_v_per_s
        inject = None
        if self._delay_s > 0:  # ... from later within the step, or a step later
            self._recent[0].append(v)
            self._recent[1].append(tau)
            ends, lags, ramps = delayed_slew(self.params.pendulum, self.dt_s,
                                             np.array(self._recent[0]),
                                             np.array(self._recent[1]), self._delay_s)
            v, self._lag_v = float(ends[-1]), float(lags[-1])
            inject = (float(ramps[0][-1]), float(ramps[1][-1]))
        dphi = self._tilt_per_v * (v - self.v_effective)
        self.v_effective = v
        if self._resonances:
            phi_u = self._tilt_per_v * (v - self._lag_v - self._v_ref)
            self._extra_m = sum(r.step(phi_u) for r in self._resonances)
        pend = self.pendulum
        pend.step(self.tilt_rad())
        if inject is not None:
            pend.theta += self._tilt_per_v * inject[0]
            pend.omega += self._tilt_per_v * inject[1]
        elif tau != 0.0:  # a held voltage (an open loop's plateau) adds nothing
            g_theta = g_omega = 0.0
            for k_theta, k_omega in self._ramp_k:
                g_theta = (g_theta + k_theta) * tau
                g_omega = (g_omega + k_omega) * tau
            pend.theta += g_theta * dphi
            pend.omega += g_omega * dphi
        self.n += 1
        self._i += 1
        if self._i >= len(self._block.noise_m):
            self._block = self._dist.next_block()
            self._i = 0

    def _sensed_m(self) -> float:
        """What the sensor's analog output says now, noise and sensor effects included."""
        b, i = self._block, self._i
        x = self._arm * self.pendulum.theta + self._extra_m + b.drift_m[i] + b.noise_m[i]
        if self._sensor_fx:  # after the noise: a coarse ADC digitizes the noisy signal
            t_s = self.n * self.dt_s
            for f in self._sensor_fx:
                x = f(x, t_s)
        return x

    def measure_block(self) -> tuple[np.ndarray, np.ndarray, bool]:
        """`samples_per_cycle` ADC conversions within this cycle: (counts, metres, railed).

        White noise of the same density seen in an n times wider band has sqrt(n) times the
        rms per conversion; the conversions spread about this cycle's noisy value so that
        their mean before the ADC is exactly that value. So averaging them changes nothing
        but the quantization, which the spread dithers away (sensor effects act on the
        cycle's value, before the spread)."""
        n = self.samples_per_cycle
        z = self._rng_sub.standard_normal(n) * self._sub_sigma_m
        x = self._sensed_m() + (z - z.mean())
        counts = np.floor((self._gain * x + self._offset - self._adc_min) / self._lsb + 0.5)
        railed = bool(counts.min() <= 0 or counts.max() >= self._top)
        counts = np.clip(counts, 0, self._top).astype(np.int64)
        return counts, (counts * self._lsb + self._adc_min - self._offset) / self._gain, railed

    def measure(self) -> tuple[int, float, bool]:
        """Sensor through the ADC, one conversion: (counts, metres the counts mean, railed)."""
        x = self._sensed_m()
        counts = math.floor((self._gain * x + self._offset - self._adc_min) / self._lsb + 0.5)
        railed = counts <= 0 or counts >= self._top
        if counts < 0:
            counts = 0
        elif counts > self._top:
            counts = self._top
        value_m = (counts * self._lsb + self._adc_min - self._offset) / self._gain
        return counts, value_m, railed

    def plate_temperature_k(self) -> float:
        """The plate's true temperature now [K] (what `thermometer_k` reads)."""
        return float(self._block.temperature_k[self._i])

    def thermometer_k(self) -> float:
        """What the plate thermometer reads now [K]: the plate temperature, its noise, its
        resolution."""
        th = self.params.thermal
        if not self._thermometer_z:  # drawn a block at a time: the same stream, 4x cheaper
            self._refill_thermometer()
        temp = (self._block.temperature_k[self._i]
                + th.thermometer_noise_k * self._thermometer_z.pop())
        res = th.thermometer_resolution_k
        return round(temp / res) * res if res > 0 else temp

    def thermometer_series_k(self, plate_k: np.ndarray) -> np.ndarray:
        """What `thermometer_k` would have read, called once at each of these plate
        temperatures in turn [K], the same draws to the bit: a simulated log's series
        at once, its plate temperatures recorded as it ran."""
        th = self.params.thermal
        z = np.empty(len(plate_k))
        k = 0
        while k < len(z):
            if not self._thermometer_z:
                self._refill_thermometer()
            take = min(len(z) - k, len(self._thermometer_z))
            z[k:k + take] = self._thermometer_z[:-take - 1:-1]  # the next, in draw order
            del self._thermometer_z[-take:]
            k += take
        temp = plate_k + th.thermometer_noise_k * z
        res = th.thermometer_resolution_k
        return np.round(temp / res) * res if res > 0 else temp

    def _refill_thermometer(self) -> None:
        self._thermometer_z = self._rng_thermometer.standard_normal(4096).tolist()[::-1]

    def truth(self, seq: int, t_s: float) -> Truth:
        b, i = self._block, self._i
        return Truth(
            seq=seq,
            t_s=t_s,
            tilt_rad=self.tilt_rad(),
            thermal_tilt_rad=b.thermal_tilt_rad[i],
            cooler_tilt_rad=b.cooler_tilt_rad[i],
            piezo_tilt_rad=self._tilt_per_v * (self.v_effective - self._v_ref),
            pendulum_rad=self.pendulum.theta,
            temperature_k=b.temperature_k[i],
            sensor_drift_m=b.drift_m[i],
        )


class _Resonance:
    """An extra resonance stepped sample by sample: the same discrete filter replay uses
    (direct form II transposed, from rest at the first input), and, with `noise_rms_m`,
    the same filter driven by white noise of its own (`rng`) scaled to that rms."""

    _BLOCK = 4096  # noise drawn this many samples at a time

    def __init__(self, fx: ExtraResonance, dt_s: float, static_m_per_rad: float,
                 rng: np.random.Generator) -> None:
        b, a = fx.discrete(dt_s)
        self._b = (b / a[0]).tolist()
        self._a = (a / a[0]).tolist()
        self._z = [0.0] * (len(self._a) - 1)
        self._zn = [0.0] * (len(self._a) - 1)
        self._k = fx.gain * static_m_per_rad
        self._x0: float | None = None
        if abs(self._b[0]) > 1e-12:
            raise ValueError("extra resonance filter must be strictly proper")
        self._rng = rng
        self._noise_in = fx.noise_rms_m / math.sqrt(impulse_energy(b, a)) if fx.noise_rms_m else 0.0
        self._draws: list[float] = []

    def _step(self, x: float, z: list[float]) -> float:
        """Consume this step's input; returns the output at the *next* sample (the ZOH
        filter has no direct term, so that output is already known)."""
        b, a = self._b, self._a
        y = b[0] * x + z[0]
        for j in range(len(z) - 1):
            z[j] = b[j + 1] * x + z[j + 1] - a[j + 1] * y
        z[-1] = b[-1] * x - a[-1] * y
        return z[0]

    def step(self, phi_u: float) -> float:
        if self._x0 is None:
            self._x0 = phi_u
        out = self._k * self._step(phi_u - self._x0, self._z)
        if self._noise_in:
            if not self._draws:
                self._draws = (self._noise_in * self._rng.standard_normal(self._BLOCK)).tolist()
            out += self._step(self._draws.pop(), self._zn)
        return out


def impulse_energy(b: np.ndarray, a: np.ndarray) -> float:
    """Sum of the squared impulse response of a stable filter: its output variance per
    unit variance of white noise at its input. By Parseval, the mean of |B/A|^2 on n points
    of the unit circle: the response folded onto n samples, which for n far beyond its
    ringing is the response itself (numpy only: scipy.signal's lfilter cost a simulated
    stand a second of start-up)."""
    r = float(np.max(np.abs(np.roots(a))))  # the slowest pole sets how long it rings
    n = int(min(1 << 22, max(4096, 40 / max(1 - r, 1e-9))))
    n += n % 2
    power = np.abs(np.fft.rfft(b, n) / np.fft.rfft(a, n)) ** 2
    return float((power[0] + power[-1] + 2 * np.sum(power[1:-1])) / n)
