"""`leveler emulate`: the simulated plant behind the real protocol, so a lab can test its
exact config (addresses, scaling, limits) on a laptop before touching the table."""

from __future__ import annotations

import argparse
import signal
import threading

from leveler.config import ConfigError
from leveler.settings import load_config
from leveler.sim.plant import Plant


def run_emulate_command(args: argparse.Namespace) -> int:
    cfg, _ = load_config(args.config)
    seed = cfg.sim.seed if args.seed is None else args.seed
    plant = Plant(cfg.plant, 1.0 / cfg.loop.rate_hz, seed)
    if args.kind != "modbus":
        raise ConfigError(f"leveler emulate {args.kind}: not available yet (modbus is)")
    s, a = cfg.sensor.modbus, cfg.actuator.modbus
    if cfg.sensor.backend != "modbus" or s is None or a is None:
        raise ConfigError(f"{args.config}: emulate modbus needs backend = \"modbus\" with "
                          "[sensor.modbus] and [actuator.modbus] tables")
    if s.transport != "tcp" or a.transport != "tcp" or (s.host, s.port) != (a.host, a.port):
        raise ConfigError(f"{args.config}: the emulator serves one Modbus TCP module: "
                          "sensor.modbus and actuator.modbus need transport = \"tcp\" and the "
                          "same host and port")
    from leveler.emulate_modbus import ModbusEmulator

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with ModbusEmulator(plant, s, a, host=s.host, port=s.port) as emu:
        print(f"leveler emulate modbus: the simulated plant ({args.config}, seed {seed}) on "
              f"{s.host}:{emu.port}; sensor in registers {s.register}..{s.register + s.words - 1}"
              f", piezo in {a.register}..{a.register + a.words - 1}; Ctrl-C stops", flush=True)
        stop.wait()
    print(f"leveler emulate modbus: stopped after {plant.n * plant.dt_s:.1f} s of plant time")
    return 0
