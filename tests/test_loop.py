"""The loop on the simulated stand in virtual time: leveling, state changes and faults."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from test_backend_parity import lock_in_amplitude

from leveler.drivers.base import Block, DriverError, Reading
from leveler.loop.clock import VirtualClock
from leveler.loop.cycle import ENGAGED, FAULT, IDLE, Loop
from leveler.loop.pid import PID, PIDGains
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


class GlitchySensor(FailingSensor):
    """Fails exactly on the listed reads (1-based): garbled replies, not a pulled cable."""

    def __init__(self, inner, bad: set[int]) -> None:  # type: ignore[no-untyped-def]
        super().__init__(inner, fail_at=0)
        self.bad = bad

    def read(self, t_s: float) -> Reading:
        self.n += 1
        if self.n in self.bad:
            raise DriverError(f"garbled reply #{self.n}")
        return self.inner.read(t_s)


class InfiniteSensor(FailingSensor):
    """Claims an OK reading of +inf on the listed reads, as a driver that parsed "inf" would."""

    def __init__(self, inner, bad: set[int]) -> None:  # type: ignore[no-untyped-def]
        super().__init__(inner, fail_at=0)
        self.bad = bad

    def read(self, t_s: float) -> Reading:
        self.n += 1
        r = self.inner.read(t_s)
        return replace(r, value_m=math.inf) if self.n in self.bad else r


def test_a_non_finite_ok_reading_is_held_not_fed_to_the_pid() -> None:
    """Hypothesis found this one: an OK-status inf reached PID.update, which raised."""
    loop, mem, clock = make_loop()
    loop.sensor = InfiniteSensor(loop.sensor, bad={10, 11})
    run(loop, clock, 5)
    loop.engage(0.5)
    run(loop, clock, 10)
    assert loop.state == ENGAGED
    held = [s for s in mem.samples if math.isinf(s.sensor_m)]
    assert len(held) == 2 and all(s.status != 0 for s in held)
    assert all(s.command_v == mem.samples[8].command_v for s in held)
    assert any(e.kind == "bad_reading" and "not finite" in e.reason for e in mem.events)


class GlitchyActuator:
    """Refuses exactly the listed writes (1-based); otherwise the real simulated actuator."""

    def __init__(self, inner, bad: set[int]) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.bad, self.n = inner, bad, 0
        self.safe_v = inner.safe_v

    def write(self, command_v: float, t_s: float) -> float:
        self.n += 1
        if self.n in self.bad:
            raise DriverError(f"exception reply to write #{self.n}")
        return float(self.inner.write(command_v, t_s))

    def make_safe(self) -> bool:
        return self.inner.make_safe()


class UnreachableActuator(GlitchyActuator):
    """The amplifier is gone: every write and every make_safe fails (fresh-eyes run)."""

    def write(self, command_v: float, t_s: float) -> float:
        raise DriverError("cannot connect")

    def make_safe(self) -> bool:
        return False


def test_a_fault_whose_safe_voltage_cannot_be_set_says_so_and_claims_nothing() -> None:
    loop, mem, clock = make_loop()
    run(loop, clock, 5)
    loop.engage(0.5)
    run(loop, clock, 5)
    loop.actuator = UnreachableActuator(loop.actuator, set())  # type: ignore[assignment]
    run(loop, clock, 5)
    assert loop.state == FAULT
    fault = next(e for e in mem.events if e.detail.get("new") == FAULT)
    assert "could NOT be set" in fault.reason
    in_fault = [s for s in mem.samples if s.state == FAULT]
    assert in_fault and all(math.isnan(s.applied_v) for s in in_fault)
    loop.reset(2.0, "reconnected")
    assert loop.held_v == loop.actuator.safe_v and not loop.safe_unconfirmed


def test_isolated_driver_errors_hold_the_voltage_are_counted_and_logged_sparingly() -> None:
    loop, mem, clock = make_loop()
    bad_reads = {20, 21, 40, 41, 42 + 1000}  # two pairs in a row, then one much later
    bad_reads |= set(range(60, 80, 2))  # every other read for 2 s at 10 Hz
    loop.sensor = GlitchySensor(loop.sensor, bad_reads)
    loop.actuator = GlitchyActuator(loop.actuator, {30, 31, 50})  # type: ignore[assignment]
    run(loop, clock, 1)
    loop.engage(0.0)
    run(loop, clock, 119)
    assert loop.state == ENGAGED
    n_bad_reads = len([n for n in bad_reads if n <= 120])
    assert loop.errors == {"sensor": n_bad_reads, "actuator": 3}
    s = mem.samples
    for n in (20, 21, 40, 41):  # the read failed: no update, the held voltage is written again
        assert math.isnan(s[n - 1].sensor_m) and s[n - 1].status == 4
        assert s[n - 1].command_v == s[n - 2].command_v
    assert math.isnan(s[29].applied_v) and math.isnan(s[30].applied_v)  # writes 30, 31 failed
    assert math.isfinite(s[31].applied_v)  # write 32 went through
    errs = [e for e in mem.events if e.kind == "driver_error"]
    # At most one event per second of loop time, and together they account for every error.
    assert all(b.t_s - a.t_s >= 1.0 - 1e-9 for a, b in itertools.pairwise(errs))
    assert errs[0].detail["device"] == "sensor" and "garbled reply #20" in errs[0].reason
    reported = sum(e.detail["since_last_event"] for e in errs)
    assert reported + loop._unreported == n_bad_reads + 3
    assert len(errs) < n_bad_reads + 3  # the every-other-read burst was summarised


def test_errors_in_a_row_fault_and_name_the_count() -> None:
    loop, mem, clock = make_loop()
    loop.sensor = GlitchySensor(loop.sensor, {10, 11, 12})
    run(loop, clock, 1)
    loop.engage(0.0)
    loop.actuator.write(90.0, 0.0)
    run(loop, clock, 10)
    assert loop.state == ENGAGED  # two in a row: ridden through
    run(loop, clock, 1)
    assert loop.state == FAULT
    fault = [e for e in mem.events if e.detail.get("new") == FAULT]
    assert "garbled reply #12 (3 driver errors in a row)" in fault[0].reason
    assert loop.actuator.plant.v_target == loop.actuator.safe_v  # type: ignore[attr-defined]
    run(loop, clock, 5)  # good reads again, but a fault waits for reconnect or reset
    assert loop.state == FAULT and loop.errors["sensor"] == 3


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


def _sub_count_stand(samples_per_cycle: int) -> Config:
    """A 12-bit ADC (24 nm a count at the sensor), zero mid-count, a 100 s cooler sawtooth
    of 0.66 count peak to peak at the sensor and no thermal wander: a signal that never
    crosses a step edge on its own."""
    cfg = Config()
    pl = cfg.plant
    lsb_v = (pl.sensor.adc_max_v - pl.sensor.adc_min_v) / (2**12 - 1)
    sensor_m_per_rad = pl.pendulum.amplification * pl.pendulum.sensor_arm_m
    pl = replace(pl, sensor=replace(pl.sensor, adc_bits=12, offset_v=lsb_v / 2,
                                    samples_per_cycle=samples_per_cycle),
                 thermal=replace(pl.thermal, random_walk_k_per_sqrt_s=0.0, daily_amplitude_k=0.0),
                 cooler=replace(pl.cooler, period_s=100.0, peak_to_peak_rad=0.66 * (
                     lsb_v / pl.sensor.gain_v_per_m) / sensor_m_per_rad),
                 platform=replace(pl.platform, initial_tilt_rad=0.0))
    return replace(cfg, plant=pl)


@pytest.mark.parametrize("samples_per_cycle", [1, 256])
def test_block_reads_averaged_by_the_loop_resolve_below_one_adc_count(
        samples_per_cycle: int) -> None:
    cfg = _sub_count_stand(samples_per_cycle)
    loop, mem, clock = make_loop(cfg)
    block = loop.sensor.read(0.0)
    assert (isinstance(block, Block) and len(block.values_m) == 256) == (samples_per_cycle > 1)
    run(loop, clock, 3000)  # 300 s, loop open: the sensor watches the cooler
    t = np.array([s.t_s for s in mem.samples])
    y = np.array([s.sensor_m for s in mem.samples])
    truth_m = np.array([tr.pendulum_rad for tr in mem.truths]) * cfg.plant.pendulum.sensor_arm_m
    lsb_m = cfg.plant.sensor.lsb_m
    f = 1 / cfg.plant.cooler.period_s
    a_true, a_read = lock_in_amplitude(t, truth_m, f), lock_in_amplitude(t, y, f)
    if samples_per_cycle == 1:  # stuck on one count: the cooler is invisible
        assert len(np.unique(y)) <= 2 and a_read < 0.2 * a_true
    else:  # the mean of 256 dithered conversions follows it, ~1/16 count fine
        assert len(np.unique(y)) > 100
        assert a_read == pytest.approx(a_true, rel=0.1)
        assert np.std(y - truth_m) < 0.1 * lsb_m


class OnceSensor:
    """The real simulated sensor, except one listed reading (1-based) reports `value_m`, OK."""

    def __init__(self, inner, n: int, value_m: float) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.at, self.value_m, self.n = inner, n, value_m, 0

    def read(self, t_s: float) -> Reading:
        self.n += 1
        r = self.inner.read(t_s)
        return replace(r, value_m=self.value_m) if self.n == self.at else r


def test_controller_overflow_faults_safe_never_a_nan_command() -> None:
    """Hypothesis found this one: a finite but absurd OK reading (1e300) while idle, huge
    gains, engage: the PID's arithmetic overflowed and a NaN command reached the plant."""
    loop, mem, clock = make_loop()
    loop.sensor = OnceSensor(loop.sensor, 2, 1e300)
    run(loop, clock, 2)
    loop.pid.set_gains(PIDGains(1e9, 0.0, 1e6))  # 1e9 x 1e300 is no float
    loop.engage(0.2)
    run(loop, clock, 5)
    assert loop.state == FAULT and "controller fault" in loop.fault_reason
    assert loop.actuator.plant.v_target == loop.actuator.safe_v
    assert all(math.isfinite(s.command_v) for s in mem.samples)


def test_simulated_actuator_refuses_a_nan_command() -> None:
    loop, _, _ = make_loop()
    with pytest.raises(DriverError, match="NaN"):
        loop.actuator.write(math.nan, 0.1)


class MovedSensor:
    """The real simulated sensor; `fail` reads raise, and `shift_m` is added to the rest."""

    def __init__(self, inner) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.fail, self.shift_m = inner, 0, 0.0

    def read(self, t_s: float) -> Reading:
        r = self.inner.read(t_s)
        if self.fail:
            self.fail -= 1
            raise DriverError("cable pulled")
        return replace(r, value_m=r.value_m + self.shift_m)


def test_after_a_reset_the_spike_filter_takes_the_first_reading_as_its_new_reference() -> None:
    """The stand moved 1 um while in fault: with a tight max_step_m the first readings after
    the reset must not be rejected as spikes against the last one before the fault."""
    cfg = Config()
    cfg = replace(cfg, loop=replace(cfg.loop, max_step_m=50e-9, spike_reject_max=5))
    loop, mem, clock = make_loop(cfg)
    loop.policy = cfg.loop
    sensor = loop.sensor = MovedSensor(loop.sensor)
    run(loop, clock, 5)
    sensor.fail = 10
    run(loop, clock, 10)
    assert loop.state == FAULT
    sensor.shift_m = 1e-6
    loop.reset(mem.samples[-1].t_s)
    n = len(mem.samples)
    run(loop, clock, 5)
    assert all(s.status == 0 for s in mem.samples[n:])
    assert not any("spike" in e.reason for e in mem.events)
