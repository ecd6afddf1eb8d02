"""`leveler emulate`: the simulated plant behind the real protocol, so a lab can test its
exact config (addresses, scaling, limits) on a laptop before touching the table."""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from leveler.emulate.faults import Fault, check_kinds, parse_fault, start_schedule
from leveler.typed_config import ConfigError

if TYPE_CHECKING:
    from leveler.settings import Config
    from leveler.sim.plant import Plant


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "emulate", help="serve the simulated plant over the real device protocol",
        description="Stand in for the hardware: serve the simulated plant ([plant] of the "
        "config) through the protocol the config's drivers speak, at the addresses and "
        "with the scaling the config gives, so `leveler run --config` the same file levels "
        "it exactly as it would the real table. modbus: a Modbus TCP server at "
        "[sensor.modbus] host:port (input registers: the sensor; holding registers: the "
        "piezo). serial: a piezo amplifier ([actuator.serial] protocol) and a sensor "
        "controller on pseudo-terminals, linked at the config's port paths (which must be "
        "free paths, e.g. /tmp/leveler-piezo, not real devices); modbus with transport = "
        "\"rtu\" serves a pty linked at serial_port. Runs until Ctrl-C.")
    p.add_argument("kind", choices=["modbus", "serial"], help="which protocol to serve")
    p.add_argument("--config", required=True, help="the lab config to serve")
    p.add_argument("--seed", type=int, default=None,
                   help="disturbance and noise seed (default: [sim] seed)")
    p.add_argument("--fault", action="append", default=[], type=parse_fault,
                   metavar="T:KIND[:COUNT]",
                   help="spoil COUNT (default 1) replies from T seconds after the start; "
                   "repeatable. modbus KINDs: no_reply, exception (code 4), garbage, drop. "
                   "serial KINDs: piezo.X or sensor.X with X one of no_reply, garbage, "
                   "partial_line, drop, error. E.g. --fault 30:garbage --fault 60:exception:2")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging

    from leveler.settings import load_config
    from leveler.sim.plant import Plant

    cfg, _ = load_config(args.config)
    try:
        check_kinds(args.fault, args.kind)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    seed = cfg.sim.seed if args.seed is None else args.seed
    plant = Plant(cfg.plant, 1.0 / cfg.loop.rate_hz, seed)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if args.kind == "serial":
        return _serial(args, cfg, plant, seed, stop)
    # A client that gave up on a late reply makes pymodbus print "Cancel send, because not
    # connected!" and a frame dump; the client (the daemon) reports its side of it.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    return _modbus(args, cfg, plant, seed, stop)


def _modbus(args: argparse.Namespace, cfg: Config, plant: Plant, seed: int,
            stop: threading.Event) -> int:
    """One module serving sensor and actuator: Modbus TCP at the config's host and port, or
    RTU on a pty linked at its serial_port."""
    s, a = cfg.sensor.modbus, cfg.actuator.modbus
    if cfg.sensor.backend != "modbus" or cfg.actuator.backend != "modbus" or s is None or a is None:
        raise ConfigError(f"{args.config}: emulate modbus needs backend = \"modbus\" with "
                          "[sensor.modbus] and [actuator.modbus] tables")
    if s.transport != a.transport:
        raise ConfigError(f"{args.config}: sensor.modbus.transport = \"{s.transport}\" but "
                          f"actuator.modbus.transport = \"{a.transport}\": the emulator serves "
                          "one module on one link")
    if s.transport == "tcp" and (s.host, s.port) != (a.host, a.port):
        raise ConfigError(f"{args.config}: the emulator serves one Modbus TCP module: "
                          "sensor.modbus and actuator.modbus need the same host and port")
    if s.transport == "rtu" and s.serial_port != a.serial_port:
        raise ConfigError(f"{args.config}: the emulator serves one Modbus RTU module on one "
                          "line: sensor.modbus.serial_port and actuator.modbus.serial_port "
                          f"differ ({s.serial_port!r}, {a.serial_port!r})")
    link = (_link_path(args, "sensor.modbus.serial_port", s.serial_port)
            if s.transport == "rtu" else None)
    from leveler.emulate.modbus import ModbusEmulator
    from leveler.rt import freeze_heap

    th = cfg.thermometer.modbus if cfg.thermometer.backend == "modbus" else None
    if th is not None and (th.transport, th.host, th.port, th.serial_port) != (
            s.transport, s.host, s.port, s.serial_port):
        raise ConfigError(f"{args.config}: the emulator serves one Modbus module: "
                          "thermometer.modbus needs the sensor's link (transport, host, port, "
                          "serial_port)")
    with (ModbusEmulator(plant, s, a, host=s.host, port=s.port, transport=s.transport,
                         thermometer_cfg=th) as emu,
          _linked({} if link is None else {link: emu.serial_port})):
        where = f"{s.host}:{emu.port}" if link is None else f"Modbus RTU at {link}"
        print(f"leveler emulate modbus: the simulated plant ({args.config}, seed {seed}) on "
              f"{where}; sensor in registers {s.register}..{s.register + s.words - 1}"
              f", piezo in {a.register}..{a.register + a.words - 1}"
              + (f", thermometer in {th.register}..{th.register + th.words - 1}" if th else "")
              + "; Ctrl-C stops", flush=True)

        def inject(f: Fault) -> None:
            emu.inject(f.kind, f.count)  # type: ignore[arg-type]  # checked by check_kinds

        start_schedule(args.fault, inject, stop)
        freeze_heap()  # a module answers in bounded time: no full collection of the set-up
        _wait_for(stop)
    print(f"leveler emulate modbus: stopped after {plant.n * plant.dt_s:.1f} s of plant time")
    return 0


def _serial(args: argparse.Namespace, cfg: Config, plant: Plant, seed: int,
            stop: threading.Event) -> int:
    """A piezo amplifier and a sensor controller on ptys, linked at the config's ports."""
    s, a = cfg.sensor.serial, cfg.actuator.serial
    if cfg.sensor.backend != "serial" or s is None or a is None:
        raise ConfigError(f"{args.config}: emulate serial needs backend = \"serial\" with "
                          "[sensor.serial] and [actuator.serial] tables")
    piezo_link = _link_path(args, "actuator.serial.port", a.port)
    sensor_link = _link_path(args, "sensor.serial.port", s.port)
    from leveler.emulate.serial import SensorFormat, SerialEmulator
    from leveler.rt import freeze_heap

    decimals = max(0, math.ceil(math.log10(s.scale_m_per_unit / 1e-12)))
    fmt = SensorFormat(query=s.query, unit_m=s.scale_m_per_unit, decimals=decimals,
                       line_ending=s.line_ending)
    with (SerialEmulator(plant, a.protocol, fmt, vlimit_v=a.max_v) as emu,
          _linked({piezo_link: emu.piezo_port, sensor_link: emu.sensor_port})):
        print(f"leveler emulate serial: the simulated plant ({args.config}, seed {seed}); "
              f"piezo amplifier ({a.protocol}) at {a.port}, sensor controller at {s.port}"
              "; Ctrl-C stops", flush=True)

        def inject(f: Fault) -> None:
            port, _, kind = f.kind.partition(".")
            emu.inject(kind, f.count, port=port)  # type: ignore[arg-type]  # checked

        start_schedule(args.fault, inject, stop)
        freeze_heap()  # a module answers in bounded time: no full collection of the set-up
        _wait_for(stop)
    print(f"leveler emulate serial: stopped after {plant.n * plant.dt_s:.1f} s of plant time")
    return 0


def _wait_for(stop: threading.Event) -> None:
    """Wait for SIGINT/SIGTERM. A signal the kernel hands to a server thread does not wake
    the main thread's lock wait, and Python runs the handler only in the main thread: an
    endless `stop.wait()` hung SIGTERM about once in 60 runs, so wake to let it run."""
    while not stop.wait(0.2):
        pass


def _link_path(args: argparse.Namespace, key: str, port: str) -> Path:
    """The config's port as a path the emulator may point at its pty: never a real device."""
    link = Path(port)
    if not link.name or (link.exists() and not link.is_symlink()):
        raise ConfigError(f"{args.config}: {key} {port!r} is not a path the emulator may "
                          "link (empty, or an existing device or file)")
    return link


@contextlib.contextmanager
def _linked(links: dict[Path, str]) -> Iterator[None]:
    """Symlink each path to its pty while the emulator serves (replacing a stale link from
    a killed run), and remove the links afterwards."""
    try:
        for link, target in links.items():
            link.unlink(missing_ok=True)
            link.symlink_to(target)
        yield
    finally:
        for link in links:
            link.unlink(missing_ok=True)
