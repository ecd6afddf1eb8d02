"""What keeps the log writer out of the 1 kHz loop's way, and bench/loop_timing.py's arithmetic
(the timings themselves are `make bench`'s)."""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

import leveler.log.writer as lw
from leveler.records import Sample
from leveler.rt import background_thread, demote_thread

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _sample(seq: int) -> Sample:
    return Sample(seq, seq / 1000, 0, 0.0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 75.0, 75.0, False, "idle")


def test_a_backlog_wakes_the_writer_at_once(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """The loop's hand-off wakes the writer once _WAKE_BACKLOG records wait: its work then
    starts right after a cycle, not at whatever moment its poll timer ends."""
    monkeypatch.setattr(lw, "_POLL_S", 30.0)  # left alone, the writer would sleep 30 s
    with lw.LogWriter(tmp_path / "x.mcap") as log:
        for i in range(lw._WAKE_BACKLOG - 1):
            log.sample(_sample(i), 1_000_000 * i)
        time.sleep(0.2)
        assert log.backlog == lw._WAKE_BACKLOG - 1  # nobody woke it
        log.sample(_sample(lw._WAKE_BACKLOG - 1), 10**9)
        assert log.wait_drained(0, timeout=5.0)  # (wait_drained wakes it too: check first)
        assert log.samples_written == lw._WAKE_BACKLOG


def test_a_backlog_wakes_the_writer_without_help(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(lw, "_POLL_S", 30.0)
    with lw.LogWriter(tmp_path / "x.mcap") as log:
        for i in range(lw._WAKE_BACKLOG):
            log.sample(_sample(i), 1_000_000 * i)
        deadline = time.monotonic() + 5.0
        while log.samples_written < lw._WAKE_BACKLOG and time.monotonic() < deadline:
            time.sleep(0.01)
        assert log.samples_written == lw._WAKE_BACKLOG


def _in_thread(fn: object) -> tuple[int, int]:
    """(policy, priority) of a fresh thread after it ran fn."""
    got: list[tuple[int, int]] = []

    def body() -> None:
        fn()  # type: ignore[operator]
        got.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))

    t = threading.Thread(target=body)
    t.start()
    t.join()
    return got[0]


def _fifo(priority: int) -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        pytest.skip("needs CAP_SYS_NICE (root) for SCHED_FIFO")


def test_log_threads_stay_real_time_below_the_loop() -> None:
    errors: list[BaseException] = []

    def as_loop_then_background() -> None:
        try:
            _fifo(50)
        except BaseException as e:  # the skip, raised in the main thread below
            errors.append(e)
            return
        background_thread()

    policy, prio = _in_thread(as_loop_then_background)
    if errors:
        raise errors[0]
    assert policy == os.SCHED_FIFO and prio == os.sched_get_priority_min(os.SCHED_FIFO)


def test_background_thread_leaves_normal_scheduling_alone() -> None:
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        pytest.skip("the test runner itself is real-time")
    assert _in_thread(background_thread) == (os.SCHED_OTHER, 0)


def test_control_threads_still_drop_to_normal_scheduling() -> None:
    errors: list[BaseException] = []

    def as_loop_then_demote() -> None:
        try:
            _fifo(50)
        except BaseException as e:
            errors.append(e)
            return
        demote_thread()

    got = _in_thread(as_loop_then_demote)
    if errors:
        raise errors[0]
    assert got == (os.SCHED_OTHER, 0)


# ---- bench/loop_timing.py's arithmetic -------------------------------------------------------

@pytest.fixture
def bench(monkeypatch: pytest.MonkeyPatch) -> Iterator[ModuleType]:
    monkeypatch.syspath_prepend(str(BENCH))
    import loop_timing

    yield loop_timing
    for name in ("common", "loop_timing"):
        sys.modules.pop(name, None)


def test_percentiles_and_late_cycles_read_histograms_as_cyclictest(bench: ModuleType) -> None:
    hist = [0] * (bench.HIST_US + 1)
    hist[20] = 98
    hist[300] = 1
    hist[1000] = 1  # exactly one period: not late (cyclictest counts from 1001 us)
    assert bench.pct_us(hist, 0.5) == 20 and bench.pct_us(hist, 0.99) == 300
    assert bench.late_cycles(hist) == 0
    hist[1001] = 3
    hist[bench.HIST_US] = 2  # overflows
    assert bench.late_cycles(hist) == 5
    assert bench.per_1e5(5, 50_000) == 10.0


def test_rss_growth_skips_the_warm_up(bench: ModuleType) -> None:
    rss = [(float(t), 1000 + 10 * t) for t in range(0, 101)]  # 10 KiB/s throughout
    g = bench.rss_growth(rss)
    assert (g.first_kib, g.last_kib, g.span_s, g.spread_kib) == (1200, 2000, 80.0, 800)
    assert g.fitted_kib == pytest.approx(800)
    assert bench.rss_growth([(0.0, 5), (1.0, 6)]) is None


def test_rss_growth_is_a_fit_one_swing_at_the_end_is_not_a_leak(bench: ModuleType) -> None:
    rss = [(float(t), 1000 + (300 if t % 2 else 0)) for t in range(0, 100)]  # flat, swinging
    rss.append((100.0, 1600))  # the last reading high: last - first = 600 KiB
    g = bench.rss_growth(rss)
    assert g.last_kib - g.first_kib == 600 and g.spread_kib == 600
    assert abs(g.fitted_kib) < 60  # the fit sees the flat run


def _run(bench: ModuleType, late_us: dict[int, int], **extra: object) -> dict[str, object]:
    hist = [0] * (bench.HIST_US + 1)
    for k, v in late_us.items():
        hist[k] = v
    return {"late_hist": hist, "late_max_ns": max(late_us) * 1000, "cycles": sum(hist),
            "gil_late_hist": [0] * (bench.HIST_US + 1), "work_cpu_hist": [0] * 2001,
            "work_cpu_mean_ns": 20_000.0, "work_cpu_max_ns": 90_000,
            "period_cpu_mean_ns": 60_000.0, "overruns": 0, "samples_written": sum(hist) + 1,
            "dropped": 0, "log_error": "", "usage": {"minflt": 0, "majflt": 0, "nvcsw": 0,
                                                       "nivcsw": 0},
            "rss_runs": [[(float(t), 400_000) for t in range(30)]],
            "rt": {"policy": "SCHED_FIFO", "priority": 50, "mlockall": "locked",
                   "sched_error": ""}, **extra}


@pytest.mark.parametrize("with_cyclictest", [True, False])
def test_rows_are_well_formed_and_judged(bench: ModuleType, with_cyclictest: bool) -> None:
    m: dict[str, object] = {
        "logged": _run(bench, {20: 980, 100: 19, 2000: 1}),
        "unlogged": _run(bench, {20: 1000}), "bare": _run(bench, {15: 1000}),
        "live": _run(bench, {20: 970, 100: 10, 2000: 20}, work_cpu_mean_ns=30_000.0,
                     watched={"/leveler/sample": 50}),
        "plan": bench.plan(False, None), "priority": 50, "quick": False}
    if with_cyclictest:
        m["cyclictest"] = {"late_hist": _run(bench, {18: 999, 1500: 1})["late_hist"],
                           "late_max_ns": 1_500_000, "cycles": 1000, "cmd": "cyclictest ..."}
    rows = bench.rows(m)
    keys = {"section", "what", "value", "unit", "baseline", "ratio", "goal", "met", "note"}
    assert all(set(r) == keys and r["section"] == "loop timing" for r in rows)
    by = {r["what"]: r for r in rows}
    assert by["real-time policy: SCHED_FIFO 50"]["met"] is True
    p99 = by["lateness p99, 1 kHz daemon, logging on"]
    late = by["late cycles (>1 period) per 1e5, log on"]
    assert p99["value"] == 100.0 and late["value"] == 100.0  # 1 of 1000
    if with_cyclictest:
        assert p99["ratio"] == pytest.approx(100 / 18) and p99["met"] is False
        assert late["ratio"] == 1.0 and late["met"] is True
    else:
        assert p99["ratio"] is None and p99["met"] is None and "not installed" in p99["note"]
    live, cpu = by["lateness p99, live view on vs off"], by["CPU per cycle, live view on vs off"]
    assert live["value"] == 2000.0 and live["ratio"] == 20.0 and live["met"] is False
    assert cpu["ratio"] == 1.5 and cpu["met"] is False  # 30 us against 20 us
    assert "/leveler/sample 50" in live["note"]
    m["quick"] = True
    assert all(r["met"] is None for r in bench.rows(m))  # a quick run judges nothing
