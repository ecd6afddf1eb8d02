"""A plain progress bar on stderr for long virtual-time runs."""

from __future__ import annotations

import sys
import time


class ProgressBar:
    """A plain progress bar on stderr, redrawn at most a few times a second."""

    def __init__(self, label: str, total_s: float) -> None:
        self.label, self.total_s = label, total_s
        self._last = 0.0
        self._tty = sys.stderr.isatty()

    def __call__(self, frac: float) -> None:
        now = time.monotonic()
        if now - self._last < (0.25 if self._tty else 5.0) and frac < 1.0:
            return
        self._last = now
        bar = "#" * int(frac * 30)
        end = "\r" if self._tty else "\n"
        sys.stderr.write(f"{self.label} [{bar:<30}] {frac * 100:5.1f}% "
                         f"{frac * self.total_s / 3600:6.2f}/{self.total_s / 3600:.2f} h{end}")
        sys.stderr.flush()

    def done(self) -> None:
        self(1.0)
        if self._tty:
            sys.stderr.write("\n")
