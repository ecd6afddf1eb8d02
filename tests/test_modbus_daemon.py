"""The daemon on config/lab-modbus.toml against `leveler emulate modbus`: real processes,
a real Modbus TCP server on 127.0.0.1, the real control socket."""

from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from conftest import daemon_config

from leveler.log.reader import read_log


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _emulator(config: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", "leveler.cli", "emulate", "modbus",
                             "--config", str(config)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()  # printed once the server listens
    assert "leveler emulate modbus" in line, proc.communicate(timeout=10)[1]
    return proc


def test_daemon_levels_the_emulated_plant_faults_when_it_goes_and_resumes(
        start_daemon: Callable[..., object], tmp_path: Path) -> None:
    replace = {"port = 5020": f"port = {_free_port()}",
               "ki_v_per_m_s = 7.0e5": "ki_v_per_m_s = 2.2e7\nd_filter_tau_s = 0.03",
               "kd_v_s_per_m = 0.0": "kd_v_s_per_m = 1.9e6",
               "engage_on_start = true": "engage_on_start = true\nreconnect_min_s = 0.5"}
    (tmp_path / "emu").mkdir()
    emu_config = daemon_config(tmp_path / "emu", tmp_path / "unused.sock", rate_hz=10.0,
                               base="lab-modbus.toml", replace=replace)
    emu = _emulator(emu_config)
    try:
        d = start_daemon(rate_hz=10.0, base="lab-modbus.toml", replace=replace)
        d.wait_status_lines(2)  # type: ignore[attr-defined]
        time.sleep(6.0)  # the loop (the default stand's gains) pulls the 1 urad start tilt in
        st = json.loads(d.cli("status", "--json").stdout)  # type: ignore[attr-defined]
        assert st["state"] == "engaged", st
        emu.terminate()
        emu.communicate(timeout=10)
        deadline = time.monotonic() + 10
        while json.loads(d.cli("status", "--json").stdout)["state"] != "fault":  # type: ignore[attr-defined]
            assert time.monotonic() < deadline, "no fault after the module went away"
            time.sleep(0.2)
        assert d.proc.poll() is None  # type: ignore[attr-defined]  # the daemon stays up
        emu = _emulator(emu_config)  # the module is back: the daemon reconnects and resumes
        deadline = time.monotonic() + 15
        while json.loads(d.cli("status", "--json").stdout)["state"] != "engaged":  # type: ignore[attr-defined]
            assert time.monotonic() < deadline, "no automatic reconnect"
            time.sleep(0.2)
        d.stop()  # type: ignore[attr-defined]
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.communicate(timeout=10)
    log = read_log(next((tmp_path / "logs").glob("*.mcap")))
    assert log.complete
    s = log.samples
    engaged = s["state"] == "engaged"
    y = s["sensor_m"][engaged & (s["status"] == 0)]
    assert len(y) > 50
    # Pulled in: the 1 urad start tilt reads ~0.45 um; after 6 s it is mostly gone.
    assert abs(y[0]) > 0.3e-6  # the start tilt, read before the loop pulls it in
    assert abs(np.median(y[-30:])) < 0.3 * abs(y[0])
    faults = [e for e in log.events if e["kind"] == "state" and "fault" in json.dumps(e)]
    assert faults and "127.0.0.1" in faults[0]["reason"], log.events
    reconnects = [e["reason"] for e in log.events if e["kind"] == "reconnect"]
    assert reconnects[-1] == "devices answer again"
    states = [e["detail"]["new"] for e in log.events if e["kind"] == "state"]
    assert states[-4:] == ["fault", "idle", "engaged", "idle"]


def test_clients_that_hang_up_before_the_reply_leave_the_emulator_quiet(tmp_path: Path) -> None:
    """A client that gives up on a late reply (the daemon after its timeout) made pymodbus
    print "Cancel send, because not connected!" and a frame dump per request into the
    emulator's output; the emulator silences that logger, and keeps serving."""
    port = _free_port()
    config = daemon_config(tmp_path, tmp_path / "unused.sock", rate_hz=10.0,
                           base="lab-modbus.toml", replace={"port = 5020": f"port = {port}"})
    emu = _emulator(config)
    try:
        read_input_registers = struct.pack(">HHHBBHH", 7, 0, 6, 1, 4, 0, 1)  # MBAP + FC 4
        for _ in range(30):  # request, then reset the connection before the reply
            with socket.create_connection(("127.0.0.1", port), timeout=5) as c:
                c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                c.sendall(read_input_registers)
        with socket.create_connection(("127.0.0.1", port), timeout=5) as c:  # still serving
            c.sendall(read_input_registers)
            reply = c.recv(64)
        assert reply[:2] == b"\x00\x07" and reply[7] == 4 and reply[8] == 2, reply.hex()
    finally:
        emu.terminate()
        _, err = emu.communicate(timeout=10)
    assert emu.returncode == 0
    assert err == "", err[:1000]
