"""Every fault of the `[[sim.faults]]` schedule, and the loop's defined reaction to it: hold,
fault with the piezo safe, automatic recovery, and the event that records it."""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
from test_loop import Memory

from leveler.drivers.simulated_config import FaultSpec
from leveler.log.reader import read_log
from leveler.loop.clock import VirtualClock
from leveler.loop.cycle import ENGAGED, FAULT, Loop
from leveler.loop.pid import PID
from leveler.settings import Config
from leveler.stand import open_stand

RATE_HZ = 10.0


def run_with(*faults: FaultSpec, seconds: float = 12.0, **policy: object
             ) -> tuple[Loop, Memory]:
    """The default stand in virtual time, engaged from t = 0, with a fault schedule."""
    cfg = Config()
    cfg = replace(cfg, sim=replace(cfg.sim, faults=faults),
                  loop=replace(cfg.loop, **policy))  # type: ignore[arg-type]
    stand = open_stand(cfg, seed=4)
    stand.connect()
    mem = Memory()
    dt = 1 / RATE_HZ
    loop = Loop(stand.sensor, stand.actuator, PID(cfg.controller.pid_config()), dt, [mem],
                stand.truth, policy=cfg.loop)
    clock = VirtualClock(dt, start_wall_ns=0)
    t = clock.tick()
    loop.cycle(t, 0)
    loop.engage(t)
    for _ in range(round(seconds * RATE_HZ)):
        t = clock.tick()
        loop.cycle(t, 0)
    return loop, mem


def _window(mem: Memory, a: float, b: float) -> list[int]:
    return [i for i, s in enumerate(mem.samples) if a - 1e-9 <= s.t_s < b - 1e-9]


def _events(mem: Memory, kind: str) -> list[str]:
    return [e.reason for e in mem.events if e.kind == kind]


@pytest.mark.parametrize(("kind", "status", "says"), [("nan", 2, "invalid"),
                                                     ("railed", 3, "railed")])
def test_bad_readings_hold_the_voltage_then_fault_if_they_persist(
        kind: str, status: int, says: str) -> None:
    loop, mem = run_with(FaultSpec(kind, at_s=3.0, duration_s=1.0))  # type: ignore[arg-type]
    bad = _window(mem, 3.0, 4.0)
    assert len(bad) == 10 and all(mem.samples[i].status == status for i in bad)
    held = mem.samples[bad[0] - 1].command_v
    assert all(mem.samples[i].command_v == held for i in bad)  # no update on a bad reading
    assert loop.state == ENGAGED and loop.bad_readings == 10
    assert _events(mem, "bad_reading") == [f"sensor reading {says}" + (
        " (NaN or unparsable)" if kind == "nan" else " (at the end of the sensor's range)")
        + "; voltage held", "readings good again after 10 bad"]
    loop, mem = run_with(FaultSpec(kind, at_s=3.0, duration_s=6.0))  # type: ignore[arg-type]
    assert loop.state == FAULT  # 50 in a row (5 s)
    assert f"50 bad sensor readings in a row (first: {says}" in loop.fault_reason
    assert loop.actuator.plant.v_target == loop.actuator.safe_v  # type: ignore[attr-defined]


def test_a_stuck_sensor_is_caught_when_detection_is_on() -> None:
    spec = FaultSpec("stuck", at_s=3.0, duration_s=3.0)
    loop, mem = run_with(spec)  # off by default: a frozen value passes as good
    assert all(mem.samples[i].status == 0 for i in _window(mem, 3.0, 6.0))
    loop, mem = run_with(spec, stuck_after_samples=20)
    frozen = _window(mem, 3.0, 6.0)
    flagged = [i for i in frozen if mem.samples[i].status == 2]
    # The first frozen reading repeats the one before (and a quantized reading may repeat
    # naturally just before): flagged from about the 20th identical one to the end.
    assert frozen[0] + 19 - 3 <= flagged[0] <= frozen[0] + 19
    assert flagged == list(range(flagged[0], frozen[-1] + 1))
    assert _events(mem, "bad_reading")[0].startswith("sensor reading stuck (20 identical")
    assert loop.state == ENGAGED


def test_spikes_are_rejected_and_a_lasting_level_is_accepted() -> None:
    _, mem = run_with(FaultSpec("spike", at_s=3.0, size=1e-6), max_step_m=50e-9)
    (i,) = _window(mem, 3.0, 3.1)
    assert mem.samples[i].status == 2
    assert mem.samples[i].command_v == mem.samples[i - 1].command_v
    assert re.search(r"spike \(\+99\d\.\d nm", _events(mem, "bad_reading")[0])
    _, mem = run_with(FaultSpec("spike", at_s=3.0, duration_s=2.0, size=1e-6),
                      max_step_m=50e-9)
    statuses = [mem.samples[i].status for i in _window(mem, 3.0, 5.0)]
    assert statuses[:3] == [2, 2, 2] and set(statuses[3:]) == {0}  # then accepted as real


def test_timeouts_and_write_failures_ride_through_until_too_many_in_a_row() -> None:
    loop, mem = run_with(FaultSpec("timeout", at_s=3.0, duration_s=0.2),
                         FaultSpec("write_fail", at_s=6.0))
    assert loop.state == ENGAGED and loop.errors == {"sensor": 2, "actuator": 1}
    assert any("injected timeout" in r for r in _events(mem, "driver_error"))
    (w,) = _window(mem, 6.0, 6.1)
    assert math.isnan(mem.samples[w].applied_v)
    loop, mem = run_with(FaultSpec("timeout", at_s=3.0, duration_s=1.0))
    assert loop.state == FAULT and "3 driver errors in a row" in loop.fault_reason


def test_a_disconnect_faults_safe_and_the_daemon_reconnects_and_resumes_after_good_samples(
        start_daemon: Callable[..., object]) -> None:
    faults = ('[[sim.faults]]\nkind = "disconnect"\nat_s = 3.0\nduration_s = 3.0\n'
              '[[sim.faults]]\nkind = "clock_step"\nat_s = 2.0\nsize = 3600.0\n')
    d = start_daemon(rate_hz=20.0, sim=faults, replace={
        "engage_on_start = true": "engage_on_start = true\nreconnect_min_s = 0.5"})
    deadline = time.monotonic() + 30
    while True:  # engaged again after one fault (the count: a poll could miss the fault)
        st = json.loads(d.cli("status", "--json").stdout)  # type: ignore[attr-defined]
        if st["state"] == "engaged" and st["faults"] == 1:
            break
        assert time.monotonic() < deadline, st
        time.sleep(0.1)
    d.stop()  # type: ignore[attr-defined]
    log = read_log(next(d.logs.glob("*.mcap")))  # type: ignore[attr-defined]
    ev = log.events
    fault = next(e for e in ev if e["kind"] == "state" and e["detail"]["new"] == "fault")
    assert "injected disconnect" in fault["reason"] and 3.0 <= fault["t_s"] < 3.5
    reconnects = [e for e in ev if e["kind"] == "reconnect"]
    assert reconnects[-1]["reason"] == "devices answer again" and reconnects[-1]["t_s"] >= 6.0
    assert any(e["reason"].startswith("failed:") for e in reconnects)  # tried while unplugged
    resume = next(e for e in ev if e["kind"] == "state" and e["reason"].startswith(
        "resume after reconnect"))
    assert "(10 good readings)" in resume["reason"]
    clock = [e for e in ev if e["kind"] == "clock"]
    assert len(clock) == 1 and "stepped by +3600.0" in clock[0]["reason"]
    t_log = np.asarray(log.samples["log_time_ns"], dtype=np.int64)
    assert np.all(np.diff(t_log) > 0)  # log times stay in order across the step
    assert (t_log[-1] - t_log[0]) / 1e9 < 60  # and the hour is not in them
