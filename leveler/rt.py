"""Real-time scheduling helpers for the daemon's threads."""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import threading
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def demote_thread() -> None:
    """Drop the calling thread to normal scheduling.

    Under the service every thread inherits the loop's SCHED_FIFO priority; a control
    client at that priority could starve the loop it serves. (sched_* with pid 0 acts on
    the calling thread on Linux.) Outside real-time scheduling this is a no-op.
    """
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def on_normal_thread(fn: Callable[[], T]) -> T:
    """fn() run on a new thread at normal scheduling: its result, or its exception.

    For a library that starts threads of its own (the Foxglove server's network runtime):
    a thread inherits its creator's policy, so started from the daemon's main thread they
    would run at the loop's SCHED_FIFO priority under the service."""
    box: dict[str, Any] = {}

    def run() -> None:
        demote_thread()
        try:
            box["result"] = fn()
        except BaseException as exc:  # handed to the caller
            box["error"] = exc

    t = threading.Thread(target=run, name="normal-priority start")
    t.start()
    t.join()
    if "error" in box:
        raise box["error"]
    return box["result"]  # type: ignore[no-any-return]


def background_thread() -> None:
    """Move the calling thread below every real-time thread, but keep it real-time.

    For the log writer's threads: they share the interpreter lock with the loop. Under
    normal scheduling, any busy process on the machine could preempt one of them while it
    holds the lock, and the loop, woken on time, would wait milliseconds for it (measured:
    most of the 1 kHz loop's overruns under load; bench/loop_timing.py). At the lowest
    real-time priority nothing but real-time threads preempts them, and the loop, higher,
    still preempts them whenever it needs the CPU. Their work is bounded by what the loop
    produces (about 5% of a core at 1 kHz). Outside real-time scheduling this is a no-op.
    """
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            low = os.sched_get_priority_min(os.SCHED_FIFO)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(low))


_MCL_CURRENT, _MCL_FUTURE = 1, 2  # <sys/mman.h> on Linux


def lock_memory() -> str:
    """mlockall(MCL_CURRENT | MCL_FUTURE) under real-time scheduling; says what happened.

    A page fault in the loop costs up to milliseconds (disk, reclaim), which is what the
    service's CAP_IPC_LOCK and LimitMEMLOCK=infinity are for. Outside real-time scheduling
    (`make run`, tests) nothing is locked: the loop has no deadline worth pinning
    hundreds of MiB for. Returns "locked", or why not, for the start event and status.
    """
    if os.sched_getscheduler(0) not in (os.SCHED_FIFO, os.SCHED_RR):
        return "not locked: not under real-time scheduling"
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        return f"not locked: mlockall failed: {os.strerror(ctypes.get_errno())}"
    return "locked"


def freeze_heap() -> int:
    """Collect once, then move every object alive now out of the garbage collector's reach.

    What exists when the loop starts (modules, config, drivers, buffers) lives as long as
    the process, and scanning it is what makes a full collection slow: measured 14-24 ms in
    the daemon at start-up, one to two periods at 100 Hz, tens at 1 kHz, on the loop
    thread. Frozen, a full collection in the loop scans only what was made since.
    Returns the number of objects frozen (for the start event).
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def scheduler() -> str:
    """The calling thread's policy and priority, e.g. "SCHED_FIFO 50", for the log."""
    policy = os.sched_getscheduler(0)
    names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO", os.SCHED_RR: "SCHED_RR"}
    name = names.get(policy, str(policy))
    return f"{name} {os.sched_getparam(0).sched_priority}" if policy != os.SCHED_OTHER else name
