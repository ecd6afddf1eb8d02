"""The docs cannot go stale: every `$ ...` transcript in README.md and docs/*.md is rerun
and must match what is written (docs/examples.py: same text, numbers within 1 % or two
units of their last digit); the README's command table names every command."""

from __future__ import annotations

import re
import sys

import pytest
from conftest import REPO

from leveler.cli.main import build_parser

sys.path.insert(0, str(REPO / "docs"))  # docs/ is no package
import examples

BLOCKS = [t for f in examples.FILES for t in examples.transcripts(f)]


def test_the_readme_and_the_procedures_have_transcripts() -> None:
    where = {t.path.name for t in BLOCKS}
    assert {"README.md", "procedures.md"} <= where
    readme = [c[0] for t in BLOCKS if t.path.name == "README.md" for c, _ in t.steps]
    assert any(c.startswith("$ leveler sim") for c in readme)


@pytest.mark.parametrize("block", BLOCKS, ids=[t.where for t in BLOCKS])
def test_each_transcript_is_what_its_commands_print(block: examples.Transcript) -> None:
    moved = examples.check(block)
    assert moved is None, f"{moved}\n(run `make docs` if the change is meant)"


@pytest.mark.parametrize(("written", "now", "ok"), [
    ("0.1 mHz  7.16   0.00194   3697.6x", "0.1 mHz  7.16   0.00194   3697.6x", True),
    ("0.1 mHz  7.16   0.00194   3697.6x", "0.1 mHz  7.17   0.00194   3697.6x", True),
    ("0.1 mHz  7.16   0.00194   3697.6x", "0.1 mHz  7.16   0.00194   3797.6x", False),
    ("ratio 117.6x", "ratio 5378.0x", False),
    ("a plain integrator", "an integral with damping", False),
    ("K0 = 0.075767 +- 0.0012", "K0 = 0.075769 +- 0.0012", True),
    ("2.53e-09", "2.55e-09", True),
    ("2.53e-09", "2.53e-08", False),
    ("in 12.1 s wall", "in 31.9 s wall", True),
    ("199315 samples", "199316 samples", True),
    ("199315 samples", "199318 samples", True),  # within 1 %
    ("3 samples", "6 samples", False),
])
def test_drift_is_told_from_noise(written: str, now: str, ok: bool) -> None:
    assert (examples.drift([written], [now]) is None) is ok
    assert examples.drift([written], [now, now]) is not None  # a line more is drift


def test_the_command_table_lists_every_command() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and "sim" in a.choices)
    table = [line for line in (REPO / "README.md").read_text().splitlines()
             if line.startswith("| `leveler")]
    listed = set(re.findall(r"`leveler ([a-z-]+)", "\n".join(table)))
    listed |= {w for line in table for w in re.findall(r"`leveler [a-z-]+` / `([a-z-]+)`", line)}
    missing = set(sub.choices) - listed
    assert not missing, f"README's command table lacks {sorted(missing)}"
