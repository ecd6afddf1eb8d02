"""The loop on the simulated stand in virtual time: leveling, state changes and faults."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from leveler.clock import VirtualClock
from leveler.drivers.base import DriverError, Reading
from leveler.loop import ENGAGED, FAULT, IDLE, Loop
from leveler.pid import PID
from leveler.records import Event, Sample, Truth
from leveler.settings import Config
from leveler.stand import open_stand


class Memory:
    def __init__(self) -> None:
        self.samples: list[Sample] = []
        self.truths: list[Truth] = []
        self.events: list[Event] = []

    def sample(self, s: Sample, log_time_ns: int) -> None:
        self.samples.append(s)

    def truth(self, t: Truth, log_time_ns: int) -> None:
        self.truths.append(t)

    def event(self, e: Event, log_time_ns: int) -> None:
        self.events.append(e)


def make_loop(cfg: Config | None = None) -> tuple[Loop, Memory, VirtualClock]:
    cfg = cfg or Config()
    stand = open_stand(cfg, seed=2)
    stand.connect()
    mem = Memory()
    dt = 1.0 / cfg.loop.rate_hz
    loop = Loop(stand.sensor, stand.actuator, PID(cfg.controller.pid_config()), dt, [mem],
                stand.truth)
    return loop, mem, VirtualClock(dt, start_wall_ns=0)


def run(loop: Loop, clock: VirtualClock, n: int) -> None:
    for _ in range(n):
        t = clock.tick()
        loop.cycle(t, clock.wall_ns(t))


def test_engaged_loop_pulls_an_offset_tilt_to_the_setpoint() -> None:
    cfg = Config()
    cfg = replace(cfg, plant=replace(cfg.plant, platform=replace(cfg.plant.platform,
                                                                  initial_tilt_rad=2e-6)))
    loop, mem, clock = make_loop(cfg)
    run(loop, clock, 1)
    start = mem.samples[-1].sensor_m
    assert abs(start) > 0.5e-6  # 2 urad x N x arm = 0.9 um
    loop.engage(0.0)
    run(loop, clock, 6000)  # 10 min
    recent = np.array([s.sensor_m for s in mem.samples[-600:]])
    assert abs(recent.mean()) < 0.01 * abs(start)
    assert abs(np.mean([t.tilt_rad for t in mem.truths[-600:]])) < 0.02 * 2e-6
    assert mem.samples[-1].state == ENGAGED
    assert [e.kind for e in mem.events] == ["state"]


def test_idle_holds_the_actuator() -> None:
    loop, mem, clock = make_loop()
    run(loop, clock, 100)
    assert loop.state == IDLE
    assert {s.applied_v for s in mem.samples} == {loop.actuator.safe_v}


def test_engage_is_bumpless() -> None:
    loop, mem, clock = make_loop()
    run(loop, clock, 50)
    loop.engage(clock.tick(), "test")
    run(loop, clock, 1)
    assert abs(mem.samples[-1].command_v - loop.actuator.safe_v) < 0.01


class FailingSensor:
    """Wraps a sensor and fails from the n-th read on."""

    def __init__(self, inner, fail_at: int) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.fail_at, self.n = inner, fail_at, 0

    def connect(self) -> None:
        self.inner.connect()

    def close(self) -> None:
        self.inner.close()

    def read(self, t_s: float) -> Reading:
        self.n += 1
        if self.n >= self.fail_at:
            raise DriverError("cable pulled")
        return self.inner.read(t_s)


def test_sensor_fault_makes_the_actuator_safe_and_is_logged() -> None:
    loop, mem, clock = make_loop()
    loop.sensor = FailingSensor(loop.sensor, fail_at=20)
    run(loop, clock, 5)
    loop.engage(0.5)
    loop.actuator.write(90.0, 0.5)  # move away from the safe voltage
    run(loop, clock, 30)
    assert loop.state == FAULT
    fault = [e for e in mem.events if e.detail.get("new") == FAULT]
    assert len(fault) == 1 and "cable pulled" in fault[0].reason
    assert loop.actuator.plant.v_target == loop.actuator.safe_v  # type: ignore[attr-defined]
    assert math.isnan(mem.samples[-1].sensor_m)
    assert mem.samples[-1].state == FAULT


@pytest.mark.parametrize("seed", [0, 7])
def test_same_seed_gives_identical_samples(seed: int) -> None:
    def once() -> list[tuple[float, ...]]:
        cfg = Config()
        stand = open_stand(cfg, seed=seed)
        stand.connect()
        mem = Memory()
        loop = Loop(stand.sensor, stand.actuator, PID(cfg.controller.pid_config()), 0.1, [mem],
                    stand.truth)
        clock = VirtualClock(0.1, start_wall_ns=0)
        run(loop, clock, 1)
        loop.engage(0.0)
        run(loop, clock, 3000)
        return [(s.sensor_m, s.command_v, s.applied_v) for s in mem.samples]

    assert once() == once()
