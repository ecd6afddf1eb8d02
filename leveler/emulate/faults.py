"""`leveler emulate --fault T:KIND[:COUNT]`: a timed schedule of spoiled replies, so a lab can
watch its exact config ride through glitches, or fault and reconnect, before the real
hardware ever does it."""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

MODBUS_KINDS = ("no_reply", "exception", "garbage", "drop")
SERIAL_KINDS = ("no_reply", "garbage", "partial_line", "drop", "error")
SERIAL_PORTS = ("piezo", "sensor")


@dataclass(frozen=True, slots=True)
class Fault:
    """Spoil `count` replies from `at_s` seconds after the emulator starts serving; `kind`
    is a Modbus fault, or `port.fault` for the serial emulator."""

    at_s: float
    kind: str
    count: int = 1


def parse_fault(text: str) -> Fault:
    """argparse type for T:KIND[:COUNT]; the kind is checked against the emulator later."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        at_s = float(parts[0].removesuffix("s"))
        count = int(parts[2]) if len(parts) == 3 else 1
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected T:KIND[:COUNT], e.g. 30:garbage or 60:sensor.no_reply:3"
        ) from None
    if not (at_s >= 0 and count >= 1):
        raise argparse.ArgumentTypeError(f"{text!r}: T must be >= 0 s and COUNT >= 1")
    return Fault(at_s, parts[1], count)


def check_kinds(faults: list[Fault], emulator: str) -> None:
    """Refuse, before serving, a kind this emulator cannot produce."""
    for f in faults:
        if emulator == "modbus":
            ok = f.kind in MODBUS_KINDS
            expected = ", ".join(MODBUS_KINDS)
        else:
            port, _, kind = f.kind.partition(".")
            ok = port in SERIAL_PORTS and kind in SERIAL_KINDS
            expected = "piezo.X or sensor.X with X in " + ", ".join(SERIAL_KINDS)
        if not ok:
            raise ValueError(f"--fault {f.at_s:g}:{f.kind}: emulate {emulator} has no fault "
                             f"{f.kind!r} (expected {expected})")


def start_schedule(faults: list[Fault], inject: Callable[[Fault], None],
                   stop: threading.Event) -> threading.Thread:
    """Inject each fault at its time (from now) until `stop`; prints what it did, so the
    emulator's output lines up with the daemon's log."""
    t0 = time.monotonic()

    def run() -> None:
        for f in sorted(faults, key=lambda f: f.at_s):
            if stop.wait(max(0.0, t0 + f.at_s - time.monotonic())):
                return
            inject(f)
            print(f"leveler emulate: injected {f.kind} x{f.count} at "
                  f"{time.monotonic() - t0:.1f} s", flush=True)

    thread = threading.Thread(target=run, name="emulate-faults", daemon=True)
    thread.start()
    return thread
