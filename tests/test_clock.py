"""The real-time clock's schedule: what counts as an overrun."""

from __future__ import annotations

import time

from leveler.loop.clock import RealtimeClock


def test_start_up_before_the_first_tick_is_not_an_overrun() -> None:
    """The daemon builds its clock, then spends tens of ms starting (freezing the heap,
    opening the socket): its first cycle was due at no earlier time."""
    clock = RealtimeClock(0.01)
    time.sleep(0.05)  # five periods of start-up
    assert clock.tick() == 0.0
    assert clock.overruns == 0


def test_a_cycle_woken_more_than_a_period_late_is_an_overrun_and_the_schedule_skips() -> None:
    clock = RealtimeClock(0.01)
    clock.tick()
    time.sleep(0.035)  # the loop's work overran: deadlines at 10, 20 and 30 ms were missed
    t = clock.tick()
    assert clock.overruns == 1

    def on_grid(x: float) -> bool:
        return abs(x / 0.01 - round(x / 0.01)) < 1e-6

    assert t >= 0.02 and on_grid(t)  # a missed deadline skipped to, not "now"
    t2 = clock.tick()
    assert t2 >= t + 0.01 - 1e-9 and on_grid(t2)  # the same grid goes on: no catch-up burst
