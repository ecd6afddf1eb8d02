"""Property: whatever the readings, gains, setpoints, limits and requests do, the piezo stays
inside its range and slew limit, and every fault leaves it at its safe voltage.

The loop drives the simulated stand in virtual time; Hypothesis draws a sequence of
operations (cycles with corrupted readings, tune, engage/stop, modulate, reset) and checks the
voltage the piezo actually saw after every cycle.
"""

from __future__ import annotations

import math
from dataclasses import replace

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from leveler.drivers.base import DriverError, Reading, Status
from leveler.loop.clock import VirtualClock
from leveler.loop.cycle import FAULT, Loop
from leveler.loop.pid import PID, ControllerConfig, PIDGains
from leveler.settings import Config
from leveler.stand import open_stand

DT_S = 0.1
readings = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300, 0.0, 5e-6, -5e-6]),
)
ops = st.one_of(
    st.tuples(st.just("cycle"), st.integers(1, 30)),
    st.tuples(st.just("reading"), readings, st.sampled_from(list(Status))),
    st.tuples(st.just("read_error"), st.integers(1, 5)),
    st.tuples(st.just("write_error"), st.integers(1, 5)),
    st.tuples(st.just("gains"), st.floats(0, 1e9), st.floats(0, 1e9), st.floats(0, 1e6)),
    st.tuples(st.just("setpoint"), st.floats(-1e-3, 1e-3)),
    st.tuples(st.just("limits"), st.floats(-50, 200), st.floats(-50, 200)),
    st.tuples(st.just("slew"), st.floats(1e-3, 1e6)),
    st.tuples(st.just("engage"),), st.tuples(st.just("stop"),), st.tuples(st.just("reset"),),
    st.tuples(st.just("modulate"), st.floats(0.01, 100), st.floats(0.1, 10), st.integers(1, 3)),
)


class Tamper:
    """The real simulated sensor/actuator, with the next reads or writes spoiled on demand."""

    def __init__(self, stand: object) -> None:
        self.inner = stand
        self.safe_v = stand.safe_v  # type: ignore[attr-defined]
        self.next_reading: Reading | None = None
        self.read_errors = 0
        self.write_errors = 0

    def connect(self) -> None:
        self.inner.connect()  # type: ignore[attr-defined]

    def close(self) -> None:
        self.inner.close()  # type: ignore[attr-defined]

    def read(self, t_s: float) -> Reading:
        if self.read_errors:
            self.read_errors -= 1
            raise DriverError("tampered read")
        real = self.inner.read(t_s)  # type: ignore[attr-defined]
        r, self.next_reading = self.next_reading, None
        return real if r is None else Reading(t_s, 0, r.value_m, r.status)

    def write(self, command_v: float, t_s: float) -> float:
        if self.write_errors:
            self.write_errors -= 1
            raise DriverError("tampered write")
        return float(self.inner.write(command_v, t_s))  # type: ignore[attr-defined]

    def make_safe(self) -> bool:
        return self.inner.make_safe()  # type: ignore[attr-defined, no-any-return]


def _tuned(c: ControllerConfig, op: tuple) -> ControllerConfig:
    """The controller settings after a tune op; ValueError if the daemon would refuse them."""
    if op[0] == "gains":
        return replace(c, kp_v_per_m=op[1], ki_v_per_m_s=op[2], kd_v_s_per_m=op[3])
    if op[0] == "setpoint":
        return replace(c, setpoint_m=op[1])
    if op[0] == "limits":
        return replace(c, output_min_v=min(op[1:]), output_max_v=max(op[1:]))
    return replace(c, slew_v_per_s=op[1])


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(ops, max_size=40))
def test_piezo_stays_in_range_and_slew_and_faults_leave_it_safe(sequence: list[tuple]) -> None:
    cfg = Config()
    stand = open_stand(cfg, seed=1)
    stand.connect()
    plant = stand.sensor.plant  # type: ignore[attr-defined]
    pz = cfg.plant.piezo
    dev = Tamper(stand.sensor)
    loop = Loop(dev, dev, PID(cfg.controller.pid_config()), DT_S, [], policy=cfg.loop)
    clock = VirtualClock(DT_S, start_wall_ns=0)
    t = clock.tick()
    loop.cycle(t, 0)
    controller = cfg.controller

    def cycle() -> None:
        nonlocal t
        before, n = plant.v_applied, plant.n
        t = clock.tick()
        loop.cycle(t, 0)  # its read steps the plant to t (none if the read failed)
        assert pz.min_v <= plant.v_applied <= pz.max_v
        steps = plant.n - n
        assert abs(plant.v_applied - before) <= pz.slew_v_per_s * DT_S * steps + 1e-9
        if loop.state == FAULT:
            assert plant.v_target == dev.safe_v

    for op in sequence:
        kind = op[0]
        if kind == "cycle":
            for _ in range(op[1]):
                cycle()
        elif kind == "reading":
            dev.next_reading = Reading(t, 0, op[1], op[2])
            cycle()
        elif kind == "read_error":
            dev.read_errors = op[1]
            cycle()
        elif kind == "write_error":
            dev.write_errors = op[1]
            cycle()
        elif kind in ("gains", "setpoint", "limits", "slew"):
            try:
                new = _tuned(controller, op)
                new.pid_config()
            except ValueError:
                continue  # the daemon refuses it the same way (tune validates first)
            controller = new  # applied as the daemon's tune applies it
            pid = loop.pid
            pid.set_limits(new.output_min_v, new.output_max_v)
            pid.set_slew(new.slew_v_per_s)
            pid.set_setpoint(new.setpoint_m)
            pid.set_gains(PIDGains(new.kp_v_per_m, new.ki_v_per_m_s, new.kd_v_s_per_m))
        elif kind == "engage":
            loop.engage(t)
        elif kind == "stop":
            loop.disengage(t)
        elif kind == "reset":
            loop.reset(t)
        elif kind == "modulate":
            try:
                loop.modulate(t, op[1], op[2], op[3])
            except ValueError:
                pass  # refused: not idle, or the wave would leave the output range
        if loop.state == FAULT:
            assert plant.v_target == dev.safe_v
