"""`leveler recover`: a complete copy of a log that a crash cut short."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "recover", help="copy everything readable from a crashed log into a complete file",
        description="A log cut short (power cut, SIGKILL) has no index; leveler's own reader "
        "still reads it, and this writes a complete copy that any MCAP tool opens.")
    p.add_argument("log", help="the damaged MCAP file (left untouched)")
    p.add_argument("--out", required=True, help="where to write the recovered copy")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from leveler.log.reader import recover

    n = recover(args.log, args.out)
    print(f"recovered {n} messages from {args.log} into {args.out}")
    return 0
