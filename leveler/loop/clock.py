"""Clocks that hand the loop its time: real (absolute deadlines) or virtual (as fast as possible).

The loop never reads a clock itself; it asks one of these for the next tick, so the daemon,
`leveler sim` and the tests run exactly the same code.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np


class VirtualClock:
    """Ticks n * period without waiting; wall time is a fixed start plus virtual time."""

    def __init__(self, period_s: float, start_wall_ns: int | None = None) -> None:
        self.period_s = period_s
        self.start_wall_ns = time.time_ns() if start_wall_ns is None else start_wall_ns
        self._n = -1

    def tick(self) -> float:
        self._n += 1
        return self._n * self.period_s

    def wall_ns(self, t_s: float) -> int:
        return self.start_wall_ns + round(t_s * 1e9)


class RealtimeClock:
    """Paces on absolute deadlines (start + n * period) so jitter never accumulates.

    A cycle that wakes more than a period late is an overrun: counted, and the schedule
    skips the missed deadlines instead of bursting to catch up. Lateness and the measured
    periods of the last `window` cycles give the statistics the status line prints; they
    live in preallocated rings so that `stats()` (called from the control thread while the
    loop runs) costs well under a millisecond of interpreter time.

    Log times are the wall time at start plus monotonic time since: a step of the system
    clock (NTP, a person) never reorders or duplicates log times; `wall_step_ns` says how far
    the system clock has moved away from that timeline, for the daemon to report.
    """

    def __init__(self, period_s: float, window: int = 10_000,
                 wall_now_ns: Callable[[], int] = time.time_ns) -> None:
        self.period_s = period_s
        self._period_ns = round(period_s * 1e9)
        self._wall_now_ns = wall_now_ns
        self._start_ns = time.monotonic_ns()
        self._wall0_ns = wall_now_ns()
        self._next_ns = self._start_ns
        self._last_ns: int | None = None
        self.overruns = 0
        self.cycles = 0
        self._periods_ns = np.zeros(window, dtype=np.int64)
        self._late_ns = np.zeros(window, dtype=np.int64)
        self._stats: dict[str, float] | None = None
        self._stats_at = 0.0

    def tick(self) -> float:
        """Sleep until the next deadline; returns loop time (s since start) of that deadline.

        The first tick starts the schedule (loop time 0): the daemon's start-up between
        building the clock and its first cycle is not a late cycle."""
        now = time.monotonic_ns()
        if self._last_ns is None:
            self._start_ns = self._next_ns = now
            self._wall0_ns = self._wall_now_ns()
        elif self._next_ns > now:
            time.sleep((self._next_ns - now) / 1e9)
            now = time.monotonic_ns()
        late = now - self._next_ns
        if late > self._period_ns:
            self.overruns += 1
            self._next_ns += (late // self._period_ns) * self._period_ns
        deadline = self._next_ns
        self._next_ns += self._period_ns
        i = self.cycles % len(self._late_ns)
        self._late_ns[i] = now - deadline
        self._periods_ns[i] = now - self._last_ns if self._last_ns is not None else self._period_ns
        self._last_ns = now
        self.cycles += 1
        return (deadline - self._start_ns) / 1e9

    def wall_ns(self, t_s: float) -> int:
        return self._wall0_ns + round(t_s * 1e9)

    def wall_step_ns(self) -> int:
        """System wall time minus this clock's timeline, now (0 until the clock steps)."""
        return self._wall_now_ns() - (self._wall0_ns + time.monotonic_ns() - self._start_ns)

    def stats(self, max_age_s: float = 1.0) -> dict[str, float]:
        """Period p50/p99/max and lateness p99 in seconds over the recent window.

        Recomputed at most every max_age_s: the percentiles hold the interpreter lock for
        a fraction of a millisecond, and a client polling status must not make the loop
        late (measured: uncached, 50 status requests/s cost a 1 kHz loop ~0.8% overruns).
        """
        now = time.monotonic()
        if self._stats is not None and now - self._stats_at < max_age_s:
            return self._stats
        self._stats, self._stats_at = self._compute_stats(), now
        return self._stats

    def _compute_stats(self) -> dict[str, float]:
        n = min(self.cycles, len(self._late_ns))
        if n < 2:
            return {"period_p50_s": 0.0, "period_p99_s": 0.0, "period_max_s": 0.0,
                    "late_p99_s": 0.0}
        per = self._periods_ns[:n] / 1e9
        late = self._late_ns[:n] / 1e9
        return {
            "period_p50_s": float(np.percentile(per, 50)),
            "period_p99_s": float(np.percentile(per, 99)),
            "period_max_s": float(per.max()),
            "late_p99_s": float(np.percentile(late, 99)),
        }
