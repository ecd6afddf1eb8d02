"""The exit paths the other tests do not take, checked on the device's side of the wire: an
unexpected exception inside the loop (a driver raising something that is not a DriverError, a
bug in the cycle) and SIGHUP reloads, accepted and rejected.

The daemon is a real process on config/lab-modbus.toml; the Modbus emulator runs in this
process, so `received_v` is every voltage that reached the amplifier's input (as in
tests/test_dropped_link.py). The exception is injected into the daemon process by a
`sitecustomize` module on its PYTHONPATH (written by this test, nothing in leveler): from the
moment a trigger file exists, one chosen method raises.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from conftest import daemon_config
from test_backend_parity import free_port

from leveler.emulate.modbus import ModbusEmulator
from leveler.log.reader import read_log
from leveler.settings import load_config
from leveler.sim.plant import Plant

SAFE_V = 60.0  # the piezo's voltage after a fault or a stop (75 V in lab-modbus.toml)
ACT_MIN_V, ACT_MAX_V, ACT_SLEW_V_PER_S = 0.0, 150.0, 100.0  # [actuator.modbus] of lab-modbus
VOLT_PER_COUNT = 150.0 / 65535  # 16-bit AO behind a 15x amplifier

HOOK = '''\
"""Test hook of tests/test_exit_paths.py: once the file $LEVELER_TEST_RAISE_WHEN exists,
each of $LEVELER_TEST_RAISE_IN (module.Class.method, comma-separated) raises
$LEVELER_TEST_RAISE (a builtin exception)."""
import builtins
import importlib
import os

_trigger = os.environ.get("LEVELER_TEST_RAISE_WHEN")


def _patch(where, exc):
    module, cls, name = where.rsplit(".", 2)
    owner = getattr(importlib.import_module(module), cls)
    original = getattr(owner, name)

    def maybe_raise(self, *args, **kwargs):
        if os.path.exists(_trigger):
            raise exc(f"injected by the test: {where}")
        return original(self, *args, **kwargs)

    setattr(owner, name, maybe_raise)


if _trigger:
    for _where in os.environ["LEVELER_TEST_RAISE_IN"].split(","):
        _patch(_where, getattr(builtins, os.environ["LEVELER_TEST_RAISE"]))
'''


def _wait_state(d: object, state: str, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        st = json.loads(d.cli("status", "--json").stdout)  # type: ignore[attr-defined]
        if st["state"] == state:
            return st
        assert time.monotonic() < deadline, f"never {state}: {st['state']}"
        time.sleep(0.1)


@contextmanager
def _modbus_emulator(tmp_path: Path) -> Iterator[tuple[ModbusEmulator, dict[str, str]]]:
    """The emulated module of lab-modbus.toml on a free port; yields it and the config
    replacements that point a daemon at it (with safe_v = SAFE_V)."""
    replace = {"port = 5020": f"port = {free_port()}", "safe_v = 75.0": f"safe_v = {SAFE_V}"}
    (tmp_path / "emu").mkdir()
    cfg, _ = load_config(daemon_config(tmp_path / "emu", tmp_path / "unused.sock",
                                       rate_hz=10.0, base="lab-modbus.toml", replace=replace))
    s, a = cfg.sensor.modbus, cfg.actuator.modbus
    assert s is not None and a is not None
    assert (a.min_v, a.max_v, a.slew_v_per_s, a.safe_v) == (ACT_MIN_V, ACT_MAX_V,
                                                            ACT_SLEW_V_PER_S, SAFE_V)
    with ModbusEmulator(Plant(cfg.plant, 1.0 / cfg.loop.rate_hz, cfg.sim.seed), s, a,
                        port=s.port) as emu:
        yield emu, replace


def _on_the_wire(received: list[float]) -> np.ndarray:
    v = np.round(np.asarray(received), 2)
    assert len(v) > 20
    assert np.all((v >= ACT_MIN_V) & (v <= ACT_MAX_V))
    return v


def _raise_in_daemon(start_daemon: Callable[..., object], tmp_path: Path, where: str,
                     exc: str) -> tuple[str, np.ndarray]:
    """A daemon on the emulated module, engaged for a few seconds until `where` raises `exc`;
    waits for it to exit and returns its stderr and the voltages on the wire."""
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(HOOK)
    trigger = tmp_path / "raise-now"
    with _modbus_emulator(tmp_path) as (emu, replace):
        d = start_daemon(rate_hz=10.0, base="lab-modbus.toml", replace=replace, env={
            "PYTHONPATH": str(hook), "LEVELER_TEST_RAISE_WHEN": str(trigger),
            "LEVELER_TEST_RAISE_IN": where, "LEVELER_TEST_RAISE": exc})
        _wait_state(d, "engaged", 15.0)
        time.sleep(4.0)  # leveling moves the piezo away from safe_v (where it starts)
        trigger.touch()
        _, err = d.proc.communicate(timeout=20)  # type: ignore[attr-defined]
        received = list(emu.received_v)
    # It stops: a traceback and a non-zero status, so systemd (Restart=on-failure) restarts it.
    assert d.proc.returncode == 1, err  # type: ignore[attr-defined]
    assert f"{exc}: injected by the test: {where.split(',')[0]}" in err
    assert not d.socket.exists()  # type: ignore[attr-defined]  # the control socket is gone
    return err, _on_the_wire(received)


@pytest.mark.parametrize(("where", "exc"), [
    ("leveler.drivers.modbus.ModbusSensor.read", "ValueError"),  # a driver bug, not DriverError
    ("leveler.drivers.modbus.ModbusActuator.write", "TypeError"),  # ... on the write side
    ("leveler.loop.pid.PID.update", "ZeroDivisionError"),  # a bug inside the cycle itself
])
def test_an_unexpected_exception_leaves_the_piezo_safe_and_the_log_finished(
        start_daemon: Callable[..., object], tmp_path: Path, where: str, exc: str) -> None:
    _, wire = _raise_in_daemon(start_daemon, tmp_path, where, exc)
    # The log is finished (summary and footer) and says what stopped the loop.
    (log_path,) = (tmp_path / "logs").glob("*.mcap")
    log = read_log(log_path)
    assert log.complete
    stop = log.events[-1]
    assert stop["kind"] == "stop" and stop["reason"] == (
        f"unexpected {exc}: injected by the test: {where}"), stop
    last_state = [e for e in log.events if e["kind"] == "state"][-1]
    assert last_state["detail"]["new"] == "idle" and last_state["reason"] == stop["reason"]
    # The last word on the wire is safe_v, after what the loop last applied (which was not).
    last_applied = round(float(log.samples["applied_v"][-1]), 2)
    assert abs(last_applied - SAFE_V) > 0.3, last_applied
    assert wire[-1] == SAFE_V, wire[-10:]
    assert last_applied in wire[-4:-1], (last_applied, wire[-10:])


def test_a_log_that_fails_with_the_loop_still_gets_the_piezo_safe_and_the_file_finished(
        start_daemon: Callable[..., object], tmp_path: Path) -> None:
    """The exception comes from the log itself, and its last events fail too: the piezo is
    made safe before any of them, and the file is still finished, the socket removed."""
    err, wire = _raise_in_daemon(
        start_daemon, tmp_path,
        "leveler.log.rotate.RotatingLog.sample,leveler.log.rotate.RotatingLog.event", "OSError")
    assert "RotatingLog.event" in err  # the stop event failed as well
    assert wire[-1] == SAFE_V and wire[-2] != SAFE_V, wire[-10:]
    log = read_log(next((tmp_path / "logs").glob("*.mcap")))
    assert log.complete  # summary and footer: nothing to recover
    assert [e["kind"] for e in log.events][-1] != "stop"  # that event could not be handed on
    assert len(log.samples["seq"]) > 30


def test_reloads_keep_the_piezo_in_range_and_slew_and_stop_leaves_it_safe(
        start_daemon: Callable[..., object], tmp_path: Path) -> None:
    """SIGHUP with a new gain and an output range that excludes the piezo's voltage (applied at
    once: the controller's output jumps into it, and only the actuator's own slew limit stands
    between that jump and the piezo), and a new safe_v (needs a restart: the running one
    stays); then two files that fail (a bad value, broken TOML). The loop stays engaged
    throughout; every voltage on the wire is in range and within the slew limit in force;
    SIGTERM leaves the running safe_v."""
    with _modbus_emulator(tmp_path) as (emu, replace):
        d = start_daemon(rate_hz=10.0, base="lab-modbus.toml", replace=replace)
        cfg_path: Path = d.config  # type: ignore[attr-defined]
        good = cfg_path.read_text()
        _wait_state(d, "engaged", 15.0)
        time.sleep(1.0)  # past the start, when the piezo goes from where it was to safe_v
        n_settled = len(emu.received_v)
        time.sleep(1.0)
        held_v = emu.received_v[-1]
        assert held_v > 55.0  # leveling moves it up from safe_v (towards about 75 V)
        new = good.replace("output_max_v = 150.0", "output_max_v = 40.0").replace(
            "ki_v_per_m_s = 7.0e5", "ki_v_per_m_s = 5.0e5").replace(
            f"safe_v = {SAFE_V}", "safe_v = 30.0")
        assert new.count("output_max_v = 40.0") == 1 and "safe_v = 30.0" in new
        assert "ki_v_per_m_s = 5.0e5" in new
        cfg_path.write_text(new)
        d.proc.send_signal(signal.SIGHUP)  # type: ignore[attr-defined]
        deadline = time.monotonic() + 10
        while _wait_state(d, "engaged", 5.0)["controller"]["output_max_v"] != 40.0:
            assert time.monotonic() < deadline, "the reload was not applied"
            time.sleep(0.1)
        time.sleep(2.0)
        for broken in (new.replace("output_max_v = 40.0", "output_max_v = -1.0"),
                       new.replace("[controller]", "[controller")):
            cfg_path.write_text(broken)
            d.proc.send_signal(signal.SIGHUP)  # type: ignore[attr-defined]
            time.sleep(1.0)
            st = _wait_state(d, "engaged", 1.0)
            assert st["controller"]["output_max_v"] == 40.0
            assert st["controller"]["ki_v_per_m_s"] == 5.0e5
        err = d.stop()  # type: ignore[attr-defined]
        received = list(emu.received_v)
    assert d.proc.returncode == 0, err  # type: ignore[attr-defined]
    log = read_log(next((tmp_path / "logs").glob("*.mcap")))
    assert log.complete
    reloads = [e for e in log.events if e["kind"] == "reload"]
    assert [e["reason"].split(":")[0] for e in reloads] == ["applied", "rejected", "rejected"]
    assert reloads[0]["detail"]["needs_restart"] == ["actuator"]
    states = [e["detail"]["new"] for e in log.events if e["kind"] == "state"]
    assert states == ["engaged", "idle"]  # engaged from the start to SIGTERM
    # The log's `applied` is what the driver sent, at loop time t_s: the actuator's slew held
    # through the jump (which it took at full slew), the controller's own (1 V a cycle)
    # before and after it.
    s = log.samples
    t, applied = np.asarray(s["t_s"]), np.round(np.asarray(s["applied_v"]), 2)
    assert np.all(np.isfinite(applied)) and np.all(np.diff(t) > 0)
    dv, dt = np.abs(np.diff(applied)), np.diff(t)
    late = t[1:] >= 1.0  # past the start
    assert np.all(dv[late] <= ACT_SLEW_V_PER_S * dt[late] + VOLT_PER_COUNT + 0.01)
    jump = late & (dv > 10.0 * dt + VOLT_PER_COUNT + 0.01)
    assert jump.sum() >= 2 and dv[jump].max() >= 0.9 * ACT_SLEW_V_PER_S * 0.1, dv[jump]
    assert np.all(t[1:][jump] >= reloads[0]["t_s"])
    assert np.all(applied[t >= reloads[0]["t_s"] + 1.0] <= 40.0)
    # On the wire: the same voltages, all in range, and SIGTERM's make_safe last.
    wire = _on_the_wire(received)
    assert set(np.unique(wire[n_settled:-1])) <= set(np.unique(applied))
    assert np.all(wire[n_settled:-1] <= round(held_v, 2) + 1.0)
    assert wire[-2] <= 40.0
    assert wire[-1] == SAFE_V, wire[-5:]  # the running safe_v, not the reloaded one
