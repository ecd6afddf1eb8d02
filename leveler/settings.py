"""The daemon's configuration file: one typed, validated tree (see docs/configuration.md)."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from leveler.drivers.modbus_config import (
    ModbusActuatorConfig,
    ModbusSensorConfig,
    ModbusThermometerConfig,
)
from leveler.drivers.nidaq_config import NidaqActuatorConfig, NidaqSensorConfig
from leveler.drivers.serial_config import SerialPiezoConfig, SerialSensorConfig
from leveler.drivers.simulated_config import FaultSpec
from leveler.live.config import EpicsConfig, LiveConfig
from leveler.log.rotate import LogConfig
from leveler.loop.cycle import LoopConfig
from leveler.loop.pid import ControllerConfig
from leveler.sim.params import PlantParams
from leveler.typed_config import ConfigError, build, load_toml, non_negative, positive


@dataclass(frozen=True, slots=True)
class ControlConfig:
    """[control]: the daemon's socket, where it lives and who may use it. Kept here, not in
    daemon/, because the daemon reads this tree: its wing sits above settings."""

    socket_path: str = ""
    group: str = ""
    max_clients: int = field(default=16, metadata={"ge": 1, "le": 1024})
    # any uid but root's and the daemon's own: one user cannot lock the others out
    max_clients_per_uid: int = field(default=8, metadata={"ge": 1, "le": 1024})
    idle_timeout_s: float = positive(60.0)


@dataclass(frozen=True, slots=True)
class SensorConfig:
    """Where readings come from: the simulated plant or a device (its table below)."""

    backend: Literal["sim", "modbus", "serial", "nidaq"] = "sim"
    modbus: ModbusSensorConfig | None = None
    serial: SerialSensorConfig | None = None
    nidaq: NidaqSensorConfig | None = None

    def __post_init__(self) -> None:
        if self.backend != "sim" and getattr(self, self.backend) is None:
            raise ValueError(f'backend = "{self.backend}" needs a [sensor.{self.backend}] table')


@dataclass(frozen=True, slots=True)
class ActuatorConfig:
    """What moves the piezo. safe_v is the simulated piezo's; a device table has its own."""

    backend: Literal["sim", "modbus", "serial", "nidaq"] = "sim"
    safe_v: float = 75.0
    modbus: ModbusActuatorConfig | None = None
    serial: SerialPiezoConfig | None = None
    nidaq: NidaqActuatorConfig | None = None

    def __post_init__(self) -> None:
        if self.backend != "sim" and getattr(self, self.backend) is None:
            raise ValueError(f'backend = "{self.backend}" needs an [actuator.{self.backend}] '
                             "table")


@dataclass(frozen=True, slots=True)
class ThermometerConfig:
    """[thermometer]: the table's temperature, read every interval_s for the temperature
    feedforward ([controller] feedforward_*) and logged on /leveler/environment. "sim"
    reads the simulated plate ([plant.thermal] thermometer_*); none by default."""

    backend: Literal["none", "sim", "modbus"] = "none"
    interval_s: float = positive(1.0)
    modbus: ModbusThermometerConfig | None = None

    def __post_init__(self) -> None:
        if self.backend == "modbus" and self.modbus is None:
            raise ValueError('backend = "modbus" needs a [thermometer.modbus] table')


@dataclass(frozen=True, slots=True)
class SimConfig:
    """Simulation-only settings (the plant itself is [plant])."""

    seed: int = field(default=0, metadata={"ge": 0})
    hang_at_s: float = non_negative(math.inf, allow_inf=True)
    hang_for_s: float = non_negative(0.0)
    fail_at_s: float = non_negative(math.inf, allow_inf=True)
    faults: tuple[FaultSpec, ...] = ()


@dataclass(frozen=True, slots=True)
class Config:
    loop: LoopConfig = field(default_factory=LoopConfig)
    log: LogConfig = field(default_factory=LogConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    actuator: ActuatorConfig = field(default_factory=ActuatorConfig)
    plant: PlantParams = field(default_factory=PlantParams)
    sim: SimConfig = field(default_factory=SimConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    epics: EpicsConfig = field(default_factory=EpicsConfig)
    thermometer: ThermometerConfig = field(default_factory=ThermometerConfig)

    def __post_init__(self) -> None:
        if (self.sensor.backend == "sim") != (self.actuator.backend == "sim"):
            raise ValueError("sensor.backend and actuator.backend: the simulated plant is "
                             "both sensor and actuator; use \"sim\" for both or for neither")
        if self.actuator.backend == "sim":  # a device table checks its own safe_v
            pz = self.plant.piezo
            if not pz.min_v <= self.actuator.safe_v <= pz.max_v:
                raise ValueError(f"actuator.safe_v: {self.actuator.safe_v} V is outside the "
                                 f"simulated piezo's range [plant.piezo] min_v..max_v = "
                                 f"[{pz.min_v}, {pz.max_v}] V")
        if self.thermometer.backend == "sim" and self.sensor.backend != "sim":
            raise ValueError('thermometer.backend: "sim" reads the simulated plate, which a '
                             f'stand on sensor.backend = "{self.sensor.backend}" does not have; '
                             'use "modbus" (or "none")')
        if self.controller.feedforward() is not None and self.thermometer.backend == "none":
            raise ValueError("controller.feedforward_gains_v_per_k: a temperature feedforward "
                             "needs a thermometer; add [thermometer] backend = \"sim\" or "
                             "\"modbus\" (docs/configuration.md)")

    def sensor_range_m(self) -> tuple[float, float, str]:
        """The readings the configured sensor can make [m], and the table that says so."""
        b = self.sensor.backend
        if b == "modbus" and self.sensor.modbus is not None:
            m = self.sensor.modbus
            ends = (m.counts_to_m(m.counts_min), m.counts_to_m(m.counts_max))
        elif b == "serial" and self.sensor.serial is not None:
            ends = (self.sensor.serial.min_m, self.sensor.serial.max_m)
        elif b == "nidaq" and self.sensor.nidaq is not None:
            n = self.sensor.nidaq
            ends = (n.volts_to_m(n.range_min_v), n.volts_to_m(n.range_max_v))
        else:
            se = self.plant.sensor
            ends = ((se.adc_min_v - se.offset_v) / se.gain_v_per_m,
                    (se.adc_max_v - se.offset_v) / se.gain_v_per_m)
            b = "plant"
        return min(ends), max(ends), f"[{b}.sensor]" if b == "plant" else f"[sensor.{b}]"

    def actuator_range_v(self) -> tuple[float, float, str]:
        """The voltages the configured actuator driver allows, and the table that says so."""
        b = self.actuator.backend
        table = getattr(self.actuator, b) if b != "sim" else None
        if table is not None:
            return table.min_v, table.max_v, f"[actuator.{b}]"
        return self.plant.piezo.min_v, self.plant.piezo.max_v, "[plant.piezo]"


PLAUSIBLE_ERROR_M = 1e-12  # a picometre: far below the noise of any displacement sensor


def gain_limits(cfg: Config) -> dict[str, float]:
    """The largest plausible gain of each kind: one that sweeps the actuator's whole range
    for a 1 pm error within one sample. Anything larger is a typo in the exponent, and it
    would overflow the controller's arithmetic on the first large error."""
    lo, hi, _ = cfg.actuator_range_v()
    span, dt = hi - lo, 1.0 / cfg.loop.rate_hz
    return {"kp_v_per_m": span / PLAUSIBLE_ERROR_M,
            "ki_v_per_m_s": span / (PLAUSIBLE_ERROR_M * dt),
            "ki2_v_per_m_s2": span / (PLAUSIBLE_ERROR_M * dt * dt),
            "kd_v_s_per_m": span * dt / PLAUSIBLE_ERROR_M}


def check_tune_values(cfg: Config, values: dict[str, float]) -> None:
    """Plausibility of live controller changes against this config's devices: a setpoint
    the sensor can read, output limits the actuator has, gains below `gain_limits`. Only
    the keys being changed are checked (a running config that predates the check is not
    refused for its own values). Raises ValueError naming the key, the value and the range."""
    for key, limit in gain_limits(cfg).items():
        if key in values and values[key] > limit:
            raise ValueError(f"{key} {values[key]:g} is implausible: above {limit:.3g}, a 1 pm "
                             "error would sweep the actuator's whole range within one "
                             f"sample at {cfg.loop.rate_hz:g} Hz (a typo in the exponent?)")
    if "setpoint_m" in values:
        lo, hi, where = cfg.sensor_range_m()
        sp = values["setpoint_m"]
        if not lo < sp < hi:
            raise ValueError(f"setpoint_m {sp:g} m is outside what the sensor reads, "
                             f"({lo:g}, {hi:g}) m ({where}); the loop could never reach it")
    nyquist = cfg.loop.rate_hz / 2
    if values.get("notch_frequency_hz", 0.0) >= nyquist:
        raise ValueError(f"notch_frequency_hz {values['notch_frequency_hz']:g} Hz is at or "
                         f"above the loop's Nyquist frequency, {nyquist:g} Hz (loop.rate_hz "
                         f"{cfg.loop.rate_hz:g}): a sampled loop cannot notch it")
    lo, hi, where = cfg.actuator_range_v()
    for key in ("output_min_v", "output_max_v"):
        if key in values and not lo <= values[key] <= hi:
            raise ValueError(f"{key} {values[key]:g} V is outside the actuator's range "
                             f"[{lo:g}, {hi:g}] V ({where})")


def load_config(path: str | Path) -> tuple[Config, str]:
    """Read and validate a config file; returns it with its text (kept in every log).

    A file with no table or key at all is refused: it would run the simulated stand on
    built-in defaults, which is never what an emptied or truncated lab config meant."""
    path = Path(path)
    data = load_toml(path)
    if not data:
        raise ConfigError(f"{path}: is empty: no tables or keys (it would run the simulator "
                          "on built-in defaults); start from config/lab.toml or config/sim.toml")
    try:
        cfg = build(Config, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    try:
        check_tune_values(cfg, {k: getattr(cfg.controller, k)
                                for k in (*gain_limits(cfg), "notch_frequency_hz")})
    except ValueError as exc:
        raise ConfigError(f"{path}: controller.{exc}") from None
    return cfg, path.read_text()


def explicit_keys(text: str) -> frozenset[str]:
    """The dotted keys a config file sets itself (an array of tables, `[[sim.faults]]`, is
    one key). A reload compares these: a file that no longer sets what the running one set
    was most likely cut short, and its missing keys would silently take their defaults."""
    def walk(table: dict[str, Any], prefix: str) -> list[str]:
        keys = []
        for name, value in table.items():
            if isinstance(value, dict):
                keys += walk(value, f"{prefix}{name}.")
            else:
                keys.append(f"{prefix}{name}")
        return keys

    return frozenset(walk(tomllib.loads(text), ""))


def effective_values(cfg: Config) -> dict[str, Any]:
    """Every setting of `cfg` by dotted key, defaults included: what a reload diff shows."""
    def walk(obj: Any, prefix: str) -> dict[str, Any]:
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            out: dict[str, Any] = {}
            for f in dataclasses.fields(obj):
                out |= walk(getattr(obj, f.name), f"{prefix}{f.name}.")
            return out
        return {prefix[:-1]: obj}

    return walk(cfg, "")


def config_diff(old: Config, new: Config) -> dict[str, tuple[Any, Any]]:
    """dotted key -> (old, new) for every effective value that differs."""
    a, b = effective_values(old), effective_values(new)
    return {k: (a.get(k), b.get(k)) for k in sorted(a.keys() | b.keys())
            if a.get(k) != b.get(k)}
