"""Shell completion, through the installed `leveler` console script as bash would run it:
argcomplete's environment protocol, the words written to _ARGCOMPLETE_STDOUT_FILENAME (in
place of the shell's fd 8). The script, not build_parser(), so the entry point's own wiring
(autocomplete before parse_args, the file completers) is what is tested."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

#: the console script pip generated beside this venv's interpreter
LEVELER = Path(sys.executable).with_name("leveler")


@pytest.fixture
def here(tmp_path: Path) -> Path:
    """The directory completion runs in: only what a test puts there (the output file is not)."""
    (tmp_path / "cwd").mkdir()
    return tmp_path / "cwd"


def complete(line: str, cwd: Path) -> list[str]:
    """The words `leveler` offers with the cursor at the end of `line`, run in `cwd`."""
    assert LEVELER.exists(), f"{LEVELER}: no console script (pip install -e . in this venv)"
    out = cwd.parent / "completions.out"
    env = {**os.environ, "_ARGCOMPLETE": "1", "_ARGCOMPLETE_IFS": "\n",
           "COMP_LINE": line, "COMP_POINT": str(len(line)),
           "_ARGCOMPLETE_STDOUT_FILENAME": str(out)}
    env.pop("_ARC_DEBUG", None)
    proc = subprocess.run([str(LEVELER)], cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    return [w.strip() for w in out.read_text().split("\n") if w.strip()]


@pytest.mark.parametrize(("line", "word"), [("leveler as", "asd"),
                                            ("leveler sim --du", "--duration")])
def test_commands_and_options_complete(here: Path, line: str, word: str) -> None:
    assert complete(line, here) == [word]


def test_log_argument_offers_mcap_files_only(here: Path) -> None:
    (here / "a.mcap").touch()
    (here / "b.txt").touch()
    (here / "runs").mkdir()
    words = complete("leveler replay ", here)
    assert "a.mcap" in words and "runs/" in words
    assert "b.txt" not in words


def test_config_option_offers_toml_files_only(here: Path) -> None:
    (here / "lab.toml").touch()
    (here / "a.mcap").touch()
    assert complete("leveler sim --config ", here) == ["lab.toml"]
