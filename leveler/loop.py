"""One control cycle: read -> update -> write -> log, with time passed in.

The loop owns the lifecycle state (idle, engaged, fault). A driver error never escapes a
cycle: the actuator goes to its safe state, the loop enters `fault` and logs why. The
daemon, `leveler sim` and the tests all drive this same class.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

from leveler.drivers.base import Actuator, DriverError, Reading, Sensor, Status
from leveler.pid import PID
from leveler.records import Event, Sample, Truth

IDLE, ENGAGED, FAULT = "idle", "engaged", "fault"


class Sink(Protocol):
    """Where records go (the MCAP writer, an in-memory recorder)."""

    def sample(self, s: Sample, log_time_ns: int) -> None: ...

    def truth(self, t: Truth, log_time_ns: int) -> None: ...

    def event(self, e: Event, log_time_ns: int) -> None: ...


class Loop:
    """The controller manager: drivers, PID and state, one `cycle(t)` at a time."""

    def __init__(self, sensor: Sensor, actuator: Actuator, pid: PID, dt_s: float,
                 sinks: list[Sink], truth: Callable[[int, float], Truth] | None = None) -> None:
        self.sensor = sensor
        self.actuator = actuator
        self.pid = pid
        self.dt_s = dt_s
        self.sinks = sinks
        self._truth = truth
        self.state = IDLE
        self.fault_reason = ""
        self.seq = 0
        self.held_v = actuator.safe_v
        self.last: Sample | None = None
        self._wall_ns = 0

    def emit(self, kind: str, reason: str, t_s: float, **detail: object) -> None:
        """Log a discrete event to every sink."""
        ev = Event(t_s, kind, reason, dict(detail))
        for sink in self.sinks:
            sink.event(ev, self._wall_ns)

    def engage(self, t_s: float, reason: str = "requested") -> None:
        """Close the loop bumplessly from the voltage the actuator holds now."""
        if self.state != IDLE:
            return
        measurement = self.last.sensor_m if self.last is not None else 0.0
        if not math.isfinite(measurement):  # the last cycle had no reading (just reset)
            measurement = self.pid.config.setpoint_m  # the first good reading corrects it
        self.pid.engage(measurement, self.held_v)
        self._transition(ENGAGED, reason, t_s)

    def disengage(self, t_s: float, reason: str = "requested") -> None:
        """Open the loop; the actuator holds its last voltage."""
        if self.state == ENGAGED:
            self._transition(IDLE, reason, t_s)

    def reset(self, t_s: float, reason: str = "requested") -> None:
        """Leave `fault` for `idle`; the actuator stays at its safe voltage until engaged."""
        if self.state == FAULT:
            self.held_v = self.actuator.safe_v
            self.fault_reason = ""
            self._transition(IDLE, reason, t_s)

    def _transition(self, new: str, reason: str, t_s: float) -> None:
        old, self.state = self.state, new
        self.emit("state", reason, t_s, old=old, new=new)

    def _fault(self, t_s: float, reason: str) -> None:
        try:
            self.actuator.make_safe()
            self.held_v = self.actuator.safe_v
        except DriverError as exc:
            reason = f"{reason}; make_safe failed too: {exc}"
        if self.state != FAULT:
            self.fault_reason = reason
            self._transition(FAULT, reason, t_s)

    def cycle(self, t_s: float, wall_ns: int) -> Sample:
        """Run one cycle at loop time t_s (s) and wall time wall_ns; never raises DriverError."""
        self._wall_ns = wall_ns
        try:
            reading = self.sensor.read(t_s)
        except DriverError as exc:
            reading = Reading(t_s, 0, math.nan, Status.FAULT)
            self._fault(t_s, f"sensor read failed: {exc}")
        pid = self.pid
        p = i = d = 0.0
        saturated = False
        setpoint = pid.config.setpoint_m
        if self.state == ENGAGED and reading.status == Status.OK:
            out = pid.update(reading.value_m, self.dt_s)
            p, i, d, saturated = out.p_v, out.i_v, out.d_v, out.saturated
            setpoint, command = out.setpoint_m, out.command_v
        else:
            command = self.held_v
        applied = command
        if self.state != FAULT:
            try:
                applied = self.actuator.write(command, t_s)
                self.held_v = command
            except DriverError as exc:
                self._fault(t_s, f"actuator write failed: {exc}")
                applied = math.nan
        sample = Sample(self.seq, t_s, reading.raw_counts, reading.value_m, int(reading.status),
                        setpoint, setpoint - reading.value_m, p, i, d, command, applied,
                        saturated, self.state)
        for sink in self.sinks:
            sink.sample(sample, wall_ns)
        if self._truth is not None:
            truth = self._truth(self.seq, t_s)
            for sink in self.sinks:
                sink.truth(truth, wall_ns)
        self.seq += 1
        self.last = sample
        return sample
