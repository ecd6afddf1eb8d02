"""Soak: the daemon's own code for seven simulated days in virtual time, with every kind of
`[[sim.faults]]` spread across the week, logging every sample to daily MCAP files.

It checks what a week unattended needs: no memory growth (tracemalloc), every sample in
exactly one file (seq contiguous from 0, none lost, none twice), every scheduled fault
answered by its event (and the faults that open the loop by a reconnect and a resume), and
no unhandled exception in any thread.

`Daemon.run` runs unchanged on the real simulated stand, RotatingLog and LogWriter; only the `time`
module that leveler.loop.clock and leveler.daemon.service see is replaced by `VirtualTime`, whose
`sleep` (the RealtimeClock's wait for its next deadline) advances monotonic and wall time at once.
Between two cycles it also paces the loop to the log writer (virtual time would otherwise outrun it)
and takes the memory readings. The log rotates daily in virtual time, as the daemon does in real
time (`[log] rotate_interval_s = 86400`).
"""

from __future__ import annotations

import gc
import threading
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import daemon_config

import leveler.daemon.service
import leveler.loop.clock
from leveler.daemon.service import Daemon
from leveler.log.reader import read_log
from leveler.log.rotate import RotatingLog

DAY_S = 86400.0
HOUR_S = 3600.0
RATE_HZ = 10.0
STATUS_S = 300.0  # status line (and wall-clock check) period: a clock step is seen within it
# Allowed growth of traced memory between the first and the last reading. Each is taken one
# second before a rotation (so the file being written is as full at both), with the writer
# drained and its open chunk closed, so what may legitimately differ is small: how many
# chunks the file holds (they close on wall time; about 0.5 KiB of index each), and from the
# second rotation on the previous file's finished writer, which the log's closer thread
# holds until its next job (measured: +0.42 MiB from day 1 to day 2, then flat within
# 0.1 MiB). A leak of 100 bytes per sample grows 518 MB between day 1 and day 7 (5.2 million
# samples), and even 0.2 bytes per sample breaks the week's 1 MiB; in the one-hour run
# (30,000 samples between its readings) 100 bytes per sample is 3 MB, and 9 bytes per
# sample breaks its 256 KiB.
MAX_GROWTH_WEEK_B = 1 << 20
MAX_GROWTH_HOUR_B = 256 << 10
_BACKLOG = 20_000  # samples the loop may run ahead of the log writer


class VirtualTime:
    """Stands in for the `time` module of leveler.loop.clock and leveler.daemon.service:
    monotonic time starts at 0 and only `sleep` advances it; wall time is a fixed start plus
    monotonic time (a `[[sim.faults]] clock_step` is the daemon's own offset on top). `between(t_s)`
    is called on the loop thread after each sleep, i.e. between two cycles at loop time t_s."""

    def __init__(self, between: Callable[[float], None]) -> None:
        self.mono_ns = 0
        self.wall0_ns = time.time_ns()
        self.between = between

    def monotonic_ns(self) -> int:
        return self.mono_ns

    def monotonic(self) -> float:
        return self.mono_ns / 1e9

    def time_ns(self) -> int:
        return self.wall0_ns + self.mono_ns

    def time(self) -> float:
        return self.time_ns() / 1e9

    def sleep(self, s: float) -> None:
        self.mono_ns += max(round(s * 1e9), 0)
        self.between(self.mono_ns / 1e9)


@dataclass(frozen=True)
class Fault:
    """One `[[sim.faults]]` entry and the event that must answer it."""

    kind: str
    duration_s: float
    event_kind: str
    says: str  # in the event's reason
    size: float = 0.0
    opens_loop: bool = False  # a fault state, then a reconnect and a resume

    def toml(self, at_s: float) -> str:
        return (f'[[sim.faults]]\nkind = "{self.kind}"\nat_s = {at_s:.1f}\n'
                f"duration_s = {self.duration_s}\nsize = {self.size}\n")


# Every kind, short (held through) and long (the loop faults, reconnects, resumes).
FAULTS = (
    Fault("timeout", 0.2, "driver_error", "sensor read failed: injected timeout"),
    Fault("nan", 1.0, "bad_reading", "sensor reading invalid (NaN or unparsable)"),
    Fault("spike", 0.0, "bad_reading", "sensor reading spike", size=1e-6),
    Fault("stuck", 5.0, "bad_reading", "sensor reading stuck (30 identical readings)"),
    Fault("railed", 1.0, "bad_reading", "sensor reading railed"),
    Fault("write_fail", 0.0, "driver_error", "actuator write failed: injected write failure"),
    Fault("clock_step", 0.0, "clock", "wall clock stepped by +3600.000 s", size=3600.0),
    Fault("disconnect", 600.0, "state", "injected disconnect", opens_loop=True),
    Fault("nan", 10.0, "state", "50 bad sensor readings in a row (first: invalid",
          opens_loop=True),
    Fault("timeout", 2.0, "state", "(3 driver errors in a row)", opens_loop=True),
    Fault("spike", 2.0, "bad_reading", "sensor reading spike", size=1e-6),
    Fault("railed", 10.0, "state", "50 bad sensor readings in a row (first: railed",
          opens_loop=True),
    Fault("clock_step", 0.0, "clock", "wall clock stepped by -3600.000 s", size=-3600.0),
    Fault("write_fail", 1.0, "state", "actuator write failed: injected write failure",
          opens_loop=True),
    Fault("disconnect", 30.0, "state", "injected disconnect", opens_loop=True),
)


@dataclass
class Soak:
    duration_s: float
    checkpoints_s: list[float]  # loop times of the memory readings
    traced_b: dict[float, int] = field(default_factory=dict)
    wall_s: float = 0.0
    files: list[Path] = field(default_factory=list)
    seq: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    events: list[dict] = field(default_factory=list)
    daemon: Daemon | None = None
    thread_errors: list[threading.ExceptHookArgs] = field(default_factory=list)


def _schedule(duration_s: float) -> list[tuple[float, Fault]]:
    """FAULTS evenly spread over the run, at whole tenths of a second; in a short run no
    fault lasts more than a third of the time to the next (recovery takes the rest)."""
    step = duration_s / (len(FAULTS) + 1)
    return [(round((i + 1) * step, 1), replace(f, duration_s=min(f.duration_s, step // 3)))
            for i, f in enumerate(FAULTS)]


def run_soak(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, duration_s: float,
             checkpoints_s: list[float], rotate_s: float = DAY_S, chunk_s: float = 1.0
             ) -> Soak:
    sim = "".join(f.toml(at) for at, f in _schedule(duration_s))
    config = daemon_config(tmp_path, tmp_path / "c.sock", rate_hz=RATE_HZ, sim=sim, replace={
        "status_interval_s = 5.0": f"status_interval_s = {STATUS_S}",
        "engage_on_start = true": "engage_on_start = true\nstuck_after_samples = 30\n"
                                  "max_step_m = 2.0e-7",
        'compression = "zstd"': f'compression = "zstd"\nrotate_interval_s = {rotate_s}',
        "chunk_interval_s = 1.0": f"chunk_interval_s = {chunk_s}"})
    soak = Soak(duration_s, checkpoints_s)
    pending = sorted(checkpoints_s)
    box: dict[str, Daemon] = {}

    def between(t_s: float) -> None:
        d = box.get("d")
        if d is None:
            return
        if d.loop.seq % 2000 == 0 or (pending and t_s >= pending[0]):
            while d.loop.seq - d.log.samples_written > (0 if pending and t_s >= pending[0]
                                                        else _BACKLOG):
                time.sleep(0.001)  # the real one: wait for the writer thread
        if pending and t_s >= pending[0]:
            time.sleep(chunk_s + 0.25)  # the writer closes its open chunk (real time)
            gc.collect()
            soak.traced_b[pending.pop(0)] = tracemalloc.get_traced_memory()[0]

    vt = VirtualTime(between)
    clock_ns = SimpleNamespace(monotonic_ns=vt.monotonic_ns, monotonic=vt.monotonic,
                               sleep=vt.sleep, time_ns=vt.time_ns)
    daemon_ns = SimpleNamespace(monotonic=vt.monotonic, time_ns=vt.time_ns, time=vt.time,
                                sleep=vt.sleep)
    monkeypatch.setattr(leveler.loop.clock, "time", clock_ns)
    monkeypatch.setattr(leveler.daemon.service, "time", daemon_ns)
    monkeypatch.setattr(leveler.daemon.service, "RotatingLog",
                        partial(RotatingLog, clock=vt.monotonic))
    previous_hook = threading.excepthook  # exceptions that end any thread: collected
    threading.excepthook = soak.thread_errors.append
    tracemalloc.start()
    start = time.perf_counter()
    try:
        d = box["d"] = Daemon(config, duration_s=duration_s)
        assert d.run() == 0
    finally:
        soak.wall_s = time.perf_counter() - start
        tracemalloc.stop()
        threading.excepthook = previous_hook
    soak.daemon = d
    soak.files = sorted((tmp_path / "logs").glob("*.mcap"))
    assert soak.files == d.log.files
    seqs = []
    for path in soak.files:
        log = read_log(path)
        assert log.complete, path
        seqs.append(np.asarray(log.samples["seq"], dtype=np.int64))
        soak.events += log.events
    soak.seq = np.concatenate(seqs)
    return soak


def check(soak: Soak) -> None:
    d = soak.daemon
    assert d is not None
    # No unhandled exception: run() returned 0 (above), no thread died, a clean stop.
    assert soak.thread_errors == []
    assert soak.events[-1]["kind"] == "stop" and soak.events[-1]["reason"] == "finished"
    last = [e for e in soak.events if e["kind"] == "state"][-1]  # the stop opens the loop ...
    assert last["reason"] == "finished" and last["detail"]["old"] == "engaged"  # ... engaged:
    # every fault that opened the loop was recovered from
    # Every sample in exactly one file, in order: nothing lost, nothing twice.
    n = d.loop.seq
    assert n == round(soak.duration_s * RATE_HZ) + 1
    assert d.log.dropped == 0 and d.log.samples_written == n
    np.testing.assert_array_equal(soak.seq, np.arange(n))
    # Each scheduled fault produced its event, when it happened.
    ev = soak.events
    schedule = _schedule(soak.duration_s)
    for i, (at_s, f) in enumerate(schedule):
        until = at_s + max(f.duration_s, 0.1) + (STATUS_S if f.kind == "clock_step" else 0)
        hits = [e for e in ev if e["kind"] == f.event_kind and f.says in e["reason"]
                and at_s - 1e-6 <= e["t_s"] <= until]
        assert hits, (at_s, f)
        if f.opens_loop:
            assert hits[0]["detail"]["new"] == "fault"
            nxt = schedule[i + 1][0] if i + 1 < len(schedule) else soak.duration_s
            back = [e for e in ev if at_s + f.duration_s <= e["t_s"] < nxt
                    and e["kind"] == "reconnect" and e["reason"] == "devices answer again"]
            resumed = [e for e in ev if at_s + f.duration_s <= e["t_s"] < nxt
                       and e["kind"] == "state" and e["reason"].startswith("resume after")]
            assert back and resumed, (at_s, f)
    faults = [e for e in ev if e["kind"] == "state" and e["detail"]["new"] == "fault"]
    assert len(faults) == sum(f.opens_loop for _, f in schedule), faults  # no others


@pytest.mark.slow
def test_seven_days_with_every_fault_no_leak_no_lost_sample(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    days = [k * DAY_S - 1.0 for k in range(1, 8)]  # just before each daily rotation
    soak = run_soak(tmp_path, monkeypatch, 7 * DAY_S, days)
    check(soak)
    assert len(soak.files) == 7  # one a day
    mem = [soak.traced_b[t] for t in days]
    print(f"\nsoak 7 d: {soak.wall_s:.0f} s wall; traced memory at the end of each day [MiB]: "
          + ", ".join(f"{b / 2**20:.3f}" for b in mem)
          + f"; day 7 - day 1: {(mem[-1] - mem[0]) / 2**10:+.0f} KiB")
    assert mem[-1] - mem[0] < MAX_GROWTH_WEEK_B, mem


def test_one_hour_with_every_fault_no_leak_no_lost_sample(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The week's schedule compressed into one hour (the long disconnect shortened to fit),
    the log rotating every 10 minutes; the same checks."""
    ends = [599.0, HOUR_S - 1.0]  # just before the first and the last rotation
    soak = run_soak(tmp_path, monkeypatch, HOUR_S, ends, rotate_s=600.0, chunk_s=0.1)
    check(soak)
    assert len(soak.files) == 6
    mem = [soak.traced_b[t] for t in ends]
    print(f"\nsoak 1 h: {soak.wall_s:.1f} s wall; traced memory after 10 and 60 min [MiB]: "
          + ", ".join(f"{b / 2**20:.3f}" for b in mem))
    assert mem[-1] - mem[0] < MAX_GROWTH_HOUR_B, mem
