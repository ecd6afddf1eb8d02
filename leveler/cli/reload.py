"""`leveler reload`: the daemon re-reads its config file (as SIGHUP) and says what changed."""

from __future__ import annotations

import argparse
from typing import Any

from leveler.cli.common import add_socket
from leveler.daemon.client import Client


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "reload", help="re-read the daemon's config file (as SIGHUP), with its diff",
        description="Ask the running daemon to re-read its config file, as `systemctl reload "
        "leveler` (SIGHUP) does, and print what changed. The file is applied only whole: it "
        "must be valid, set every key the running file set (a file cut short at a line "
        "boundary is still valid TOML, and its missing keys would take their defaults), and "
        "new gains must make a loop the plant model predicts stable. [controller] applies at "
        "once (bumpless); other sections at the next restart. Every applied reload logs its "
        "diff of effective values (journal and the log's `reload` event).")
    p.add_argument("--accept-dropped", action="store_true",
                   help="apply even though the file no longer sets keys the running one set "
                   "(they go back to their defaults), or does not end with a newline (its "
                   "last line may be cut short)")
    p.add_argument("--force", action="store_true",
                   help="apply gains even if the plant model predicts an unstable loop")
    add_socket(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    with Client(args.socket) as client, client.reading():
        print(format_reload(client.request("reload", accept_dropped=args.accept_dropped,
                                           force=args.force)))
    return 0


def format_reload(reply: dict[str, Any]) -> str:
    """What a reload changed, one effective value a line; sections that wait for a restart."""
    changed = reply["changed"]
    lines = [f"reload applied: {len(changed)} value(s) changed"
             + (":" if changed else " (the file says what the daemon runs)")]
    lines += [f"  {key}: {old!r} -> {new!r}" for key, (old, new) in changed.items()]
    if reply["dropped"]:
        lines.append("back to their defaults (no longer in the file): "
                     + ", ".join(reply["dropped"]))
    if reply["needs_restart"]:
        lines.append("takes effect at the next restart: ["
                     + "], [".join(reply["needs_restart"]) + "]")
    return "\n".join(lines)
