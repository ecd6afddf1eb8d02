"""`leveler watch`: a live view of the running loop, values and a trend of the sensor."""

from __future__ import annotations

import argparse
import sys

from leveler.cli.common import add_socket
from leveler.daemon.client import Client

_BARS = " ▁▂▃▄▅▆▇█"


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("watch", help="live view of the running loop: values and a small trend",
                       description="Stream samples from the running daemon at a decimated rate "
                       "and show them with a trend of the last 40 sensor readings. Ctrl-C ends "
                       "it (the daemon carries on).")
    p.add_argument("--rate", type=float, default=2.0, help="samples per second (default: 2)")
    p.add_argument("--count", type=int, default=None, help="stop after this many samples")
    add_socket(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print samples as they come: values and a trend of the last 40 sensor readings."""
    tty = sys.stdout.isatty()
    trend: list[float] = []
    with Client(args.socket) as client, client.reading():
        for n, s in enumerate(client.watch(args.rate), start=1):
            if s["sensor_m"] is not None:
                trend = [*trend[-39:], s["sensor_m"]]
            sensor = (f"{s['sensor_m'] * 1e9:+9.2f} nm" if s["sensor_m"] is not None
                      else "   (no reading)")
            line = (f"t={s['t_s']:10.2f} s  {s['state']:<7}  sensor={sensor}  "
                    f"piezo={s['applied_v']:8.3f} V  {sparkline(trend)}")
            sys.stdout.write(f"\r{line}\033[K" if tty else f"{line}\n")
            sys.stdout.flush()
            if args.count is not None and n >= args.count:
                break
        if tty:
            sys.stdout.write("\n")
    return 0


def sparkline(values: list[float]) -> str:
    """A small trend: one block character per value, scaled to the window's range."""
    if not values:
        return ""
    lo, hi = min(values), max(values)
    span = hi - lo or 1.0
    return "".join(_BARS[round((v - lo) / span * (len(_BARS) - 1))] for v in values)
