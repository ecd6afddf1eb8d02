"""Progress of long commands on stderr: tqdm's bar, with rate and time left, on a terminal;
nothing on a pipe or with --json, where it would only be noise in a file or a parser's way."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

from tqdm import tqdm


def shown(quiet: bool = False) -> bool:
    """A bar only where someone watches: stderr is a terminal and no --json was asked."""
    return not quiet and sys.stderr.isatty()


def bar(label: str, total: float, unit: str, *, quiet: bool = False,
        scale: float = 1.0) -> tqdm:
    """A bar over `total` (in `unit` after `scale`); a disabled one when not `shown`."""
    return tqdm(total=total * scale, desc=label, unit=unit, file=sys.stderr,
                disable=not shown(quiet), dynamic_ncols=True, leave=True,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.3g}/{total:.3g} {unit} "
                           "[{elapsed}<{remaining}, {rate_fmt}]")


def fraction(b: tqdm) -> Callable[[float], None]:
    """A `progress(fraction done)` callback that moves `b` (run_virtual, read_log)."""
    def update(frac: float) -> None:
        b.update(frac * b.total - b.n)
    return update


def reading(path: str | Path, *, quiet: bool = False) -> tqdm:
    """A bar over the bytes of the log at `path` [MB], moved by read_log's `progress`."""
    size = os.path.getsize(path) if os.path.isfile(path) else 0
    return bar(f"reading {Path(path).name}", size, "MB", quiet=quiet, scale=1e-6)


class Stages:
    """One bar per stage of an analysis that reports `(stage, done, total)`; a new stage
    fills and closes the bar of the last one (it is over), so a terminal shows where a
    minute-long run stands. A context manager: leaving it normally ends the last stage."""

    def __init__(self, command: str, *, quiet: bool = False) -> None:
        self.command, self.quiet = command, quiet
        self._stage: str | None = None
        self._bar: tqdm | None = None

    def __enter__(self) -> Stages:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        self._close(finished=kind is None)

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not shown(self.quiet):
            return
        if stage != self._stage or self._bar is None:
            self._close(finished=True)
            self._stage = stage
            self._bar = tqdm(total=total, desc=f"{self.command}: {stage}", unit="step",
                             file=sys.stderr, dynamic_ncols=True, leave=True)
        self._bar.update(done - self._bar.n)

    def _close(self, finished: bool) -> None:
        if self._bar is not None:
            if finished:
                self._bar.update(self._bar.total - self._bar.n)
            self._bar.close()
            self._bar = None
