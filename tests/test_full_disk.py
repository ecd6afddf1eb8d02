"""A full disk under the real daemon (issue 8): a fault event, and control goes on.

The log directory is a 1 MiB tmpfs, nearly filled before the daemon starts, so its writes
meet a real ENOSPC from the kernel. While the disk is full the loop must stay engaged and
keep cycling, the failure must be reported once, and retries must leave no stray files;
once space returns, logging resumes in a new file that says how many samples were lost
and between which times. A file finished before the fault stays byte for byte the same,
and the one that met it reads up to its last whole chunk.
(tests/test_logrotate.py checks the same on RotatingLog alone, with exact counts.)
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from leveler.cli.status import format_status
from leveler.daemon.client import Client
from leveler.log.reader import read_log

LOSS = re.compile(r"log write failed: \[Errno 28\] No space left on device; (\d+) samples lost "
                  r"between (\S+) and (\S+)")
FREE_BYTES = 200_000  # ~1.5 s of samples and truth at 1 kHz
RETRY_S = 0.5


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """tmp_path/logs (the daemon's log dir) as a 1 MiB tmpfs. Mounting needs root (CI and
    the dev container are); elsewhere the test skips rather than fake ENOSPC."""
    disk = tmp_path / "logs"
    disk.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)],
                          capture_output=True, text=True)
    if done.returncode:
        pytest.skip(f"cannot mount a tmpfs: {done.stderr.strip()}")
    yield disk
    subprocess.run(["umount", str(disk)], check=True, timeout=30)


def status(sock: Path) -> dict[str, Any]:
    with Client(sock) as c:
        return c.request("status")["status"]


def wait_status(sock: Path, cond: Callable[[dict[str, Any]], bool], what: str,
                timeout_s: float = 20.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while not cond(st := status(sock)):
        assert time.monotonic() < deadline, f"timed out waiting for {what}: {st}"
        time.sleep(0.05)
    return st


def test_full_disk_is_a_fault_event_and_control_continues(
        tiny_disk: Path, start_daemon) -> None:  # type: ignore[no-untyped-def]
    vfs = os.statvfs(tiny_disk)
    filler = tiny_disk / "filler"
    filler.write_bytes(b"\0" * (vfs.f_bavail * vfs.f_frsize - FREE_BYTES))
    d = start_daemon(rate_hz=1000.0, replace={
        'compression = "zstd"': f'compression = "zstd"\nretry_interval_s = {RETRY_S}'})
    # A finished file from before the fault, which must come through it untouched.
    (earlier,) = tiny_disk.glob("*.mcap")
    with Client(d.socket) as c:
        c.request("rotate")
    deadline = time.monotonic() + 10
    while not read_log(earlier).complete:
        assert time.monotonic() < deadline, "the rotated file was never finished"
        time.sleep(0.05)
    earlier_bytes = earlier.read_bytes()

    full = wait_status(d.socket, lambda st: not st["log"]["healthy"], "the disk to fill")
    assert "No space left on device" in full["log"]["error"]
    assert full["log"]["path"] is None  # no file while logging is down
    text = format_status(full).splitlines()[-1]
    assert text.startswith("log         no file open (logging is down; retrying), "), text
    assert "FAULT: [Errno 28] No space left on device" in text
    # Several retry intervals on the full disk: the loop goes on, closed, cycle after cycle.
    seen = [full]
    while seen[-1]["uptime_s"] < full["uptime_s"] + 4 * RETRY_S:
        time.sleep(0.2)
        seen.append(status(d.socket))
    for a, b in pairwise(seen):
        assert b["state"] == "engaged" and not b["log"]["healthy"], b
        assert b["sample"]["seq"] > a["sample"]["seq"]
        assert b["log"]["dropped"] > a["log"]["dropped"]
    cycles = seen[-1]["loop"]["cycles"] - full["loop"]["cycles"]
    assert cycles >= 0.5 * 1000 * (seen[-1]["uptime_s"] - full["uptime_s"])  # near its rate
    failed = sorted(tiny_disk.glob("*.mcap"))[1:]
    assert len(failed) == 1, failed  # the failed retries left no log file

    filler.unlink()
    resumed = wait_status(d.socket, lambda st: st["log"]["healthy"], "logging to resume")
    assert resumed["state"] == "engaged"
    assert resumed["log"]["error"] is None  # no stale error beside healthy: true
    assert format_status(resumed).splitlines()[-1].startswith(
        f"log         {resumed['log']['path']}, ")
    time.sleep(1.0)
    d.proc.send_signal(signal.SIGTERM)
    out, err = d.proc.communicate(timeout=20)
    assert d.proc.returncode == 0, err
    assert err.count("log write failed") == 1, err  # reported once, not per sample or retry
    assert "LOG FAULT: [Errno 28] No space left on device" in out  # the status line says it

    zeroth, first, second = sorted(tiny_disk.iterdir())  # nor anything else
    assert [zeroth, first] == [earlier, *failed] and second.suffix == ".mcap"
    assert zeroth.read_bytes() == earlier_bytes
    seq0 = read_log(zeroth).samples["seq"]
    before = read_log(first)  # cut short by ENOSPC, readable up to its last whole chunk
    n_old = len(seq0) + len(before.samples["seq"])
    assert not before.complete and n_old >= 500
    np.testing.assert_array_equal(np.concatenate([seq0, before.samples["seq"]]), np.arange(n_old))
    after = read_log(second)
    assert after.complete
    fault, back = after.events[:2]
    assert fault["kind"] == "fault", after.events[:3]
    m = LOSS.fullmatch(fault["reason"])
    assert m, fault["reason"]
    lost = int(m[1])
    assert fault["detail"]["lost_samples"] == lost and fault["detail"]["file"] == first.name
    assert (back["kind"], back["reason"]) == ("log", "logging resumed")
    # The loop counted every cycle through the outage: the new file starts exactly after
    # the lost ones, engaged, and runs on without a gap to the clean stop.
    seq = after.samples["seq"]
    assert seq[0] == n_old + lost
    np.testing.assert_array_equal(seq, np.arange(seq[0], seq[0] + len(seq)))
    gap_s = (fault["detail"]["to_log_time_ns"] - fault["detail"]["from_log_time_ns"]) / 1e9
    assert gap_s >= 4 * RETRY_S  # the outage, as the event states it, lasted as long as seen
    assert set(after.samples["state"]) == {"engaged"}
    assert after.events[-1]["kind"] == "stop"
    print(f"{n_old} samples before the disk filled, {lost} lost over {gap_s:.2f} s, "
          f"{len(seq)} after it was freed")
