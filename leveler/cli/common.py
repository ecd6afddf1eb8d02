"""Argparse pieces several commands share: a duration option type, the --socket option and
the shell completion of file arguments."""

from __future__ import annotations

import argparse

from argcomplete.completers import FilesCompleter

from leveler.cli.durations import parse_duration

#: what a shell offers for these options (and their directories); any other file argument
#: gets argcomplete's default, every file
CONFIG_OPTIONS = frozenset({"--config", "--model"})
CONFIG_FILES = FilesCompleter(allowednames=("toml",))
LOG_FILES = FilesCompleter(allowednames=("mcap",))


def duration(text: str) -> float:
    """An option type for durations: '90s', '10m', '6h', '1d' (a unit is required)."""
    try:
        return parse_duration(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_socket(p: argparse.ArgumentParser) -> None:
    """--socket: which running daemon a command talks to."""
    p.add_argument("--socket", default=None,
                   help="control socket of the daemon (default: $LEVELER_SOCKET, then "
                   "/run/leveler/control.sock, then your own runtime directory's)")


def add_file_completers(parser: argparse.ArgumentParser) -> None:
    """Offer *.toml for --config/--model and *.mcap for a LOG positional, in `parser` and all
    its subcommands: set here in one walk so a command module need not know of completion."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                add_file_completers(subparser)
        elif CONFIG_OPTIONS.intersection(action.option_strings):
            action.completer = CONFIG_FILES  # type: ignore[attr-defined]
        elif not action.option_strings and action.dest == "log":
            action.completer = LOG_FILES  # type: ignore[attr-defined]
