"""The simulated stand: platform, piezo, inverted pendulum, capacitive sensor and ADC.

State advances in fixed steps of dt with the piezo voltage held over each step. The
measurement at step n uses the pendulum state at t = n dt; the step from n to n+1 uses the
platform tilt at t = n dt. Driver, replay and discrepancy tools all use this one model.
"""

from __future__ import annotations

import math

from leveler.records import Truth
from leveler.sim.disturbance import Block, Disturbances
from leveler.sim.params import PlantParams
from leveler.sim.pendulum import PendulumModel


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
        self._arm = params.pendulum.sensor_arm_m
        self._gain, self._offset = se.gain_v_per_m, se.offset_v
        self._adc_min, self._lsb = se.adc_min_v, se.lsb_v
        self._top = 2**se.adc_bits - 1
        self._offset_tilt = params.platform.initial_tilt_rad
        self._dist = Disturbances(params, dt_s, seed)
        self._block: Block = self._dist.next_block()
        self._i = 0
        self.pendulum = PendulumModel(params.pendulum, dt_s)
        self.pendulum.settle(params.pendulum, self.tilt_rad())

    def tilt_rad(self) -> float:
        """True platform tilt now: piezo stroke / spacing + thermal + cooler + offset."""
        b, i = self._block, self._i
        return (self._tilt_per_v * (self.v_applied - self._v_ref) + b.thermal_tilt_rad[i]
                + b.cooler_tilt_rad[i] + self._offset_tilt)

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
        self.v_applied = self._slewed()
        self.pendulum.step(self.tilt_rad())
        self.n += 1
        self._i += 1
        if self._i >= len(self._block.noise_m):
            self._block = self._dist.next_block()
            self._i = 0

    def measure(self) -> tuple[int, float, bool]:
        """Sensor through the ADC: (counts, metres the counts mean, railed)."""
        b, i = self._block, self._i
        x = self._arm * self.pendulum.theta + b.drift_m[i] + b.noise_m[i]
        counts = math.floor((self._gain * x + self._offset - self._adc_min) / self._lsb + 0.5)
        railed = counts <= 0 or counts >= self._top
        if counts < 0:
            counts = 0
        elif counts > self._top:
            counts = self._top
        value_m = (counts * self._lsb + self._adc_min - self._offset) / self._gain
        return counts, value_m, railed

    def truth(self, seq: int, t_s: float) -> Truth:
        b, i = self._block, self._i
        return Truth(
            seq=seq,
            t_s=t_s,
            tilt_rad=self.tilt_rad(),
            thermal_tilt_rad=b.thermal_tilt_rad[i],
            cooler_tilt_rad=b.cooler_tilt_rad[i],
            piezo_tilt_rad=self._tilt_per_v * (self.v_applied - self._v_ref),
            pendulum_rad=self.pendulum.theta,
            temperature_k=b.temperature_k[i],
            sensor_drift_m=b.drift_m[i],
        )
