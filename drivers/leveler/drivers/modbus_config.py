"""Configuration of Modbus analog I/O channels: link, register layout and scaling, in SI units.

One table per channel (`[sensor.modbus]`, `[actuator.modbus]`) holds everything needed to
reach the module and to say what its counts mean. The conversions live here, next to the
numbers they use, so the drivers and the emulator cannot disagree about an encoding.

Scaling is ADAM style: counts_min..counts_max are linear over value_at_min..value_at_max volts
(e.g. 0..65535 over -10..+10 V for an ADAM-6017 on its +-10 V range).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal

from leveler.drivers.limits import check_piezo_range
from leveler.typed_config import positive

MAX_REGISTER = 0xFFFF


@dataclass(frozen=True, slots=True)
class ModbusChannelConfig:
    """How to reach one analog channel and how its registers encode counts."""

    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: int = field(default=502, metadata={"ge": 1, "le": 65535})
    serial_port: str = ""
    baudrate: int = field(default=9600, metadata={"gt": 0})
    device_id: int = field(default=1, metadata={"ge": 1, "le": 247})
    timeout_s: float = positive(0.2)
    retries: int = field(default=0, metadata={"ge": 0, "le": 10})
    reconnect_min_s: float = positive(0.5)
    reconnect_max_s: float = positive(30.0)
    register: int = field(default=0, metadata={"ge": 0, "le": MAX_REGISTER})
    words: int = field(default=1, metadata={"ge": 1, "le": 2})
    signed: bool = False
    word_order: Literal["big", "little"] = "big"
    counts_min: int = 0
    counts_max: int = 65535
    value_at_min: float = -10.0
    value_at_max: float = 10.0

    def __post_init__(self) -> None:
        _check_bounds(self)
        if self.transport == "rtu" and not self.serial_port:
            raise ValueError("transport 'rtu' needs serial_port (e.g. '/dev/ttyUSB0')")
        if not 0 <= self.register <= MAX_REGISTER - self.words + 1:
            raise ValueError(f"register {self.register} + {self.words} word(s) exceeds the "
                             f"Modbus address space 0..{MAX_REGISTER}")
        if not 0 < self.reconnect_min_s <= self.reconnect_max_s:
            raise ValueError(f"reconnect_min_s ({self.reconnect_min_s}) must be > 0 and <= "
                             f"reconnect_max_s ({self.reconnect_max_s})")
        lo, hi = self.representable_counts
        kind = f"{'signed' if self.signed else 'unsigned'} {16 * self.words}-bit"
        if not lo <= self.counts_min < self.counts_max <= hi:
            raise ValueError(f"counts range [{self.counts_min}, {self.counts_max}] must be "
                             f"ordered and within the {kind} range [{lo}, {hi}]")
        if not self.value_at_min < self.value_at_max:
            raise ValueError(f"value_at_min ({self.value_at_min} V) must be below "
                             f"value_at_max ({self.value_at_max} V)")

    @property
    def representable_counts(self) -> tuple[int, int]:
        """The integers the configured words can hold."""
        bits = 16 * self.words
        return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if self.signed else (0, (1 << bits) - 1)

    @property
    def where(self) -> str:
        """The link and device, for error messages."""
        link = (f"tcp {self.host}:{self.port}" if self.transport == "tcp"
                else f"rtu {self.serial_port} @ {self.baudrate} Bd")
        return f"modbus {link} device {self.device_id}"

    @property
    def volts_per_count(self) -> float:
        return (self.value_at_max - self.value_at_min) / (self.counts_max - self.counts_min)

    def counts_to_volts(self, counts: int) -> float:
        return self.value_at_min + (counts - self.counts_min) * self.volts_per_count

    def volts_to_counts(self, volts: float) -> float:
        """Fractional counts; the caller rounds and clamps as its direction requires."""
        return self.counts_min + (volts - self.value_at_min) / self.volts_per_count

    def encode(self, counts: int) -> list[int]:
        """Counts as register words (two's complement if signed), in the configured order."""
        lo, hi = self.representable_counts
        if not lo <= counts <= hi:
            raise ValueError(f"{counts} counts do not fit the configured registers")
        raw = counts & ((1 << (16 * self.words)) - 1)
        words = [(raw >> (16 * i)) & 0xFFFF for i in reversed(range(self.words))]
        return words if self.word_order == "big" else words[::-1]

    def decode(self, registers: list[int]) -> int:
        """Register words (as read, in the configured order) back to counts."""
        words = registers if self.word_order == "big" else registers[::-1]
        raw = 0
        for w in words:
            raw = (raw << 16) | (w & 0xFFFF)
        bits = 16 * self.words
        if self.signed and raw >= 1 << (bits - 1):
            raw -= 1 << bits
        return raw


@dataclass(frozen=True, slots=True)
class ModbusSensorConfig(ModbusChannelConfig):
    """An analog input (ADAM-6017 style) reading the displacement sensor's voltage.

    register_kind: ADAM-6017 serves its AI as holding registers (function 3); many other
    modules use input registers (function 4).
    """

    register_kind: Literal["input", "holding"] = "input"
    m_per_v: float = positive(5.0e-6)
    offset_m: float = 0.0

    def __post_init__(self) -> None:
        ModbusChannelConfig.__post_init__(self)

    def counts_to_m(self, counts: int) -> float:
        return self.offset_m + self.m_per_v * self.counts_to_volts(counts)

    def m_to_counts(self, value_m: float) -> float:
        return self.volts_to_counts((value_m - self.offset_m) / self.m_per_v)


@dataclass(frozen=True, slots=True)
class ModbusActuatorConfig(ModbusChannelConfig):
    """An analog output (ADAM-6024 style) driving the piezo amplifier's input.

    Piezo limits are in piezo volts (after the amplifier); the driver enforces them itself,
    whatever the controller asks. Defaults: AO0 of an ADAM-6024 at address 10, 12-bit over
    0..10 V, a x15 amplifier for a 0..150 V piezo.
    """

    register: int = field(default=10, metadata={"ge": 0, "le": MAX_REGISTER})
    counts_max: int = 4095
    value_at_min: float = 0.0
    value_at_max: float = 10.0
    amplifier_gain: float = positive(15.0)
    min_v: float = 0.0
    max_v: float = 150.0
    slew_v_per_s: float = positive(100.0)
    safe_v: float = 75.0

    def __post_init__(self) -> None:
        ModbusChannelConfig.__post_init__(self)
        check_piezo_range(self.min_v, self.max_v, self.safe_v, self.amplifier_gain,
                          self.value_at_min, self.value_at_max, "it spans")
        count_v = self.amplifier_gain * self.volts_per_count
        if self.max_v - self.min_v < count_v:
            raise ValueError(f"piezo range [{self.min_v}, {self.max_v}] V is narrower than "
                             f"one AO count ({count_v:.4g} piezo V)")

    def counts_to_piezo_v(self, counts: int) -> float:
        return self.amplifier_gain * self.counts_to_volts(counts)

    def piezo_v_to_counts(self, piezo_v: float) -> float:
        return self.volts_to_counts(piezo_v / self.amplifier_gain)


def _check_bounds(cfg: ModbusChannelConfig) -> None:
    """The fields' gt/ge/le metadata, also for configs built in code rather than from TOML."""
    for f in dataclasses.fields(cfg):
        value, meta = getattr(cfg, f.name), f.metadata
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{f.name} must be finite, got {value!r}")
        if "gt" in meta and not value > meta["gt"]:
            raise ValueError(f"{f.name} must be > {meta['gt']}, got {value!r}")
        if "ge" in meta and not value >= meta["ge"]:
            raise ValueError(f"{f.name} must be >= {meta['ge']}, got {value!r}")
        if "le" in meta and not value <= meta["le"]:
            raise ValueError(f"{f.name} must be <= {meta['le']}, got {value!r}")


@dataclass(frozen=True, slots=True)
class ModbusThermometerConfig(ModbusChannelConfig):
    """An analog input reading the table's thermometer through a transmitter (a PT100 on a
    4-20 mA or 0-10 V transmitter into an AI channel, as the sensor's).

    temperature [K] = offset_k + k_per_v x volts; the defaults read 0-10 V as 0-100 degC.
    A reading at either end of the counts is railed (a broken wire or an open loop current),
    not a temperature.
    """

    register: int = field(default=2, metadata={"ge": 0, "le": MAX_REGISTER})
    register_kind: Literal["input", "holding"] = "input"
    value_at_min: float = 0.0
    value_at_max: float = 10.0
    k_per_v: float = positive(10.0)
    offset_k: float = 273.15

    def __post_init__(self) -> None:
        ModbusChannelConfig.__post_init__(self)

    def counts_to_k(self, counts: int) -> float:
        return self.offset_k + self.k_per_v * self.counts_to_volts(counts)

    def k_to_counts(self, temperature_k: float) -> float:
        return self.volts_to_counts((temperature_k - self.offset_k) / self.k_per_v)
