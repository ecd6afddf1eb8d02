"""Modbus drivers against a real pymodbus server (the plant emulator) on loopback.

Every timeout is short (1 s: a loaded CI machine missed 0.25 s on a plain connect) and every
backoff short, so each test takes well under 5 s.
"""

from __future__ import annotations

import dataclasses
import math
import socket
import time
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymodbus.client import ModbusTcpClient

from leveler.drivers.base import Actuator, DriverError, Sensor, Status
from leveler.drivers.modbus import ModbusActuator, ModbusLink, ModbusSensor
from leveler.drivers.modbus_config import ModbusActuatorConfig, ModbusSensorConfig
from leveler.emulate.modbus import ModbusEmulator
from leveler.sim.params import PlantParams
from leveler.sim.plant import Plant
from leveler.typed_config import ConfigError, build

FAST = {"timeout_s": 1.0, "reconnect_min_s": 0.2, "reconnect_max_s": 0.8}


def _plant() -> Plant:
    return Plant(PlantParams(), dt_s=0.01, seed=1)


@dataclasses.dataclass
class Rig:
    plant: Plant
    emu: ModbusEmulator
    sensor_cfg: ModbusSensorConfig
    actuator_cfg: ModbusActuatorConfig

    def sensor(self) -> ModbusSensor:
        s = ModbusSensor(self.sensor_cfg)
        s.connect()
        return s

    def actuator(self) -> ModbusActuator:
        a = ModbusActuator(self.actuator_cfg)
        a.connect()
        return a


def _rig(sensor_cfg: ModbusSensorConfig | None = None,
         actuator_cfg: ModbusActuatorConfig | None = None) -> Iterator[Rig]:
    plant = _plant()
    s = sensor_cfg or ModbusSensorConfig(**FAST)
    a = actuator_cfg or ModbusActuatorConfig(**FAST)
    with ModbusEmulator(plant, s, a, no_reply_s=2.0) as emu:
        yield Rig(plant, emu, dataclasses.replace(s, port=emu.port),
                  dataclasses.replace(a, port=emu.port))


@pytest.fixture
def rig() -> Iterator[Rig]:
    yield from _rig()


def _one_count_m(cfg: ModbusSensorConfig) -> float:
    return cfg.m_per_v * cfg.volts_per_count


def _assert_reads_plant(rig: Rig, sensor: ModbusSensor) -> None:
    reading = sensor.read(0.0)
    _, plant_m, _ = rig.plant.measure()  # the plant only steps when the server is asked
    assert reading.status is Status.OK
    assert abs(reading.value_m - plant_m) <= _one_count_m(rig.sensor_cfg)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- normal operation ---------------------------------------------------------------------

def test_drivers_implement_the_protocols(rig: Rig) -> None:
    assert isinstance(ModbusSensor(rig.sensor_cfg), Sensor)
    assert isinstance(ModbusActuator(rig.actuator_cfg), Actuator)


def test_sensor_reads_plant_displacement_within_one_count(rig: Rig) -> None:
    sensor = rig.sensor()
    for _ in range(5):
        _assert_reads_plant(rig, sensor)
        time.sleep(0.02)
    assert rig.plant.n > 0  # plant time followed the wall clock
    sensor.close()


def test_actuator_write_moves_the_plant(rig: Rig) -> None:
    actuator, sensor = rig.actuator(), rig.sensor()
    v0 = rig.plant.v_applied
    applied = [actuator.write(90.0, 0.05 * k) for k in range(6)]
    assert applied[0] == pytest.approx(v0, abs=0.04)  # first write: no time yet, hold
    assert applied[-1] == pytest.approx(90.0, abs=0.04)  # 100 V/s x 0.25 s > 15 V
    assert rig.emu.received_v == applied
    assert rig.plant.v_target == applied[-1]
    time.sleep(0.1)
    sensor.read(0.0)  # the next request steps the plant towards the target
    assert rig.plant.v_applied > v0 + 5.0
    actuator.close()
    sensor.close()


@pytest.mark.parametrize("layout", [
    {"words": 1, "signed": False, "counts_min": 0, "counts_max": 65535},
    {"words": 1, "signed": True, "counts_min": -32768, "counts_max": 32767},
    {"words": 2, "signed": False, "counts_min": 0, "counts_max": 2**32 - 1},
    {"words": 2, "signed": True, "counts_min": -(2**31), "counts_max": 2**31 - 1},
    {"words": 2, "signed": True, "counts_min": -(2**31), "counts_max": 2**31 - 1,
     "word_order": "little"},
    {"words": 2, "signed": False, "counts_min": 0, "counts_max": 2**20, "word_order": "little",
     "register_kind": "holding"},
])
def test_encodings_round_trip_through_the_emulator(layout: dict[str, object]) -> None:
    cfg = ModbusSensorConfig(register=3, **FAST, **layout)  # type: ignore[arg-type]
    for rig in _rig(sensor_cfg=cfg):
        _assert_reads_plant(rig, rig.sensor())


@settings(max_examples=200, deadline=None)
@given(words=st.sampled_from([1, 2]), signed=st.booleans(),
       word_order=st.sampled_from(["big", "little"]), data=st.data())
def test_encoding_matches_pymodbus(words: int, signed: bool, word_order: str,
                                   data: st.DataObject) -> None:
    """An independent implementation (pymodbus's own converters) agrees on every layout."""
    bits = 16 * words
    lo, hi = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if signed else (0, 2**bits - 1)
    cfg = ModbusSensorConfig(words=words, signed=signed, word_order=word_order,  # type: ignore[arg-type]
                             counts_min=lo, counts_max=hi)
    counts = data.draw(st.integers(lo, hi))
    dtype = getattr(ModbusTcpClient.DATATYPE, f"{'' if signed else 'U'}INT{bits}")
    regs = ModbusTcpClient.convert_to_registers(counts, dtype, word_order=word_order)  # type: ignore[arg-type]
    assert cfg.encode(counts) == regs
    assert cfg.decode(regs) == counts


def test_counts_at_range_ends_are_railed() -> None:
    cfg = ModbusSensorConfig(offset_m=1.0, **FAST)  # the plant's few nm read as -200 kV: rail
    for rig in _rig(sensor_cfg=cfg):
        reading = rig.sensor().read(0.0)
        assert (reading.raw_counts, reading.status) == (cfg.counts_min, Status.RAILED)


# --- faults and recovery ------------------------------------------------------------------

@pytest.mark.parametrize(("code", "meaning"), [(4, "SLAVE_DEVICE_FAILURE"),
                                               (2, "ILLEGAL_DATA_ADDRESS")])
def test_exception_reply_is_a_clear_error_and_the_link_stays_up(rig: Rig, code: int,
                                                                meaning: str) -> None:
    sensor = rig.sensor()
    rig.emu.inject("exception", code=code)
    with pytest.raises(DriverError) as err:
        sensor.read(0.0)
    msg = str(err.value)
    for part in (f"127.0.0.1:{rig.emu.port}", "device 1", "input register 0",
                 f"exception {code}", meaning):
        assert part in msg
    _assert_reads_plant(rig, sensor)  # no reconnect needed: the device answered


@pytest.mark.parametrize(("kind", "says"), [("no_reply", "no valid reply within 1.0 s"),
                                            ("garbage", "no valid reply"),
                                            ("drop", "connection lost")])
def test_link_fault_is_a_clear_error_then_backoff_then_recovery(rig: Rig, kind: str,
                                                                says: str) -> None:
    sensor = rig.sensor()
    rig.emu.inject(kind)  # type: ignore[arg-type]
    t0 = time.monotonic()
    with pytest.raises(DriverError, match=says) as err:
        sensor.read(0.0)
    assert time.monotonic() - t0 < 1.8  # bounded by timeout_s, not by the server (2 s)
    assert f"127.0.0.1:{rig.emu.port} device 1" in str(err.value)
    t0 = time.monotonic()
    with pytest.raises(DriverError, match="next reconnect attempt in"):
        sensor.read(0.0)  # within the backoff wait: fails at once, no connect attempt
    assert time.monotonic() - t0 < 0.05
    time.sleep(rig.sensor_cfg.reconnect_min_s)
    _assert_reads_plant(rig, sensor)


def test_a_glitch_after_good_replies_reconnects_at_once_a_second_one_backs_off(
        rig: Rig) -> None:
    sensor = rig.sensor()
    _assert_reads_plant(rig, sensor)  # the device has answered
    rig.emu.inject("garbage")
    with pytest.raises(DriverError, match="reconnecting at the next request"):
        sensor.read(0.0)
    _assert_reads_plant(rig, sensor)  # the next cycle's read reconnects and works
    rig.emu.inject("drop", count=2)
    with pytest.raises(DriverError, match=r"connection lost: .*reconnecting at the next request"):
        sensor.read(0.0)
    with pytest.raises(DriverError, match=r"reconnecting in 0\.20 s"):
        sensor.read(0.0)  # failed again right after reconnecting: now it waits
    with pytest.raises(DriverError, match="next reconnect attempt in"):
        sensor.read(0.0)
    time.sleep(rig.sensor_cfg.reconnect_min_s)
    _assert_reads_plant(rig, sensor)


def test_failed_write_reads_the_ao_back_before_the_next_one(rig: Rig) -> None:
    actuator = rig.actuator()
    actuator.write(80.0, 0.0)
    rig.emu.inject("exception")
    with pytest.raises(DriverError, match="write holding register 10"):
        actuator.write(80.0, 1.0)
    assert actuator.write(80.0, 2.0) == pytest.approx(80.0, abs=0.04)
    assert rig.plant.v_target == pytest.approx(80.0, abs=0.04)


def test_backoff_doubles_up_to_the_maximum_and_never_blocks() -> None:
    now = [100.0]
    cfg = ModbusSensorConfig(port=_free_port(), timeout_s=0.1, reconnect_min_s=0.5,
                             reconnect_max_s=2.0)
    link = ModbusLink(cfg, clock_s=lambda: now[0])
    waits = []
    for _ in range(5):
        with pytest.raises(DriverError, match=r"cannot connect .* retrying in (\S+) s") as err:
            link.read("input", 0, 1)
        waits.append(float(str(err.value).rsplit("retrying in ", 1)[1].split()[0]))
        t0 = time.monotonic()
        with pytest.raises(DriverError, match="next reconnect attempt"):
            link.read("input", 0, 1)
        assert time.monotonic() - t0 < 0.05
        now[0] += waits[-1]
    assert waits == [0.5, 1.0, 2.0, 2.0, 2.0]


def test_make_safe_on_a_dead_server_does_not_raise_and_says_it_failed() -> None:
    for rig in _rig():
        actuator = rig.actuator()
        actuator.write(100.0, 0.0)
        actuator.write(100.0, 1.0)
        assert actuator.make_safe() is True
        assert rig.emu.received_v[-1] == pytest.approx(actuator.safe_v, abs=0.04)
        rig.emu.close()
        t0 = time.monotonic()
        assert actuator.make_safe() is False
        assert actuator.make_safe() is False  # also during the backoff wait: a real attempt
        assert time.monotonic() - t0 < 1.0
        with pytest.raises(DriverError):
            actuator.write(75.0, 2.0)


def test_rtu_without_the_port_names_it() -> None:
    cfg = ModbusSensorConfig(transport="rtu", serial_port="/dev/leveler-no-such-tty", **FAST)
    with pytest.raises(DriverError, match="rtu /dev/leveler-no-such-tty @ 9600 Bd device 1"):
        ModbusSensor(cfg).connect()


# --- the actuator's own limits --------------------------------------------------------------

_commands = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from(
    [math.nan, math.inf, -math.inf, 1e300, -1e300, -5.0, 0.0, 150.0, 151.0])
_steps_s = st.floats(-0.05, 0.5) | st.just(math.nan)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # one server for all
@given(sequence=st.lists(st.tuples(_commands, _steps_s), min_size=1, max_size=25))
def test_no_command_outside_the_limits_reaches_the_wire(
        rig: Rig, sequence: list[tuple[float, float]]) -> None:
    cfg, received = rig.actuator_cfg, rig.emu.received_v
    if not received:  # a first value on the wire to compare with, from another driver
        seed = rig.actuator()
        seed.write(75.0, 0.0)
        seed.close()
    actuator = rig.actuator()
    start, prev_v = len(received), received[-1]
    clock_s, latest_t_s = 0.0, math.nan  # NaN steps write at t = NaN
    applied = []
    for command_v, step_s in sequence:
        clock_s += 0.0 if math.isnan(step_s) else step_s
        t_s = math.nan if math.isnan(step_s) else clock_s
        applied.append(actuator.write(command_v, t_s))
        dt_s = t_s - latest_t_s  # from the latest time seen: never backwards
        allowed_v = cfg.slew_v_per_s * dt_s if dt_s > 0 else 0.0
        assert cfg.min_v <= received[-1] <= cfg.max_v
        assert abs(received[-1] - prev_v) <= allowed_v + 1e-9
        prev_v = received[-1]
        if not (math.isnan(t_s) or t_s <= latest_t_s):
            latest_t_s = t_s
    assert received[start:] == applied
    actuator.close()


# --- configuration ------------------------------------------------------------------------

@pytest.mark.parametrize(("cls", "kwargs", "says"), [
    (ModbusSensorConfig, {"counts_min": 100, "counts_max": 10}, "counts range"),
    (ModbusSensorConfig, {"signed": True}, "signed 16-bit range"),
    (ModbusSensorConfig, {"value_at_min": 5.0, "value_at_max": -5.0}, "value_at_min"),
    (ModbusSensorConfig, {"register": 65535, "words": 2}, "exceeds the Modbus address space"),
    (ModbusSensorConfig, {"words": 3}, "words must be <= 2"),
    (ModbusSensorConfig, {"device_id": 0}, "device_id must be >= 1"),
    (ModbusSensorConfig, {"transport": "rtu"}, "needs serial_port"),
    (ModbusSensorConfig, {"timeout_s": 0.0}, "timeout_s must be > 0"),
    (ModbusSensorConfig, {"reconnect_min_s": 5.0, "reconnect_max_s": 1.0}, "reconnect_min_s"),
    (ModbusSensorConfig, {"m_per_v": math.nan}, "m_per_v must be finite"),
    (ModbusActuatorConfig, {"safe_v": 200.0}, "safe_v"),
    (ModbusActuatorConfig, {"min_v": 100.0, "max_v": 50.0}, "min_v"),
    (ModbusActuatorConfig, {"amplifier_gain": 10.0}, "needs the AO to span"),
    (ModbusActuatorConfig, {"min_v": 0.0, "max_v": 0.01, "safe_v": 0.0}, "narrower than one"),
])
def test_config_validation_names_the_problem(cls: type, kwargs: dict[str, object],
                                             says: str) -> None:
    with pytest.raises(ValueError, match=says):
        cls(**kwargs)


def test_config_tables_build_from_toml_values() -> None:
    cfg = build(ModbusActuatorConfig, {"host": "10.0.0.7", "register": 11, "safe_v": 70.0},
                "actuator.modbus")
    assert (cfg.host, cfg.register, cfg.safe_v) == ("10.0.0.7", 11, 70.0)
    with pytest.raises(ConfigError, match=r"sensor\.modbus\.device_id: must be <= 247"):
        build(ModbusSensorConfig, {"device_id": 300}, "sensor.modbus")
    with pytest.raises(ConfigError, match="word_order: expected 'big' or 'little'"):
        build(ModbusSensorConfig, {"word_order": "middle"}, "sensor.modbus")
    with pytest.raises(ConfigError, match="safe_v"):
        build(ModbusActuatorConfig, {"safe_v": -1.0}, "actuator.modbus")


def test_emulator_rejects_overlapping_registers() -> None:
    with pytest.raises(ValueError, match="overlap"):
        ModbusEmulator(_plant(), ModbusSensorConfig(register=10),
                       ModbusActuatorConfig(register=10))
