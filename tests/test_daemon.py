"""`leveler run` as a real subprocess: status lines, a clean stop on a signal, a readable log."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from leveler.logreader import read_log

REPO = Path(__file__).resolve().parents[1]


def start_daemon(tmp_path: Path, rate_hz: float = 50.0) -> subprocess.Popen[str]:
    cfg = (REPO / "config" / "sim.toml").read_text()
    cfg = cfg.replace("rate_hz = 10.0", f"rate_hz = {rate_hz}")
    cfg = cfg.replace("status_interval_s = 5.0", "status_interval_s = 0.5")
    cfg = cfg.replace('dir = "logs"', f'dir = "{tmp_path / "logs"}"')
    path = tmp_path / "daemon.toml"
    path.write_text(cfg)
    return subprocess.Popen(
        [sys.executable, "-m", "leveler.cli", "run", "--config", str(path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def wait_for_status(proc: subprocess.Popen[str], lines: int, timeout_s: float = 30.0) -> list[str]:
    got: list[str] = []
    deadline = time.monotonic() + timeout_s
    assert proc.stdout is not None
    while len([ln for ln in got if "period p50/p99/max" in ln]) < lines:
        assert time.monotonic() < deadline, f"no status lines in time; got {got}"
        line = proc.stdout.readline()
        assert line, f"daemon exited early: {proc.stderr.read() if proc.stderr else ''}"
        got.append(line)
    return got


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_daemon_levels_prints_status_and_stops_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    proc = start_daemon(tmp_path)
    try:
        lines = wait_for_status(proc, 3)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "engaged" in lines[-1] and "piezo=" in lines[-1] and "tilt=" in lines[-1]
    assert f"stopped ({sig.name})" in err
    logs = list((tmp_path / "logs").glob("leveler-*Z.mcap"))
    assert len(logs) == 1
    data = read_log(logs[0])
    assert data.complete
    seq = data.samples["seq"]
    assert len(seq) >= 50  # at least 1.5 s at 50 Hz
    np.testing.assert_array_equal(seq, np.arange(len(seq)))
    assert len(data.truth["tilt_rad"]) == len(seq)
    kinds = [e["kind"] for e in data.events]
    assert kinds[0] == "start" and kinds[-1] == "stop"
    assert data.events[-1]["reason"] == sig.name
    assert "[controller]" in data.metadata["leveler"]["config"]
    assert set(data.samples["state"][5:]) == {"engaged"}


def test_daemon_refuses_a_bad_config_naming_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[loop]\nrate_hz = -1\n")
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "run", "--config", str(bad)],
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert proc.returncode == 2
    assert "loop.rate_hz" in proc.stderr and str(bad) in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "logs").exists()


@pytest.mark.parametrize("rate_hz", [10.0, 200.0])
def test_sigkill_loses_at_most_about_a_second(tmp_path: Path, rate_hz: float) -> None:
    """A daemon killed without warning leaves a log readable up to ~1 s before the kill."""
    proc = start_daemon(tmp_path, rate_hz=rate_hz)
    try:
        lines = wait_for_status(proc, 5)
        proc.kill()
        proc.wait(timeout=10)
    finally:
        proc.kill()
    # loop time of the last status line printed before the kill
    last_t = float(lines[-1].split("t=")[1].split(" s")[0])
    (log,) = (tmp_path / "logs").glob("leveler-*Z.mcap")
    data = read_log(log)
    assert not data.complete
    seq = data.samples["seq"]
    np.testing.assert_array_equal(seq, np.arange(len(seq)))
    assert data.samples["t_s"][-1] >= last_t - 1.5, "lost more than ~1 s of samples"
