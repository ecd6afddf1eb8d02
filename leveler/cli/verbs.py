"""`leveler start|stop|reset|rotate`: the one-word requests to the running daemon."""

from __future__ import annotations

import argparse

from leveler.cli.common import add_socket
from leveler.daemon.client import Client

#: each verb and what it asks the daemon to do (its help, and the start of its description)
VERBS = {
    "start": "close the loop (bumpless, from the voltage the piezo holds now)",
    "stop": "open the loop: keep sampling and logging, hold the piezo where it is",
    "reset": "leave the fault state after the cause is fixed (the loop stays open)",
    "rotate": "close the current log file and start a new one",
}


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    for name, text in VERBS.items():
        p = sub.add_parser(name, help=text, description=f"{text[0].upper()}{text[1:]}. Talks "
                           "to the running daemon over its control socket; needs membership of "
                           "the daemon's group (or root).")
        add_socket(p)
        p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    with Client(args.socket) as client, client.reading():
        if args.command == "rotate":
            print(f"logging to {client.request('rotate')['path']}")
        else:
            print(f"state: {client.request(args.command)['state']}")
    return 0
