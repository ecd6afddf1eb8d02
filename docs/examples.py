"""The command transcripts in README.md and docs/*.md, made by running the commands.

A transcript is a fenced block whose first line starts with `$ `. Each `$` command (with
its `\\` continuation lines) runs in bash in a scratch directory that links the repository's
config/, with `leveler` the one beside this Python and $REPO the checkout; stdout and stderr
as a user sees them on a pipe (progress bars never reach one) replace the lines up to the
next `$` line. The commands of a block share the directory, so an import can feed an
analysis. A block that needs files it does not make names a SETUPS entry in an HTML comment
on the line before its fence: `<!-- example-setup: NAME -->`.

    python docs/examples.py            rewrite the transcripts that drifted, from the real commands
    python docs/examples.py --check    exit 1 and show the drift where one no longer matches

A transcript matches when its text is the same once numbers and runs of spaces are set
aside, and each number is within TOLERANCE_REL of the printed one or within two units of
its last printed digit: the same run on another machine's BLAS moves last digits, not the
story. A wall-clock time ("12.1 s wall") is free. tests/test_docs_examples.py runs --check
on every transcript, so a change that moves a number fails the suite until `make docs`.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
FILES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
TOLERANCE_REL = 0.01
_SETUP = re.compile(r"<!--\s*example-setup:\s*([\w-]+)\s*-->")
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
_WALL = re.compile(r"[-+]?\d+(?:\.\d+)?(?= s wall)")


def _bench(module: str) -> Any:
    """A module of bench/ (no package): the independent generators and the score scripts'
    helpers the worked examples are made with."""
    sys.path.insert(0, str(REPO / "bench"))
    try:
        return importlib.import_module(module)
    finally:
        sys.path.remove(str(REPO / "bench"))


def _thrust_stand(cwd: Path) -> None:
    """The stand's file the docs show the head of."""
    _bench("independent.thrust_stand").write_recording(1, cwd, scenario="stepped")


def _tiltmeter(cwd: Path) -> None:
    """The config a lab writes for seed 1's tiltmeter (the block makes the recording)."""
    truth = _bench("independent.tiltmeter").write_recording(1, cwd, "sine", drift_scale=0.1)
    (cwd / "stand.toml").write_text(_bench("com_score").stand_config(truth))


SETUPS: dict[str, Callable[[Path], None]] = {"thrust-stand-1": _thrust_stand,
                                             "tiltmeter-1": _tiltmeter}


@dataclass
class Transcript:
    """One block: where it sits, its setup, and its (command, output) pairs."""

    path: Path
    first: int  # index of the line after the opening fence
    last: int  # index of the closing fence
    setup: str | None
    steps: list[tuple[list[str], list[str]]]  # (command lines as written, output lines)

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(REPO)}:{self.first}"


def transcripts(path: Path) -> Iterator[Transcript]:
    lines = path.read_text().splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("```") and i + 1 < len(lines) and lines[i + 1].startswith("$ "):
            end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
            found = _SETUP.search(lines[i - 1]) if i else None
            yield Transcript(path, i + 1, end, found and found.group(1),
                             _steps(lines[i + 1 : end]))
            i = end
        i += 1


def _steps(body: list[str]) -> list[tuple[list[str], list[str]]]:
    steps: list[tuple[list[str], list[str]]] = []
    k = 0
    while k < len(body):
        command = [body[k]]
        while command[-1].endswith("\\"):
            k += 1
            command.append(body[k])
        k += 1
        start = k
        while k < len(body) and not body[k].startswith("$ "):
            k += 1
        steps.append((command, body[start:k]))
    return steps


def run_step(command: list[str], cwd: Path) -> list[str]:
    """The output of one `$ ...` command, run as a user runs it."""
    script = "\n".join(command)[2:]
    # One BLAS thread, as `make test` checks them: a thread count rounds a fit's sums
    # differently, and the 1 h closed-loop predictions of `tune --suggest` (through the
    # ADC's steps) move by up to 7 % with a fitted model 1e-5 apart.
    env = os.environ | {"REPO": str(REPO), "PYTHONUNBUFFERED": "1",  # stderr kept in order
                        "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",
                        "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(["bash", "-c", script], cwd=cwd, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"`{' '.join(command)}` exited {proc.returncode}:\n{proc.stdout}")
    # a path a command prints in full is relative to where the reader runs it
    return proc.stdout.replace(f"{cwd}/", "").rstrip("\n").splitlines()


def regenerate(t: Transcript) -> list[tuple[list[str], list[str]]]:
    """The block's steps with the output each command gives today."""
    with tempfile.TemporaryDirectory(prefix="leveler-docs-") as tmp:
        cwd = Path(tmp).resolve()
        (cwd / "config").symlink_to(REPO / "config")
        if t.setup:
            SETUPS[t.setup](cwd)
        return [(command, run_step(command, cwd)) for command, _ in t.steps]


def _skeleton(line: str) -> str:
    return " ".join(_NUMBER.sub("#", _WALL.sub("W", line)).split())


def _close(written: str, now: str) -> bool:
    a, b = float(written), float(now)
    digits = len(written.split("e")[0].split("E")[0].partition(".")[2])
    exp = int(re.split("[eE]", written)[1]) if re.search("[eE]", written) else 0
    return abs(a - b) <= max(TOLERANCE_REL * abs(a), 2 * 10.0 ** (exp - digits))


def drift(written: list[str], now: list[str]) -> str | None:
    """Where `now` departs from `written` beyond the tolerance, or None."""
    if len(written) != len(now):
        return f"{len(written)} lines written, {len(now)} now"
    for k, (w, n) in enumerate(zip(written, now, strict=True)):
        if _skeleton(w) != _skeleton(n):
            return f"line {k + 1} reads differently:\n  written: {w}\n  now:     {n}"
        for a, b in zip(_NUMBER.findall(_WALL.sub("W", w)), _NUMBER.findall(_WALL.sub("W", n)),
                        strict=True):
            if not _close(a, b):
                return f"line {k + 1}: {a} is now {b}:\n  written: {w}\n  now:     {n}"
    return None


def check(t: Transcript) -> str | None:
    """None when every output of the block still matches; else what moved."""
    for (command, written), (_, now) in zip(t.steps, regenerate(t), strict=True):
        moved = drift(written, now)
        if moved:
            return f"{t.where}: `{command[0]}`: {moved}"
    return None


def rewrite(path: Path) -> int:
    """Regenerate the transcripts of `path` in place; the number of outputs that changed.
    An output still within the tolerance is left as written: no churn of last digits and
    wall times in every commit."""
    lines = path.read_text().splitlines()
    changed = 0
    for t in reversed(list(transcripts(path))):  # from the end: line numbers stay valid
        body = []
        for (command, written), (_, now) in zip(t.steps, regenerate(t), strict=True):
            moved = drift(written, now) is not None
            changed += moved
            body += [*command, *(now if moved else written)]
        lines[t.first : t.last] = body
    path.write_text("\n".join(lines) + "\n")
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="compare instead of rewriting; exit 1 on drift")
    args = ap.parse_args(argv)
    if args.check:
        problems = [p for f in FILES for t in transcripts(f) if (p := check(t))]
        print("\n\n".join(problems) or "every transcript matches its command")
        return 1 if problems else 0
    for f in FILES:
        if any(True for _ in transcripts(f)):
            print(f"{f.relative_to(REPO)}: {rewrite(f)} output(s) changed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
