"""RotatingLog: files rotated by time, size and request with no sample lost or repeated at a
boundary, file work kept off the loop thread, and a real full disk survived and reported."""

from __future__ import annotations

import os
import random
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from leveler.log import rotate as logrotate
from leveler.log.reader import LogData, read_log
from leveler.log.rotate import RotatingLog
from leveler.log.writer import LogWriter
from leveler.records import Event, Sample

ROOT = Path(__file__).resolve().parents[1]
T0_NS = 1_700_000_000_000_000_000
NAME = re.compile(r"leveler-\d{8}T\d{6}\.\d{6}Z\.mcap")
LOSS = re.compile(r"log write failed: (.+); (\d+) samples lost between (\S+) and (\S+)")


class FakeClock:
    """The log's clock, stepped by the test: rotation and retry times without sleeping."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def make_sample(seq: int, rng: random.Random) -> Sample:
    """Random values, so the data compresses like real data, not like zeros."""
    return Sample(seq, seq * 1e-3, rng.randrange(-32768, 32768), rng.gauss(0, 1e-6), 0, 0.0,
                  rng.gauss(0, 1e-6), rng.gauss(0, 0.1), rng.gauss(0, 0.1), rng.gauss(0, 0.1),
                  rng.uniform(-10, 10), rng.uniform(-10, 10), False, "engaged")


def utc(log_time_ns: int) -> str:
    return datetime.fromtimestamp(log_time_ns / 1e9, UTC).isoformat(timespec="milliseconds")


def wait_for(cond: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    """Wait for a real background thread; never a step of the test's own time."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.001)


def read_all(log: RotatingLog) -> list[LogData]:
    return [read_log(p) for p in log.files]


def all_seqs(logs: list[LogData]) -> np.ndarray:
    return np.concatenate([d.samples["seq"] for d in logs])


def test_time_rotation_continues_seq_across_files_off_the_loop_thread(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    opened, closed = [], []

    class Recording(LogWriter):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            opened.append(threading.current_thread().name)
            super().__init__(*args, **kwargs)

        def close(self) -> None:
            closed.append(threading.current_thread().name)
            super().close()

    monkeypatch.setattr(logrotate, "LogWriter", Recording)
    clock, rng = FakeClock(), random.Random(1)
    log = RotatingLog(tmp_path, metadata={"config": "x"}, truth=False, rotate_interval_s=10.0,
                      clock=clock)
    for seq in range(35):  # one sample per fake second
        clock.t = float(seq)
        before = log.path
        log.sample(make_sample(seq, rng), T0_NS + seq)
        if seq in (10, 20, 30):  # due: the opener thread swaps files without another sample
            wait_for(lambda b=before: log.path != b, "the time rotation")
    log.close()

    assert opened == ["MainThread"] + ["logrotate open"] * 3  # only the first, before the loop
    assert set(closed) == {"logrotate close"}
    assert [p.name for p in log.files] == sorted(p.name for p in tmp_path.iterdir())
    assert all(NAME.fullmatch(p.name) for p in log.files)
    logs = read_all(log)
    assert all(d.complete for d in logs)
    assert [d.samples["seq"][0] for d in logs] == [0, 11, 21, 31]  # each at its interval
    np.testing.assert_array_equal(all_seqs(logs), np.arange(35))
    assert log.samples_written == 35 and log.dropped == 0 and log.healthy
    for i, d in enumerate(logs):
        meta = d.metadata["leveler"]
        assert meta["config"] == "x" and meta["part"] == str(i + 1)
        if i:
            assert meta["previous"] == log.files[i - 1].name
            assert (d.events[0]["kind"], d.events[0]["reason"]) == ("log", "rotated (time)")
        if i < len(logs) - 1:
            assert d.events[-1]["reason"] == f"continues in {log.files[i + 1].name}"


def test_size_rotation(tmp_path: Path) -> None:
    rng = random.Random(2)
    log = RotatingLog(tmp_path, metadata={}, truth=False, chunk_interval_s=0.005,
                      rotate_bytes=20_000, clock=FakeClock())
    seq, firsts = 0, [0]
    for _ in range(3):
        before = log.path
        assert before is not None
        # The writer closes a chunk every 5 ms. Wait for the size the log checks, not the
        # file's: the writer thread writes a chunk before it counts it, and a sample handed
        # in between saw the old count, asked for nothing, and the test waited in vain.
        while log._writer is None or log._writer.bytes_written < 20_000:
            for _ in range(20):
                log.sample(make_sample(seq, rng), T0_NS + seq)
                seq += 1
            time.sleep(0.001)
        log.sample(make_sample(seq, rng), T0_NS + seq)  # sees the size: asks for a new file
        seq += 1
        wait_for(lambda b=before: log.path != b, "the size rotation")
        firsts.append(seq)
    log.sample(make_sample(seq, rng), T0_NS + seq)
    seq += 1
    log.close()
    logs = read_all(log)
    assert all(d.complete for d in logs)
    assert [d.samples["seq"][0] for d in logs] == firsts
    np.testing.assert_array_equal(all_seqs(logs), np.arange(seq))
    assert all(p.stat().st_size >= 20_000 for p in log.files[:-1])
    assert all(d.events[0]["reason"] == "rotated (size)" for d in logs[1:])


def test_manual_rotate_twice_in_a_second_gives_distinct_ordered_files(tmp_path: Path) -> None:
    rng = random.Random(3)
    log = RotatingLog(tmp_path, metadata={}, truth=False, clock=FakeClock())
    first = log.path
    log.sample(make_sample(0, rng), T0_NS)
    second = log.rotate()
    log.sample(make_sample(1, rng), T0_NS + 1)
    third = log.rotate("requested by uid 0")
    log.sample(make_sample(2, rng), T0_NS + 2)
    assert log.path == third
    log.close()
    assert log.files == [first, second, third]
    assert len({p.name for p in log.files}) == 3 and sorted(log.files) == log.files
    logs = read_all(log)
    assert all(d.complete for d in logs)
    assert [list(d.samples["seq"]) for d in logs] == [[0], [1], [2]]
    assert logs[1].events[0]["reason"] == "rotated (requested)"
    assert logs[2].events[0]["reason"] == "rotated (requested by uid 0)"


def test_close_is_idempotent_and_finishes_every_file(tmp_path: Path) -> None:
    clock, rng = FakeClock(), random.Random(4)
    log = RotatingLog(tmp_path, metadata={}, truth=False, rotate_interval_s=1.0, clock=clock)
    for seq in range(100):
        clock.t = seq * 0.1
        log.sample(make_sample(seq, rng), T0_NS + seq)
    clock.t = 100.0
    log.sample(make_sample(100, rng), T0_NS + 100)  # a rotation is under way while closing
    log.close()
    log.close()
    log.sample(make_sample(101, rng), T0_NS + 101)  # a late sample is counted, not raised
    assert sorted(tmp_path.iterdir()) == log.files  # an open that lost the race left nothing
    logs = read_all(log)
    assert all(d.complete for d in logs)
    np.testing.assert_array_equal(all_seqs(logs), np.arange(101))
    assert log.samples_written == 101 and log.dropped == 1


def test_no_directory_at_start_is_a_fault_and_logging_resumes(tmp_path: Path) -> None:
    blocked = tmp_path / "logs"
    blocked.write_text("a file where the log directory should be")
    clock, rng, faults = FakeClock(), random.Random(5), []
    log = RotatingLog(blocked, metadata={}, truth=False, retry_interval_s=5.0, clock=clock,
                      on_fault=faults.append)
    assert not log.healthy and log.path is None and log.files == []
    assert len(faults) == 1 and "cannot start logging" in faults[0]
    assert log.last_error and "Errno" in log.last_error
    for seq in range(10):
        clock.t = seq * 0.1
        log.sample(make_sample(seq, rng), T0_NS + seq * 1_000_000)
    log.event(Event(0.5, "state", "engaged while the log was down", {}), T0_NS + 500_000_000)
    assert log.dropped == 10 and log.files == []  # no retry before retry_interval_s
    blocked.unlink()
    clock.t = 5.0
    log.sample(make_sample(10, rng), T0_NS + 10_000_000)  # the retry is due: requested
    wait_for(lambda: log.healthy, "the retry")
    assert log.last_error is None  # healthy again: no stale error beside it (`status`)
    log.sample(make_sample(11, rng), T0_NS + 11_000_000)
    log.close()
    assert len(faults) == 1
    (data,) = read_all(log)
    assert data.complete and list(data.samples["seq"]) == [11]
    fault, resumed, held = data.events
    assert fault["kind"] == "fault"
    m = LOSS.fullmatch(fault["reason"])
    assert m and "Errno" in m[1] and int(m[2]) == 11 == log.dropped
    assert (m[3], m[4]) == (utc(T0_NS), utc(T0_NS + 10_000_000))  # the first and last lost
    assert (resumed["kind"], resumed["reason"]) == ("log", "logging resumed")
    assert held["reason"] == "engaged while the log was down"


def full_disk_scenario(directory: Path) -> str:
    """Fill the file system mounted at `directory` (2 MiB), free it, check the log resumes.

    Module level so the unshare fallback can run it in a child process.
    """
    filler = directory / "filler"
    filler.write_bytes(os.urandom(512 * 1024))
    clock, rng, faults = FakeClock(), random.Random(6), []
    log = RotatingLog(directory, metadata={}, truth=False, chunk_interval_s=0.02,
                      retry_interval_s=10.0, clock=clock, on_fault=faults.append)
    seq = 0

    def feed(n: int) -> None:
        nonlocal seq
        for _ in range(n):
            log.sample(make_sample(seq, rng), T0_NS + seq * 1_000_000)  # must never raise
            seq += 1

    deadline = time.monotonic() + 20
    while log.healthy:
        assert time.monotonic() < deadline, "the disk never filled"
        feed(200)
        time.sleep(0.002)  # the writer thread must run to hit ENOSPC
    failed = log.files[0]
    dropped = log.dropped
    assert dropped > 0
    feed(500)
    assert log.dropped == dropped + 500
    wait_for(lambda: len(faults) == 1, "on_fault")
    assert "No space left on device" in faults[0]

    clock.t = 10.0  # a retry on the still-full disk fails and leaves no file behind
    feed(1)
    wait_for(lambda: "cannot create log" in (log.last_error or ""), "the failed retry")
    assert not log.healthy and sorted(p.name for p in directory.iterdir()) == sorted(
        [failed.name, "filler"])

    filler.unlink()
    clock.t = 20.0
    deadline = time.monotonic() + 10
    while not log.healthy:
        assert time.monotonic() < deadline, "logging did not resume"
        feed(1)
        time.sleep(0.001)
    feed(300)
    log.close()
    assert len(faults) == 1

    old, new = read_all(log)
    n_old, n_new = len(old.samples["seq"]), len(new.samples["seq"])
    assert not old.complete and n_old > 1000  # the chunks before the failure are readable
    np.testing.assert_array_equal(old.samples["seq"], np.arange(n_old))
    assert new.complete
    assert new.events[0]["kind"] == "fault"
    m = LOSS.fullmatch(new.events[0]["reason"])
    assert m and "No space left on device" in m[1]
    lost = int(m[2])
    assert (new.events[1]["kind"], new.events[1]["reason"]) == ("log", "logging resumed")
    assert new.samples["seq"][0] == n_old + lost  # the count is the gap, exactly
    np.testing.assert_array_equal(new.samples["seq"], np.arange(n_old + lost, seq))
    assert log.dropped == lost and log.samples_written == n_old + n_new
    return f"{n_old} samples written, {lost} lost while full, {n_new} after resuming"


def _mount_tmpfs(directory: Path) -> bool:
    cmd = ["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(directory)]
    return subprocess.run(cmd, capture_output=True).returncode == 0


def test_full_disk_is_a_fault_that_logging_survives(tmp_path: Path) -> None:
    """A real ENOSPC from a 2 MiB tmpfs; in a user namespace if mounting is not allowed."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") and _mount_tmpfs(disk):
        try:
            print(full_disk_scenario(disk))
        finally:
            subprocess.run(["umount", str(disk)], check=True)
        return
    child = (f"import sys; sys.path[:0] = [{str(ROOT)!r}, {str(ROOT / 'tests')!r}]\n"
             "from pathlib import Path; import test_logrotate as t\n"
             "print(t.full_disk_scenario(Path(sys.argv[1])))\n")
    script = 'mount -t tmpfs -o size=2m tmpfs "$1" && exec "$0" -c "$2" "$1"'
    probe = ["unshare", "-rm", "mount", "-t", "tmpfs", "tmpfs", str(disk)]
    if not shutil.which("unshare") or subprocess.run(probe, capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs: not root and no user namespaces (unshare -rm)")
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script, sys.executable, str(disk), child],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    print(done.stdout)


def _sample_until(log: RotatingLog, seq: int, rng: random.Random, cond: Callable[[], bool],
                  what: str) -> int:
    """Hand on samples (every 2 ms of real time: the writer's checks run on its thread)
    until cond(); returns the next seq."""
    deadline = time.monotonic() + 10.0
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        log.sample(make_sample(seq, rng), T0_NS + seq * 1_000_000)
        seq += 1
        time.sleep(0.002)
    return seq


def test_a_file_deleted_while_written_is_a_fault_copied_back_and_continued(
        tmp_path: Path) -> None:
    """`rm -rf logs` under a running log: the writer notices at its next chunk, a new file
    opens in the re-created directory, and the deleted one, still open, is copied back."""
    logs, rng, faults = tmp_path / "logs", random.Random(6), []
    log = RotatingLog(logs, metadata={}, truth=False, chunk_interval_s=0.02,
                      clock=FakeClock(), on_fault=faults.append)
    first = log.path
    assert first is not None
    seq = _sample_until(log, 0, rng, lambda: log.samples_written >= 20, "20 samples")
    shutil.rmtree(logs)
    seq = _sample_until(log, seq, rng, lambda: log.faults == 1, "the deletion to be noticed")
    seq = _sample_until(log, seq, rng, lambda: first.exists() and log.path != first,
                        "the copy back and a new file")
    log.close()
    assert faults == [f"{first} was deleted while being written (its directory is gone); "
                      "writing goes on into the open file until a new one is open, then it "
                      "is copied back"]
    assert log.healthy and log.dropped == 0 and log.samples_written == seq
    assert log.faults == 1 and log.last_fault is not None
    assert log.last_fault.endswith(f"{first.name} was deleted while being written; restored "
                                   f"from its open descriptor into {first} "
                                   f"({len(read_log(first).samples['seq'])} samples)")
    assert sorted(p.name for p in logs.iterdir()) == sorted(p.name for p in log.files)
    data = read_all(log)
    assert all(d.complete for d in data)
    np.testing.assert_array_equal(all_seqs(data), np.arange(seq))
    assert data[1].events[0]["reason"].startswith(f"rotated ({first} was deleted")


def test_a_deleted_file_that_cannot_be_copied_back_is_counted_as_lost(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(LogWriter, "open_deleted", lambda self: None)  # as without /proc
    logs, rng, faults = tmp_path / "logs", random.Random(7), []
    log = RotatingLog(logs, metadata={}, truth=False, chunk_interval_s=0.02,
                      clock=FakeClock(), on_fault=faults.append)
    first = log.path
    seq = _sample_until(log, 0, rng, lambda: log.samples_written >= 20, "20 samples")
    first.unlink()  # the file alone, the directory stays
    seq = _sample_until(log, seq, rng, lambda: log.path != first, "a new file")
    for n in range(seq, seq + 5):
        log.sample(make_sample(n, rng), T0_NS + n * 1_000_000)
    seq += 5
    log.close()
    assert not first.exists()
    (data,) = read_all(log)
    lost = int(data.samples["seq"][0])
    assert log.dropped == lost and log.samples_written == seq - lost
    assert faults[-1] == (f"{first} was deleted while being written and cannot be restored: "
                          "no descriptor to read it through (is /proc mounted?); its "
                          f"{lost} samples are lost")
    np.testing.assert_array_equal(data.samples["seq"], np.arange(lost, seq))


def test_a_rotation_that_fails_is_a_fault_retried_until_a_file_opens(tmp_path: Path) -> None:
    logs, clock, rng = tmp_path / "logs", FakeClock(), random.Random(8)
    log = RotatingLog(logs, metadata={}, truth=False, retry_interval_s=5.0, clock=clock)
    first = log.path
    log.sample(make_sample(0, rng), T0_NS)
    real_open = log._open
    log._open = lambda: "[Errno 13] Permission denied: 'logs'"  # type: ignore[method-assign]
    with pytest.raises(logrotate.LogError, match=r"cannot start a new log file: \[Errno 13\]"):
        log.rotate("requested by uid 0")
    assert not log.healthy and log.faults == 1 and log.path == first
    assert log.last_error == ("cannot start a new log file: [Errno 13] Permission denied: "
                              f"'logs'; still writing {first.name}")
    log.sample(make_sample(1, rng), T0_NS + 1)  # no retry before retry_interval_s
    assert log.path == first
    log._open = real_open  # type: ignore[method-assign]
    clock.t = 5.0
    log.sample(make_sample(2, rng), T0_NS + 2)
    wait_for(lambda: log.healthy, "the retry")
    assert log.faults == 1 and log.last_error is None and log.path != first
    log.sample(make_sample(3, rng), T0_NS + 3)
    log.close()
    data = read_all(log)
    assert [list(d.samples["seq"]) for d in data] == [[0, 1, 2], [3]]
    assert data[1].events[0]["reason"].startswith("rotated (retry after: cannot start")
