"""SIGKILL of the real daemon at seeded random moments (issue 8): every log file reads,
directly and after `leveler recover`; `seq` never repeats and has no gap but the crash's;
and no more than about a second of samples is lost.

Each trial is a `leveler run` process on config/sim.toml with rotation turned up (time at
10 Hz, size at 1 kHz), so a kill also meets files of earlier rotations: those must be
finished and byte for byte what they were before the kill. Only the open file, and the
one retired just before the kill if its close was still under way, may be cut short; a
gap in `seq` is allowed only after a cut file. Trials run ten at a time: the kill moments
are seeded, the machine's load is not, which is the point.

The bound asserted, loss_bound_s(rate) = chunk_interval_s + 0.25 s + one period, on the
loop time from the last sample before the first gap to the kill: the writer closes and
hands to the OS a chunk once chunk_interval_s has passed since the last, noticing within
its 25 ms poll, and a sample reaches the open chunk within that poll too; at 10 Hz the
kill can come up to a period after the last cycle even when nothing is lost; the rest
(about 0.2 s) is scheduling on a 2-core machine running ten daemons at once.
"""

from __future__ import annotations

import hashlib
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from conftest import daemon_config

from leveler.daemon.client import Client
from leveler.log.reader import LogData, read_log

CHUNK_INTERVAL_S = 1.0  # config/sim.toml's [log] chunk_interval_s, the documented default
KILL_WINDOW_S = (1.5, 6.0)  # kill this long after the control socket appears
CLOSE_WINDOW_S = 1.0  # a file retired less than this before the kill may still be closing
# Rotation every ~2 s, so a kill lands with 0-3 finished files before the open one: by time
# at 10 Hz; by size at 1 kHz (~140 kB/s of samples and truth).
ROTATE = {10.0: "rotate_interval_s = 2.0", 1000.0: "rotate_bytes = 200000"}


def loss_bound_s(rate_hz: float) -> float:
    """The most a kill may cost, in seconds of loop time: see the module docstring."""
    return CHUNK_INTERVAL_S + 0.25 + 1.0 / rate_hz


@dataclass
class Outcome:
    """What one killed daemon left: the figures for the report."""

    rate_hz: float
    kill_after_s: float  # after the socket appeared
    t_kill_s: float  # loop time of the kill, by the daemon's clock
    files: int
    finished: int  # files complete before the kill (byte-compared after it)
    recovered: int  # files that needed `leveler recover`
    readable: int  # samples readable after the kill
    lost: int  # samples the daemon had produced by the kill that no file holds
    lost_s: float  # loop time from the last sample before the first gap to the kill

    def row(self) -> str:
        return (f"{self.rate_hz:6g} Hz  kill {self.kill_after_s:4.2f} s after socket "
                f"(t={self.t_kill_s:5.2f} s)  files {self.files} ({self.finished} finished "
                f"before, {self.recovered} recovered)  readable {self.readable:5d}  "
                f"lost {self.lost:4d} samples = {self.lost_s:.3f} s")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def start_ns(log: Path) -> int:
    """A log file's UTC start time from its name (leveler-YYYYmmddTHHMMSS.ffffffZ.mcap)."""
    stamp = datetime.strptime(log.name, "leveler-%Y%m%dT%H%M%S.%fZ.mcap").replace(tzinfo=UTC)
    return int(stamp.timestamp()) * 10**9 + stamp.microsecond * 1000


def finished_files(logs: Path) -> dict[Path, str]:
    """Files the daemon has finished (summary and footer written), with their digests."""
    return {p: sha256(p) for p in sorted(logs.glob("*.mcap")) if read_log(p).complete}


def read_or_recover(log: Path, out_dir: Path) -> tuple[LogData, bool]:
    """The file's data and whether it was cut short. A cut one must read directly and
    through `leveler recover` (a separate process, as an operator would run it) alike,
    and the recovered copy must be finished."""
    direct = read_log(log)
    if direct.complete:
        return direct, False
    out = out_dir / log.name
    done = subprocess.run([sys.executable, "-m", "leveler.cli", "recover", str(log), "--out",
                           str(out)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    fixed = read_log(out)
    assert fixed.complete, f"{log}: recovered copy incomplete: {fixed.stop_reason}"
    for key in ("seq", "t_s", "log_time_ns"):
        np.testing.assert_array_equal(fixed.samples[key], direct.samples[key], err_msg=key)
    assert fixed.events == direct.events and fixed.metadata == direct.metadata
    return fixed, True


def run_trial(root: Path, short: Path, rate_hz: float, index: int,
              kill_after_s: float) -> Outcome:
    """Start a daemon, SIGKILL it `kill_after_s` after its socket appears, check its logs."""
    trial = root / f"{rate_hz:g}hz-{index}"
    trial.mkdir()
    sock = short / f"{rate_hz:g}-{index}.sock"
    config = daemon_config(trial, sock, rate_hz=rate_hz, replace={
        'compression = "zstd"': f'compression = "zstd"\n{ROTATE[rate_hz]}'})
    logs = trial / "logs"
    with open(trial / "stdout", "w") as out, open(trial / "stderr", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "leveler.cli", "run", "--config",
                                 str(config)], stdout=out, stderr=err, cwd=trial)
    try:
        deadline = time.monotonic() + 60
        while not sock.exists():
            assert proc.poll() is None, (trial / "stderr").read_text()
            assert time.monotonic() < deadline, "daemon socket never appeared"
            time.sleep(0.01)
        appeared = time.monotonic()
        time.sleep(max(0.0, kill_after_s - 0.2))
        before = finished_files(logs)  # the daemon's finished files just before the kill
        time.sleep(max(0.0, appeared + kill_after_s - time.monotonic()))
        with Client(sock) as c:
            status = c.request("status")["status"]
        replied = time.monotonic()
        proc.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        kill_ns = time.time_ns()
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert status["state"] == "engaged" and status["log"]["healthy"]
    s = status["sample"]
    t_kill = s["t_s"] + (killed - replied)
    seq_kill = s["seq"] + int((killed - replied) * rate_hz)

    files = sorted(logs.glob("*.mcap"))
    assert set(before) <= set(files)
    recovered_dir = trial / "recovered"
    recovered_dir.mkdir()
    datas: list[LogData] = []
    cut: list[bool] = []
    for i, log in enumerate(files):
        data, was_cut = read_or_recover(log, recovered_dir)
        # Only the open file, or the one retired just before the kill, may be cut short.
        closing = i == len(files) - 2 and kill_ns - start_ns(files[-1]) < CLOSE_WINDOW_S * 1e9
        assert not was_cut or i == len(files) - 1 or closing, (
            f"{log.name} (file {i + 1} of {len(files)}) was cut short")
        if not was_cut and i < len(files) - 1:
            assert data.events[-1]["reason"] == f"continues in {files[i + 1].name}"
        datas.append(data)
        cut.append(was_cut)
    for log, digest in before.items():
        assert sha256(log) == digest, f"{log.name} changed after it was finished"

    # seq: no repeat, and a step other than one only after a file the kill cut short.
    all_seq = np.concatenate([d.samples["seq"] for d in datas])
    t_s = np.concatenate([d.samples["t_s"] for d in datas])
    assert len(all_seq) and all_seq[0] == 0
    steps = np.diff(all_seq)
    assert (steps >= 1).all(), f"seq repeats or goes back at {np.flatnonzero(steps < 1)}"
    ends = np.cumsum([len(d.samples["seq"]) for d in datas]) - 1
    cut_ends = {int(e) for e, c in zip(ends, cut, strict=True) if c}
    gaps = [int(i) for i in np.flatnonzero(steps != 1)]
    assert set(gaps) <= cut_ends, f"seq gaps {gaps} inside files or after a finished one"
    contiguous_end = gaps[0] if gaps else len(all_seq) - 1
    lost_s = t_kill - t_s[contiguous_end]
    lost = seq_kill + 1 - len(all_seq)
    outcome = Outcome(rate_hz, kill_after_s, t_kill, len(files), len(before), sum(cut),
                      len(all_seq), lost, lost_s)
    assert lost_s <= loss_bound_s(rate_hz), f"lost too much: {outcome.row()}"
    return outcome


def run_trials(tmp_path: Path, per_rate: int, seed: int, concurrent: int) -> None:
    """`per_rate` trials at 10 Hz and at 1 kHz, killed at seeded random moments,
    `concurrent` daemons at a time; prints one row per trial and the worst per rate, then
    raises the first failure."""
    rng = random.Random(seed)
    trials = [(rate, i, rng.uniform(*KILL_WINDOW_S)) for i in range(per_rate) for rate in ROTATE]
    short = Path(tempfile.mkdtemp(prefix="lv", dir="/tmp"))  # AF_UNIX paths are short
    try:
        with ThreadPoolExecutor(concurrent) as pool:
            futures = [pool.submit(run_trial, tmp_path, short, *t) for t in trials]
        outcomes = [f.exception() or f.result() for f in futures]
    finally:
        shutil.rmtree(short, ignore_errors=True)
    for (rate, i, kill), o in zip(trials, outcomes, strict=True):
        print(o.row() if isinstance(o, Outcome) else f"{rate:6g} Hz #{i} kill {kill:.2f} s: {o!r}")
    for rate in ROTATE:
        good = [o for o in outcomes if isinstance(o, Outcome) and o.rate_hz == rate]
        if good:
            worst = max(good, key=lambda o: o.lost_s)
            print(f"worst of {len(good)} at {rate:g} Hz: {worst.lost} samples, "
                  f"{worst.lost_s:.3f} s (bound {loss_bound_s(rate):.3f} s)")
    for o in outcomes:
        if isinstance(o, BaseException):
            raise o


def test_sigkill_at_random_moments_loses_at_most_about_a_second(tmp_path: Path) -> None:
    """6 trials at 10 Hz and 6 at 1 kHz, six daemons at a time (make test-slow: 50 more)."""
    run_trials(tmp_path, per_rate=6, seed=8, concurrent=6)


@pytest.mark.slow
def test_sigkill_at_many_random_moments(tmp_path: Path) -> None:
    """50 more trials per rate at other kill moments."""
    run_trials(tmp_path, per_rate=50, seed=80, concurrent=10)


STALL_IN_OPEN = """
import sys, time
from pathlib import Path
from leveler.log import writer as logwriter

def stall(self, name, data):
    Path(sys.argv[2]).touch()
    time.sleep(60)

logwriter._McapFile.metadata = stall  # in the open, before the header is flushed
logwriter.LogWriter(Path(sys.argv[1]))
"""


def test_sigkill_while_a_file_is_created_leaves_no_unreadable_log(tmp_path: Path) -> None:
    """The window the random trials found (about 1 kill in 100, at a rotation): a file
    created but its header not yet flushed. Held open here, so the kill lands in it."""
    log, inside = tmp_path / "new.mcap", tmp_path / "inside"
    proc = subprocess.Popen([sys.executable, "-c", STALL_IN_OPEN, str(log), str(inside)])
    try:
        deadline = time.monotonic() + 30
        while not inside.exists():
            assert proc.poll() is None and time.monotonic() < deadline, "never got there"
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert not log.exists()  # the name appears only once the file reads
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inside", "new.mcap.new"]
