"""Progress on long commands: a bar with rate and time left on a terminal (a real pty), not
a byte of it on a pipe or with --json; diagnose says which stage it is in."""

from __future__ import annotations

import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios
import threading
from pathlib import Path

import pytest
from conftest import REPO

from leveler.cli.main import main

SIM = ["sim", "--config", str(REPO / "config" / "sim.toml"), "--seed", "1"]


def run(args: list[str], *, terminal: bool, cwd: Path) -> tuple[str, str]:
    """The command as a subprocess; its stderr on a 120-column pty when `terminal`."""
    cmd = [sys.executable, "-m", "leveler.cli", *args]
    if not terminal:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=cwd)
        assert proc.returncode == 0, proc.stderr
        return proc.stdout, proc.stderr
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    chunks: list[bytes] = []

    def drain() -> None:  # the pty's buffer is small: read while the command writes
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: every writer has closed the slave
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=slave, text=True, cwd=cwd)
    os.close(slave)
    out, _ = proc.communicate(timeout=120)
    reader.join(timeout=10)
    os.close(master)
    assert proc.returncode == 0
    return out, b"".join(chunks).decode(errors="replace")


def test_sim_on_a_terminal_shows_rate_and_time_left(tmp_path: Path) -> None:
    out, err = run([*SIM, "--duration", "2h"], terminal=True, cwd=tmp_path)
    assert "closed loop:" in err and "open loop" in err
    assert "100%" in err and "2/2 h" in err  # filled, in the run's own unit
    assert "h/s]" in err  # the rate, after [elapsed<remaining, ...]
    assert "<" in err.split("closed loop:")[1]  # elapsed<remaining
    assert "frequency" in out and "closed loop" not in out  # the table alone on stdout


def test_nothing_on_a_pipe_or_with_json(tmp_path: Path) -> None:
    out, err = run([*SIM, "--duration", "1h"], terminal=False, cwd=tmp_path)
    assert err == ""
    assert "frequency" in out
    out, err = run([*SIM, "--duration", "1h", "--json"], terminal=True, cwd=tmp_path)
    assert err == ""
    assert out.startswith("{")


def test_asd_shows_its_reading_on_a_terminal(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    run([*SIM, "--duration", "1h", "--out", str(log)], terminal=False, cwd=tmp_path)
    _, err = run(["asd", str(log), "--channel", "sensor_m"], terminal=True, cwd=tmp_path)
    assert "reading run.mcap:" in err and "MB" in err and "100%" in err


def test_diagnose_reports_each_stage_in_order(tmp_path: Path) -> None:
    from leveler.analysis.diagnose import diagnose
    from leveler.analysis.predict import load_measured

    log = tmp_path / "run.mcap"
    assert main([*SIM, "--duration", "2h", "--out", str(log), "--json"]) == 0
    seen: list[tuple[str, int, int]] = []
    read: list[float] = []
    diagnose(load_measured(log, progress=read.append), max_effects=1,
             progress=lambda *a: seen.append(a))
    assert read[-1] == 1.0 and read == sorted(read)
    stages = list(dict.fromkeys(s for s, _, _ in seen))
    assert stages == ["recalibrating the model", "round 1: fitting each family of effects",
                      "recalibrating with what was found", "looking for what is left"]
    fits = [(done, total) for s, done, total in seen if s.startswith("round 1")]
    assert fits[0][0] == 0 and fits[-1][0] == fits[-1][1] >= 5  # every family, counted


def test_stages_draw_only_where_someone_watches(capsys: pytest.CaptureFixture[str]) -> None:
    """Under pytest stderr is no terminal: no bar, though nothing asked for quiet."""
    from leveler.cli.progress import Stages

    with Stages("diagnose") as stages:
        stages("one", 0, 2)
        stages("one", 2, 2)
    assert capsys.readouterr().err == ""
