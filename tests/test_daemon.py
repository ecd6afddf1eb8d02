"""`leveler run` as a real subprocess: status lines, a clean stop on a signal, a readable log."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from leveler.log.reader import read_log

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_daemon_levels_prints_status_and_stops_cleanly(tmp_path: Path, sig: signal.Signals,
                                                      start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon()
    lines = d.wait_status_lines(3)
    err = d.stop(sig)
    assert d.proc.returncode == 0, err
    assert "engaged" in lines[-1] and "piezo=" in lines[-1] and "tilt=" in lines[-1]
    assert f"stopped ({sig.name})" in err
    logs = list((tmp_path / "logs").glob("leveler-*.mcap"))
    assert len(logs) == 1
    data = read_log(logs[0])
    assert data.complete
    seq = data.samples["seq"]
    assert len(seq) >= 50  # at least 1.5 s at 50 Hz
    np.testing.assert_array_equal(seq, np.arange(len(seq)))
    assert len(data.truth["tilt_rad"]) == len(seq)
    kinds = [e["kind"] for e in data.events]
    assert kinds[0] == "start" and kinds[-1] == "stop"
    # the start-up heap (numpy, mcap, the config: ~33k objects) frozen, so no full
    # collection scans it
    assert data.events[0]["detail"]["heap_frozen"] > 20_000
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


@pytest.mark.parametrize("text", ["", "# leveler config\n\n"])
def test_daemon_refuses_an_empty_config(tmp_path: Path, text: str) -> None:
    """An emptied or truncated config must not run the simulated stand on defaults."""
    empty = tmp_path / "leveler.toml"
    empty.write_text(text)
    env = {**os.environ, "RUNTIME_DIRECTORY": str(tmp_path / "run")}  # not the service's
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "run", "--config", str(empty),
                           "--duration", "3s"], capture_output=True, text=True, timeout=60,
                          cwd=tmp_path, env=env)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr == f"leveler run: error: {empty}: is empty: no tables or keys (it " \
        "would run the simulator on built-in defaults); start from config/lab.toml or " \
        "config/sim.toml\n"
    assert proc.stdout == ""
    assert not (tmp_path / "logs").exists() and not (tmp_path / "run").exists()


@pytest.mark.parametrize("rate_hz", [10.0, 200.0])
def test_sigkill_loses_at_most_about_a_second(tmp_path: Path, rate_hz: float,
                                             start_daemon) -> None:  # type: ignore[no-untyped-def]
    """A daemon killed without warning leaves a log readable up to ~1 s before the kill."""
    d = start_daemon(rate_hz=rate_hz)
    lines = d.wait_status_lines(5)
    d.proc.kill()
    d.proc.wait(timeout=10)
    # loop time of the last status line printed before the kill
    last_t = float(lines[-1].split("t=")[1].split(" s")[0])
    (log,) = (tmp_path / "logs").glob("leveler-*.mcap")
    data = read_log(log)
    assert not data.complete
    seq = data.samples["seq"]
    np.testing.assert_array_equal(seq, np.arange(len(seq)))
    assert data.samples["t_s"][-1] >= last_t - 1.5, "lost more than ~1 s of samples"


def test_a_device_missing_at_start_is_one_clear_line_and_exit_1(tmp_path: Path) -> None:
    """Nothing listens on the module's port: no traceback, a line that says what to check,
    and exit 1 (not 2, which the unit's RestartPreventExitStatus reserves for bad configs),
    so that systemd tries again once the module is powered."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    text = (REPO / "config" / "lab-modbus.toml").read_text().replace("port = 5020",
                                                                      f"port = {port}")
    text += f'\n[control]\nsocket_path = "{tmp_path / "c.sock"}"\n'
    text = text.replace('dir = "logs"', f'dir = "{tmp_path / "logs"}"')
    cfg = tmp_path / "lab.toml"
    cfg.write_text(text)
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "run", "--config", str(cfg)],
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "cannot start, a device does not answer" in proc.stderr
    assert f"127.0.0.1:{port}" in proc.stderr and "retrying in" not in proc.stderr
