"""The command set that `leveler --help` offers, pinned: every command and subcommand with
its options, positionals and choices. A reorganisation of the code must not change what a
user types; a deliberate change of the interface updates tests/data/cli_surface.json with
`python tests/test_cli_surface.py --write`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from leveler.cli.main import build_parser

SURFACE = Path(__file__).with_name("data") / "cli_surface.json"


def surface(parser: argparse.ArgumentParser, path: str = "leveler") -> dict[str, Any]:
    """{"leveler tune": {"--kp": {...}, ...}, ...}: what each (sub)command accepts."""
    out: dict[str, Any] = {}
    args: dict[str, Any] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                out.update(surface(child, f"{path} {name}"))
            continue
        key = " ".join(action.option_strings) or action.dest
        choices = None if action.choices is None else sorted(map(str, action.choices))
        args[key] = {"nargs": action.nargs, "required": action.required, "choices": choices,
                     "flag": action.nargs == 0, "default": repr(action.default)}
    out[path] = args
    return out


def test_the_command_set_is_the_pinned_one() -> None:
    pinned = json.loads(SURFACE.read_text())
    now = surface(build_parser())
    assert sorted(now) == sorted(pinned), "commands differ"
    for command, options in pinned.items():
        assert now[command] == options, command


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    SURFACE.write_text(json.dumps(surface(build_parser()), indent=1, sort_keys=True) + "\n")
