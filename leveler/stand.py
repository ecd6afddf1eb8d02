"""Builds the drivers a config asks for, so the loop never knows which backend it drives."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from leveler.drivers.base import Actuator, Sensor, Thermometer
from leveler.records import Truth
from leveler.settings import Config


@dataclass
class Stand:
    """The connected hardware (or its simulation) the loop drives."""

    sensor: Sensor
    actuator: Actuator
    truth: Callable[[int, float], Truth] | None
    thermometer: Thermometer | None = None

    def _devices(self) -> list[Sensor | Actuator | Thermometer]:
        out: list[Sensor | Actuator | Thermometer] = []
        for d in (self.sensor, self.actuator, self.thermometer):
            if d is not None and all(d is not o for o in out):
                out.append(d)
        return out

    def connect(self) -> None:
        for device in self._devices():
            device.connect()

    def close(self) -> None:
        for device in self._devices():
            device.close()


def open_stand(cfg: Config, seed: int | None = None) -> Stand:
    """Make (not yet connect) the drivers named in cfg; `seed` overrides [sim] seed."""
    sensor: Sensor
    actuator: Actuator
    if cfg.sensor.backend == "modbus":
        from leveler.drivers.modbus import ModbusSensor

        assert cfg.sensor.modbus is not None
        sensor = ModbusSensor(cfg.sensor.modbus)
    elif cfg.sensor.backend == "serial":
        from leveler.drivers.sensor_serial import SerialSensor

        assert cfg.sensor.serial is not None
        sensor = SerialSensor(cfg.sensor.serial)
    elif cfg.sensor.backend == "nidaq":
        from leveler.drivers.nidaq import NidaqSensor

        assert cfg.sensor.nidaq is not None
        sensor = NidaqSensor(cfg.sensor.nidaq)
    if cfg.actuator.backend == "modbus":
        from leveler.drivers.modbus import ModbusActuator

        assert cfg.actuator.modbus is not None
        actuator = ModbusActuator(cfg.actuator.modbus)
    elif cfg.actuator.backend == "serial":
        from leveler.drivers.piezo_serial import SerialPiezo

        assert cfg.actuator.serial is not None
        actuator = SerialPiezo(cfg.actuator.serial)
    elif cfg.actuator.backend == "nidaq":
        from leveler.drivers.nidaq import NidaqActuator

        assert cfg.actuator.nidaq is not None
        actuator = NidaqActuator(cfg.actuator.nidaq)
    thermometer: Thermometer | None = None
    if cfg.thermometer.backend == "modbus":
        from leveler.drivers.modbus import ModbusThermometer

        assert cfg.thermometer.modbus is not None
        thermometer = ModbusThermometer(cfg.thermometer.modbus)
    if cfg.sensor.backend != "sim":
        return Stand(sensor, actuator, None, thermometer)
    # the simulation, and scipy with it, only for a simulated stand: a hardware daemon
    # stays lean (issue 21)
    from leveler.drivers.simulated import SimulatedStand
    from leveler.sim.plant import Plant

    dt_s = 1.0 / cfg.loop.rate_hz
    plant = Plant(cfg.plant, dt_s, cfg.sim.seed if seed is None else seed)
    sim = SimulatedStand(plant, cfg.actuator.safe_v, hang_at_s=cfg.sim.hang_at_s,
                         hang_for_s=cfg.sim.hang_for_s, fail_at_s=cfg.sim.fail_at_s,
                         faults=cfg.sim.faults)
    return Stand(sensor=sim, actuator=sim, truth=sim.truth,
                 thermometer=sim if cfg.thermometer.backend == "sim" else thermometer)
