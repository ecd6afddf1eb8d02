"""`leveler emulate`: the simulated plant behind the real protocol, so a lab can test its
exact config (addresses, scaling, limits) on a laptop before touching the table."""

from __future__ import annotations

import argparse
import math
import signal
import threading
from pathlib import Path

from leveler.config import ConfigError
from leveler.settings import Config, load_config
from leveler.sim.plant import Plant


def run_emulate_command(args: argparse.Namespace) -> int:
    cfg, _ = load_config(args.config)
    seed = cfg.sim.seed if args.seed is None else args.seed
    plant = Plant(cfg.plant, 1.0 / cfg.loop.rate_hz, seed)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if args.kind == "serial":
        return _serial(args, cfg, plant, seed, stop)
    s, a = cfg.sensor.modbus, cfg.actuator.modbus
    if cfg.sensor.backend != "modbus" or s is None or a is None:
        raise ConfigError(f"{args.config}: emulate modbus needs backend = \"modbus\" with "
                          "[sensor.modbus] and [actuator.modbus] tables")
    if s.transport != "tcp" or a.transport != "tcp" or (s.host, s.port) != (a.host, a.port):
        raise ConfigError(f"{args.config}: the emulator serves one Modbus TCP module: "
                          "sensor.modbus and actuator.modbus need transport = \"tcp\" and the "
                          "same host and port")
    from leveler.emulate_modbus import ModbusEmulator

    with ModbusEmulator(plant, s, a, host=s.host, port=s.port) as emu:
        print(f"leveler emulate modbus: the simulated plant ({args.config}, seed {seed}) on "
              f"{s.host}:{emu.port}; sensor in registers {s.register}..{s.register + s.words - 1}"
              f", piezo in {a.register}..{a.register + a.words - 1}; Ctrl-C stops", flush=True)
        stop.wait()
    print(f"leveler emulate modbus: stopped after {plant.n * plant.dt_s:.1f} s of plant time")
    return 0


def _serial(args: argparse.Namespace, cfg: Config, plant: Plant, seed: int,
            stop: threading.Event) -> int:
    """A piezo amplifier and a sensor controller on ptys, linked at the config's ports."""
    s, a = cfg.sensor.serial, cfg.actuator.serial
    if cfg.sensor.backend != "serial" or s is None or a is None:
        raise ConfigError(f"{args.config}: emulate serial needs backend = \"serial\" with "
                          "[sensor.serial] and [actuator.serial] tables")
    links = [Path(a.port), Path(s.port)]
    for link in links:
        if not link.name or (link.exists() and not link.is_symlink()):
            raise ConfigError(f"{args.config}: port {str(link)!r} is not a path the emulator "
                              "may link (empty, or an existing device or file)")
    from leveler.emulate_serial import SensorFormat, SerialEmulator

    decimals = max(0, math.ceil(math.log10(s.scale_m_per_unit / 1e-12)))
    fmt = SensorFormat(query=s.query, unit_m=s.scale_m_per_unit, decimals=decimals,
                       line_ending=s.line_ending)
    with SerialEmulator(plant, a.protocol, fmt, vlimit_v=a.max_v) as emu:
        for link, target in zip(links, (emu.piezo_port, emu.sensor_port), strict=True):
            link.unlink(missing_ok=True)
            link.symlink_to(target)
        try:
            print(f"leveler emulate serial: the simulated plant ({args.config}, seed {seed}); "
                  f"piezo amplifier ({a.protocol}) at {a.port}, sensor controller at {s.port}"
                  "; Ctrl-C stops", flush=True)
            stop.wait()
        finally:
            for link in links:
                link.unlink(missing_ok=True)
    print(f"leveler emulate serial: stopped after {plant.n * plant.dt_s:.1f} s of plant time")
    return 0
