"""Real-time scheduling helpers for the daemon's threads."""

from __future__ import annotations

import contextlib
import os


def demote_thread() -> None:
    """Drop the calling thread to normal scheduling.

    Under the service every thread inherits the loop's SCHED_FIFO priority; a log writer
    or a control client at that priority could starve the loop it serves. (sched_* with
    pid 0 acts on the calling thread on Linux.) Outside real-time scheduling this is a
    no-op.
    """
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
