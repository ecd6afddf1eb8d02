"""The daemon on config/lab-serial.toml against `leveler emulate serial`: real processes,
a Thorlabs-protocol piezo amplifier and a sensor controller on pseudo-terminals."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from conftest import daemon_config

from leveler.log.reader import read_log


def test_daemon_levels_the_emulated_plant_over_serial(
        start_daemon: Callable[..., object], tmp_path: Path) -> None:
    replace = {'port = "/tmp/leveler-sensor"': f'port = "{tmp_path / "sensor"}"',
               'port = "/tmp/leveler-piezo"': f'port = "{tmp_path / "piezo"}"',
               "ki_v_per_m_s = 7.0e5": "ki_v_per_m_s = 2.2e7\nd_filter_tau_s = 0.03",
               "kd_v_s_per_m = 0.0": "kd_v_s_per_m = 1.9e6"}
    (tmp_path / "emu").mkdir()
    emu_config = daemon_config(tmp_path / "emu", tmp_path / "unused.sock", rate_hz=10.0,
                               base="lab-serial.toml", replace=replace)
    emu = subprocess.Popen([sys.executable, "-m", "leveler.cli", "emulate", "serial",
                            "--config", str(emu_config)], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        assert emu.stdout is not None
        assert "leveler emulate serial" in emu.stdout.readline(), emu.communicate(timeout=10)
        assert (tmp_path / "piezo").is_symlink() and (tmp_path / "sensor").is_symlink()
        d = start_daemon(rate_hz=10.0, base="lab-serial.toml", replace=replace)
        d.wait_status_lines(2)  # type: ignore[attr-defined]
        time.sleep(6.0)  # the loop (the default stand's gains) pulls the 1 urad start tilt in
        st = json.loads(d.cli("status", "--json").stdout)  # type: ignore[attr-defined]
        assert st["state"] == "engaged", st
        emu.terminate()
        emu.communicate(timeout=10)
        assert not (tmp_path / "piezo").exists()  # the emulator removed its links
        deadline = time.monotonic() + 10
        while True:
            r = d.cli("status", "--json")  # type: ignore[attr-defined]
            assert r.returncode == 0, r.stderr  # the daemon outlives its devices
            if json.loads(r.stdout)["state"] == "fault":
                break
            assert time.monotonic() < deadline, "no fault after the devices went away"
            time.sleep(0.2)
        d.stop()  # type: ignore[attr-defined]
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.communicate(timeout=10)
    log = read_log(next((tmp_path / "logs").glob("*.mcap")))
    assert log.complete
    s = log.samples
    y = s["sensor_m"][(s["state"] == "engaged") & (s["status"] == 0)]
    assert len(y) > 50
    assert abs(y[0]) > 0.3e-6  # the start tilt, read before the loop pulls it in
    assert abs(np.median(y[-30:])) < 0.3 * abs(y[0])
    faults = [e for e in log.events if e["kind"] == "state" and "fault" in json.dumps(e)]
    assert faults and str(tmp_path) in faults[0]["reason"], log.events
