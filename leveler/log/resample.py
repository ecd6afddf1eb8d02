"""A nearly uniform time base put on an exact one, with everything changed on the way reported.

Real loggers jitter, swap a pair of rows, write a row twice and miss a few samples; replay
and the spectra need one constant interval. Resampling sorts the rows, drops exact repeats,
and interpolates every column linearly onto the grid of the log's own mean interval. A gap
longer than the limit is an error, not a line drawn across it: minutes of invented data would
pass for a measurement. Every sample that no measured one stands near is flagged, so the log
says which readings were made up (`import-csv --resample`, docs/log-format.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from leveler.errors import LogError

GAP_FACTOR = 1.5  # an interval this many times the mean is a gap (samples missing)
DEFAULT_MAX_GAP_INTERVALS = 60  # 30 s at 2 Hz: a logger's hiccup, not an outage


@dataclass(frozen=True)
class Gap:
    """Samples missing between two rows of the file."""

    after_line: int  # the row before the gap
    before_line: int  # the row after it
    t_s: float  # the time the gap starts
    length_s: float  # from the row before to the row after
    filled: int  # grid samples interpolated in it


@dataclass
class Resampling:
    """What resampling did, line by line, for the import's report and the log's events."""

    interval_s: float
    rows_in: int
    moved: list[int] = field(default_factory=list)  # lines sorted in (out of order in the file)
    duplicates: list[int] = field(default_factory=list)  # lines repeating a row, dropped
    conflicts: list[int] = field(default_factory=list)  # a time already taken, other values
    gaps: list[Gap] = field(default_factory=list)
    filled: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # per output sample

    @property
    def rows_out(self) -> int:
        return len(self.filled)

    def summary(self) -> str:
        """One clause for the import's summary line."""
        longest = max((g.length_s for g in self.gaps), default=0.0)
        return (f"resampled {self.rows_in} rows onto {self.rows_out} at {self.interval_s:.9g} s "
                f"(moved {len(self.moved)}, repeats dropped {len(self.duplicates)}, "
                f"conflicting dropped {len(self.conflicts)}, gaps {len(self.gaps)} with "
                f"{int(self.filled.sum())} samples interpolated, longest {longest:.6g} s)")


def _nearest_distance(t: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Distance from each grid time to the nearest measured time."""
    i = np.clip(np.searchsorted(t, grid), 1, len(t) - 1)
    return np.minimum(np.abs(grid - t[i - 1]), np.abs(t[i] - grid))


def resample(t: np.ndarray, columns: dict[str, np.ndarray], lines: np.ndarray,
             max_gap_s: float | None, source: str) -> tuple[np.ndarray, dict[str, np.ndarray],
                                                              Resampling]:
    """(grid, columns on it, report): rows sorted by time, exact repeats dropped, each column
    interpolated linearly onto start + k * interval, the line through the rows' times against
    their places on the grid (the logger's clock, its jitter averaged out).

    Raises LogError naming the lines of the first gap longer than `max_gap_s` (default
    DEFAULT_MAX_GAP_INTERVALS intervals)."""
    running = np.maximum.accumulate(t)
    moved = lines[1:][t[1:] < running[:-1]].tolist()
    order = np.argsort(t, kind="stable")
    t, lines = t[order], lines[order]
    columns = {k: v[order] for k, v in columns.items()}
    same = np.flatnonzero(np.diff(t) == 0) + 1
    equal = np.ones(len(same), bool)
    for v in columns.values():
        equal &= v[same] == v[same - 1]
    report = Resampling(math.nan, len(t), moved, lines[same[equal]].tolist(),
                        lines[same[~equal]].tolist())
    keep = np.ones(len(t), bool)
    keep[same] = False
    t, lines = t[keep], lines[keep]
    columns = {k: v[keep] for k, v in columns.items()}
    dt = np.diff(t)
    median = float(np.median(dt))
    # each row's place on the grid, counted interval by interval (a count from the span alone,
    # (t_last - t_first) / median, is off by one on a day whose median is rounded to the
    # file's time resolution); the clock is the line through them, not the first row's jitter
    idx = np.concatenate([[0], np.cumsum(np.maximum(np.rint(dt / median), 1))])
    interval, start = (np.polyfit(idx, t, 1) if idx[-1] > 0 else (median, t[0]))
    interval, start, steps = float(interval), float(start), int(idx[-1])
    limit = DEFAULT_MAX_GAP_INTERVALS * interval if max_gap_s is None else max_gap_s
    too_long = np.flatnonzero(dt > limit)
    if too_long.size:
        i = int(too_long[0])
        raise LogError(
            f"{source}: line {lines[i + 1]}: {dt[i]:.6g} s without a sample since line "
            f"{lines[i]} ({too_long.size} gap{'s' if too_long.size > 1 else ''} longer than "
            f"{limit:.6g} s); resampling would invent that much data. Allow it with --max-gap, "
            "or import the parts on either side as separate logs.")
    grid = start + interval * np.arange(steps + 1)
    out = {k: np.interp(grid, t, v) for k, v in columns.items()}
    report.interval_s = interval
    report.filled = _nearest_distance(t, grid) > 0.5 * interval
    for i in np.flatnonzero(dt > GAP_FACTOR * interval):
        inside = (grid > t[i]) & (grid < t[i + 1])
        report.gaps.append(Gap(int(lines[i]), int(lines[i + 1]), float(t[i]), float(dt[i]),
                               int((inside & report.filled).sum())))
    return grid, out, report


__all__ = ["Gap", "Resampling", "resample"]
