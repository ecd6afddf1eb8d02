"""`leveler run`: the leveling daemon in the foreground, as systemd starts it."""

from __future__ import annotations

import argparse

from leveler.cli.common import duration


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "run", help="run the leveling daemon in the foreground (what systemd starts)",
        description="Run the control loop in real time on the backend the config names "
        "(backend = \"sim\" runs the simulated plant). Prints a status line every "
        "loop.status_interval_s; logs every sample to <log.dir>/leveler-<UTC time>Z.mcap. "
        "Ctrl-C or SIGTERM stops it cleanly: actuator to its safe voltage, log finished.")
    p.add_argument("--config", required=True, help="TOML config file (e.g. config/sim.toml)")
    p.add_argument("--duration", type=duration, default=None,
                   help="stop by itself after this long (e.g. 90s, 10m); default: run until "
                   "signalled")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from leveler.daemon.service import run_daemon

    return run_daemon(args.config, duration_s=args.duration)
