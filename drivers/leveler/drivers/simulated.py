"""The simulated plant as a driver: one object that is both the sensor and the actuator.

It paces nothing: `read(t)` advances the plant to loop time t in its fixed steps, so the
same class serves the real-time daemon and virtual-time simulation.
"""

from __future__ import annotations

import math
import time

from leveler.drivers.base import Block, DriverError, Reading, Status
from leveler.records import Truth
from leveler.sim.plant import Plant


class SimulatedStand:
    """Sensor + actuator backed by `leveler.sim.plant.Plant`."""

    def __init__(self, plant: Plant, safe_v: float, *, hang_at_s: float = math.inf,
                 hang_for_s: float = 0.0, fail_at_s: float = math.inf) -> None:
        """Fault injection: a read stalls for hang_for_s at hang_at_s (a hung device, for
        the watchdog); reads fail from fail_at_s until the next connect() (a pulled cable,
        put back when the daemon reconnects, for fault handling)."""
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
        plant = self.plant
        target = round(t_s / plant.dt_s)
        while plant.n < target:
            plant.step()
        if plant.samples_per_cycle > 1:
            counts_n, values_m, railed = plant.measure_block()
            return Block(t_s, counts_n, values_m, Status.RAILED if railed else Status.OK)
        counts, value_m, railed = plant.measure()
        return Reading(t_s, counts, value_m, Status.RAILED if railed else Status.OK)

    def write(self, command_v: float, t_s: float) -> float:
        if not self._connected:
            raise DriverError("simulated actuator written before connect()")
        return self.plant.command(command_v)

    def make_safe(self) -> None:
        self.plant.command(self._safe_v)

    def truth(self, seq: int, t_s: float) -> Truth:
        return self.plant.truth(seq, t_s)
