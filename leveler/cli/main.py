# PYTHON_ARGCOMPLETE_OK: argcomplete's global completion looks for this in the first 1 KiB of
# the module the `leveler` console script imports
"""The `leveler` command: one subcommand per job, each with --help that answers questions."""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
from collections.abc import Sequence

import argcomplete

from leveler import __version__
from leveler.cli import (
    analyze,
    asd,
    calibrate_com,
    common,
    design,
    diagnose,
    emulate,
    import_csv,
    modulate,
    recover,
    reload,
    replay,
    run,
    sim,
    status,
    tune,
    verbs,
    watch,
)
from leveler.daemon.client import ClientError
from leveler.errors import ControlError, LogError
from leveler.typed_config import ConfigError

#: the commands, in the order `leveler --help` lists them: each module's add_parser(sub)
#: registers its subparser(s), whose `func` is the module's run(args)
COMMANDS = (run, sim, asd, recover, import_csv, replay, diagnose, emulate, design, analyze,
            calibrate_com, verbs, status, reload, watch, tune, modulate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="leveler",
        description="Real-time drag-free leveling of a tilting lab table: an inverted pendulum "
        "senses the tilt, a PID drives a piezo under one support, every sample goes to MCAP.",
        epilog="Units are SI throughout (m, rad, V, s, K). docs/ describes the config and the log.",
    )
    parser.add_argument("--version", action="version",
                        version=f"%(prog)s {__version__} (Python {sys.version.split()[0]})")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    common.add_file_completers(parser)
    return parser


#: what a shell reports for a command killed by SIGPIPE (`yes | head` gives it to `yes`)
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE


def _run(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    argcomplete.autocomplete(parser)  # under the shell's completion: print the words and exit
    args = parser.parse_args(argv)
    if args.command is None:  # a bare `leveler`: what it can do, not an error
        parser.print_help()
        return 0
    try:
        return int(args.func(args))
    except (ConfigError, LogError, ClientError, ControlError) as exc:
        print(f"leveler {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"leveler {args.command}: interrupted", file=sys.stderr)
        return 130


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Output into a pipe that closed early (`leveler status | head -3`)
    ends it quietly, as SIGPIPE ends other tools: no traceback, exit 141."""
    try:
        try:
            return _run(argv)
        finally:  # here rather than at exit, where a closed pipe can only be complained of
            sys.stdout.flush()
    except BrokenPipeError:
        with contextlib.suppress(OSError):  # nothing more may reach the closed pipe
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


if __name__ == "__main__":
    sys.exit(main())
