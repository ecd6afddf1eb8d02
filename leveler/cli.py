"""The `leveler` command: one subcommand per job, each with --help that answers questions."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from leveler.config import ConfigError
from leveler.durations import parse_duration
from leveler.logreader import LogError


def _duration(text: str) -> float:
    try:
        return parse_duration(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _cmd_run(args: argparse.Namespace) -> int:
    from leveler.daemon import run_daemon

    return run_daemon(args.config, duration_s=args.duration)


def _cmd_sim(args: argparse.Namespace) -> int:
    from leveler.simcmd import run_sim_command

    return run_sim_command(args)


def _cmd_asd(args: argparse.Namespace) -> int:
    from leveler.asdcmd import run_asd_command

    return run_asd_command(args)


def _cmd_recover(args: argparse.Namespace) -> int:
    from leveler.logreader import recover

    n = recover(args.log, args.out)
    print(f"recovered {n} messages from {args.log} into {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="leveler",
        description="Real-time drag-free leveling of a tilting lab table: an inverted pendulum "
        "senses the tilt, a PID drives a piezo under one support, every sample goes to MCAP.",
        epilog="Units are SI throughout (m, rad, V, s, K). docs/ describes the config and the log.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser(
        "run", help="run the leveling daemon in the foreground (what systemd starts)",
        description="Run the control loop in real time on the backend the config names "
        "(backend = \"sim\" runs the simulated plant). Prints a status line every "
        "loop.status_interval_s; logs every sample to <log.dir>/leveler-<UTC time>Z.mcap. "
        "Ctrl-C or SIGTERM stops it cleanly: actuator to its safe voltage, log finished.")
    run.add_argument("--config", required=True, help="TOML config file (e.g. config/sim.toml)")
    run.add_argument("--duration", type=_duration, default=None,
                     help="stop by itself after this long (e.g. 90s, 10m); default: run until "
                     "signalled")
    run.set_defaults(func=_cmd_run)

    sim = sub.add_parser(
        "sim", help="simulate a long run in virtual time; report how much tilt the loop removed",
        description="Run the daemon's loop on the simulated plant in virtual time, closed loop "
        "and, with the same disturbance realization, open loop (piezo held). Reports the "
        "amplitude spectral density at 0.1 mHz, 1 mHz and 10 mHz of the in-loop sensor "
        "(pendulum-end displacement) and of the true platform tilt (out of loop).")
    sim.add_argument("--config", default="config/sim.toml",
                     help="TOML config (default: %(default)s)")
    sim.add_argument("--duration", type=_duration, default=parse_duration("24h"),
                     help="virtual time to simulate: 3600s, 90m, 6h, 1d (default: 24h; "
                     "0.1 mHz needs several hours)")
    sim.add_argument("--seed", type=int, default=None,
                     help="disturbance and noise seed (default: [sim] seed of the config)")
    sim.add_argument("--out", default=None, help="write the closed-loop run to this MCAP file")
    sim.add_argument("--json", action="store_true",
                     help="print one JSON object on stdout instead of the table")
    sim.add_argument("--plot", default=None, help="save open vs closed loop ASD plot (PNG)")
    sim.set_defaults(func=_cmd_sim)

    asd = sub.add_parser(
        "asd", help="amplitude spectral density of a logged channel (LPSD, log-spaced)",
        description="Estimate the ASD of one channel of a leveler MCAP log with the LPSD "
        "method (Troebs & Heinzel 2006), which keeps many averages at high frequency and "
        "still reaches 0.1 mHz in a long log. Channels: any numeric field of the sample "
        "topic (sensor_m, applied_v, error_m, ...) or, in simulated logs, the truth topic "
        "(tilt_rad, thermal_tilt_rad, pendulum_rad, ...).")
    asd.add_argument("log", help="MCAP log written by leveler")
    asd.add_argument("--channel", default="sensor_m",
                     help="field to analyse (default: %(default)s)")
    asd.add_argument("--compare", default=None,
                     help="a second log (e.g. open loop) drawn and tabulated against the first")
    asd.add_argument("--plot", default=None, help="save the ASD plot as PNG")
    asd.add_argument("--json", action="store_true", help="print the spectrum as JSON")
    asd.set_defaults(func=_cmd_asd)

    rec = sub.add_parser(
        "recover", help="copy everything readable from a crashed log into a complete file",
        description="A log cut short (power cut, SIGKILL) has no index; leveler's own reader "
        "still reads it, and this writes a complete copy that any MCAP tool opens.")
    rec.add_argument("log", help="the damaged MCAP file (left untouched)")
    rec.add_argument("--out", required=True, help="where to write the recovered copy")
    rec.set_defaults(func=_cmd_recover)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ConfigError, LogError) as exc:
        print(f"leveler {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"leveler {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
