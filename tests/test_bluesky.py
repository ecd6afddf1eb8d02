"""The ophyd-async device (leveler.live.device) in real Bluesky plans against the running
daemon's PVs: docs/live.md's example, run as written by a RunEngine in a process of its own
(aioca, EPICS base's C client, finds the server through the test's CA port on loopback),
counts and scans it; the run's documents carry the leveling state with its units while the
setpoint moves on the daemon, and a setpoint the daemon refuses fails the move."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from typing import Any

import pytest
from ca_server import ca_env, epics_daemon
from conftest import REPO

from leveler.log.reader import read_log

pytest.importorskip("ophyd_async.epics.core", reason="ophyd-async (the test extra) is missing")
pytest.importorskip("aioca", reason="aioca (ophyd-async's CA backend, the test extra) is missing")

def documented_plan() -> str:
    """The Python block of docs/live.md's Bluesky section, run as written."""
    text = (REPO / "docs" / "live.md").read_text()
    section = text[text.index("## In a Bluesky scan"):]
    return section[section.index("```python\n") + 10:section.index("\n```\n")]


#: after the documented plan: a read-only readout counted, a refused move, what came out
CHECKS = """
import json
import bluesky.plan_stubs as bps
from leveler.live.device import LevelerReadout
with init_devices():
    readout = LevelerReadout("LEV:")
RE(bp.count([readout], num=1))
try:
    RE(bps.mv(lev, 1.0))  # a setpoint of 1 m: a unit slip the daemon refuses
    refused = ""
except Exception as exc:
    refused = repr(exc)
out = {"descriptors": [d["data_keys"] for n, d in docs if n == "descriptor"],
       "events": [d["data"] for n, d in docs if n == "event"],
       "stops": [d["exit_status"] for n, d in docs if n == "stop"], "refused": refused}
print(json.dumps(out, default=str))
"""


def run_plan(port: int) -> dict[str, Any]:
    proc = subprocess.run([sys.executable, "-c", documented_plan() + CHECKS],
                          env={**os.environ, **ca_env(port)}, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_scan_records_the_leveling_state_and_moves_the_setpoint(start_daemon: Any) -> None:
    d, port = epics_daemon(start_daemon, writable=True)
    out = run_plan(port)
    count_keys, scan_keys, readout_keys = out["descriptors"]
    assert count_keys["lev-reading"]["units"] == "m"
    assert count_keys["lev-tilt"]["units"] == "rad"
    assert count_keys["lev-piezo"]["units"] == "V"
    assert count_keys["lev-state"]["choices"] == ["idle", "engaged", "fault", "modulating"]
    assert scan_keys["lev-setpoint"]["units"] == "m"
    assert set(readout_keys) == {"readout-reading", "readout-tilt", "readout-piezo",
                                 "readout-state"}
    counted = out["events"][:3] + out["events"][5:]
    assert all(e.get("lev-state", e.get("readout-state")) == "engaged" for e in counted)
    assert all(abs(e.get("lev-reading", e.get("readout-reading"))) < 1e-6
               and 0 < e.get("lev-piezo", e.get("readout-piezo")) < 150 for e in counted)
    first, second = out["events"][3:5]
    assert first["lev-setpoint"] == pytest.approx(3e-8)
    assert first["lev-reading"] == pytest.approx(3e-8, abs=5e-9)  # settled before the read
    assert second["lev-setpoint"] == 0.0 and abs(second["lev-reading"]) <= 5e-9
    assert out["stops"] == ["success"] * 3
    assert "leveler refused setpoint 1.0 m (it stays 0.0 m)" in out["refused"]
    status = json.loads(d.cli("status", "--json").stdout)
    assert status["controller"]["setpoint_m"] == 0.0 and status["state"] == "engaged"
    d.stop()
    tunes = [e for e in read_log(next(d.logs.glob("*.mcap"))).events if e["kind"] == "tune"]
    assert len(tunes) == 2 and all(t["reason"].startswith("tune by EPICS ") for t in tunes)


SUSPENDED = """
import json
import bluesky.plans as bp
from bluesky import RunEngine
from ophyd_async.core import init_devices
from leveler.live.device import LevelerReadout, suspend_unless_engaged

RE = RunEngine({})
docs = []
RE.subscribe(lambda name, doc: docs.append((name, doc)))
RE.subscribe(lambda name, doc: print("EVENT", flush=True), "event")
with init_devices():
    lev = LevelerReadout("LEV:")
RE.install_suspender(suspend_unless_engaged(lev, sleep=0.5))
print("READY", flush=True)
RE(bp.count([lev], num=10, delay=0.5))
events = [d for n, d in docs if n == "event"]
print(json.dumps({"states": [e["data"]["lev-state"] for e in events],
                  "times": [e["time"] for e in events],
                  "stops": [d["exit_status"] for n, d in docs if n == "stop"]}, default=str))
"""


def test_a_scan_pauses_while_the_loop_is_open_and_resumes_when_it_closes(
        start_daemon: Any) -> None:
    import time

    d, port = epics_daemon(start_daemon)
    proc = subprocess.Popen([sys.executable, "-c", SUSPENDED], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env={**os.environ, **ca_env(port)})
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "READY", proc.communicate(timeout=30)[1]
        for _ in range(2):  # two points recorded, however slow the machine
            assert proc.stdout.readline().strip() == "EVENT", proc.communicate(timeout=30)[1]
        d.cli("stop")  # the loop opened by hand: the scan must wait
        time.sleep(3.0)
        d.cli("start")
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    got = json.loads(out.strip().splitlines()[-1])
    d.stop()
    assert got["stops"] == ["success"] and len(got["states"]) >= 10  # a redone point too
    assert set(map(str, got["states"])) == {"engaged"}, got["states"]
    gaps = [b - a for a, b in itertools.pairwise(got["times"])]
    assert max(gaps) > 2.5, gaps  # the pause: no point while the loop was open
