"""One control cycle: read -> update -> write -> log, with time passed in.

The loop owns the lifecycle state (idle, engaged, fault, modulating). A driver error never
escapes a cycle. One bad reply (a garbled line, a Modbus exception, a timeout) is counted and
logged and the actuator holds its voltage for that cycle; `fault_after_errors` errors in a row
mean the device is gone: the actuator goes to its safe state, the loop enters `fault` and logs
why. A reading that arrives but cannot be trusted (NaN, railed, stuck, a spike: `_screen`)
holds the voltage too, and `fault_after_bad_readings` of them in a row fault. A thermometer,
when there is one, is read every `interval_s` for the temperature feedforward; it is an
auxiliary device: its failures are logged and hold the feedforward, and never fault the loop.
The daemon, `leveler sim` and the tests all drive this same class.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from leveler.drivers.base import (
    Actuator,
    Block,
    DriverError,
    Reading,
    Sensor,
    Status,
    TemperatureReading,
    Thermometer,
)
from leveler.loop.feedforward import Feedforward, FeedforwardFilter
from leveler.loop.modulation import Wave
from leveler.loop.pid import PID
from leveler.records import Environment, Event, Sample, Truth
from leveler.typed_config import non_negative, positive


@dataclass(frozen=True, slots=True)
class LoopConfig:
    """[loop]: the cycle's rate, status cadence, and when bad readings fault and resume."""

    rate_hz: float = positive(10.0)
    status_interval_s: float = positive(5.0)
    engage_on_start: bool = True
    ready_samples: int = field(default=10, metadata={"ge": 1})
    fault_after_errors: int = field(default=3, metadata={"ge": 1})
    fault_after_bad_readings: int = field(default=50, metadata={"ge": 1})
    stuck_after_samples: int = field(default=0, metadata={"ge": 0})
    max_step_m: float = non_negative(0.0)
    spike_reject_max: int = field(default=3, metadata={"ge": 1})
    resume_after_good_samples: int = field(default=10, metadata={"ge": 1})
    reconnect_min_s: float = positive(2.0)
    reconnect_max_s: float = positive(60.0)
    resume_after_reconnect: bool = True


IDLE, ENGAGED, FAULT, MODULATING = "idle", "engaged", "fault", "modulating"
ERROR_EVENT_INTERVAL_S = 1.0  # at most one driver_error event per second; the counts are exact
THERMOMETER_EVENT_INTERVAL_S = 60.0  # at most one thermometer event a minute while it fails
RESUME_AFTER_READS = 10  # readings missed before the feedforward restarts from the next one


class Sink(Protocol):
    """Where records go (the MCAP writer, an in-memory recorder)."""

    def sample(self, s: Sample, log_time_ns: int) -> None: ...

    def truth(self, t: Truth, log_time_ns: int) -> None: ...

    def event(self, e: Event, log_time_ns: int) -> None: ...

    def environment(self, e: Environment, log_time_ns: int) -> None: ...


class Loop:
    """The controller manager: drivers, PID and state, one `cycle(t)` at a time."""

    def __init__(self, sensor: Sensor, actuator: Actuator, pid: PID, dt_s: float,
                 sinks: list[Sink], truth: Callable[[int, float], Truth] | None = None,
                 *, policy: LoopConfig | None = None, thermometer: Thermometer | None = None,
                 thermometer_interval_s: float = 1.0,
                 feedforward: Feedforward | None = None) -> None:
        self.sensor = sensor
        self.actuator = actuator
        self.pid = pid
        self.dt_s = dt_s
        self.sinks = sinks
        self._truth = truth
        self.state = IDLE
        self.fault_reason = ""
        # Kept after a reset or an automatic reconnect: a fault that healed itself at 3 a.m.
        # is still told by `leveler status` in the morning.
        self.faults = 0
        self.last_fault = ""
        self.seq = 0
        self.held_v = actuator.safe_v
        self.safe_unconfirmed = False  # in fault: make_safe failed, applied_v is unknown
        self.last: Sample | None = None
        self.wave: Wave | None = None  # the tilt modulation while `modulating`
        self._wall_ns = 0
        self.policy = policy or LoopConfig()
        self.fault_after_errors = self.policy.fault_after_errors
        self.errors = {"sensor": 0, "actuator": 0}  # driver errors outside fault, since start
        self._in_a_row = 0
        self._unreported = 0
        self._next_error_event_s = -math.inf
        self.bad_readings = 0  # untrustworthy readings outside fault, since start
        self._bad_in_a_row = 0
        self._bad_why = ""
        self._same_in_a_row = 0  # readings identical to the one before (a stuck sensor)
        self._spikes_in_a_row = 0
        self._last_value_m = math.nan
        self._last_good_m = math.nan
        self.thermometer = thermometer
        self.thermometer_interval_s = thermometer_interval_s
        self._next_temperature_s = -math.inf
        self.temperature: TemperatureReading | None = None  # the last good reading
        self.thermometer_errors = 0  # failed or unusable readings, since start
        self.thermometer_trouble = ""  # why the last reading failed, while they fail
        self._trouble_since_s = math.nan
        self._trouble_unreported = 0
        self._next_trouble_event_s = -math.inf
        self.ff: FeedforwardFilter | None = None
        if feedforward is not None:
            self.set_feedforward(feedforward)

    def set_feedforward(self, feedforward: Feedforward | None) -> None:
        """Switch the temperature feedforward on, off or to other paths without a bump:
        what the old one added moves into the PID's integral, and the new one starts from
        zero at the last reading. ValueError without a thermometer."""
        if feedforward is not None and self.thermometer is None:
            raise ValueError("a temperature feedforward needs a thermometer ([thermometer] "
                             "backend)")
        self.pid.absorb_feedforward()
        self.ff = None if feedforward is None else FeedforwardFilter(
            feedforward, RESUME_AFTER_READS * self.thermometer_interval_s)
        if self.ff is not None and self.temperature is not None:
            self.ff.feed(self.temperature.t_s, self.temperature.temperature_k)

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
        if self.ff is not None:
            self.ff.rezero()  # the integral holds the present; the feedforward adds changes
        self._transition(ENGAGED, reason, t_s)

    def disengage(self, t_s: float, reason: str = "requested") -> None:
        """Open the loop, or abort a modulation (back to its centre voltage)."""
        if self.state == ENGAGED:
            self._transition(IDLE, reason, t_s)
        elif self.state == MODULATING:
            self._end_modulation(t_s, f"modulation aborted: {reason}")

    def modulate(self, t_s: float, amplitude_v: float, period_s: float, cycles: int,
                 reason: str = "requested", shape: str = "square") -> Wave:
        """From idle, drive a square or triangle wave about the held voltage with the loop
        open; back to idle at that voltage when it ends (or on `disengage`). ValueError if
        the wave does not fit the controller's output range or the loop rate."""
        if self.state != IDLE:
            raise ValueError(f"modulation needs the loop idle, not {self.state}")
        wave = Wave(self.held_v, amplitude_v, period_s, cycles, start_t_s=t_s, shape=shape)
        c = self.pid.config
        wave.check_fits(c.output_min_v, c.output_max_v, self.dt_s)
        self.wave = wave
        self._transition(MODULATING, reason, t_s)
        self.emit("procedure", "modulation started", t_s, center_v=wave.center_v,
                  amplitude_v=amplitude_v, period_s=period_s, cycles=cycles,
                  start_t_s=t_s, end_t_s=wave.end_t_s, shape=shape)
        return wave

    def _end_modulation(self, t_s: float, reason: str) -> None:
        assert self.wave is not None
        self.held_v = self.wave.center_v
        self.wave = None
        self.emit("procedure", reason, t_s)
        self._transition(IDLE, reason, t_s)

    def reset(self, t_s: float, reason: str = "requested") -> None:
        """Leave `fault` for `idle`; the actuator stays at its safe voltage until engaged."""
        if self.state == FAULT:
            self.held_v = self.actuator.safe_v  # what the next idle cycle writes
            self.safe_unconfirmed = False
            self.fault_reason = ""
            self._in_a_row = 0
            self._bad_in_a_row = 0
            # The stand may have moved during a long fault: the first reading after it is
            # the new reference, not a spike against the last one before it.
            self._last_good_m = self._last_value_m = math.nan
            self._spikes_in_a_row = self._same_in_a_row = 0
            self._transition(IDLE, reason, t_s)

    def _transition(self, new: str, reason: str, t_s: float) -> None:
        old, self.state = self.state, new
        self.emit("state", reason, t_s, old=old, new=new)

    def _fault(self, t_s: float, reason: str) -> None:
        try:
            self.safe_unconfirmed = not self.actuator.make_safe()
        except DriverError as exc:  # the protocol says never; a driver that does is heard
            self.safe_unconfirmed, reason = True, f"{reason} ({exc})"
        if self.safe_unconfirmed:
            # The amplifier holds its last voltage; the log must not claim safe_v.
            reason = (f"{reason}; the safe voltage could NOT be set (actuator unreachable): "
                      "the piezo holds its last voltage")
        else:
            self.held_v = self.actuator.safe_v
        if self.state != FAULT:
            if self.wave is not None:
                self.wave = None
                self.emit("procedure", f"modulation aborted: {reason}", t_s)
            self.fault_reason = self.last_fault = reason
            self.faults += 1
            self._transition(FAULT, reason, t_s)

    def _driver_error(self, t_s: float, device: str, what: str) -> None:
        """Count an error; fault on the `fault_after_errors`-th in a row, else log it. In
        fault the device is known to be gone: its failures are neither counted nor logged."""
        if self.state == FAULT:
            return
        self.errors[device] += 1
        self._in_a_row += 1
        if self._in_a_row >= self.fault_after_errors:
            self._unreported = 0  # the fault event tells the end of the run
            self._fault(t_s, what if self._in_a_row == 1 else
                        f"{what} ({self._in_a_row} driver errors in a row)")
            return
        self._unreported += 1
        if t_s >= self._next_error_event_s:
            self._report_errors(t_s, f"{what}; voltage held", device=device)

    def _report_errors(self, t_s: float, reason: str, **detail: object) -> None:
        self.emit("driver_error", reason, t_s, in_a_row=self._in_a_row,
                  since_last_event=self._unreported, sensor_errors=self.errors["sensor"],
                  actuator_errors=self.errors["actuator"], **detail)
        self._unreported = 0
        self._next_error_event_s = t_s + ERROR_EVENT_INTERVAL_S

    def _screen(self, r: Reading) -> Reading:
        """Mark a reading the controller must not trust (stuck, spike), and count runs of
        untrustworthy readings: the first is logged, `fault_after_bad_readings` in a row
        fault, and the end of a run is logged with its length."""
        p = self.policy
        why = {Status.TIMEOUT: "timeout", Status.INVALID: "invalid (NaN or unparsable)",
               Status.RAILED: "railed (at the end of the sensor's range)"}.get(r.status, "")
        if r.status == Status.OK and not math.isfinite(r.value_m):
            why = "not finite despite an OK status"  # a driver parsed "inf": never to the PID
        elif r.status == Status.OK:
            same = r.value_m == self._last_value_m
            self._same_in_a_row = self._same_in_a_row + 1 if same else 0
            if p.stuck_after_samples and self._same_in_a_row + 1 >= p.stuck_after_samples:
                why = f"stuck ({self._same_in_a_row + 1} identical readings)"
            elif (p.max_step_m and abs(r.value_m - self._last_good_m) > p.max_step_m
                  and self._spikes_in_a_row < p.spike_reject_max):
                self._spikes_in_a_row += 1
                why = (f"spike ({(r.value_m - self._last_good_m) * 1e9:+.1f} nm from the last "
                       f"good reading, over max_step_m)")
            else:
                self._spikes_in_a_row = 0  # a level that persists is accepted
        self._last_value_m = r.value_m
        if not why:
            self._last_good_m = r.value_m
            if self._bad_in_a_row and self.state != FAULT:
                self.emit("bad_reading", f"readings good again after {self._bad_in_a_row} "
                          "bad", r.t_s, in_a_row=self._bad_in_a_row)
            self._bad_in_a_row = 0
            return r
        if self.state == FAULT:
            return Reading(r.t_s, r.raw_counts, r.value_m, Status.INVALID)
        self.bad_readings += 1
        self._bad_in_a_row += 1
        if self._bad_in_a_row == 1:
            self._bad_why = why
            self.emit("bad_reading", f"sensor reading {why}; voltage held", r.t_s,
                      value_m=r.value_m, status=int(r.status))
        if self._bad_in_a_row >= p.fault_after_bad_readings:
            self._bad_in_a_row = 0
            self._fault(r.t_s, f"{p.fault_after_bad_readings} bad sensor readings in a row "
                        f"(first: {self._bad_why}; last: {why})")
        status = r.status if r.status != Status.OK else Status.INVALID
        return Reading(r.t_s, r.raw_counts, r.value_m, status)

    def _read_temperature(self, t_s: float) -> Environment:
        """One thermometer reading, fed to the feedforward; failures are counted, logged
        (the first, then at most once a minute) and hold the feedforward."""
        assert self.thermometer is not None
        self._next_temperature_s = t_s + self.thermometer_interval_s - 0.5 * self.dt_s
        why = ""
        try:
            r = self.thermometer.read_temperature(t_s)
        except DriverError as exc:
            why = f"thermometer read failed: {exc}"
        else:
            if r.status != Status.OK or not math.isfinite(r.temperature_k):
                why = f"thermometer reading {Status(r.status).name.lower()} ({r.temperature_k!r} K)"
        held = self.ff.v if self.ff is not None else 0.0
        if why:
            self.thermometer_errors += 1
            self._trouble_unreported += 1
            if not self.thermometer_trouble:
                self._trouble_since_s = t_s
            self.thermometer_trouble = why
            if t_s >= self._next_trouble_event_s:
                self.emit("thermometer", f"{why}; feedforward held at {held:+.4g} V", t_s,
                          since_s=t_s - self._trouble_since_s,
                          missed=self._trouble_unreported, errors=self.thermometer_errors)
                self._trouble_unreported = 0
                self._next_trouble_event_s = t_s + THERMOMETER_EVENT_INTERVAL_S
            return Environment(self.seq, t_s, math.nan, held)
        if self.thermometer_trouble:
            self.emit("thermometer", f"thermometer readings again after "
                      f"{t_s - self._trouble_since_s:.1f} s; feedforward goes on from "
                      f"{held:+.4g} V", t_s, missed=self._trouble_unreported)
            self.thermometer_trouble = ""
            self._trouble_unreported = 0
            self._next_trouble_event_s = -math.inf
        self.temperature = r
        v = self.ff.feed(t_s, r.temperature_k) if self.ff is not None else 0.0
        return Environment(self.seq, t_s, r.temperature_k, v)

    def cycle(self, t_s: float, wall_ns: int) -> Sample:
        """Run one cycle at loop time t_s (s) and wall time wall_ns; never raises DriverError."""
        self._wall_ns = wall_ns
        errors_before = self.errors["sensor"] + self.errors["actuator"]
        try:
            got = self.sensor.read(t_s)
            reading = got.mean() if isinstance(got, Block) else got  # decimate to the loop rate
        except DriverError as exc:
            reading = Reading(t_s, 0, math.nan, Status.FAULT)
            self._driver_error(t_s, "sensor", f"sensor read failed: {exc}")
        else:
            reading = self._screen(reading)
        env = (self._read_temperature(t_s) if self.thermometer is not None
               and t_s >= self._next_temperature_s else None)
        pid = self.pid
        p = i = d = 0.0
        saturated = False
        setpoint = pid.config.setpoint_m
        if self.state == ENGAGED and reading.status == Status.OK:
            try:
                out = pid.update(reading.value_m, self.dt_s,
                                 0.0 if self.ff is None else self.ff.v)
            except OverflowError as exc:  # an absurd reading or gain: stop, do not guess
                self._fault(t_s, f"controller fault: {exc}")
                command = self.held_v
            else:
                p, i, d, saturated = out.p_v, out.i_v, out.d_v, out.saturated
                setpoint, command = out.setpoint_m, out.command_v
        else:
            command = self.held_v
            if self.state == MODULATING:
                assert self.wave is not None
                wave_v = self.wave.command_v(t_s)
                if wave_v is None:
                    self._end_modulation(t_s, "modulation done")
                    command = self.held_v
                else:
                    command = wave_v
        applied = math.nan if self.state == FAULT and self.safe_unconfirmed else command
        if self.state != FAULT:
            try:
                applied = self.actuator.write(command, t_s)
                self.held_v = command
            except DriverError as exc:
                self._driver_error(t_s, "actuator", f"actuator write failed: {exc}")
                applied = math.nan
        if self.errors["sensor"] + self.errors["actuator"] == errors_before:
            self._in_a_row = 0  # a cycle without a driver error ends a run of them
        if self._unreported and t_s >= self._next_error_event_s:  # the rest of a burst
            self._report_errors(t_s, f"{self._unreported} more driver error(s) in the last "
                                f"{ERROR_EVENT_INTERVAL_S:g} s; voltage held")
        sample = Sample(self.seq, t_s, reading.raw_counts, reading.value_m, int(reading.status),
                        setpoint, setpoint - reading.value_m, p, i, d, command, applied,
                        saturated, self.state)
        for sink in self.sinks:
            sink.sample(sample, wall_ns)
        if self._truth is not None:
            truth = self._truth(self.seq, t_s)
            for sink in self.sinks:
                sink.truth(truth, wall_ns)
        if env is not None:
            for sink in self.sinks:
                sink.environment(env, wall_ns)
        self.seq += 1
        self.last = sample
        return sample
