"""Argparse pieces several commands share: a duration option type and the --socket option."""

from __future__ import annotations

import argparse

from leveler.cli.durations import parse_duration


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
