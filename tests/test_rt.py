"""Memory locking and the scheduler report, in real processes (mlockall is process-wide)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

PROBE = ("from leveler.rt import lock_memory, scheduler; r = lock_memory(); "
         "vmlck = [ln for ln in open('/proc/self/status') if ln.startswith('VmLck')][0]; "
         "print(r, '|', scheduler(), '|', vmlck.split()[1])")


def _probe(*prefix: str) -> list[str]:
    out = subprocess.run([*prefix, sys.executable, "-c", PROBE], capture_output=True,
                         text=True, timeout=60, check=True).stdout
    return [part.strip() for part in out.split("|")]


def test_nothing_is_locked_outside_real_time_scheduling() -> None:
    result, sched, locked_kib = _probe()
    assert result == "not locked: not under real-time scheduling"
    assert sched == "SCHED_OTHER" and locked_kib == "0"


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("chrt") is None,
                    reason="needs root and chrt to run under SCHED_FIFO")
def test_under_fifo_memory_is_locked_as_the_service_asks() -> None:
    result, sched, locked_kib = _probe("chrt", "-f", "10")
    assert result == "locked"
    assert sched == "SCHED_FIFO 10"
    assert int(locked_kib) > 10_000  # the interpreter, numpy and the rest, resident for good


def test_freezing_the_heap_leaves_the_collector_only_what_comes_later() -> None:
    probe = ("import gc, numpy, leveler.daemon.service; from leveler.rt import freeze_heap; "
             "n = freeze_heap(); later = [[i] for i in range(1000)]; "
             "print(n, len(gc.get_objects(2)), gc.get_freeze_count())")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=60, check=True).stdout.split()
    frozen, old_left, count = (int(v) for v in out)
    assert frozen > 10_000 and count == frozen  # the daemon's modules, numpy (no scipy)
    assert old_left < 1_000  # what a full collection still scans of them: nearly nothing
