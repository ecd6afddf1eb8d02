"""Modbus RTU end to end: the real drivers (pyserial under pymodbus's serial client) against
the emulator's RTU server through real ttys, two pty pairs joined as a null-modem cable.

Every timeout is short (1 s: a loaded CI machine missed 0.25 s on a plain connect) and every
backoff short; ptys ignore the baud rate, so this proves framing and error handling, not line
timing.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import daemon_config

from leveler.drivers.base import DriverError, Status
from leveler.drivers.modbus import ModbusActuator, ModbusSensor
from leveler.drivers.modbus_config import ModbusActuatorConfig, ModbusSensorConfig
from leveler.emulate.modbus import ModbusEmulator
from leveler.sim.params import PlantParams
from leveler.sim.plant import Plant

FAST = {"timeout_s": 1.0, "reconnect_min_s": 0.2, "reconnect_max_s": 0.8}
RTU = {"transport": "rtu", "serial_port": "/dev/unused-until-the-emulator-starts", **FAST}


@dataclasses.dataclass
class Rig:
    plant: Plant
    emu: ModbusEmulator
    sensor_cfg: ModbusSensorConfig
    actuator_cfg: ModbusActuatorConfig


@pytest.fixture
def rig() -> Iterator[Rig]:
    plant = Plant(PlantParams(), dt_s=0.01, seed=1)
    s, a = ModbusSensorConfig(**RTU), ModbusActuatorConfig(**RTU)  # type: ignore[arg-type]
    with ModbusEmulator(plant, s, a, transport="rtu") as emu:
        yield Rig(plant, emu, dataclasses.replace(s, serial_port=emu.serial_port),
                  dataclasses.replace(a, serial_port=emu.serial_port))


@pytest.fixture
def sensor(rig: Rig) -> Iterator[ModbusSensor]:
    s = ModbusSensor(rig.sensor_cfg)
    s.connect()
    yield s
    s.close()


def _assert_reads_plant(rig: Rig, sensor: ModbusSensor) -> None:
    reading = sensor.read(0.0)
    _, plant_m, _ = rig.plant.measure()  # the plant only steps when the server is asked
    cfg = rig.sensor_cfg
    assert reading.status is Status.OK
    assert abs(reading.value_m - plant_m) <= cfg.m_per_v * cfg.volts_per_count


def test_sensor_and_actuator_share_the_line_and_drive_the_plant(rig: Rig,
                                                                 sensor: ModbusSensor) -> None:
    """One port, one client: the second driver on the line must not be locked out."""
    actuator = ModbusActuator(rig.actuator_cfg)
    actuator.connect()
    for _ in range(3):
        _assert_reads_plant(rig, sensor)
    v0 = rig.plant.v_applied
    applied = [actuator.write(90.0, 0.05 * k) for k in range(6)]
    assert applied[0] == pytest.approx(v0, abs=0.04)  # first write: no time yet, hold
    assert applied[-1] == pytest.approx(90.0, abs=0.04)  # 100 V/s x 0.25 s > 15 V
    assert rig.emu.received_v == applied
    assert rig.plant.v_target == applied[-1]
    time.sleep(0.1)
    _assert_reads_plant(rig, sensor)  # the next request steps the plant towards the target
    assert rig.plant.v_applied > v0 + 5.0
    actuator.close()


def test_channels_on_one_line_must_agree_on_its_settings(rig: Rig,
                                                         sensor: ModbusSensor) -> None:
    slower = dataclasses.replace(rig.actuator_cfg, baudrate=19200)
    with pytest.raises(ValueError, match=r"another channel on this serial port has baudrate"):
        ModbusActuator(slower)


@pytest.mark.parametrize(("code", "meaning"), [(4, "SLAVE_DEVICE_FAILURE"),
                                               (2, "ILLEGAL_DATA_ADDRESS")])
def test_exception_reply_is_a_clear_error_and_the_line_stays_open(
        rig: Rig, sensor: ModbusSensor, code: int, meaning: str) -> None:
    rig.emu.inject("exception", code=code)
    with pytest.raises(DriverError) as err:
        sensor.read(0.0)
    msg = str(err.value)
    for part in (f"rtu {rig.emu.serial_port} @ 9600 Bd device 1", "input register 0",
                 f"exception {code}", meaning):
        assert part in msg
    _assert_reads_plant(rig, sensor)  # no reconnect needed: the device answered


@pytest.mark.parametrize(("kind", "says"), [("no_reply", "no valid reply within 1.0 s"),
                                            ("garbage", "no valid reply"),
                                            ("drop", "connection lost")])
def test_line_fault_is_a_clear_error_then_backoff_then_recovery(
        rig: Rig, sensor: ModbusSensor, kind: str, says: str) -> None:
    rig.emu.inject(kind)  # type: ignore[arg-type]
    t0 = time.monotonic()
    with pytest.raises(DriverError, match=says) as err:
        sensor.read(0.0)
    assert time.monotonic() - t0 < 1.8  # bounded by timeout_s
    assert f"rtu {rig.emu.serial_port} @ 9600 Bd device 1" in str(err.value)
    with pytest.raises(DriverError, match="next reconnect attempt in"):
        sensor.read(0.0)  # within the backoff wait: fails at once
    time.sleep(rig.sensor_cfg.reconnect_min_s)
    _assert_reads_plant(rig, sensor)  # reopened at the same path (a new pty after "drop")


def test_emulate_command_serves_rtu_at_the_configured_port(tmp_path: Path) -> None:
    port = tmp_path / "modbus"
    config = daemon_config(tmp_path, tmp_path / "unused.sock", base="lab-modbus.toml",
                           replace={'transport = "tcp"':
                                    f'transport = "rtu"\nserial_port = "{port}"'})
    emu = subprocess.Popen([sys.executable, "-m", "leveler.cli", "emulate", "modbus",
                            "--config", str(config)], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        assert emu.stdout is not None
        line = emu.stdout.readline()  # printed once the server serves
        assert f"Modbus RTU at {port}" in line, emu.communicate(timeout=10)
        assert port.is_symlink()
        cfg = dataclasses.replace(ModbusSensorConfig(**RTU), serial_port=str(port))  # type: ignore[arg-type]
        sensor = ModbusSensor(cfg)
        sensor.connect()
        reading = sensor.read(0.0)
        sensor.close()
        assert reading.status is Status.OK
        assert abs(reading.value_m) < 2e-6  # the 1 urad start tilt reads ~0.45 um
        emu.terminate()
        assert emu.communicate(timeout=10)[0].startswith("leveler emulate modbus: stopped")
        assert not port.exists() and not port.is_symlink()  # the link went with it
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.communicate(timeout=10)


def test_emulate_command_will_not_link_over_a_real_file(tmp_path: Path) -> None:
    port = tmp_path / "ttyUSB0"
    port.write_text("not a tty")
    config = daemon_config(tmp_path, tmp_path / "unused.sock", base="lab-modbus.toml",
                           replace={'transport = "tcp"':
                                    f'transport = "rtu"\nserial_port = "{port}"'})
    out = subprocess.run([sys.executable, "-m", "leveler.cli", "emulate", "modbus",
                          "--config", str(config)], capture_output=True, text=True, timeout=30)
    assert out.returncode != 0
    assert f"{config}: sensor.modbus.serial_port '{port}' is not a path" in out.stderr
    assert port.read_text() == "not a tty"
