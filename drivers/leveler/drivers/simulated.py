"""The simulated plant as a driver: one object that is both the sensor and the actuator.

It paces nothing: `read(t)` advances the plant to loop time t in its fixed steps, so the
same class serves the real-time daemon and virtual-time simulation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

from leveler.drivers.base import Block, DriverError, Reading, Status, TemperatureReading
from leveler.drivers.simulated_config import FaultSpec
from leveler.records import Truth
from leveler.sim.plant import Plant


class SimulatedStand:
    """Sensor + actuator (+ the plate thermometer) backed by `leveler.sim.plant.Plant`."""

    def __init__(self, plant: Plant, safe_v: float, *, hang_at_s: float = math.inf,
                 hang_for_s: float = 0.0, fail_at_s: float = math.inf,
                 faults: Sequence[FaultSpec] = ()) -> None:
        """Fault injection: a read stalls for hang_for_s at hang_at_s (a hung device, for
        the watchdog); reads fail from fail_at_s until the next connect() (a pulled cable,
        put back when the daemon reconnects, for fault handling); `faults` is a schedule of
        the kinds in FaultSpec (see docs/reliability.md for the loop's reaction to each)."""
        pz = plant.params.piezo
        if not pz.min_v <= safe_v <= pz.max_v:
            raise DriverError(
                f"safe_v {safe_v} V outside the piezo range [{pz.min_v}, {pz.max_v}] V")
        self.plant = plant
        self._safe_v = safe_v
        self._connected = False
        self._hang_at_s = hang_at_s
        self._hang_for_s = hang_for_s
        self._fail_at_s = fail_at_s
        self._unplugged = False
        self._faults = [f for f in faults if f.kind != "clock_step"]
        self._last: Reading | None = None

    def _fault(self, kind: str, t_s: float) -> FaultSpec | None:
        if not self._faults:  # the usual stand: eight asks a cycle, 15 % of a virtual day
            return None
        return next((f for f in self._faults
                     if f.kind == kind and f.active(t_s, self.plant.dt_s)), None)

    @property
    def safe_v(self) -> float:
        return self._safe_v

    def connect(self) -> None:
        self._connected = True
        self._unplugged = False

    def close(self) -> None:
        self._connected = False

    def read(self, t_s: float) -> Reading | Block:
        if not self._connected:
            raise DriverError("simulated sensor read before connect()")
        if t_s >= self._hang_at_s:
            self._hang_at_s = math.inf
            time.sleep(self._hang_for_s)  # the device stops answering, once
        if t_s >= self._fail_at_s:
            self._unplugged = True
            self._fail_at_s = math.inf
        if self._unplugged:
            raise DriverError("injected sensor fault: no reply since [sim] fail_at_s")
        if self._fault("disconnect", t_s):
            raise DriverError("injected disconnect: the sensor does not answer")
        if self._fault("timeout", t_s):
            raise DriverError("injected timeout: no reply from the sensor in time")
        plant = self.plant
        target = round(t_s / plant.dt_s)
        while plant.n < target:
            plant.step()
        if plant.samples_per_cycle > 1:
            counts_n, values_m, railed = plant.measure_block()
            block = Block(t_s, counts_n, values_m, Status.RAILED if railed else Status.OK)
            mean = block.mean()
            spoiled = self._spoiled(mean)
            return block if spoiled is mean else spoiled
        counts, value_m, railed = plant.measure()
        reading = Reading(t_s, counts, value_m, Status.RAILED if railed else Status.OK)
        return self._spoiled(reading)

    def _spoiled(self, r: Reading) -> Reading:
        """The reading as a scheduled sensor fault would corrupt it (`r` itself if none)."""
        t_s = r.t_s
        if self._fault("nan", t_s):
            r = Reading(t_s, r.raw_counts, math.nan, Status.INVALID)
        elif self._fault("railed", t_s):
            top = 2**self.plant.params.sensor.adc_bits - 1
            se = self.plant.params.sensor
            r = Reading(t_s, top, (se.adc_max_v - se.offset_v) / se.gain_v_per_m, Status.RAILED)
        elif self._fault("stuck", t_s) and self._last is not None:
            r = Reading(t_s, self._last.raw_counts, self._last.value_m, self._last.status)
        elif spike := self._fault("spike", t_s):
            r = Reading(t_s, r.raw_counts, r.value_m + spike.size, r.status)
        self._last = r
        return r

    def write(self, command_v: float, t_s: float) -> float:
        if not self._connected:
            raise DriverError("simulated actuator written before connect()")
        if self._fault("disconnect", t_s):
            raise DriverError("injected disconnect: the piezo amplifier does not answer")
        if self._fault("write_fail", t_s):
            raise DriverError("injected write failure: the piezo amplifier refused the command")
        if math.isnan(command_v):  # as the real drivers do: an upstream bug is not hidden
            raise DriverError(f"refusing command {command_v} V (NaN)")
        return self.plant.command(command_v)

    def make_safe(self) -> bool:
        self.plant.command(self._safe_v)
        return True

    def read_temperature(self, t_s: float) -> TemperatureReading:
        """The plate thermometer at the plant's present step (the loop reads the sensor,
        which advances the plant, first)."""
        if not self._connected:
            raise DriverError("simulated thermometer read before connect()")
        if self._unplugged or self._fault("disconnect", t_s):
            raise DriverError("injected disconnect: the thermometer does not answer")
        if self._fault("thermometer", t_s):
            raise DriverError("injected thermometer fault: no reply")
        return TemperatureReading(t_s, self.plant.thermometer_k())

    def truth(self, seq: int, t_s: float) -> Truth:
        return self.plant.truth(seq, t_s)
