"""The serial drivers against the device emulator over real ptys: protocol, faults, limits."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leveler.drivers.base import Actuator, DriverError, Sensor, Status
from leveler.drivers.piezo_serial import SerialPiezo
from leveler.drivers.sensor_serial import SerialSensor
from leveler.drivers.serial_config import SerialPiezoConfig, SerialSensorConfig
from leveler.emulate.serial import FAULT_KINDS, SensorFormat, SerialEmulator
from leveler.sim.params import PlantParams
from leveler.sim.plant import Plant
from leveler.typed_config import ConfigError, build

PROTOCOLS = {"thorlabs_mdt": "x", "pi_gcs2": "1"}  # protocol -> axis
# what each fault must say (DriverError text), besides naming port and command
FAULT_TEXT = {"no_reply": "no reply", "garbage": "garbled reply",
              "partial_line": "incomplete reply",
              "drop": "device disconnected|Input/output error",
              "error": "CMD_NOT_DEFINED|device error 7|unparsable reply 'ERROR'"}


def emulator(protocol: Any = "thorlabs_mdt", **kwargs: Any) -> SerialEmulator:
    return SerialEmulator(Plant(PlantParams(), dt_s=0.01, seed=1), protocol, **kwargs)


def piezo_for(emu: SerialEmulator, protocol: Any, **cfg: Any) -> SerialPiezo:
    """A connected driver for the emulated amplifier."""
    piezo = SerialPiezo(SerialPiezoConfig(port=emu.piezo_port, protocol=protocol,
                                          axis=PROTOCOLS[protocol], **cfg))
    piezo.connect()
    return piezo


def sensor_for(emu: SerialEmulator, **cfg: Any) -> SerialSensor:
    """A connected driver for the emulated sensor controller."""
    sensor = SerialSensor(SerialSensorConfig(port=emu.sensor_port, **cfg))
    sensor.connect()
    return sensor


@pytest.fixture(params=list(PROTOCOLS))
def stand(request: pytest.FixtureRequest) -> Iterator[tuple[SerialEmulator, SerialPiezo]]:
    with emulator(request.param) as emu:
        piezo = piezo_for(emu, request.param)
        yield emu, piezo
        piezo.close()


def test_drivers_satisfy_the_protocols() -> None:
    assert isinstance(SerialPiezo(SerialPiezoConfig()), Actuator)
    assert isinstance(SerialSensor(SerialSensorConfig()), Sensor)


def test_round_trip_plant_follows(stand: tuple[SerialEmulator, SerialPiezo]) -> None:
    emu, piezo = stand
    assert piezo.write(80.0, 0.0) == 75.0  # no elapsed time yet: holds the read-back output
    assert piezo.write(80.0, 1.0) == 80.0  # 10 V/s for 1 s allows the whole 5 V
    assert emu.received_v == [75.0, 80.0]
    assert emu.plant.v_target == 80.0
    time.sleep(0.1)  # the plant slews 100 V/s in wall time
    assert piezo.read_v() == pytest.approx(80.0, abs=0.01)
    assert emu.plant.v_applied == pytest.approx(80.0)


@pytest.mark.parametrize("fmt", [SensorFormat(), SensorFormat(unit_m=1e-9, decimals=0)])
def test_sensor_reads_plant_displacement(fmt: SensorFormat) -> None:
    with emulator(sensor_format=fmt) as emu:
        sensor = sensor_for(emu, scale_m_per_unit=fmt.unit_m)
        time.sleep(0.05)
        reading = sensor.read(1.5)
        _, value_m, _ = emu.plant.measure()  # the plant does not move between requests
        assert reading.t_s == 1.5 and reading.status is Status.OK
        assert reading.value_m == pytest.approx(value_m, abs=fmt.resolution_m / 2 + 1e-15)
        expected_counts = round(value_m / fmt.unit_m) if fmt.decimals == 0 else 0
        assert reading.raw_counts == expected_counts
        sensor.close()


def test_sensor_outside_range_is_railed() -> None:
    with emulator() as emu:
        _, value_m, _ = emu.plant.measure()
        sensor = sensor_for(emu, min_m=value_m + 1e-6, max_m=value_m + 2e-6)
        assert sensor.read(0.0).status is Status.RAILED
        sensor.close()


def test_connect_refuses_amplifier_limited_below_max_v() -> None:
    with emulator(vlimit_v=100.0) as emu:
        with pytest.raises(DriverError, match=r"limit 100.0 V is below max_v = 150.0 V"):
            piezo_for(emu, "thorlabs_mdt")
        piezo_for(emu, "thorlabs_mdt", max_v=100.0, safe_v=50.0).close()


@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_piezo_fault_raises_then_recovers(stand: tuple[SerialEmulator, SerialPiezo],
                                          kind: Any) -> None:
    emu, piezo = stand
    piezo.write(75.0, 0.0)
    emu.inject(kind)
    with pytest.raises(DriverError, match=FAULT_TEXT[kind]) as err:
        piezo.write(76.0, 1.0)
    assert emu.piezo_port in str(err.value) and "76.000" in str(err.value)
    if kind == "drop":  # what `leveler reset` does: close and connect again; the first
        piezo.close()     # write then holds the read-back output
        piezo.connect()
        assert piezo.write(77.0, 2.0) == piezo.last_v
    else:  # the slew reference is what went on the wire: 76 V at 1 s
        assert piezo.write(77.0, 2.0) == 77.0
    assert piezo.read_v() == pytest.approx(emu.plant.v_applied, abs=0.01)


@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_sensor_fault_raises_then_recovers(kind: Any) -> None:
    with emulator() as emu:
        sensor = sensor_for(emu)
        emu.inject(kind, port="sensor")
        with pytest.raises(DriverError, match=FAULT_TEXT[kind]) as err:
            sensor.read(0.0)
        assert emu.sensor_port in str(err.value) and "MEAS?" in str(err.value)
        if kind == "drop":
            sensor.close()
            sensor.connect()
        assert sensor.read(0.1).status is Status.OK
        sensor.close()


def test_fault_count_spoils_that_many_replies() -> None:
    with emulator() as emu:
        sensor = sensor_for(emu)
        emu.inject("garbage", count=2, port="sensor")
        for _ in range(2):
            with pytest.raises(DriverError, match="garbled"):
                sensor.read(0.0)
        assert sensor.read(0.0).status is Status.OK
        sensor.close()


def test_make_safe_sets_safe_voltage(stand: tuple[SerialEmulator, SerialPiezo]) -> None:
    emu, piezo = stand
    piezo.write(80.0, 0.0)
    piezo.write(80.0, 1.0)
    piezo.make_safe()
    assert emu.received_v[-1] == 75.0 and emu.plant.v_target == 75.0


def test_make_safe_on_dead_port_logs_and_returns(caplog: pytest.LogCaptureFixture) -> None:
    emu = emulator("pi_gcs2")
    emu.start()
    piezo = piezo_for(emu, "pi_gcs2")
    emu.close()  # the amplifier vanishes: pty and port path are gone
    with caplog.at_level(logging.ERROR):
        piezo.make_safe()
    assert "could not set safe voltage 75.000 V" in caplog.text
    piezo.close()


def test_nan_command_is_refused_and_nothing_is_sent(
        stand: tuple[SerialEmulator, SerialPiezo]) -> None:
    emu, piezo = stand
    with pytest.raises(DriverError, match="NaN"):
        piezo.write(math.nan, 0.0)
    assert emu.received_v == []


def test_write_before_connect_is_an_error() -> None:
    with pytest.raises(DriverError, match="before connect"):
        SerialPiezo(SerialPiezoConfig(port="/nonexistent")).write(1.0, 0.0)


@pytest.mark.parametrize(("kwargs", "text"), [
    ({"min_v": 10.0, "max_v": 10.0}, "must be below max_v"),
    ({"safe_v": 200.0}, "safe_v"),
    ({"axis": "1"}, "Thorlabs MDT axis"),
])
def test_piezo_config_refuses_unsafe_values(kwargs: dict[str, Any], text: str) -> None:
    with pytest.raises(ValueError, match=text):
        SerialPiezoConfig(**kwargs)


def test_config_tables_load_through_the_config_builder() -> None:
    cfg = build(SerialPiezoConfig, {"port": "/dev/ttyUSB0", "protocol": "pi_gcs2", "axis": "1",
                                    "max_v": 100, "safe_v": 50}, "actuator.serial")
    assert cfg.max_v == 100.0 and cfg.baudrate == 115200
    with pytest.raises(ConfigError, match=r"actuator.serial.slew_v_per_s: must be > 0"):
        build(SerialPiezoConfig, {"slew_v_per_s": 0.0}, "actuator.serial")
    with pytest.raises(ConfigError, match=r"sensor.serial.protocol: unknown key"):
        build(SerialSensorConfig, {"protocol": "pi_gcs2"}, "sensor.serial")


def test_sensor_config_needs_a_number_group() -> None:
    with pytest.raises(ValueError, match="needs a group"):
        SerialSensorConfig(reply_pattern=r"^\d+$")


LIMITS = {"min_v": 10.0, "max_v": 140.0, "slew_v_per_s": 50.0}
COMMANDS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                     st.floats(-20.0, 170.0),
                     st.sampled_from([1e308, -1e308, -5.0, 0.0, 200.0]))
STEPS = st.lists(st.tuples(COMMANDS, st.floats(-0.5, 2.0)), max_size=12)


@pytest.mark.parametrize("protocol", list(PROTOCOLS))
def test_nothing_outside_range_or_slew_reaches_the_wire(protocol: str) -> None:
    """Whatever the controller asks (NaN: DriverError, nothing sent; +-inf, huge: clamped),
    every voltage the amplifier receives is in [min_v, max_v] and no faster than the slew
    limit since the previous write, measured in the loop time passed to write."""
    with emulator(protocol) as emu:

        @settings(max_examples=60, deadline=None)
        @given(steps=STEPS, t0_s=st.floats(0.0, 1e6))
        def check(steps: list[tuple[float, float]], t0_s: float) -> None:
            piezo = piezo_for(emu, protocol, **LIMITS)
            ref_v, ref_t_s, t_s = piezo.last_v, None, t0_s
            assert ref_v is not None
            for command_v, dt_s in steps:
                t_s += dt_s
                sent = len(emu.received_v)
                if math.isnan(command_v):
                    with pytest.raises(DriverError):
                        piezo.write(command_v, t_s)
                    assert len(emu.received_v) == sent
                    continue
                v = piezo.write(command_v, t_s)
                assert emu.received_v[sent:] == [v]
                assert LIMITS["min_v"] <= v <= LIMITS["max_v"]
                elapsed_s = 0.0 if ref_t_s is None else max(0.0, t_s - ref_t_s)
                assert abs(v - ref_v) <= LIMITS["slew_v_per_s"] * elapsed_s + 1e-9
                ref_v, ref_t_s = v, t_s if ref_t_s is None else max(ref_t_s, t_s)
            piezo.close()

        check()
